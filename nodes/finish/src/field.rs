//! The contact-field wear model: where the media can reach, how much one contact wears there,
//! and the process time extrapolated over every reachable peak (docs/finish.md, "The contact
//! field").
//!
//! 1. **Contact field.** A medium of radius R lowered onto the surface rests on the envelope of
//!    the rolling ball: the morphological closing of the surface with the ball (dilation with
//!    the ball from above, then erosion). A cell lies at gap g = envelope - height below it
//!    and is reached only by an impact whose elastic approach exceeds g. The sphere is
//!    approximated by its paraboloid r^2 / 2R, which makes the closing separable and exact in
//!    O(n) per line (the lower envelope of parabolas); the paraboloid differs from the sphere
//!    by r^4 / 8R^3, 0.06 um at 200 um from the contact for R = 1.5 mm.
//! 2. **Approach distribution.** Hertz: a sphere striking at normal speed v_n approaches by
//!    (15 m v_n^2 / (16 E* sqrt(R)))^(2/5). With a macro run, each of its contact samples
//!    (the ones the micro passes draw) has its approach at the real stiffness, and p(g) is
//!    the share of them beyond g ([`ApproachPhysics::from_samples`]). Without one, the
//!    impact angle is spread uniformly over [0, 2 x the setting's angle] (mean: the setting's
//!    angle) at the media speed, and the static press of the load is a floor; P(approach > g)
//!    is the contact probability p(g).
//! 3. **Wear per contact** is measured from each DEM segment: the DEM's wear on the cells of a
//!    gap bin, per impact, divided by the bin's summed contact probability ([`WearTable`]).
//! 4. **Extrapolation.** The process delivers Gamma impacts per area and second (barrel
//!    kinematics, [`impact_rate_per_m2_s`]); over the process time the surface loses
//!    s x p(g) x w(g) per impact, re-closed after every small step, so the envelope comes
//!    down as peaks are cut and the contact set grows. The scale s (Finnie's k over the DEM's
//!    k) is fitted once to the calibration target ([`fit_scale`]).

use anyhow::{bail, Result};
use surfstream_core::Sampling;

use crate::machine::{ContactSample, Percentiles, PercentilesOf};
use crate::setting::{effective_modulus_pa, Action, Media, MediaPhysics, Workpiece};

/// The contact field's records (finish.json `contact_field`, a cycle's `contact_field`) are
/// core's; their physics is here ([`ApproachPhysics`], [`WearTablePhysics`]).
pub use surfstream_core::record::finish::{
    ApproachDistribution, Extrapolation, FieldCheck, KinematicApproach, SampledApproach, WearBin,
    WearTable,
};

/// The lower envelope of parabolas along one line: out[i] = min_j f[j] + ((i - j) pitch)^2 / 2R
/// (Felzenszwalb and Huttenlocher's distance transform; exact, O(n)).
fn parabola_envelope(f: &[f64], pitch_um: f64, radius_um: f64, out: &mut [f64]) {
    let n = f.len();
    if n == 0 {
        return;
    }
    // Work in units where the parabola is (x - q)^2: F = 2R f, x = i * pitch.
    let two_r = 2.0 * radius_um;
    let x = |i: usize| i as f64 * pitch_um;
    let g = |i: usize| two_r * f[i] + x(i) * x(i);
    let mut v = vec![0usize; n];
    let mut z = vec![0f64; n + 1];
    let mut k = 0usize;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in 1..n {
        // z[0] = -inf: the pop stops at k = 0 at the latest.
        let mut s = (g(q) - g(v[k])) / (2.0 * (x(q) - x(v[k])));
        while s <= z[k] {
            k -= 1;
            s = (g(q) - g(v[k])) / (2.0 * (x(q) - x(v[k])));
        }
        k += 1;
        v[k] = q;
        z[k] = s;
        z[k + 1] = f64::INFINITY;
    }
    k = 0;
    for (i, o) in out.iter_mut().enumerate() {
        while z[k + 1] < x(i) {
            k += 1;
        }
        let d = x(i) - x(v[k]);
        *o = f[v[k]] + d * d / two_r;
    }
}

/// min over (j, l) of z[j, l] + |(i, k) - (j, l)|^2 / 2R on a rows x cols grid (separable).
fn envelope_2d(z: &[f64], rows: usize, cols: usize, px: f64, py: f64, r: f64) -> Vec<f64> {
    let mut tmp = vec![0.0; z.len()];
    for i in 0..rows {
        parabola_envelope(
            &z[i * cols..(i + 1) * cols],
            px,
            r,
            &mut tmp[i * cols..(i + 1) * cols],
        );
    }
    let mut out = vec![0.0; z.len()];
    let mut col = vec![0.0; rows];
    let mut res = vec![0.0; rows];
    for j in 0..cols {
        for i in 0..rows {
            col[i] = tmp[i * cols + j];
        }
        parabola_envelope(&col, py, r, &mut res);
        for i in 0..rows {
            out[i * cols + j] = res[i];
        }
    }
    out
}

/// The gap of every cell below the envelope of a ball of `radius_um` rolled over the surface
/// from above (the closing with the paraboloid r^2 / 2R, minus the surface), um, >= 0.
pub fn ball_gap_um(heights_um: &[f64], at: Sampling, radius_um: f64) -> Vec<f64> {
    let (rows, cols) = (at.rows(), at.cols());
    let (pitch_x_um, pitch_y_um) = (at.pitch_x_um(), at.pitch_y_um());
    // Dilation: the ball's lowest point over (x) = max_y h(y) - |x - y|^2 / 2R.
    let neg: Vec<f64> = heights_um.iter().map(|h| -h).collect();
    let lowest: Vec<f64> = envelope_2d(&neg, rows, cols, pitch_x_um, pitch_y_um, radius_um)
        .into_iter()
        .map(|v| -v)
        .collect();
    // Erosion: the envelope at y = min_x lowest(x) + |x - y|^2 / 2R.
    let env = envelope_2d(&lowest, rows, cols, pitch_x_um, pitch_y_um, radius_um);
    env.iter()
        .zip(heights_um)
        .map(|(e, h)| (e - h).max(0.0))
        .collect()
}

