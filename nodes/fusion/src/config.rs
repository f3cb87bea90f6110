//! The fusion's one front door: [`FusionConfig`], its parameters as a graph file gives them
//! (typed: the method, the wavelet and the Zarr choice are parsed when the graph is read, a
//! bad value refused with its key), and [`FusionConfig::settings`], which checks them into
//! the [`FusionSettings`] the [`crate::StreamingFusion`] fuses with.

use serde::Deserialize;
use surfstream_core::choice::{from_text, from_text_opt};
use surfstream_wavelet::Wavelet;

use crate::stream::FusionSettings;
use crate::{FusionMethod, WaveletFusion};

/// Panoramas from this size (64 Mi px, a 512 MiB f64 .npy) get a panorama.zarr with "auto".
pub const ZARR_AUTO_MIN_PX: usize = 1 << 26;

/// The fusion node's `params` table. Every field has the graph's default.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionConfig {
    /// "gradual" (the paper's gradual in-and-out, eq. 5; default), "average" (eq. 4) or
    /// "wavelet" (eq. 6).
    #[serde(deserialize_with = "from_text")]
    pub method: FusionMethod,
    /// Wavelet of the wavelet fusion (default sym5).
    #[serde(deserialize_with = "from_text_opt")]
    pub wavelet: Option<Wavelet>,
    /// Decomposition levels of the wavelet fusion (default 2, clamped to the overlap).
    pub wavelet_level: Option<usize>,
    /// Weight ramp length from a tile's border, px. Default: half the tile.
    pub ramp_px: Option<f64>,
    /// Write panorama.npy and panorama.png into the out dir.
    pub write_files: bool,
    /// Also write panorama.zarr (Zarr v3, chunked).
    pub zarr: ZarrChoice,
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            method: FusionMethod::Gradual,
            wavelet: None,
            wavelet_level: None,
            ramp_px: None,
            write_files: true,
            zarr: ZarrChoice::default(),
        }
    }
}

/// When the fusion writes panorama.zarr beside panorama.npy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ZarrChoice {
    /// For panoramas of at least [`ZARR_AUTO_MIN_PX`] (default).
    #[default]
    Auto,
    Always,
    Never,
}

impl ZarrChoice {
    /// The smallest panorama that gets a Zarr copy, px (`None`: never).
    pub fn min_px(self) -> Option<usize> {
        match self {
            ZarrChoice::Auto => Some(ZARR_AUTO_MIN_PX),
            ZarrChoice::Always => Some(0),
            ZarrChoice::Never => None,
        }
    }
}

impl FusionConfig {
    /// The settings these parameters ask for; the error names the parameter.
    pub fn settings(&self) -> Result<FusionSettings, String> {
        let mut wavelet = WaveletFusion::default();
        if let Some(w) = self.wavelet {
            wavelet.wavelet = w;
        }
        if let Some(level) = self.wavelet_level {
            let max = surfstream_wavelet::MAX_LEVEL;
            if !(1..=max).contains(&level) {
                return Err(format!("wavelet_level = {level}: expected 1..={max}"));
            }
            wavelet.level = level;
        }
        if let Some(r) = self.ramp_px.filter(|r| !(r.is_finite() && *r > 0.0)) {
            return Err(format!("ramp_px = {r}: expected > 0 px"));
        }
        Ok(FusionSettings {
            method: self.method,
            wavelet,
            ramp_px: self.ramp_px,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(json: &str) -> Result<FusionConfig, String> {
        serde_json::from_str(json).map_err(|e| e.to_string())
    }

    #[test]
    fn parameters_become_settings_or_name_the_bad_one() {
        let d = config("{}").unwrap();
        assert_eq!(d.settings().unwrap().method, FusionMethod::Gradual);
        assert_eq!(d.zarr.min_px(), Some(ZARR_AUTO_MIN_PX));
        let w = config(r#"{"method": " Wavelet", "wavelet": "db4", "wavelet_level": 3}"#)
            .unwrap()
            .settings()
            .unwrap();
        assert_eq!(w.method, FusionMethod::Wavelet);
        assert_eq!((w.wavelet.wavelet.name(), w.wavelet.level), ("db4", 3));
        assert_eq!(config(r#"{"zarr": "never"}"#).unwrap().zarr.min_px(), None);
        for (bad, says) in [
            (r#"{"method": "median"}"#, "expected \"gradual\""),
            (r#"{"wavelet": "haar"}"#, "\"haar\": expected"),
            (r#"{"zarr": "sometimes"}"#, "`always`"),
            (r#"{"colour": 1}"#, "unknown field"),
        ] {
            let e = config(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
        for (bad, says) in [
            (r#"{"wavelet_level": 0}"#, "wavelet_level = 0"),
            (r#"{"ramp_px": -1}"#, "ramp_px = -1"),
        ] {
            let e = config(bad).unwrap().settings().unwrap_err();
            assert!(e.starts_with(says), "{bad}: {e}");
        }
    }
}
