//! The matcher's one front door: [`MatcherConfig`], its parameters as a graph file gives them
//! (typed: the method is a [`RegistrationMethod`], refused with the key and the allowed
//! spellings when unknown), checked and turned into the library's [`ScanParams`], so the node
//! only maps frames to calls.

use std::path::Path;
use std::str::FromStr;

use serde::Deserialize;

use crate::raster::InputError;
use crate::scan::ScanParams;
use crate::{FeatureMethod, FeatureParams};

/// How each tile is registered against its neighbours.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RegistrationMethod {
    /// Phase correlation with NCC-verified candidates ("auto" or "phase").
    #[default]
    Phase,
    /// The reference study's Harris + NCC feature matcher.
    Harris,
    /// The reference study's SIFT feature matcher.
    Sift,
}

impl FromStr for RegistrationMethod {
    type Err = InputError;

    fn from_str(s: &str) -> Result<Self, InputError> {
        match s {
            "auto" | "phase" => Ok(Self::Phase),
            "harris" => Ok(Self::Harris),
            "sift" => Ok(Self::Sift),
            m => Err(InputError::InvalidParameter {
                name: "method".into(),
                reason: format!("{m:?}: expected \"auto\", \"phase\", \"harris\" or \"sift\""),
            }),
        }
    }
}

/// The matcher node's `params` table.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MatcherConfig {
    /// Registration method: "auto" (= "phase": phase correlation with NCC-verified
    /// candidates, the default), "harris" or "sift" (the reference study's feature matchers).
    #[serde(default, deserialize_with = "surfstream_core::choice::from_text")]
    pub method: RegistrationMethod,
    /// Lowest NCC of the overlap at the chosen shift for a link to be trusted.
    pub min_ncc: Option<f64>,
    /// A round peak whose NCC is below `min_ncc` but at least this, and well above every
    /// other candidate, is accepted and flagged in the pair's record and the verdict (0.15;
    /// 1 refuses every link below `min_ncc`).
    pub min_ncc_distinct: Option<f64>,
    /// Largest accepted deviation from the stage's nominal offset, px.
    pub max_shift_px: Option<f64>,
    /// Refine each accepted pair by Lucas-Kanade on the heights, with its covariance (true;
    /// false keeps the NCC peak's sub-pixel fit and the NCC-based weight).
    pub lucas_kanade: Option<bool>,
    /// Standard deviation of the stage positions, px: the weight of the prior in the global
    /// solve (5).
    pub stage_sigma_px: Option<f64>,
    /// A link disagreeing with the global solve by more than this (px) is removed (1).
    pub outlier_px: Option<f64>,
    /// A ground_truth.json (make_tiles.py's, or the simulated stage's truth.json; relative to
    /// the output directory): with a feature method, r and MAP against it (crate::efficiency).
    pub truth: Option<String>,
}

impl MatcherConfig {
    /// The key of [`MatcherConfig::method`] in a graph's `params` (the `stitch` verb's
    /// `--method` sets it).
    pub const METHOD_KEY: &'static str = "method";

    /// The scan's parameters, defaults where a value is not given; `out_dir` anchors a
    /// relative `truth`. Refuses an unknown method and out-of-range values.
    pub fn scan_params(&self, out_dir: &Path) -> Result<ScanParams, InputError> {
        let features = match self.method {
            RegistrationMethod::Phase => None,
            RegistrationMethod::Harris => Some(FeatureParams::for_method(FeatureMethod::Harris)),
            RegistrationMethod::Sift => Some(FeatureParams::for_method(FeatureMethod::Sift)),
        };
        let mut params = ScanParams {
            features,
            truth: self.truth.as_ref().map(|t| out_dir.join(t)),
            spill_dir: Some(out_dir.to_path_buf()),
            ..ScanParams::default()
        };
        if let Some(v) = self.min_ncc {
            params.phase.min_ncc = v;
        }
        if let Some(v) = self.min_ncc_distinct {
            params.phase.min_ncc_distinct = v;
        }
        if let Some(v) = self.max_shift_px {
            params.phase.max_shift_px = v;
        }
        if let Some(v) = self.lucas_kanade {
            params.phase.lucas_kanade = v;
        }
        params.phase.validate()?;
        for (name, value, field) in [
            (
                "stage_sigma_px",
                self.stage_sigma_px,
                &mut params.solve.stage_sigma_px,
            ),
            ("outlier_px", self.outlier_px, &mut params.solve.outlier_px),
        ] {
            if let Some(v) = value {
                if !(v.is_finite() && v > 0.0) {
                    return Err(InputError::InvalidParameter {
                        name: name.into(),
                        reason: format!("{v}: expected a number > 0"),
                    });
                }
                *field = v;
            }
        }
        Ok(params)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(method: &str) -> MatcherConfig {
        MatcherConfig {
            method: method.parse().unwrap(),
            ..MatcherConfig::default()
        }
    }

    #[test]
    fn methods_and_bad_values_are_checked() {
        let dir = Path::new("out");
        assert!(params("auto").scan_params(dir).unwrap().features.is_none());
        assert!(params("sift").scan_params(dir).unwrap().features.is_some());
        assert!("fft".parse::<RegistrationMethod>().is_err());
        let from = |t: &str| -> Result<MatcherConfig, String> {
            serde_json::from_str(t).map_err(|e| e.to_string())
        };
        assert_eq!(from("{}").unwrap().method, RegistrationMethod::Phase);
        let harris = from(r#"{"method": "harris"}"#).unwrap();
        assert_eq!(harris.method, RegistrationMethod::Harris);
        let e = from(r#"{"method": "fft"}"#).unwrap_err();
        assert!(e.contains("\"fft\": expected \"auto\", \"phase\""), "{e}");
        let mut p = params("phase");
        p.outlier_px = Some(0.0);
        assert!(p.scan_params(dir).is_err());
        p.outlier_px = Some(2.0);
        p.truth = Some("t.json".into());
        let s = p.scan_params(dir).unwrap();
        assert_eq!(s.solve.outlier_px, 2.0);
        assert_eq!(s.truth.as_deref(), Some(Path::new("out/t.json")));
    }
}
