//! The wear laws over process time: the surface worn by the laws whose rates the DEM
//! gives, at one fitted scale ([`fit_scale`]), sampled at several times ([`series`]), and
//! the plateau cut of the no-DEM baseline ([`plateau_cut`]); [`crate::predict`] runs them
//! for a finish.
//!
//! The laws ([`WearLaw`]), summed per cell of the surface (patch and guard band), each
//! re-evaluated on the surface re-closed with the media's ball after every step of at most
//! [`FieldGrid::step_depth_um`] at the deepest cell:
//!
//! - **Impacts (Finnie)**: `impacts_per_s` on the evaluated patch (the rate the machine
//!   delivers) x p(gap) x the DEM's wear per contact w(gap) ([`field::WearTable`]).
//! - **Sliding (Archard)**: an enduring contact pressed by F_n and sliding removes
//!   K/H x F_n x distance, so the volume per area and second is K/H x the sliding work per
//!   area and second (the macro run's `sliding_work_j_per_mm2_s`), whatever the real contact
//!   area. Where it goes: the ball pressed by each of the sampled normal forces sinks by its
//!   Hertz approach d(F) below its envelope, and a cell at gap g carries a pressure
//!   proportional to its interference max(d - g, 0) (an elastic foundation): the peaks
//!   under the envelope first.
//! - **Constant** (the baseline): the same depth per second on every cell within `reach_um`
//!   of the envelope, no DEM in it.
//!
//! Every law's rate is linear in the fitted scale, and the surface's evolution depends only
//! on the surface: wearing at scale s for a time t is wearing at scale 1 for s x t. The fit
//! ([`fit_scale`]) therefore wears at scale 1 until the calibration target is crossed.

use std::sync::atomic::AtomicBool;

use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};

use crate::field::{
    ball_gap_um, hertz_static_approach_um, wear_in_steps, wear_in_steps_untargeted, worn_share,
    ApproachDistribution, Extrapolation, FieldGrid, SaTarget, WearTable, WearTablePhysics,
};
use crate::setting::{Media, Workpiece};

/// The Finnie part: impacts delivered over the evaluated patch per second, each wearing
/// p(gap) x w(gap) (the DEM's table).
#[derive(Debug, Clone)]
pub struct ImpactLaw {
    pub dist: ApproachDistribution,
    pub table: WearTable,
    pub impacts_per_s: f64,
    /// The DEM's volume per impact over the evaluated patch's area, um (the table's
    /// `dem_volume_um3 / impacts / area`): with it, each impact removes that volume on any
    /// surface and the table only says where (p(gap) x w(gap), normalised over the cells).
    /// Without it the volume is the table's sum over the cells, which grows as wear flattens
    /// the surface: every cell at a small gap counts as reachable by every impact, while an
    /// impact's footprint is finite (the DEM's volume per impact stayed 10.5-13.7 um^3 over
    /// the demo's first three cycles while the table's wear per expected contact fell 10-20x).
    pub mean_depth_per_impact_um: Option<f64>,
}

impl ImpactLaw {
    /// The law whose impacts each remove the DEM's volume per impact of `table`, spread over
    /// the evaluated patch's `area_um2` ([`ImpactLaw::mean_depth_per_impact_um`]).
    pub fn volume_per_impact(
        dist: ApproachDistribution,
        table: WearTable,
        impacts_per_s: f64,
        area_um2: f64,
    ) -> Self {
        let mean = if table.impacts > 0 && area_um2 > 0.0 {
            Some(table.dem_volume_um3 / table.impacts as f64 / area_um2)
        } else {
            None
        };
        ImpactLaw {
            dist,
            table,
            impacts_per_s,
            mean_depth_per_impact_um: mean,
        }
    }
}