/// Hertz approach of a sphere striking a flat at normal speed `v_n` (m/s), um.
pub fn hertz_approach_um(media: &Media, part: &Workpiece, v_n: f64) -> f64 {
    let e = effective_modulus_pa(media, part);
    let m = media.mass_kg();
    (15.0 * m * v_n * v_n / (16.0 * e * media.radius_m().sqrt())).powf(0.4) * 1e6
}

/// Hertz approach of a sphere pressed on a flat by `force_n` (N), um: F = 4/3 E* sqrt(R) d^(3/2).
pub fn hertz_static_approach_um(media: &Media, part: &Workpiece, force_n: f64) -> f64 {
    let e = effective_modulus_pa(media, part);
    (3.0 * force_n.max(0.0) / (4.0 * e * media.radius_m().sqrt())).powf(2.0 / 3.0) * 1e6
}

/// The approach distribution's physics (the record, [`ApproachDistribution`], is core's):
/// p(gap) made from Hertz approaches and evaluated.
pub trait ApproachPhysics: Sized {
    /// p(gap) from the barrel kinematics' assumptions (no macro run).
    fn of(media: &Media, part: &Workpiece, action: &Action, press_force_n: f64) -> Self;

    /// p(gap) from the macro run's contacts (`samples`), at the part's real stiffness.
    fn from_samples(media: &Media, part: &Workpiece, samples: &[ContactSample]) -> Self;

    /// The largest approach, um: cells deeper below the envelope are never touched.
    fn max_um(&self) -> f64;

    /// P(approach > gap): the share of the macro run's contacts, or of the impact angles,
    /// whose approach reaches `gap_um`.
    fn probability(&self, gap_um: f64) -> f64;
}

impl ApproachPhysics for ApproachDistribution {
    fn of(media: &Media, part: &Workpiece, action: &Action, press_force_n: f64) -> Self {
        let v = action.media_velocity_m_s;
        ApproachDistribution::Kinematics(KinematicApproach {
            full_speed_approach_um: hertz_approach_um(media, part, v),
            max_impact_angle_deg: (2.0 * action.impact_angle_deg).min(90.0),
            static_approach_um: hertz_static_approach_um(media, part, press_force_n),
            mean_angle_approach_um: hertz_approach_um(
                media,
                part,
                v * action.impact_angle_deg.to_radians().sin(),
            ),
        })
    }

    fn from_samples(media: &Media, part: &Workpiece, samples: &[ContactSample]) -> Self {
        let mut approaches_um: Vec<f64> = samples
            .iter()
            .map(|s| {
                let impact = hertz_approach_um(media, part, s.normal_speed_m_s);
                if s.enduring {
                    hertz_static_approach_um(media, part, s.normal_force_n).max(impact)
                } else {
                    impact
                }
            })
            .filter(|a| a.is_finite())
            .collect();
        approaches_um.sort_by(f64::total_cmp);
        let q = Percentiles::of(&approaches_um);
        ApproachDistribution::MacroSamples(SampledApproach {
            contacts: approaches_um.len(),
            impacts: samples.iter().filter(|s| !s.enduring).count(),
            p10_um: q.p10,
            p50_um: q.p50,
            p90_um: q.p90,
            max_um: approaches_um.last().copied().unwrap_or(0.0),
            approaches_um,
        })
    }

    fn max_um(&self) -> f64 {
        match self {
            ApproachDistribution::MacroSamples(sa) => sa.max_um,
            ApproachDistribution::Kinematics(k) => {
                let s = k.max_impact_angle_deg.to_radians().sin();
                (k.full_speed_approach_um * s.powf(0.8)).max(k.static_approach_um)
            }
        }
    }

    fn probability(&self, gap_um: f64) -> f64 {
        let k = match self {
            ApproachDistribution::MacroSamples(sa) => {
                let n = sa.approaches_um.len();
                if n == 0 {
                    return 0.0;
                }
                let below = sa.approaches_um.partition_point(|a| *a <= gap_um);
                return (n - below) as f64 / n as f64;
            }
            ApproachDistribution::Kinematics(k) => k,
        };
        if gap_um <= k.static_approach_um {
            return 1.0;
        }
        let a = k.full_speed_approach_um;
        if a <= 0.0 || gap_um >= a {
            return 0.0;
        }
        // approach(theta) = a sin(theta)^(4/5) >= g  <=>  sin(theta) >= (g / a)^(5/4).
        let theta_min = (gap_um / a).powf(1.25).asin();
        let theta_max = k.max_impact_angle_deg.to_radians();
        if theta_min >= theta_max {
            0.0
        } else {
            (theta_max - theta_min) / theta_max
        }
    }
}

/// Impacts of the media bed per area of the part and second, 1/(m^2 s): the contact layer
/// holds one medium per 2 sqrt(3) r^2 (hexagonal), and each strikes afresh once per diameter
/// it travels at the relative media speed (an assumption, stated in finish.json).
pub fn impact_rate_per_m2_s(media: &Media, action: &Action) -> f64 {
    let r = media.radius_m();
    let layer_per_m2 = 1.0 / (2.0 * 3f64.sqrt() * r * r);
    layer_per_m2 * action.media_velocity_m_s / (2.0 * r)
}

/// Bins of the gap: `BINS` equal bins over [0, the largest approach].
pub const BINS: usize = 12;

fn bin_of(gap_um: f64, reach_um: f64) -> Option<usize> {
    if gap_um > reach_um || reach_um <= 0.0 {
        return None;
    }
    Some(((gap_um / reach_um * BINS as f64) as usize).min(BINS - 1))
}

/// The wear table's measurement from DEM segments and its use (the record, [`WearTable`], is
/// core's).
pub trait WearTablePhysics {
    /// A table of [`BINS`] empty bins over [0, `reach_um`].
    fn empty(reach_um: f64) -> Self;

    /// Adds a DEM segment: `impacts` passes gave `dem_depth_um` on cells of gap `gap_um`
    /// (same length, the evaluated patch), each cell `cell_area_um2`.
    fn add_segment(
        &mut self,
        dist: &ApproachDistribution,
        gap_um: &[f64],
        dem_depth_um: &[f64],
        impacts: usize,
        cell_area_um2: f64,
    ) -> Result<()>;

