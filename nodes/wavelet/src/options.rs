//! The separation's options as text (a graph file's params, the `separate` verb's flags): one
//! parser per option, so the node and the verb accept and refuse the same spellings, and the
//! wavelet node's parameters ([`WaveletConfig`]) parsed by them.
//!
//! Every parser trims and ignores ASCII case. The error names what was expected; the caller
//! prefixes where the value came from (`--level`, `graph 'g', node 'w': level = `).

use std::fmt;
use std::str::FromStr;

use serde::Deserialize;
use surfstream_core::choice::{from_number_or_text, from_text, from_text_opt};

use crate::{BaseChoice, LevelChoice, Mode, PoolOp, SeparationKind, SeparationMethod, Wavelet};

/// A value an option does not accept.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OptionError {
    /// The value as given.
    pub value: String,
    /// What the option accepts.
    pub expected: &'static str,
}

impl fmt::Display for OptionError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}: expected {}", self.value, self.expected)
    }
}

impl std::error::Error for OptionError {}

fn refuse(value: &str, expected: &'static str) -> OptionError {
    OptionError {
        value: value.to_string(),
        expected,
    }
}

fn is_auto(s: &str) -> bool {
    s.trim().eq_ignore_ascii_case("auto")
}

impl FromStr for Wavelet {
    type Err = OptionError;
    /// A PyWavelets name: db1..db10, sym2..sym10, coif1..coif5.
    fn from_str(s: &str) -> Result<Self, OptionError> {
        Wavelet::by_name(s).ok_or_else(|| refuse(s, "db1..db10, sym2..sym10 or coif1..coif5"))
    }
}

impl FromStr for BaseChoice {
    type Err = OptionError;
    /// A wavelet name, or "auto": minimum reconstruction RMSE (eq. 10).
    fn from_str(s: &str) -> Result<Self, OptionError> {
        if is_auto(s) {
            return Ok(BaseChoice::MinRmse);
        }
        Wavelet::by_name(s)
            .map(BaseChoice::Named)
            .ok_or_else(|| refuse(s, "db1..db10, sym2..sym10, coif1..coif5 or \"auto\""))
    }
}

impl FromStr for LevelChoice {
    type Err = OptionError;
    /// A decomposition level >= 1, or "auto": minimum approximation energy (Fig. 13).
    fn from_str(s: &str) -> Result<Self, OptionError> {
        if is_auto(s) {
            return Ok(LevelChoice::MinEnergy);
        }
        match s.trim().parse::<usize>() {
            Ok(level) if level >= 1 => Ok(LevelChoice::Fixed(level)),
            _ => Err(refuse(s, "a decomposition level >= 1 or \"auto\"")),
        }
    }
}

impl FromStr for Mode {
    type Err = OptionError;
    /// "symmetric" or "periodization".
    fn from_str(s: &str) -> Result<Self, OptionError> {
        Mode::by_name(s).ok_or_else(|| refuse(s, "\"symmetric\" or \"periodization\""))
    }
}

impl FromStr for PoolOp {
    type Err = OptionError;
    /// "max" or "mean".
    fn from_str(s: &str) -> Result<Self, OptionError> {
        PoolOp::by_name(s).ok_or_else(|| refuse(s, "\"max\" or \"mean\""))
    }
}

/// The wavelet node's `params` table (typed: each choice is parsed by its option's parser
/// above when the graph is read, and refused with its key). `None`: the default.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WaveletConfig {
    /// "wavelet" (the paper; default), "gaussian" (ISO 16610-61) or "robust-gaussian"
    /// (ISO 16610-71).
    #[serde(deserialize_with = "from_text")]
    pub method: SeparationKind,
    /// The L-filter's cutoff wavelength lambda_c, µm (filter methods only).
    pub cutoff_um: Option<f64>,
    /// The S-filter's cutoff lambda_s, µm (filter methods only; none by default).
    pub lambda_s_um: Option<f64>,
    /// A base name (default sym5), or "auto": minimum reconstruction RMSE (eq. 10; it ranks
    /// round-off).
    #[serde(deserialize_with = "from_text_opt")]
    pub wavelet: Option<BaseChoice>,
    /// Decomposition level of the datum (clamped to the largest useful level of the
    /// panorama), or "auto": minimum approximation energy proportion (Fig. 13).
    #[serde(deserialize_with = "from_number_or_text")]
    pub level: LevelChoice,
    /// "symmetric" (default) or "periodization".
    #[serde(deserialize_with = "from_text")]
    pub mode: Mode,
    /// Pooling block, px.
    pub pool: usize,
    /// "max" (the paper; default) or "mean".
    #[serde(deserialize_with = "from_text")]
    pub pool_op: PoolOp,
    /// Publish live (preview) patches while tiles arrive.
    pub live: bool,
    /// Context around the changed region for a live patch, px.
    pub live_margin_px: usize,
    pub write_files: bool,
}