/// The Archard part (see the module doc).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlidingLaw {
    /// Archard's K / H, 1/Pa.
    pub k_over_h_per_pa: f64,
    /// Sliding work (integral of F_n |v_t| dt) per area of the part and second, J/(m^2 s).
    pub sliding_work_j_per_m2_s: f64,
    /// Hertz approach of the ball pressed by each sampled normal force (equal weights), um.
    pub contact_depths_um: Vec<f64>,
}

impl SlidingLaw {
    /// The law for sliding contacts pressed by `normal_forces_n` (e.g. the macro run's
    /// p10/p50/p90, equal weights) on a flat of the part's material.
    pub fn new(
        k_over_h_per_pa: f64,
        sliding_work_j_per_m2_s: f64,
        normal_forces_n: &[f64],
        media: &Media,
        part: &Workpiece,
    ) -> Self {
        SlidingLaw {
            k_over_h_per_pa,
            sliding_work_j_per_m2_s,
            contact_depths_um: normal_forces_n
                .iter()
                .map(|f| hertz_static_approach_um(media, part, *f))
                .collect(),
        }
    }

    /// Mean depth per second over the part, um/s (K/H x sliding work per area).
    pub fn mean_depth_um_per_s(&self) -> f64 {
        self.k_over_h_per_pa * self.sliding_work_j_per_m2_s * 1e6
    }

    /// The share of the load on a cell at `gap_um`, unnormalised.
    fn weight(&self, gap_um: f64) -> f64 {
        if self.contact_depths_um.is_empty() {
            return 0.0;
        }
        self.contact_depths_um
            .iter()
            .map(|d| (d - gap_um).max(0.0))
            .sum::<f64>()
            / self.contact_depths_um.len() as f64
    }
}

/// One wear law of a prediction.
#[derive(Debug, Clone)]
pub enum WearLaw {
    Impacts(ImpactLaw),
    Sliding(SlidingLaw),
    /// A constant depth per second on every cell within `reach_um` of the ball's envelope.
    Constant {
        depth_um_per_s: f64,
        reach_um: f64,
    },
}

/// The depth per second at scale 1 of every cell of `heights_um` under `laws`, into `rate`
/// (and the impact laws' part of it into `impact_rate`, when given); returns the largest.
pub fn depth_rates(
    heights_um: &[f64],
    g: FieldGrid,
    laws: &[WearLaw],
    rate: &mut [f64],
    mut impact_rate: Option<&mut [f64]>,
) -> f64 {
    let gap = ball_gap_um(heights_um, g.sampling, g.radius_um);
    rate.iter_mut().for_each(|r| *r = 0.0);
    if let Some(ir) = impact_rate.as_deref_mut() {
        ir.iter_mut().for_each(|r| *r = 0.0);
    }
    for law in laws {
        match law {
            WearLaw::Impacts(l) => {
                let d: Vec<f64> = gap
                    .iter()
                    .map(|gp| l.table.depth_per_impact_um(&l.dist, *gp))
                    .collect();
                // Normalised to the DEM's volume per impact, when given, over every cell.
                let per = match l.mean_depth_per_impact_um {
                    Some(m) => {
                        let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
                        if mean > 0.0 {
                            m / mean
                        } else {
                            0.0
                        }
                    }
                    None => 1.0,
                };
                for (k, (r, dk)) in rate.iter_mut().zip(&d).enumerate() {
                    let v = l.impacts_per_s * dk * per;
                    *r += v;
                    if let Some(ir) = impact_rate.as_deref_mut() {
                        ir[k] += v;
                    }
                }
            }
            WearLaw::Sliding(l) => {
                let w: Vec<f64> = gap.iter().map(|gp| l.weight(*gp)).collect();
                let mean = w.iter().sum::<f64>() / w.len().max(1) as f64;
                if mean > 0.0 {
                    let per = l.mean_depth_um_per_s() / mean;
                    for (r, wi) in rate.iter_mut().zip(&w) {
                        *r += per * wi;
                    }
                }
            }
            WearLaw::Constant {
                depth_um_per_s,
                reach_um,
            } => {
                for (r, gp) in rate.iter_mut().zip(&gap) {
                    if *gp <= *reach_um {
                        *r += depth_um_per_s;
                    }
                }
            }
        }
    }
    rate.iter().cloned().fold(0.0, f64::max)
}