    /// Pools `other` (binned over the same reach, cells of `cell_area_um2`) into this table,
    /// as if its segments had been added here.
    fn merge(&mut self, other: &WearTable, cell_area_um2: f64);

    /// Expected wear depth of a cell at `gap_um` per impact aimed over the patch, um.
    fn depth_per_impact_um(&self, dist: &ApproachDistribution, gap_um: f64) -> f64;
}

impl WearTablePhysics for WearTable {
    fn empty(reach_um: f64) -> Self {
        WearTable {
            bins: (0..BINS)
                .map(|b| WearBin {
                    gap_from_um: reach_um * b as f64 / BINS as f64,
                    gap_to_um: reach_um * (b + 1) as f64 / BINS as f64,
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        }
    }

    fn add_segment(
        &mut self,
        dist: &ApproachDistribution,
        gap_um: &[f64],
        dem_depth_um: &[f64],
        impacts: usize,
        cell_area_um2: f64,
    ) -> Result<()> {
        if gap_um.len() != dem_depth_um.len() {
            bail!(
                "wear table: {} gaps for {} wear depths",
                gap_um.len(),
                dem_depth_um.len()
            );
        }
        let reach = dist.max_um();
        let mut beyond = 0.0;
        for (g, w) in gap_um.iter().zip(dem_depth_um) {
            self.dem_volume_um3 += w * cell_area_um2;
            match bin_of(*g, reach) {
                Some(b) => {
                    let bin = &mut self.bins[b];
                    bin.cells += 1;
                    bin.expected_contacts += dist.probability(*g) * impacts as f64;
                    bin.dem_depth_sum_um += w;
                    bin.dem_worn_cells += usize::from(*w > 0.0);
                }
                None => beyond += w * cell_area_um2,
            }
        }
        self.dem_volume_beyond_reach_um3 += beyond;
        self.impacts += impacts;
        update_wear_per_contact(self, cell_area_um2);
        Ok(())
    }

    fn merge(&mut self, other: &WearTable, cell_area_um2: f64) {
        for (b, o) in self.bins.iter_mut().zip(&other.bins) {
            b.cells += o.cells;
            b.expected_contacts += o.expected_contacts;
            b.dem_depth_sum_um += o.dem_depth_sum_um;
            b.dem_worn_cells += o.dem_worn_cells;
        }
        self.impacts += other.impacts;
        self.dem_volume_beyond_reach_um3 += other.dem_volume_beyond_reach_um3;
        self.dem_volume_um3 += other.dem_volume_um3;
        update_wear_per_contact(self, cell_area_um2);
    }

    fn depth_per_impact_um(&self, dist: &ApproachDistribution, gap_um: f64) -> f64 {
        match bin_of(gap_um, dist.max_um()) {
            Some(b) => dist.probability(gap_um) * self.bins[b].wear_per_contact_um,
            None => 0.0,
        }
    }
}

/// Each bin's wear per expected contact, the DEM's volume beyond reach given to the
/// reachable bins in proportion to their wear, then pooled so that the mean depth per
/// impact of a bin's cells does not rise with the gap ([`WearTable::pooled_bins`]).
fn update_wear_per_contact(table: &mut WearTable, cell_area_um2: f64) {
    let inside: f64 = table.bins.iter().map(|b| b.dem_depth_sum_um).sum();
    let factor = if inside > 0.0 {
        table.dem_volume_um3 / (inside * cell_area_um2)
    } else {
        0.0
    };
    // Bins that can carry wear: cells in them and contacts reaching them. The others
    // keep 0 (as before pooling) and do not take part.
    let carrying: Vec<usize> = (0..table.bins.len())
        .filter(|&i| table.bins[i].cells > 0 && table.bins[i].expected_contacts > 0.0)
        .collect();
    let depth: Vec<f64> = carrying
        .iter()
        .map(|&i| table.bins[i].dem_depth_sum_um * factor / table.bins[i].cells as f64)
        .collect();
    let weight: Vec<f64> = carrying
        .iter()
        .map(|&i| table.bins[i].cells as f64)
        .collect();
    let pooled = non_increasing_fit(&depth, &weight);
    for b in &mut table.bins {
        b.wear_per_contact_um = 0.0;
        b.measured_wear_per_contact_um = 0.0;
        b.pooled = false;
    }
    table.pooled_bins = 0;
    for ((&i, d), (fit, in_block)) in carrying.iter().zip(&depth).zip(&pooled) {
        let b = &mut table.bins[i];
        let per_depth = b.cells as f64 / b.expected_contacts;
        b.measured_wear_per_contact_um = d * per_depth;
        b.wear_per_contact_um = fit * per_depth;
        b.pooled = *in_block;
        table.pooled_bins += usize::from(*in_block);
    }
}

/// The weighted least-squares fit of `values` that does not increase along the slice (pool
/// adjacent violators), with, per value, whether it was pooled with a neighbour. Each pooled
/// block takes its weighted mean, so the weighted sum of the values is kept exactly.
fn non_increasing_fit(values: &[f64], weights: &[f64]) -> Vec<(f64, bool)> {
    // Blocks of (weighted mean, weight, members).
    let mut blocks: Vec<(f64, f64, usize)> = Vec::with_capacity(values.len());
    for (&v, &w) in values.iter().zip(weights) {
        blocks.push((v, w, 1));
        while blocks.len() > 1 {
            let (m2, w2, n2) = blocks[blocks.len() - 1];
            let (m1, w1, n1) = blocks[blocks.len() - 2];
            if m2 <= m1 {
                break;
            }
            blocks.truncate(blocks.len() - 2);
            let w = w1 + w2;
            let m = if w > 0.0 {
                (m1 * w1 + m2 * w2) / w
            } else {
                0.5 * (m1 + m2)
            };
            blocks.push((m, w, n1 + n2));
        }
    }
    blocks
        .iter()
        .flat_map(|&(m, _, n)| std::iter::repeat_n((m, n > 1), n))
        .collect()
}

/// The check of one DEM segment against the contact field (on the evaluated patch).
pub fn check_field(
    dist: &ApproachDistribution,
    gap_um: &[f64],
    dem_depth_um: &[f64],
) -> FieldCheck {
    let n = gap_um.len();
    if n == 0 {
        return FieldCheck::default();
    }
    let reach = dist.max_um();
    let total: f64 = dem_depth_um.iter().sum();
    let within: f64 = gap_um
        .iter()
        .zip(dem_depth_um)
        .filter(|(g, _)| dist.probability(**g) > 0.0 || **g <= reach)
        .map(|(_, w)| *w)
        .sum();
    // AUC by ranks (Mann-Whitney): sort by gap, ties share their mean rank.
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|a, b| gap_um[*a].total_cmp(&gap_um[*b]));
    let worn: Vec<bool> = dem_depth_um.iter().map(|w| *w > 0.0).collect();
    let n_pos = worn.iter().filter(|w| **w).count();
    let n_neg = n - n_pos;
    let mut rank_sum_pos = 0.0;
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j + 1 < n && gap_um[idx[j + 1]] == gap_um[idx[i]] {
            j += 1;
        }
        let mean_rank = (i + j) as f64 / 2.0 + 1.0;
        for k in &idx[i..=j] {
            if worn[*k] {
                rank_sum_pos += mean_rank;
            }
        }
        i = j + 1;
    }
    // Ranks ascend with the gap: a worn cell ranked low (small gap) counts as predicted.
    let auc = if n_pos > 0 && n_neg > 0 {
        let u_pos = rank_sum_pos - (n_pos * (n_pos + 1)) as f64 / 2.0;
        1.0 - u_pos / (n_pos as f64 * n_neg as f64)
    } else {
        f64::NAN
    };
    let median = |mut v: Vec<f64>| -> f64 {
        if v.is_empty() {
            return f64::NAN;
        }
        v.sort_by(|a, b| a.total_cmp(b));
        v[v.len() / 2]
    };
    FieldCheck {
        auc_gap_predicts_worn: auc,
        dem_volume_within_reach: if total > 0.0 {
            within / total
        } else {
            f64::NAN
        },
        cells_within_reach: gap_um.iter().filter(|g| **g <= reach).count() as f64 / n as f64,
        dem_worn_cells: n_pos as f64 / n as f64,
        median_gap_worn_um: median(
            gap_um
                .iter()
                .zip(&worn)
                .filter(|(_, w)| **w)
                .map(|(g, _)| *g)
                .collect(),
        ),
        median_gap_all_um: median(gap_um.to_vec()),
    }
}