impl Default for WaveletConfig {
    fn default() -> Self {
        Self {
            method: SeparationKind::default(),
            cutoff_um: None,
            lambda_s_um: None,
            wavelet: None,
            level: LevelChoice::Default,
            mode: Mode::default(),
            pool: 4,
            pool_op: PoolOp::Max,
            live: true,
            live_margin_px: 256,
            write_files: true,
        }
    }
}

/// The base when none is named: sym5 (the paper's).
pub fn default_base() -> Result<Wavelet, String> {
    Wavelet::by_name("sym5").ok_or_else(|| "the built-in wavelet sym5 is missing".into())
}

impl WaveletConfig {
    /// The separation these parameters ask for; the error names the parameter.
    pub fn settings(&self) -> Result<SeparationSettings, String> {
        if self.pool == 0 {
            return Err("pool = 0: expected a block size of at least 1 px".into());
        }
        let method = SeparationMethod::with_cutoff(self.method, self.cutoff_um)?;
        let lambda_s_um = match (self.lambda_s_um, method.cutoff_um()) {
            (None, _) => None,
            (Some(ls), Some(lc)) if ls.is_finite() && ls > 0.0 && ls < lc => Some(ls),
            (Some(ls), Some(_)) => {
                return Err(format!(
                "lambda_s_um = {ls}: expected a positive wavelength in µm shorter than cutoff_um"
            ))
            }
            (Some(_), None) => {
                return Err(
                    "lambda_s_um: applies to method \"gaussian\" or \"robust-gaussian\"".into(),
                )
            }
        };
        let base = match self.wavelet {
            Some(b) => b,
            None => BaseChoice::Named(default_base()?),
        };
        Ok(SeparationSettings {
            method,
            lambda_s_um,
            base,
            level: self.level,
            mode: self.mode,
            pool_block: self.pool,
            pool_op: self.pool_op,
        })
    }
}

/// How the panorama is separated and pooled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeparationSettings {
    /// Wavelet (base, level, mode below) or an ISO 16610 L-filter.
    pub method: SeparationMethod,
    /// S-filter cutoff, µm (filter methods only).
    pub lambda_s_um: Option<f64>,
    pub base: BaseChoice,
    pub level: LevelChoice,
    pub mode: Mode,
    /// Pooling block, px (>= 1).
    pub pool_block: usize,
    pub pool_op: PoolOp,
}

impl SeparationSettings {
    /// The base of live passes: the named one, the default (sym5) when the final base is chosen by RMSE
    /// (ranking every base per live window would cost 23 separations).
    pub fn live_wavelet(&self) -> anyhow::Result<Wavelet> {
        match self.base {
            BaseChoice::Named(w) => Ok(w),
            BaseChoice::MinRmse => default_base().map_err(|e| anyhow::anyhow!(e)),
        }
    }

    /// The level asked for, when it is a fixed one (live passes use it; the default otherwise).
    pub fn fixed_level(&self) -> Option<usize> {
        match self.level {
            LevelChoice::Fixed(l) => Some(l),
            _ => None,
        }
    }
}