/// The surface being worn: heights, the depth removed so far, and the impact laws' part of it.
#[derive(Debug, Clone)]
pub struct Worn {
    pub heights_um: Vec<f64>,
    pub wear_um: Vec<f64>,
    pub impact_wear_um: Vec<f64>,
}

impl Worn {
    pub fn new(original_um: &[f64]) -> Self {
        Worn {
            heights_um: original_um.to_vec(),
            wear_um: vec![0.0; original_um.len()],
            impact_wear_um: vec![0.0; original_um.len()],
        }
    }
}

/// Wears `w` for `seconds` at `scale` under `laws`, re-closing after every step of at most
/// [`FieldGrid::step_depth_um`].
pub fn advance_worn(
    w: &mut Worn,
    g: FieldGrid,
    laws: &[WearLaw],
    seconds: f64,
    scale: f64,
) -> Extrapolation {
    let rates = |h: &[f64], r: &mut [f64], ir: Option<&mut [f64]>| depth_rates(h, g, laws, r, ir);
    wear_in_steps_untargeted(
        &mut w.heights_um,
        &mut w.wear_um,
        Some(&mut w.impact_wear_um),
        g,
        seconds * scale,
        rates,
    )
    .extrapolation
}

/// Wears `heights_um` for `seconds` at `scale` under `laws` (as [`advance_worn`]); adds the
/// removed depth to `wear_um`.
pub fn advance(
    heights_um: &mut [f64],
    wear_um: &mut [f64],
    g: FieldGrid,
    laws: &[WearLaw],
    seconds: f64,
    scale: f64,
) -> Extrapolation {
    let mut w = Worn {
        heights_um: heights_um.to_vec(),
        wear_um: wear_um.to_vec(),
        impact_wear_um: vec![0.0; heights_um.len()],
    };
    let e = advance_worn(&mut w, g, laws, seconds, scale);
    heights_um.copy_from_slice(&w.heights_um);
    wear_um.copy_from_slice(&w.wear_um);
    e
}

/// The scale at which the laws bring `sa_of` (Sa of the evaluated patch) of `original_um`
/// to `target_sa_um` after `at_s` seconds: wears at scale 1 (the crossing step cut by
/// bisection) and returns used seconds / `at_s`, whether the target was reached, and the
/// extrapolation. Gives up at `max_scale`, when Sa stalls, or on `stop`.
#[allow(clippy::too_many_arguments)]
pub fn fit_scale(
    original_um: &[f64],
    g: FieldGrid,
    laws: &[WearLaw],
    at_s: f64,
    max_scale: f64,
    target_sa_um: f64,
    stop: &AtomicBool,
    mut sa_of: impl FnMut(&[f64]) -> Result<f64>,
) -> Result<(f64, bool, Extrapolation)> {
    if !(at_s.is_finite() && at_s > 0.0) {
        bail!("calibration time {at_s} s: expected seconds > 0");
    }
    let mut h = original_um.to_vec();
    let mut wear = vec![0.0; h.len()];
    let rates = |h: &[f64], r: &mut [f64], _: Option<&mut [f64]>| depth_rates(h, g, laws, r, None);
    let target = SaTarget {
        sa_um: target_sa_um,
        sa_of: &mut sa_of,
        stop,
    };
    let s = wear_in_steps(
        &mut h,
        &mut wear,
        None,
        g,
        at_s * max_scale,
        rates,
        Some(target),
    )?;
    Ok((s.used / at_s, s.reached, s.extrapolation))
}

