//! FFT sizing shared by the crates that transform rasters (matcher, replay's specimen).

/// The smallest `m >= n` whose only prime factors are 2, 3 and 5: the lengths rustfft handles
/// with its fast mixed-radix algorithms.
pub fn fast_len(n: usize) -> usize {
    let mut m = n.max(1);
    loop {
        let mut k = m;
        for p in [2, 3, 5] {
            while k.is_multiple_of(p) {
                k /= p;
            }
        }
        if k == 1 {
            return m;
        }
        m += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::fast_len;

    #[test]
    fn fast_lengths_are_smooth_and_minimal() {
        assert_eq!(fast_len(0), 1);
        assert_eq!(fast_len(1), 1);
        assert_eq!(fast_len(7), 8);
        assert_eq!(fast_len(1021), 1024);
        assert_eq!(fast_len(1025), 1080);
        for n in 1..500usize {
            let m = fast_len(n);
            assert!(m >= n);
            assert!((n..m).all(|k| fast_len(k) == m));
        }
    }
}
