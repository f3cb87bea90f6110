//! Order statistics of large height fields without sorting a copy of them.
//!
//! [`median_magnitude`] is the median of |v| over the values of an f32 field (the mesher's
//! outlier scale, the robust Gaussian filter's MAD); the Abbott curve's many ranks of an f64
//! map are [`crate::metrology`]'s own bucket pass (signed values, ~20 000 ranks at once).

use rayon::prelude::*;

/// The median of |v(i)| over i in 0..len where v(i) is not NaN: the element at index n / 2
/// of their sorted magnitudes, exactly what `select_nth_unstable_by(n / 2, f32::total_cmp)`
/// of a collected copy gives, without the copy. The magnitudes' bit patterns order as the
/// values do (sign cleared, no NaN), so the element is found by counting them, by their high
/// 16 bits and then by the low 16 bits within its bin: two passes over `v`, two 64 K-entry
/// histograms per thread. `None`: no value.
pub fn median_magnitude(len: usize, v: impl Fn(usize) -> f32 + Sync) -> Option<f32> {
    const BINS: usize = 1 << 16;
    const CHUNK: usize = 1 << 16;
    let count = |high: Option<u32>| -> Vec<u64> {
        (0..len.div_ceil(CHUNK))
            .into_par_iter()
            .fold(
                || vec![0u64; BINS],
                |mut hist, c| {
                    for i in c * CHUNK..((c + 1) * CHUNK).min(len) {
                        let x = v(i);
                        if x.is_nan() {
                            continue;
                        }
                        let b = x.abs().to_bits();
                        match high {
                            None => hist[(b >> 16) as usize] += 1,
                            Some(h) if b >> 16 == h => hist[(b & 0xffff) as usize] += 1,
                            Some(_) => {}
                        }
                    }
                    hist
                },
            )
            .reduce(
                || vec![0u64; BINS],
                |mut a, b| {
                    a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                    a
                },
            )
    };
    // The bin holding the element of rank `k` (0-based), and its rank within the bin.
    let find = |hist: &[u64], k: u64| -> (u32, u64) {
        let mut below = 0;
        for (bin, &n) in hist.iter().enumerate() {
            if k < below + n {
                return (bin as u32, k - below);
            }
            below += n;
        }
        (BINS as u32 - 1, 0) // unreachable: k < the total
    };
    let high = count(None);
    let n: u64 = high.iter().sum();
    if n == 0 {
        return None;
    }
    let (h, k) = find(&high, n / 2);
    let (l, _) = find(&count(Some(h)), k);
    Some(f32::from_bits((h << 16) | l))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_median_magnitude_is_the_sorted_copys() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for n in [1usize, 2, 3, 10, 1000, 65_536, 65_537, 200_001] {
            let mut v: Vec<f32> = (0..n)
                .map(|_| match next() % 23 {
                    0 => f32::NAN,
                    1 => 0.0,
                    2 => -0.0,
                    3 => f32::INFINITY,
                    4 => 1.5,
                    _ => (next() % 2_000_001) as f32 * 1e-3 - 1e3,
                })
                .collect();
            v[0] = 0.25;
            let mut abs: Vec<f32> = v.iter().filter(|r| !r.is_nan()).map(|r| r.abs()).collect();
            let k = abs.len() / 2;
            let (_, m, _) = abs.select_nth_unstable_by(k, f32::total_cmp);
            let m = *m;
            assert_eq!(
                median_magnitude(v.len(), |i| v[i]).map(f32::to_bits),
                Some(m.to_bits()),
                "n = {n}"
            );
        }
        assert_eq!(median_magnitude(2, |_| f32::NAN), None);
        assert_eq!(median_magnitude(0, |_| 0.0), None);
    }
}