/// The times of the series: the given ones, else the paper's 1, 2, 3, 5 and 10 min up to the
/// process time and the fifths of the process time (at least 5 times, the process time last).
pub fn series_times_s(process_time_s: f64, given: Option<&[f64]>) -> Result<Vec<f64>> {
    let mut t: Vec<f64> = match given {
        Some(g) => {
            for v in g {
                if !(v.is_finite() && *v > 0.0 && *v <= process_time_s * (1.0 + 1e-12)) {
                    bail!(
                        "--series-s {v}: expected seconds in (0, the process time {process_time_s}]"
                    );
                }
            }
            g.to_vec()
        }
        None => [60.0, 120.0, 180.0, 300.0, 600.0]
            .into_iter()
            .filter(|v| *v <= process_time_s)
            .chain((1..=5).map(|k| process_time_s * k as f64 / 5.0))
            .collect(),
    };
    t.sort_by(|a, b| a.total_cmp(b));
    t.dedup_by(|a, b| surfstream_core::record::finish::same_time_s(*a, *b));
    Ok(t)
}

/// The surface worn at each of `times_s` (ascending) from `original_um` at `scale`, handed to
/// `visit(time_s, worn)` in order; returns the extrapolation of the whole.
pub fn series(
    original_um: &[f64],
    g: FieldGrid,
    laws: &[WearLaw],
    scale: f64,
    times_s: &[f64],
    mut visit: impl FnMut(f64, &Worn) -> Result<()>,
) -> Result<Extrapolation> {
    let mut w = Worn::new(original_um);
    let mut t_now = 0.0;
    let mut total = Extrapolation::default();
    for &t in times_s {
        let e = advance_worn(&mut w, g, laws, (t - t_now).max(0.0), scale);
        total.steps += e.steps;
        total.volume_um3 += e.volume_um3;
        total.truncated_at_max_steps |= e.truncated_at_max_steps;
        t_now = t;
        visit(t, &w)?;
    }
    total.worn_cells = worn_share(&w.wear_um);
    Ok(total)
}

/// `heights_um` cut flat at `level_um` (a plateau), and the volume removed per cell area, um.
pub fn plateau_cut(heights_um: &[f64], level_um: f64) -> (Vec<f64>, f64) {
    let mut removed = 0.0;
    let z = heights_um
        .iter()
        .map(|h| {
            if *h > level_um {
                removed += h - level_um;
                level_um
            } else {
                *h
            }
        })
        .collect();
    (z, removed)
}

/// The plateau level that removes `depth_sum_um` (volume / cell area) from `heights_um`,
/// by bisection between the lowest and the highest point.
pub fn plateau_level_for_removal(heights_um: &[f64], depth_sum_um: f64) -> f64 {
    let hi = heights_um.iter().cloned().fold(f64::MIN, f64::max);
    let lo = heights_um.iter().cloned().fold(f64::MAX, f64::min);
    if depth_sum_um <= 0.0 || heights_um.is_empty() {
        return hi;
    }
    let (mut a, mut b) = (lo, hi);
    for _ in 0..80 {
        let m = 0.5 * (a + b);
        if plateau_cut(heights_um, m).1 > depth_sum_um {
            a = m;
        } else {
            b = m;
        }
    }
    0.5 * (a + b)
}

