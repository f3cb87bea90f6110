//! Every parameter at once (`surfstream params --all`): the families computed side by side
//! (rayon::join), each value with its ISO name, unit and family.

use serde::Serialize;

use super::feature::{feature_params, FeatureParams, DEFAULT_PRUNING_PCT};
use super::functional::{AbbottCurve, FunctionalParams};
use super::spatial::{spatial_params, SpatialParams};
use super::{params, Grid, MetrologyError, Params};

/// Height of Smr(c), um above the mean plane.
pub const SMR_C_UM: f64 = 0.0;
/// Material ratio of Smc(mr), %.
pub const SMC_MR_PCT: f64 = 10.0;

/// All parameters of one surface.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AllParams {
    #[serde(flatten)]
    pub basic: Params,
    #[serde(flatten)]
    pub spatial: SpatialParams,
    #[serde(flatten)]
    pub functional: FunctionalParams,
    /// Smr(c) at c = [`SMR_C_UM`] (%).
    pub smr_c: f64,
    /// Smc(mr) at mr = [`SMC_MR_PCT`] (um about the mean).
    pub smc_mr: f64,
    #[serde(flatten)]
    pub feature: FeatureParams,
}

/// One named value: ISO name, value, unit ("" = dimensionless), family.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ParamValue {
    pub name: &'static str,
    pub value: f64,
    pub unit: &'static str,
    pub family: &'static str,
}

const fn pv(
    name: &'static str,
    value: f64,
    unit: &'static str,
    family: &'static str,
) -> ParamValue {
    ParamValue {
        name,
        value,
        unit,
        family,
    }
}

impl Params {
    /// The nine values with their units and families (the first nine of [`AllParams::named`]).
    pub fn named_values(&self) -> Vec<ParamValue> {
        let b = self;
        vec![
            pv("Sa", b.sa, "um", "height"),
            pv("Sq", b.sq, "um", "height"),
            pv("Sp", b.sp, "um", "height"),
            pv("Sv", b.sv, "um", "height"),
            pv("Sz", b.sz, "um", "height"),
            pv("Ssk", b.ssk, "", "height"),
            pv("Sku", b.sku, "", "height"),
            pv("Sdq", b.sdq, "", "hybrid"),
            pv("Sdr", b.sdr, "%", "hybrid"),
        ]
    }
}

impl AllParams {
    /// Every value in the order of ISO 25178-2's families.
    pub fn named(&self) -> Vec<ParamValue> {
        let s = &self.spatial;
        let f = &self.functional;
        let e = &self.feature;
        let mut all = self.basic.named_values();
        all.extend([
            pv("Sal", s.sal, "um", "spatial"),
            pv("Str", s.str_, "", "spatial"),
            pv("Std", s.std, "deg", "spatial"),
            pv("Sk", f.sk, "um", "functional"),
            pv("Spk", f.spk, "um", "functional"),
            pv("Svk", f.svk, "um", "functional"),
            pv("Smr1", f.smr1, "%", "functional"),
            pv("Smr2", f.smr2, "%", "functional"),
            pv("Spkx", f.spkx, "um", "functional"),
            pv("Svkx", f.svkx, "um", "functional"),
            pv("Sxp", f.sxp, "um", "functional"),
            pv("Vmp", f.vmp, "ml/m^2", "functional"),
            pv("Vmc", f.vmc, "ml/m^2", "functional"),
            pv("Vvv", f.vvv, "ml/m^2", "functional"),
            pv("Vvc", f.vvc, "ml/m^2", "functional"),
            pv("Smr(c=0um)", self.smr_c, "%", "functional"),
            pv("Smc(mr=10%)", self.smc_mr, "um", "functional"),
            pv("Spd", e.spd, "1/um^2", "feature"),
            pv("Spc", e.spc, "1/um", "feature"),
            pv("S5p", e.s5p, "um", "feature"),
            pv("S5v", e.s5v, "um", "feature"),
            pv("S10z", e.s10z, "um", "feature"),
            pv("Sda", e.sda, "um^2", "feature"),
            pv("Sha", e.sha, "um^2", "feature"),
            pv("Sdv", e.sdv, "um^3", "feature"),
            pv("Shv", e.shv, "um^3", "feature"),
        ]);
        all
    }
}

/// Every parameter of `g` (Wolf pruning at the ISO default 5 % of Sz).
pub fn all_params(g: &Grid) -> Result<AllParams, MetrologyError> {
    all_params_pruned(g, DEFAULT_PRUNING_PCT)
}

/// Every parameter of `g`, Wolf pruning at `pruning_pct` % of Sz.
pub fn all_params_pruned(g: &Grid, pruning_pct: f64) -> Result<AllParams, MetrologyError> {
    // Three phases, so that no two working sets are held at once (each is parallel inside):
    // the FFT family (see `spatial_params` for its memory), the order statistics beside the
    // height parameters, then the two segmentations (one after the other).
    let spatial = spatial_params(g);
    let (basic, curve) = rayon::join(|| params(g), || AbbottCurve::of(g));
    let feature = feature_params(g, pruning_pct);
    let curve = curve?;
    Ok(AllParams {
        basic: basic?,
        spatial: spatial?,
        functional: curve.params(),
        smr_c: curve.smr(SMR_C_UM),
        smc_mr: curve.smc(SMC_MR_PCT),
        feature: feature?,
    })
}