/// The surface and its geometry for the extrapolation.
#[derive(Debug, Clone, Copy)]
pub struct FieldGrid {
    pub sampling: Sampling,
    pub radius_um: f64,
    /// Deepest wear of one step, um ([`step_depth_um`]).
    pub step_depth_um: f64,
}

/// The step of the extrapolation for contacts that reach `reach_um` below the envelope:
/// [`STEP_DEPTH_UM`], or half the reach when that is smaller (the macro run's gentle
/// contacts reach some 0.1 um: a step deeper than the reach would cut below where any
/// contact goes before the envelope is re-closed).
pub fn step_depth_um(reach_um: f64) -> f64 {
    if reach_um.is_finite() && reach_um > 0.0 {
        STEP_DEPTH_UM.min(0.5 * reach_um)
    } else {
        STEP_DEPTH_UM
    }
}

/// Deepest wear of one step of the extrapolation, um: small against the approach (about
/// 1 um) so that a cut peak lets its neighbours into contact before it is cut further.
pub const STEP_DEPTH_UM: f64 = 0.1;
/// Most steps of one extrapolation (a guard; the demo takes about sixty).
pub const MAX_STEPS: usize = 5_000;
/// [`wear_to_target`] gives up when Sa fell by less than this share of the way to the
/// target over the last [`STALL_STEPS`] steps (the surface wears without getting smoother,
/// e.g. a form the ball follows).
pub const STALL_SHARE: f64 = 0.002;
pub const STALL_STEPS: usize = 100;

/// The depth one impact wears at each cell of the current surface (re-closed with the ball),
/// into `rate`; returns the largest.
fn wear_rates(
    heights_um: &[f64],
    g: FieldGrid,
    dist: &ApproachDistribution,
    table: &WearTable,
    rate: &mut [f64],
) -> f64 {
    let gap = ball_gap_um(heights_um, g.sampling, g.radius_um);
    let mut max_rate: f64 = 0.0;
    for (r, gp) in rate.iter_mut().zip(&gap) {
        *r = table.depth_per_impact_um(dist, *gp);
        max_rate = max_rate.max(*r);
    }
    max_rate
}

/// Where a stepped wear stops before its budget is spent: when `sa_of` (Sa of the evaluated
/// patch of a surface, um) falls to `sa_um` (the step that crosses it cut by bisection: within
/// a step the wear is linear), when Sa stalls ([`STALL_SHARE`] over [`STALL_STEPS`]), or when
/// `stop` is set (Ctrl-C).
pub struct SaTarget<'a, E = anyhow::Error> {
    pub sa_um: f64,
    pub sa_of: &'a mut dyn FnMut(&[f64]) -> std::result::Result<f64, E>,
    pub stop: &'a std::sync::atomic::AtomicBool,
}

/// What [`wear_in_steps`] did: the budget used, the extrapolation, the target reached.
pub struct Stepped {
    pub used: f64,
    pub extrapolation: Extrapolation,
    pub reached: bool,
}