/// The plateau level at which `sa_of` of the cut surface equals `target_sa_um` (Sa falls as
/// the level comes down from the highest point): bisection; None when no cut reaches it.
pub fn plateau_level_for_sa(
    heights_um: &[f64],
    target_sa_um: f64,
    mut sa_of: impl FnMut(&[f64]) -> Result<f64>,
) -> Result<Option<f64>> {
    let hi = heights_um.iter().cloned().fold(f64::MIN, f64::max);
    let lo = heights_um.iter().cloned().fold(f64::MAX, f64::min);
    if sa_of(heights_um)? <= target_sa_um {
        return Ok(Some(hi));
    }
    if sa_of(&plateau_cut(heights_um, lo).0)? > target_sa_um {
        return Ok(None);
    }
    let (mut a, mut b) = (lo, hi);
    for _ in 0..60 {
        let m = 0.5 * (a + b);
        if sa_of(&plateau_cut(heights_um, m).0)? > target_sa_um {
            b = m;
        } else {
            a = m;
        }
    }
    Ok(Some(0.5 * (a + b)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{extrapolate, ApproachPhysics, KinematicApproach};
    use surfstream_core::{Sampling, Shape};

    fn grid(rows: usize, cols: usize, p: f64) -> FieldGrid {
        FieldGrid {
            sampling: Sampling::square(Shape::new(rows, cols), p).unwrap(),
            radius_um: 1500.0,
            step_depth_um: crate::field::STEP_DEPTH_UM,
        }
    }

    #[test]
    fn an_extrapolation_that_runs_out_of_steps_says_so() {
        let g = grid(8, 8, 1.0);
        let laws = [WearLaw::Constant {
            depth_um_per_s: 1.0,
            reach_um: 1e9,
        }];
        // 0.1 um per step: 10 s need 100 steps, 1 000 s need 10 000 (> MAX_STEPS).
        let mut w = Worn::new(&rough(8, 8));
        let e = advance_worn(&mut w, g, &laws, 10.0, 1.0);
        assert!(!e.truncated_at_max_steps, "{e:?}");
        let mut w = Worn::new(&rough(8, 8));
        let e = advance_worn(&mut w, g, &laws, 1000.0, 1.0);
        assert!(
            e.truncated_at_max_steps && e.steps == crate::field::MAX_STEPS,
            "{e:?}"
        );
        let s = series(&rough(8, 8), g, &laws, 1.0, &[10.0, 1000.0], |_, _| Ok(())).unwrap();
        assert!(s.truncated_at_max_steps, "{s:?}");
    }

    fn rough(rows: usize, cols: usize) -> Vec<f64> {
        (0..rows * cols)
            .map(|k| {
                let (i, j) = ((k / cols) as f64, (k % cols) as f64);
                (i * 0.31).sin() * (j * 0.23).cos() * 2.0 + (i * 0.07 + j * 0.11).sin() * 1.5
            })
            .collect()
    }

    fn sa(h: &[f64]) -> Result<f64> {
        let m = h.iter().sum::<f64>() / h.len() as f64;
        Ok(h.iter().map(|v| (v - m).abs()).sum::<f64>() / h.len() as f64)
    }

    #[test]
    fn a_constant_rate_where_the_ball_touches_smooths_but_one_over_the_whole_surface_does_not() {
        // The constant-wear baseline: the cells within one step of the envelope (the ones
        // the ball touches) lose peaks first and reach half the Sa; the same rate on every
        // cell only lowers the surface, and its Sa never falls. The largest scale, 30, is
        // 9 um of depth (90 steps): the rough surface spans 7 um.
        let (rows, cols) = (30, 40);
        let g = grid(rows, cols, 2.0);
        let z = rough(rows, cols);
        let (sa0, stop) = (sa(&z).unwrap(), AtomicBool::new(false));
        let touched = [WearLaw::Constant {
            depth_um_per_s: 1e-3,
            reach_um: g.step_depth_um,
        }];
        let (s, reached, e) =
            fit_scale(&z, g, &touched, 300.0, 30.0, 0.5 * sa0, &stop, sa).unwrap();
        assert!(reached && s > 0.0 && !e.truncated_at_max_steps, "{s} {e:?}");
        let mut w = Worn::new(&z);
        advance_worn(&mut w, g, &touched, 300.0, s);
        let sa_after = sa(&w.heights_um).unwrap();
        assert!(
            (sa_after - 0.5 * sa0).abs() < 0.05 * sa0,
            "{sa_after} vs {}",
            0.5 * sa0
        );
        // The lowest cell is untouched: only what the ball reaches wears.
        let lowest = (0..z.len()).min_by(|a, b| z[*a].total_cmp(&z[*b])).unwrap();
        assert_eq!(w.wear_um[lowest], 0.0);
        let everywhere = [WearLaw::Constant {
            depth_um_per_s: 1e-3,
            reach_um: 1e9,
        }];
        let (_, reached, _) =
            fit_scale(&z, g, &everywhere, 300.0, 30.0, 0.5 * sa0, &stop, sa).unwrap();
        assert!(!reached);
    }

    fn dist() -> ApproachDistribution {
        ApproachDistribution::Kinematics(KinematicApproach {
            full_speed_approach_um: 3.0,
            max_impact_angle_deg: 40.0,
            static_approach_um: 0.05,
            mean_angle_approach_um: 1.5,
        })
    }

    fn table(z: &[f64], g: FieldGrid) -> WearTable {
        let d = dist();
        let gap = ball_gap_um(z, g.sampling, g.radius_um);
        let dem: Vec<f64> = gap
            .iter()
            .map(|g| if *g < 1.5 { 0.02 } else { 0.0 })
            .collect();
        let mut t = WearTable::empty(d.max_um());
        let cell = g.sampling.pitch().cell_area_um2();
        t.add_segment(&d, &gap, &dem, 10, cell).unwrap();
        t
    }

    #[test]
    fn the_impact_law_over_time_is_the_contact_fields_extrapolation_over_impacts() {
        let (rows, cols) = (40, 50);
        let g = grid(rows, cols, 2.0);
        let z = rough(rows, cols);
        let t = table(&z, g);
        let laws = [WearLaw::Impacts(ImpactLaw {
            dist: dist(),
            table: t.clone(),
            impacts_per_s: 4.0,
            mean_depth_per_impact_um: None,
        })];
        let (mut h1, mut w1) = (z.clone(), vec![0.0; z.len()]);
        advance(&mut h1, &mut w1, g, &laws, 10.0, 0.5);
        let (mut h2, mut w2) = (z.clone(), vec![0.0; z.len()]);
        extrapolate(&mut h2, &mut w2, g, &dist(), &t, 40.0, 0.5);
        let diff = h1
            .iter()
            .zip(&h2)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(diff < 1e-9, "{diff}");
    }

    #[test]
    fn each_impact_removes_the_dems_volume_per_impact_on_a_flattened_surface_too() {
        // The table measured on the rough surface reproduces its DEM volume there; on the
        // same surface with its crests cut (a worn state) the unnormalised law wears more
        // per impact (more cells at small gaps), the normalised one the same volume.
        let (rows, cols) = (40, 50);
        let g = grid(rows, cols, 2.0);
        let z = rough(rows, cols);
        let t = table(&z, g);
        let area = (rows * cols) as f64 * g.sampling.pitch().cell_area_um2();
        let normalised = ImpactLaw::volume_per_impact(dist(), t.clone(), 1.0, area);
        let m = normalised.mean_depth_per_impact_um.unwrap();
        assert!((m * area / (t.dem_volume_um3 / t.impacts as f64) - 1.0).abs() < 1e-12);
        let plain = ImpactLaw {
            mean_depth_per_impact_um: None,
            ..normalised.clone()
        };
        let mean_rate = |law: &ImpactLaw, h: &[f64]| {
            let mut r = vec![0.0; h.len()];
            depth_rates(h, g, &[WearLaw::Impacts(law.clone())], &mut r, None);
            r.iter().sum::<f64>() / r.len() as f64
        };
        let flattened = plateau_cut(&z, 0.5).0;
        for h in [&z, &flattened] {
            assert!((mean_rate(&normalised, h) / m - 1.0).abs() < 1e-9);
        }
        let (rough_plain, flat_plain) = (mean_rate(&plain, &z), mean_rate(&plain, &flattened));
        assert!((rough_plain / m - 1.0).abs() < 1e-6, "{rough_plain} vs {m}");
        assert!(flat_plain > 1.2 * rough_plain, "{rough_plain} {flat_plain}");
    }

    #[test]
    fn the_sliding_law_removes_k_over_h_times_the_sliding_work_wherever_the_contact_is() {
        // Archard: volume per area and second = K/H x sliding work per area and second.
        let (rows, cols, p) = (30, 40, 2.0);
        let g = grid(rows, cols, p);
        let law = SlidingLaw::new(
            5e-14,
            2.0e3,
            &[0.01, 0.02, 0.04],
            &Media::default(),
            &Workpiece::default(),
        );
        let expect = 5e-14 * 2.0e3 * 1e6;
        assert!((law.mean_depth_um_per_s() - expect).abs() < 1e-18);
        for z in [vec![0.0; rows * cols], rough(rows, cols)] {
            let (mut h, mut w) = (z.clone(), vec![0.0; z.len()]);
            let e = advance(
                &mut h,
                &mut w,
                g,
                &[WearLaw::Sliding(law.clone())],
                30.0,
                2.0,
            );
            let per_cell = e.volume_um3 / (rows * cols) as f64 / (p * p);
            assert!(
                (per_cell / (expect * 60.0) - 1.0).abs() < 1e-9,
                "{per_cell} vs {}",
                expect * 60.0
            );
        }
    }

    /// z = A cos(2 pi x / L) along x.
    fn sinusoid(rows: usize, cols: usize, a: f64, l: f64, p: f64) -> Vec<f64> {
        (0..rows * cols)
            .map(|k| a * (std::f64::consts::TAU * (k % cols) as f64 * p / l).cos())
            .collect()
    }

    #[test]
    fn a_sinusoid_loses_its_peaks_first_under_the_sliding_law() {
        let (rows, cols, p, l, a) = (6, 400, 1.0, 100.0, 1.0);
        let g = grid(rows, cols, p);
        let z = sinusoid(rows, cols, a, l, p);
        let law = SlidingLaw::new(
            5e-14,
            1e3,
            &[0.02, 0.04, 0.08],
            &Media::default(),
            &Workpiece::default(),
        );
        let laws = [WearLaw::Sliding(law)];
        let stop = AtomicBool::new(false);
        let target = 0.6 * sa(&z).unwrap();
        let (scale, reached, _) = fit_scale(&z, g, &laws, 60.0, 1e12, target, &stop, sa).unwrap();
        assert!(reached && scale > 0.0);
        let (mut h, mut w) = (z.clone(), vec![0.0; z.len()]);
        advance(&mut h, &mut w, g, &laws, 60.0, scale);
        assert!((sa(&h).unwrap() / target - 1.0).abs() < 1e-6);
        // Crests (x = 0, L, ..) lost, troughs (x = L/2, ..) untouched; the profile's
        // maximum fell, its minimum stayed.
        let row = &w[2 * cols..3 * cols];
        for c in [100, 200, 300] {
            assert!(row[c] > 0.3, "crest {c}: {}", row[c]);
        }
        for c in [150, 250, 350] {
            assert_eq!(row[c], 0.0, "trough {c}");
        }
        for c in 200..250 {
            assert!(row[c] >= row[c + 1], "{c}: {} < {}", row[c], row[c + 1]);
        }
        let max = |v: &[f64]| v.iter().cloned().fold(f64::MIN, f64::max);
        let min = |v: &[f64]| v.iter().cloned().fold(f64::MAX, f64::min);
        assert!(max(&h) < max(&z) - 0.3 && (min(&h) - min(&z)).abs() < 1e-12);
    }

    #[test]
    fn the_prediction_changes_with_the_dems_contact_statistics_not_only_with_the_fit() {
        // Same calibration target; sliding forces from two macro runs: the fitted scale
        // differs (sliding work), and so does the shape of the worn surface at the same Sa
        // (the contact depth, from the forces).
        let (rows, cols, p) = (40, 60, 2.0);
        let g = grid(rows, cols, p);
        let z = rough(rows, cols);
        let stop = AtomicBool::new(false);
        let target = 0.7 * sa(&z).unwrap();
        let run = |work: f64, forces: &[f64]| {
            let laws = [WearLaw::Sliding(SlidingLaw::new(
                5e-14,
                work,
                forces,
                &Media::default(),
                &Workpiece::default(),
            ))];
            let (s, ok, _) = fit_scale(&z, g, &laws, 60.0, 1e12, target, &stop, sa).unwrap();
            assert!(ok);
            let (mut h, mut w) = (z.clone(), vec![0.0; z.len()]);
            advance(&mut h, &mut w, g, &laws, 60.0, s);
            let q = (h.iter().map(|v| v * v).sum::<f64>() / h.len() as f64
                - (h.iter().sum::<f64>() / h.len() as f64).powi(2))
            .sqrt();
            (s, q, w)
        };
        let (s1, q1, w1) = run(1e3, &[0.01, 0.02, 0.04]);
        let (s2, q2, _) = run(2e3, &[0.01, 0.02, 0.04]);
        let (_, q3, w3) = run(1e3, &[1.0, 2.0, 4.0]);
        // Twice the sliding work: half the fitted scale, the same surface.
        assert!((s2 / s1 - 0.5).abs() < 1e-6, "{s1} {s2}");
        assert!((q2 / q1 - 1.0).abs() < 1e-6);
        // 100 x the force: a deeper contact, a different surface at the same Sa.
        let diff = w1
            .iter()
            .zip(&w3)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(diff > 0.05 && (q3 - q1).abs() > 1e-3, "{diff} {q1} {q3}");
    }

    #[test]
    fn series_times_follow_the_paper_and_the_process_time() {
        assert_eq!(
            series_times_s(300.0, None).unwrap(),
            vec![60.0, 120.0, 180.0, 240.0, 300.0]
        );
        assert_eq!(
            series_times_s(600.0, None).unwrap(),
            vec![60.0, 120.0, 180.0, 240.0, 300.0, 360.0, 480.0, 600.0]
        );
        assert!(series_times_s(300.0, Some(&[400.0])).is_err());
    }

    #[test]
    fn the_series_at_its_times_is_the_advance_to_each_time() {
        let (rows, cols) = (30, 40);
        let g = grid(rows, cols, 2.0);
        let z = rough(rows, cols);
        let laws = [WearLaw::Constant {
            depth_um_per_s: 0.01,
            reach_um: 0.5,
        }];
        let mut seen = vec![];
        series(&z, g, &laws, 2.0, &[10.0, 30.0], |t, w| {
            seen.push((t, w.heights_um.clone()));
            Ok(())
        })
        .unwrap();
        let (mut h, mut w) = (z.clone(), vec![0.0; z.len()]);
        advance(&mut h, &mut w, g, &laws, 10.0, 2.0);
        assert_eq!(seen[0].1, h);
        advance(&mut h, &mut w, g, &laws, 20.0, 2.0);
        assert_eq!(seen[1].1, h);
    }

    #[test]
    fn a_plateau_cut_reaches_the_sa_and_the_removal_asked() {
        let z = rough(30, 40);
        let target = 0.5 * sa(&z).unwrap();
        let level = plateau_level_for_sa(&z, target, sa).unwrap().unwrap();
        let (cut, removed) = plateau_cut(&z, level);
        assert!((sa(&cut).unwrap() / target - 1.0).abs() < 1e-9);
        let back = plateau_level_for_removal(&z, removed);
        assert!((back - level).abs() < 1e-9, "{back} vs {level}");
        assert!(cut.iter().all(|v| *v <= level + 1e-12));
    }
}