/// Whether the final pass streams ([`crate::separate_streamed`]): a named wavelet at a fixed
/// or the default level. Choosing the base by RMSE (every base over the whole map), the level
/// by minimum energy, and the ISO filter methods (FFT) keep the in-memory path.
pub fn final_pass_streams(settings: &SeparationSettings) -> bool {
    matches!(settings.method, SeparationMethod::Wavelet)
        && matches!(settings.base, BaseChoice::Named(_))
        && matches!(settings.level, LevelChoice::Fixed(_) | LevelChoice::Default)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_option_accepts_its_spellings_and_names_what_it_expects() {
        assert_eq!("sym5".parse::<Wavelet>().unwrap().name(), "sym5");
        assert_eq!(" AUTO ".parse::<BaseChoice>(), Ok(BaseChoice::MinRmse));
        assert!(
            matches!("DB4".parse::<BaseChoice>(), Ok(BaseChoice::Named(w)) if w.name() == "db4")
        );
        assert_eq!("auto".parse::<LevelChoice>(), Ok(LevelChoice::MinEnergy));
        assert_eq!(" 8".parse::<LevelChoice>(), Ok(LevelChoice::Fixed(8)));
        assert_eq!("Periodization".parse::<Mode>(), Ok(Mode::Periodization));
        assert_eq!("mean".parse::<PoolOp>(), Ok(PoolOp::Mean));
        for bad in ["0", "-1", "eight", ""] {
            assert!(bad.parse::<LevelChoice>().is_err(), "{bad}");
        }
        let e = "haar".parse::<BaseChoice>().unwrap_err();
        assert_eq!(
            e.to_string(),
            "\"haar\": expected db1..db10, sym2..sym10, coif1..coif5 or \"auto\""
        );
        assert!("zero".parse::<Mode>().is_err());
        assert!("min".parse::<PoolOp>().is_err());
        assert!("auto".parse::<Wavelet>().is_err());
    }

    #[test]
    fn node_params_become_settings_or_name_the_bad_one() {
        let p = |json: &str| -> WaveletConfig { serde_json::from_str(json).expect("params") };
        let s = p(r#"{"level": 6, "pool_op": "Mean"}"#).settings().unwrap();
        assert_eq!(s.level, LevelChoice::Fixed(6));
        assert_eq!((s.pool_block, s.pool_op), (4, PoolOp::Mean));
        assert_eq!(p("{}").settings().unwrap().level, LevelChoice::Default);
        assert_eq!(
            p("{}").settings().unwrap().method,
            SeparationMethod::Wavelet
        );
        let g = p(r#"{"method": "robust-gaussian", "cutoff_um": 250, "lambda_s_um": 2.5}"#)
            .settings()
            .unwrap();
        assert_eq!(
            g.method,
            SeparationMethod::RobustGaussian { cutoff_um: 250.0 }
        );
        assert_eq!(g.lambda_s_um, Some(2.5));
        assert_eq!(
            p(r#"{"level": "auto", "wavelet": "auto"}"#)
                .settings()
                .unwrap()
                .base,
            BaseChoice::MinRmse
        );
        // A choice is refused when read (the graph's reader prefixes its key).
        for (bad, says) in [
            (r#"{"level": 0}"#, "\"0\": expected a decomposition level"),
            (r#"{"level": -2}"#, "\"-2\": expected a decomposition level"),
            (r#"{"mode": "zero"}"#, "\"zero\": expected \"symmetric\""),
            (r#"{"wavelet": "haar"}"#, "\"haar\": expected db1"),
            (
                r#"{"method": "median"}"#,
                "\"median\": expected \"wavelet\"",
            ),
            (r#"{"pool_op": "min"}"#, "\"min\": expected"),
            (r#"{"colour": 1}"#, "unknown field"),
        ] {
            let e = serde_json::from_str::<WaveletConfig>(bad).unwrap_err();
            assert!(e.to_string().contains(says), "{bad}: {e}");
        }
        for (bad, field) in [
            (r#"{"pool": 0}"#, "pool = 0"),
            (r#"{"method": "gaussian"}"#, "cutoff_um"),
            (r#"{"method": "gaussian", "cutoff_um": 0}"#, "cutoff_um = 0"),
            (r#"{"cutoff_um": 80}"#, "cutoff_um"),
            (
                r#"{"method": "gaussian", "cutoff_um": 80, "lambda_s_um": 90}"#,
                "lambda_s_um = 90",
            ),
            (r#"{"lambda_s_um": 2.5}"#, "lambda_s_um"),
        ] {
            let e = p(bad).settings().unwrap_err();
            assert!(e.starts_with(field), "{bad}: {e}");
        }
    }
}