/// The one stepping scheme of every prediction. Each step takes the depth rates of the
/// current surface (`rates` fills them per unit of budget, re-closing the surface, and
/// returns the largest; a second slice, when given, takes the impacts' share), wears for as
/// much budget (impacts or seconds) as takes the fastest cell [`FieldGrid::step_depth_um`]
/// deep, and adds the depth to `wear_um` (and the impacts' to `impact_wear_um`). It ends when
/// `budget` is spent, nothing wears, [`MAX_STEPS`] are taken, or at the `target`.
/// Without a target nothing in it can fail: the caller names `E` as
/// [`std::convert::Infallible`] ([`wear_in_steps_untargeted`]).
pub fn wear_in_steps<E>(
    heights_um: &mut [f64],
    wear_um: &mut [f64],
    mut impact_wear_um: Option<&mut [f64]>,
    g: FieldGrid,
    budget: f64,
    mut rates: impl FnMut(&[f64], &mut [f64], Option<&mut [f64]>) -> f64,
    mut target: Option<SaTarget<'_, E>>,
) -> std::result::Result<Stepped, E> {
    let mut left = budget;
    let mut used = 0.0;
    let mut out = Extrapolation::default();
    let cell = g.sampling.pitch().cell_area_um2();
    let mut rate = vec![0.0; heights_um.len()];
    let mut impact_rate = impact_wear_um.as_ref().map(|_| vec![0.0; heights_um.len()]);
    let mut trial = if target.is_some() {
        vec![0.0; heights_um.len()]
    } else {
        Vec::new()
    };
    let (sa_start, mut reached) = match target.as_mut() {
        Some(t) => {
            let sa = (t.sa_of)(heights_um)?;
            (sa, sa <= t.sa_um)
        }
        None => (f64::NAN, false),
    };
    let mut sa_mark = sa_start;
    while !reached && left > 0.0 && out.steps < MAX_STEPS {
        if let Some(t) = &target {
            if t.stop.load(std::sync::atomic::Ordering::Relaxed) {
                break;
            }
        }
        let max_rate = rates(heights_um, &mut rate, impact_rate.as_deref_mut());
        if max_rate <= 0.0 {
            break;
        }
        let mut n = left.min(g.step_depth_um / max_rate);
        let mut sa_step = f64::NAN;
        if let Some(t) = target.as_mut() {
            let worn = |n: f64, trial: &mut [f64]| {
                for ((o, h), r) in trial.iter_mut().zip(heights_um.iter()).zip(&rate) {
                    *o = h - n * r;
                }
            };
            worn(n, &mut trial);
            sa_step = (t.sa_of)(&trial)?;
            if sa_step <= t.sa_um {
                let (mut a, mut b) = (0.0, n);
                for _ in 0..30 {
                    let m = 0.5 * (a + b);
                    worn(m, &mut trial);
                    if (t.sa_of)(&trial)? > t.sa_um {
                        a = m;
                    } else {
                        b = m;
                    }
                }
                n = b;
                reached = true;
            }
        }
        for ((h, w), r) in heights_um.iter_mut().zip(wear_um.iter_mut()).zip(&rate) {
            let d = n * r;
            *h -= d;
            *w += d;
            out.volume_um3 += d * cell;
        }
        if let (Some(iw), Some(ir)) = (impact_wear_um.as_deref_mut(), &impact_rate) {
            for (w, r) in iw.iter_mut().zip(ir) {
                *w += n * r;
            }
        }
        left -= n;
        used += n;
        out.steps += 1;
        if let Some(t) = &target {
            if out.steps % STALL_STEPS == 0 {
                if sa_mark - sa_step < STALL_SHARE * (sa_start - t.sa_um) {
                    break;
                }
                sa_mark = sa_step;
            }
        }
    }
    // A fit's budget is a bound, not a time to reach: only a plain extrapolation is truncated.
    out.truncated_at_max_steps = target.is_none() && left > 0.0 && out.steps >= MAX_STEPS;
    out.worn_cells = worn_share(wear_um);
    Ok(Stepped {
        used,
        extrapolation: out,
        reached,
    })
}

/// [`wear_in_steps`] to the end of `budget`, with no Sa target: infallible by its type.
pub fn wear_in_steps_untargeted(
    heights_um: &mut [f64],
    wear_um: &mut [f64],
    impact_wear_um: Option<&mut [f64]>,
    g: FieldGrid,
    budget: f64,
    rates: impl FnMut(&[f64], &mut [f64], Option<&mut [f64]>) -> f64,
) -> Stepped {
    let none: Option<SaTarget<'_, std::convert::Infallible>> = None;
    match wear_in_steps(heights_um, wear_um, impact_wear_um, g, budget, rates, none) {
        Ok(s) => s,
        Err(never) => match never {},
    }
}

/// Share of the cells worn at all.
pub fn worn_share(wear_um: &[f64]) -> f64 {
    wear_um.iter().filter(|w| **w > 0.0).count() as f64 / wear_um.len().max(1) as f64
}

/// Wears `heights_um` by `impacts` impacts (each spread over the whole grid by the contact
/// field) at scale `scale`, re-closing after each step of at most [`FieldGrid::step_depth_um`]
/// ([`wear_in_steps`]). Adds the removed depth to `wear_um`.
pub fn extrapolate(
    heights_um: &mut [f64],
    wear_um: &mut [f64],
    g: FieldGrid,
    dist: &ApproachDistribution,
    table: &WearTable,
    impacts: f64,
    scale: f64,
) -> Extrapolation {
    let rates = |h: &[f64], r: &mut [f64], _: Option<&mut [f64]>| wear_rates(h, g, dist, table, r);
    wear_in_steps_untargeted(heights_um, wear_um, None, g, impacts * scale, rates).extrapolation
}

