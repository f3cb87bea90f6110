//! Wavelets, signal-extension modes and the size rules of PyWavelets.

use std::fmt;

use serde::{Deserialize, Serialize};

use crate::filters::{FilterBank, FILTER_BANKS};

/// An orthogonal wavelet: db1..db10, sym2..sym10 or coif1..coif5, with PyWavelets' filters.
///
/// Cheap to copy (it points into a static table).
#[derive(Clone, Copy)]
pub struct Wavelet {
    bank: &'static FilterBank,
}

impl Wavelet {
    /// Look a wavelet up by its PyWavelets name ("db4", "sym5", "coif2", ...), ignoring ASCII
    /// case. `None` for names outside db1..db10, sym2..sym10, coif1..coif5.
    pub fn by_name(name: &str) -> Option<Wavelet> {
        let name = name.trim();
        FILTER_BANKS
            .iter()
            .find(|b| b.name.eq_ignore_ascii_case(name))
            .map(|bank| Wavelet { bank })
    }

    /// Every supported name, in the order db1..db10, sym2..sym10, coif1..coif5.
    pub fn names() -> impl Iterator<Item = &'static str> {
        FILTER_BANKS.iter().map(|b| b.name)
    }

    /// The PyWavelets name, e.g. "sym5".
    pub fn name(&self) -> &'static str {
        self.bank.name
    }

    /// Number of filter taps (`pywt.Wavelet(name).dec_len`): 10 for sym5, 2 for db1.
    pub fn filter_len(&self) -> usize {
        self.bank.dec_lo.len()
    }

    /// Decomposition low-pass filter (`pywt.Wavelet(name).dec_lo`).
    pub fn dec_lo(&self) -> &'static [f64] {
        self.bank.dec_lo
    }

    /// Decomposition high-pass filter (`dec_hi`).
    pub fn dec_hi(&self) -> &'static [f64] {
        self.bank.dec_hi
    }

    /// Reconstruction low-pass filter (`rec_lo`, the reversed `dec_lo`).
    pub fn rec_lo(&self) -> &'static [f64] {
        self.bank.rec_lo
    }

    /// Reconstruction high-pass filter (`rec_hi`).
    pub fn rec_hi(&self) -> &'static [f64] {
        self.bank.rec_hi
    }
}

impl PartialEq for Wavelet {
    fn eq(&self, other: &Self) -> bool {
        self.bank.name == other.bank.name
    }
}

impl Eq for Wavelet {}

impl fmt::Debug for Wavelet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Wavelet({})", self.bank.name)
    }
}

impl fmt::Display for Wavelet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.bank.name)
    }
}

/// Signal extension at the borders, with PyWavelets' meaning and names.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// Half-sample symmetric: `... x1 x0 | x0 x1 ... x(N-1) | x(N-1) x(N-2) ...` (PyWavelets'
    /// default, 'symmetric'). A level keeps `floor((N + L - 1) / 2)` coefficients per axis, so
    /// the coefficients outnumber the samples a little.
    #[default]
    Symmetric,
    /// Periodic extension of the signal, padded to even length by repeating its last sample
    /// ('periodization'). A level keeps `ceil(N / 2)` coefficients per axis: for even sizes the
    /// transform is orthogonal and non-redundant.
    Periodization,
}

impl Mode {
    /// The PyWavelets name: "symmetric" or "periodization".
    pub fn name(self) -> &'static str {
        match self {
            Mode::Symmetric => "symmetric",
            Mode::Periodization => "periodization",
        }
    }

    /// Parse a PyWavelets mode name ("symmetric", "periodization"; ASCII case ignored).
    pub fn by_name(name: &str) -> Option<Mode> {
        let name = name.trim();
        [Mode::Symmetric, Mode::Periodization]
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(name))
    }
}

impl fmt::Display for Mode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Deepest level at which every coefficient still sees some unpadded sample, as
/// `pywt.dwt_max_level(len, filter_len)`: `floor(log2(len / (filter_len - 1)))`, and 0 when
/// `len < filter_len - 1` or `filter_len < 2`.
pub fn dwt_max_level(len: usize, filter_len: usize) -> usize {
    if filter_len < 2 || len < filter_len - 1 {
        return 0;
    }
    // floor(log2(floor(a / b))) == floor(log2(a / b)) for a / b >= 1, as PyWavelets computes it.
    (len / (filter_len - 1)).ilog2() as usize
}

/// Number of coefficients one level produces from `len` samples, as
/// `pywt.dwt_coeff_len(len, filter_len, mode)`.
pub fn dwt_coeff_len(len: usize, filter_len: usize, mode: Mode) -> usize {
    match mode {
        Mode::Symmetric => (len + filter_len).saturating_sub(1) / 2,
        Mode::Periodization => len.div_ceil(2),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_is_complete_and_consistent() {
        let names: Vec<_> = Wavelet::names().collect();
        assert_eq!(names.len(), 24);
        for name in names {
            let w = Wavelet::by_name(name).expect("listed name resolves");
            let l = w.filter_len();
            assert!(l >= 2 && l.is_multiple_of(2), "{name}: even length");
            // rec_lo is the reversed dec_lo; dec_hi[k] = (-1)^(k+1) dec_lo[L-1-k].
            for k in 0..l {
                assert_eq!(w.rec_lo()[k], w.dec_lo()[l - 1 - k], "{name}");
                let sign = if k % 2 == 0 { -1.0 } else { 1.0 };
                assert_eq!(w.dec_hi()[k], sign * w.dec_lo()[l - 1 - k], "{name}");
            }
            let norm: f64 = w.dec_lo().iter().map(|h| h * h).sum();
            assert!((norm - 1.0).abs() < 1e-11, "{name}: unit norm");
        }
        assert_eq!(Wavelet::by_name("sym5").map(|w| w.filter_len()), Some(10));
        assert_eq!(Wavelet::by_name("SYM5").map(|w| w.name()), Some("sym5"));
        assert_eq!(Wavelet::by_name("coif5").map(|w| w.filter_len()), Some(30));
        assert!(Wavelet::by_name("sym1").is_none());
        assert!(Wavelet::by_name("bior2.2").is_none());
    }

    #[test]
    fn size_rules_match_pywt() {
        // Values from pywt.dwt_max_level / pywt.dwt_coeff_len.
        assert_eq!(dwt_max_level(1024, 10), 6);
        assert_eq!(dwt_max_level(1024, 2), 10);
        assert_eq!(dwt_max_level(8, 10), 0);
        assert_eq!(dwt_max_level(9, 10), 0);
        assert_eq!(dwt_max_level(18, 10), 1);
        assert_eq!(dwt_max_level(0, 10), 0);
        assert_eq!(dwt_max_level(5, 1), 0);
        assert_eq!(dwt_coeff_len(17, 10, Mode::Symmetric), 13);
        assert_eq!(dwt_coeff_len(17, 10, Mode::Periodization), 9);
        assert_eq!(dwt_coeff_len(1024, 10, Mode::Symmetric), 516);
        assert_eq!(Mode::by_name("Periodization"), Some(Mode::Periodization));
        assert_eq!(Mode::default().name(), "symmetric");
    }
}