/// Wears `heights_um` with the contact field, step by step as [`extrapolate`] at scale 1,
/// until `sa_of` (Sa of the evaluated patch of a surface, um) falls to `target_sa_um` or
/// `max_impacts` are spent ([`SaTarget`]). Returns the impacts used (the fitted scale is their
/// ratio to the process's impacts), the extrapolation, and whether the target was reached.
/// Running [`extrapolate`] from the same surface with scale = used / N over N impacts takes
/// the same steps. A set `stop` (Ctrl-C) ends it early, not reached.
#[allow(clippy::too_many_arguments)]
pub fn wear_to_target(
    heights_um: &mut [f64],
    wear_um: &mut [f64],
    g: FieldGrid,
    dist: &ApproachDistribution,
    table: &WearTable,
    max_impacts: f64,
    target_sa_um: f64,
    stop: &std::sync::atomic::AtomicBool,
    mut sa_of: impl FnMut(&[f64]) -> Result<f64>,
) -> Result<(f64, Extrapolation, bool)> {
    let rates = |h: &[f64], r: &mut [f64], _: Option<&mut [f64]>| wear_rates(h, g, dist, table, r);
    let target = SaTarget {
        sa_um: target_sa_um,
        sa_of: &mut sa_of,
        stop,
    };
    let s = wear_in_steps(
        heights_um,
        wear_um,
        None,
        g,
        max_impacts,
        rates,
        Some(target),
    )?;
    Ok((s.used, s.extrapolation, s.reached))
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::Shape;

    #[test]
    fn the_envelope_of_parabolas_matches_brute_force() {
        let f: Vec<f64> = (0..57)
            .map(|i| ((i * 37 % 11) as f64 - 5.0) * 0.7 + (i as f64 * 0.3).sin())
            .collect();
        let mut out = vec![0.0; f.len()];
        parabola_envelope(&f, 2.5, 40.0, &mut out);
        for (i, o) in out.iter().enumerate() {
            let b = (0..f.len())
                .map(|j| {
                    let d = (i as f64 - j as f64) * 2.5;
                    f[j] + d * d / 80.0
                })
                .fold(f64::INFINITY, f64::min);
            assert!((o - b).abs() < 1e-9, "{i}: {o} vs {b}");
        }
    }

    #[test]
    fn sampled_contacts_give_the_share_of_them_that_reach_each_gap() {
        let (media, part) = (Media::default(), Workpiece::default());
        let impact = |v: f64| ContactSample {
            normal_speed_m_s: v,
            tangential_speed_m_s: 0.1,
            normal_force_n: 0.0,
            duration_s: 1e-4,
            enduring: false,
        };
        let pressed = ContactSample {
            normal_speed_m_s: 0.0,
            normal_force_n: 0.05,
            enduring: true,
            ..impact(0.0)
        };
        let samples = [impact(0.01), impact(0.1), impact(1.0), pressed];
        let d = ApproachDistribution::from_samples(&media, &part, &samples);
        let a = |v: f64| hertz_approach_um(&media, &part, v);
        let e = effective_modulus_pa(&media, &part);
        let static_um = (3.0 * 0.05 / (4.0 * e * media.radius_m().sqrt())).powf(2.0 / 3.0) * 1e6;
        let mut expected = [a(0.01), a(0.1), a(1.0), static_um];
        expected.sort_by(f64::total_cmp);
        assert_eq!(d.max_um(), expected[3]);
        // Just below each approach, one contact more reaches than just above it.
        for (k, x) in expected.iter().enumerate() {
            let above = (3 - k) as f64 / 4.0;
            assert_eq!(d.probability(x * 0.999), above + 0.25, "{k}");
            assert_eq!(d.probability(x * 1.001), above, "{k}");
        }
        assert_eq!(d.probability(0.0), 1.0);
        let s = d.sampled().unwrap();
        assert_eq!((s.contacts, s.impacts), (4, 3));
        // The reach sets the step: half of it when it is under twice the default step.
        assert_eq!(step_depth_um(0.06), 0.03);
        assert_eq!(step_depth_um(3.0), STEP_DEPTH_UM);
    }

    #[test]
    fn a_flat_surface_has_a_uniform_contact_field() {
        let (rows, cols) = (40, 50);
        let z = vec![3.25; rows * cols];
        let at = Sampling::new(Shape::new(rows, cols), 1.0, 1.5).unwrap();
        let gap = ball_gap_um(&z, at, 1500.0);
        assert!(gap.iter().all(|g| g.abs() < 1e-9), "{gap:?}");
        let d = ApproachDistribution::Kinematics(KinematicApproach {
            full_speed_approach_um: 2.0,
            max_impact_angle_deg: 40.0,
            static_approach_um: 0.05,
            mean_angle_approach_um: 1.0,
        });
        assert!(gap.iter().all(|g| d.probability(*g) == 1.0));
    }

    #[test]
    fn a_sinusoid_is_touched_at_its_crests_first_and_bridged_over_its_troughs() {
        // z = A cos(2 pi x / L) along x, constant along y: the ball (curvature 1/R far below
        // A (2 pi / L)^2) rests on the flanks next to neighbouring crests and bridges the
        // troughs. Reference: the closing of the profile by brute force (O(n^2)).
        let (rows, cols, p) = (8, 400, 1.0);
        let (a, l, r) = (1.0, 100.0, 1500.0);
        let prof: Vec<f64> = (0..cols)
            .map(|c| a * (std::f64::consts::TAU * c as f64 * p / l).cos())
            .collect();
        let z: Vec<f64> = (0..rows * cols).map(|k| prof[k % cols]).collect();
        let gap = ball_gap_um(&z, Sampling::square(Shape::new(rows, cols), p).unwrap(), r);
        let par = |i: usize, j: usize| {
            let d = (i as f64 - j as f64) * p;
            d * d / (2.0 * r)
        };
        let lowest: Vec<f64> = (0..cols)
            .map(|i| {
                (0..cols)
                    .map(|j| prof[j] - par(i, j))
                    .fold(f64::MIN, f64::max)
            })
            .collect();
        let env: Vec<f64> = (0..cols)
            .map(|j| {
                (0..cols)
                    .map(|i| lowest[i] + par(i, j))
                    .fold(f64::MAX, f64::min)
            })
            .collect();
        let row = &gap[3 * cols..4 * cols];
        for c in 0..cols {
            assert!(
                (row[c] - (env[c] - prof[c])).abs() < 1e-9,
                "{c}: {} vs {}",
                row[c],
                env[c] - prof[c]
            );
        }
        for c in [100, 200, 300] {
            assert!(row[c].abs() < 1e-9, "crest {c}: {}", row[c]);
        }
        // The trough lies below the chord over the crests: at least 2A - (L/2)^2 / 2R.
        let chord = 2.0 * a - (l / 2.0) * (l / 2.0) / (2.0 * r);
        for c in [150, 250] {
            assert!(row[c] >= chord, "trough {c}: {} vs {chord}", row[c]);
        }
        // Contact probability falls from crest to trough.
        let d = ApproachDistribution::Kinematics(KinematicApproach {
            full_speed_approach_um: 2.5,
            max_impact_angle_deg: 40.0,
            static_approach_um: 0.05,
            mean_angle_approach_um: 1.0,
        });
        let p_of = |c: usize| d.probability(row[c]);
        assert_eq!(p_of(200), 1.0);
        for c in 200..250 {
            assert!(p_of(c) >= p_of(c + 1), "{c}: {} < {}", p_of(c), p_of(c + 1));
        }
        assert!(p_of(250) < 0.5, "{}", p_of(250));
    }

    #[test]
    fn hertz_approach_of_the_papers_media_is_about_one_and_a_half_micrometres() {
        // docs/finish.md: 0.537 m/s normal (1.571 m/s at 20 deg) gives 1.63 um.
        let a = hertz_approach_um(&Media::default(), &Workpiece::default(), 0.537);
        assert!((a - 1.63).abs() < 0.02, "{a}");
    }

    fn rough(rows: usize, cols: usize) -> Vec<f64> {
        (0..rows * cols)
            .map(|k| {
                let (i, j) = ((k / cols) as f64, (k % cols) as f64);
                (i * 0.31).sin() * (j * 0.23).cos() * 2.0 + (i * 0.07 + j * 0.11).sin() * 1.5
            })
            .collect()
    }

    /// A rough surface, its gaps under a ball of `r` um and a kinematic approach of 3 um at most.
    fn rough_field(
        rows: usize,
        cols: usize,
        p: f64,
        r: f64,
    ) -> (Vec<f64>, Vec<f64>, ApproachDistribution) {
        let z = rough(rows, cols);
        let gap = ball_gap_um(&z, Sampling::square(Shape::new(rows, cols), p).unwrap(), r);
        let d = ApproachDistribution::Kinematics(KinematicApproach {
            full_speed_approach_um: 3.0,
            max_impact_angle_deg: 40.0,
            static_approach_um: 0.05,
            mean_angle_approach_um: 1.5,
        });
        (z, gap, d)
    }

    #[test]
    fn the_table_reproduces_the_dem_volume_and_the_extrapolation_conserves_it() {
        let (rows, cols, p, r) = (60, 70, 2.0, 1500.0);
        let (z, gap, d) = rough_field(rows, cols, p, r);
        // A "DEM" map: wear where the gap is small, some beyond reach too.
        let dem: Vec<f64> = gap
            .iter()
            .enumerate()
            .map(|(k, g)| {
                if *g < 1.0 || k % 97 == 0 {
                    0.01 * (1.0 + (k % 7) as f64)
                } else {
                    0.0
                }
            })
            .collect();
        let mut t = WearTable::empty(d.max_um());
        t.add_segment(&d, &gap, &dem, 17, p * p).unwrap();
        let dem_volume: f64 = dem.iter().sum::<f64>() * p * p;
        assert!(t.dem_volume_beyond_reach_um3 > 0.0);
        // The table evaluated on the DEM's own surface and impact count gives its volume.
        let model_volume: f64 = gap
            .iter()
            .map(|g| 17.0 * t.depth_per_impact_um(&d, *g))
            .sum::<f64>()
            * p
            * p;
        assert!(
            (model_volume / dem_volume - 1.0).abs() < 1e-12,
            "{model_volume} vs {dem_volume}"
        );
        // Two segments merged as tables are the two added to one table.
        let mut both = WearTable::empty(d.max_um());
        both.add_segment(&d, &gap, &dem, 17, p * p).unwrap();
        both.add_segment(&d, &gap, &dem, 17, p * p).unwrap();
        let mut merged = t.clone();
        merged.merge(&t, p * p);
        for (a, b) in merged.bins.iter().zip(&both.bins) {
            assert!(
                (a.wear_per_contact_um - b.wear_per_contact_um).abs()
                    <= 1e-12 * b.wear_per_contact_um.abs()
            );
        }
        assert_eq!(merged.impacts, both.impacts);
        // The extrapolation removes exactly the depth it records, and wears peaks first.
        let mut h = z.clone();
        let mut wear = vec![0.0; h.len()];
        let g = FieldGrid {
            sampling: Sampling::square(Shape::new(rows, cols), p).unwrap(),
            radius_um: r,
            step_depth_um: STEP_DEPTH_UM,
        };
        let e = extrapolate(&mut h, &mut wear, g, &d, &t, 40.0, 1.0);
        let lost: f64 = z.iter().zip(&h).map(|(a, b)| a - b).sum::<f64>() * p * p;
        let recorded: f64 = wear.iter().sum::<f64>() * p * p;
        assert!((lost / e.volume_um3 - 1.0).abs() < 1e-12 && (recorded / lost - 1.0).abs() < 1e-12);
        assert!(e.steps > 1, "{e:?}");
        // Step-wise re-closing: the first step's volume at the first surface equals the table's.
        let hi = z.iter().cloned().fold(f64::MIN, f64::max);
        let top = z.iter().position(|v| *v == hi).unwrap();
        assert!(wear[top] > 0.0);
    }

    #[test]
    fn the_approach_record_names_its_source_and_holds_only_its_numbers() {
        let kin = ApproachDistribution::Kinematics(KinematicApproach {
            full_speed_approach_um: 3.0,
            max_impact_angle_deg: 40.0,
            static_approach_um: 0.05,
            mean_angle_approach_um: 1.5,
        });
        let sampled = ApproachDistribution::MacroSamples(SampledApproach {
            contacts: 10,
            impacts: 4,
            p10_um: 0.1,
            p50_um: 0.4,
            p90_um: 2.0,
            max_um: 5.0,
            approaches_um: Vec::new(),
        });
        let k = serde_json::to_value(&kin).unwrap();
        assert_eq!(k["source"], "kinematics");
        assert!(k.get("p50_um").is_none());
        let m = serde_json::to_value(&sampled).unwrap();
        assert_eq!(m["source"], "macro-samples");
        assert!(m.get("full_speed_approach_um").is_none() && m.get("sampled").is_none());
        for v in [&kin, &sampled] {
            let back: ApproachDistribution =
                serde_json::from_value(serde_json::to_value(v).unwrap()).unwrap();
            assert_eq!(&back, v);
        }
        // Records written before the source was named read as what they were.
        let old_sampled = serde_json::json!({"full_speed_approach_um": 0.0, "max_impact_angle_deg": 0.0,
            "static_approach_um": 0.0, "mean_angle_approach_um": 0.0,
            "sampled": {"contacts": 10, "impacts": 4, "p10_um": 0.1, "p50_um": 0.4, "p90_um": 2.0, "max_um": 5.0}});
        assert_eq!(
            serde_json::from_value::<ApproachDistribution>(old_sampled).unwrap(),
            sampled
        );
        let old_kin = serde_json::json!({"full_speed_approach_um": 3.0, "max_impact_angle_deg": 40.0,
            "static_approach_um": 0.05, "mean_angle_approach_um": 1.5});
        assert_eq!(
            serde_json::from_value::<ApproachDistribution>(old_kin).unwrap(),
            kin
        );
        let e =
            serde_json::from_value::<ApproachDistribution>(serde_json::json!({"source": "guess"}))
                .unwrap_err()
                .to_string();
        assert!(e.contains("guess") && e.contains("macro-samples"), "{e}");
    }

    #[test]
    fn the_monotone_fit_pools_only_violators_and_keeps_the_weighted_sum() {
        let fit = non_increasing_fit(
            &[5.0, 3.0, 4.0, 1.0, 2.0, 2.0],
            &[1.0, 1.0, 3.0, 2.0, 1.0, 1.0],
        );
        let values: Vec<f64> = fit.iter().map(|f| f.0).collect();
        let pooled: Vec<bool> = fit.iter().map(|f| f.1).collect();
        // 3 and 4 pool to (3 + 12) / 4; 1, 2, 2 pool to (2 + 2 + 2) / 4.
        let want = [5.0, 3.75, 3.75, 1.5, 1.5, 1.5];
        for (v, w) in values.iter().zip(want) {
            assert!((v - w).abs() < 1e-12, "{values:?}");
        }
        assert_eq!(pooled, [false, true, true, true, true, true]);
        // Already non-increasing: unchanged, nothing pooled.
        let same = non_increasing_fit(&[4.0, 4.0, 2.0, 0.0], &[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(
            same,
            [(4.0, false), (4.0, false), (2.0, false), (0.0, false)]
        );
        assert!(non_increasing_fit(&[], &[]).is_empty());
    }

    #[test]
    fn a_table_whose_deep_cells_wore_more_is_pooled_and_keeps_the_dem_volume() {
        let (rows, cols, p, r) = (60, 70, 2.0, 1500.0);
        let (_, gap, d) = rough_field(rows, cols, p, r);
        // A noisy "DEM": the deepest reachable cells wore twice the crests.
        let reach = d.max_um();
        let dem: Vec<f64> = gap
            .iter()
            .map(|g| {
                if *g > 0.75 * reach && *g <= reach {
                    0.02
                } else if *g < 0.3 {
                    0.01
                } else {
                    0.0
                }
            })
            .collect();
        let mut t = WearTable::empty(reach);
        t.add_segment(&d, &gap, &dem, 17, p * p).unwrap();
        assert!(t.pooled_bins > 0, "{t:?}");
        let per_impact: Vec<f64> = t
            .bins
            .iter()
            .filter(|b| b.cells > 0 && b.expected_contacts > 0.0)
            .map(|b| b.wear_per_contact_um * b.expected_contacts / b.cells as f64)
            .collect();
        assert!(
            per_impact.windows(2).all(|w| w[1] <= w[0] * (1.0 + 1e-12)),
            "{per_impact:?}"
        );
        // The measured values stay on record and differ where pooled.
        assert!(t
            .bins
            .iter()
            .any(|b| b.pooled && b.measured_wear_per_contact_um != b.wear_per_contact_um));
        let dem_volume: f64 = dem.iter().sum::<f64>() * p * p;
        let model_volume: f64 = gap
            .iter()
            .map(|g| 17.0 * t.depth_per_impact_um(&d, *g))
            .sum::<f64>()
            * p
            * p;
        assert!(
            (model_volume / dem_volume - 1.0).abs() < 1e-12,
            "{model_volume} vs {dem_volume}"
        );
    }

    #[test]
    fn wearing_to_a_target_stops_at_it_and_matches_the_plain_extrapolation() {
        let (rows, cols, p, r) = (50, 60, 2.0, 1500.0);
        let z = rough(rows, cols);
        let gap = ball_gap_um(&z, Sampling::square(Shape::new(rows, cols), p).unwrap(), r);
        let d = ApproachDistribution::Kinematics(KinematicApproach {
            full_speed_approach_um: 3.0,
            max_impact_angle_deg: 40.0,
            static_approach_um: 0.05,
            mean_angle_approach_um: 1.5,
        });
        let dem: Vec<f64> = gap
            .iter()
            .map(|g| if *g < 1.5 { 0.02 } else { 0.0 })
            .collect();
        let mut t = WearTable::empty(d.max_um());
        t.add_segment(&d, &gap, &dem, 10, p * p).unwrap();
        let sa = |h: &[f64]| -> Result<f64> {
            let m = h.iter().sum::<f64>() / h.len() as f64;
            Ok(h.iter().map(|v| (v - m).abs()).sum::<f64>() / h.len() as f64)
        };
        let sa0 = sa(&z).unwrap();
        let target = 0.6 * sa0;
        let g = FieldGrid {
            sampling: Sampling::square(Shape::new(rows, cols), p).unwrap(),
            radius_um: r,
            step_depth_um: STEP_DEPTH_UM,
        };
        let mut h = z.clone();
        let mut w = vec![0.0; h.len()];
        let stop = std::sync::atomic::AtomicBool::new(false);
        let (used, _, ok) =
            wear_to_target(&mut h, &mut w, g, &d, &t, 1e9, target, &stop, sa).unwrap();
        assert!(ok, "target not reached");
        assert!(
            (sa(&h).unwrap() / target - 1.0).abs() < 1e-6,
            "{} vs {target}",
            sa(&h).unwrap()
        );
        // The plain extrapolation with the fitted impacts lands on the same surface.
        let mut h2 = z.clone();
        let mut w2 = vec![0.0; h2.len()];
        extrapolate(&mut h2, &mut w2, g, &d, &t, used, 1.0);
        let diff = h
            .iter()
            .zip(&h2)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(diff < 1e-9, "{diff}");
    }
}
