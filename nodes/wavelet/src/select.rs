//! The paper's selections of the wavelet base and the decomposition level, and the bias that
//! pooling introduces.
//!
//! * **Level** (paper Fig. 13): the level `l` in `1..=max` that minimises the approximation's
//!   energy proportion `E(cA_l) / (E(cA_l) + sum_{k<=l} E(cH_k, cV_k, cD_k))`, `E` = sum of
//!   squares, computed on the map after filling its holes ([`crate::fill_invalid`]) and
//!   subtracting the least-squares plane of its valid pixels. Without the levelling the mean
//!   height holds nearly all the energy at every level and the rule picks noise.
//! * **Base** (paper eq. 10): the base whose reconstruction `waverec2(wavedec2(x))` has the
//!   smallest RMSE against `x` over the valid pixels. Every base here is orthogonal, so that
//!   RMSE is floating-point round-off (~1e-15 relative; ~1e-12 for the sym / coif filters
//!   PyWavelets stores to 12-13 digits): the rule ranks round-off, not the fitness of the base
//!   for the surface. It is implemented because the paper uses it, and reported with its
//!   numbers so a reader can see that.
//! * **Pooling bias**: mean height, Sa, Sq and Sz of the map before and after pooling
//!   (max pooling lifts the mean and shrinks the valleys).

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
/// The summary types are the run record's ([`surfstream_core::record`]), which report.html
/// reads back; they keep their names here.
pub use surfstream_core::record::{
    BaseRmse, EnergyPoint, HeightStats, PoolingBias, SeparationChoices,
};

use crate::error::{check_raster, Result, WaveletError};
use crate::separate::{default_level, fill_invalid};
use crate::wavelet::{dwt_max_level, Mode, Wavelet};
use crate::{wavedec2, waverec2};

/// The approximation's energy proportion at every level `1..=dwt_max_level` of the
/// plane-levelled, hole-filled map.
pub fn energy_curve(
    heights: &[f32],
    rows: usize,
    cols: usize,
    wavelet: &Wavelet,
    mode: Mode,
) -> Result<Vec<EnergyPoint>> {
    // Errors on empty / too small maps, like the separation.
    default_level(rows, cols, wavelet, Some(1))?;
    let max = dwt_max_level(rows.min(cols), wavelet.filter_len());
    let mut a = levelled(heights, rows, cols)?;
    let (mut r, mut c) = (rows, cols);
    let mut detail_energy = 0.0f64;
    let mut curve = Vec::with_capacity(max);
    for level in 1..=max {
        // wavedec2 is iterated single-level dwt2 (PyWavelets' definition), so one level at a
        // time on the previous approximation gives every level's bands in one sweep.
        let co = wavedec2(&a, r, c, wavelet, mode, 1)?;
        for d in &co.details {
            detail_energy += energy(d.h.values()) + energy(d.v.values()) + energy(d.d.values());
        }
        let ea = energy(co.approx.values());
        let total = ea + detail_energy;
        curve.push(EnergyPoint {
            level,
            approx_energy_fraction: if total > 0.0 { ea / total } else { 0.0 },
        });
        (r, c) = (co.approx.rows(), co.approx.cols());
        a = co.approx.into_values();
    }
    Ok(curve)
}

/// The level of minimal approximation energy proportion (ties: the lower level).
pub fn level_by_min_energy(curve: &[EnergyPoint]) -> Option<usize> {
    curve
        .iter()
        .fold(None::<&EnergyPoint>, |best, p| match best {
            Some(b) if b.approx_energy_fraction <= p.approx_energy_fraction => Some(b),
            _ => Some(p),
        })
        .map(|p| p.level)
}

/// Eq. 10 for every base, each at `level` (default: [`crate::DEFAULT_LEVEL`]) clamped to what
/// the map supports for that base; bases the map is too small for are left out. Sorted by
/// RMSE, smallest (the paper's choice) first.
pub fn rmse_per_base(
    heights: &[f32],
    rows: usize,
    cols: usize,
    mode: Mode,
    level: Option<usize>,
) -> Result<Vec<BaseRmse>> {
    check_raster(heights.len(), rows, cols)?;
    let filled = fill_invalid(heights, rows, cols)?;
    let mut out = Vec::new();
    for name in Wavelet::names() {
        let Some(w) = Wavelet::by_name(name) else {
            continue;
        };
        let Ok(l) = default_level(rows, cols, &w, level) else {
            continue;
        };
        let rec = waverec2(&wavedec2(&filled, rows, cols, &w, mode, l)?, &w, mode)?;
        let rc = rec.cols();
        let (mut sq, mut n) = (0.0f64, 0usize);
        for r in 0..rows {
            for c in 0..cols {
                if heights[r * cols + c].is_finite() {
                    let d = filled[r * cols + c] - rec.values()[r * rc + c];
                    sq += d * d;
                    n += 1;
                }
            }
        }
        out.push(BaseRmse {
            wavelet: w.name().into(),
            level: l,
            rmse_um: (sq / n.max(1) as f64).sqrt(),
        });
    }
    if out.is_empty() {
        return Err(WaveletError::TooSmall {
            rows,
            cols,
            wavelet: "db1",
            min_side: 2,
        });
    }
    out.sort_by(|a, b| a.rmse_um.total_cmp(&b.rmse_um));
    Ok(out)
}

/// Sum of squares, in fixed blocks added in order (the same bits whatever the threads).
fn energy(v: &[f64]) -> f64 {
    v.par_chunks(1 << 14)
        .map(|b| b.iter().map(|x| x * x).sum::<f64>())
        .collect::<Vec<f64>>()
        .iter()
        .sum()
}

/// The filled map minus the least-squares plane `a + b x + c y` of its valid pixels.
fn levelled(heights: &[f32], rows: usize, cols: usize) -> Result<Vec<f64>> {
    let mut filled = fill_invalid(heights, rows, cols)?;
    let (coef, cx, cy) = plane_coef(heights, rows, cols);
    filled
        .par_chunks_mut(cols)
        .enumerate()
        .for_each(|(r, row)| {
            for (c, z) in row.iter_mut().enumerate() {
                *z -= coef[0] + coef[1] * (c as f64 - cx) + coef[2] * (r as f64 - cy);
            }
        });
    Ok(filled)
}

/// The least-squares plane of the valid pixels: `([a, b, c], cx, cy)` for
/// `a + b (x - cx) + c (y - cy)`.
pub(crate) fn plane_coef(heights: &[f32], rows: usize, cols: usize) -> ([f64; 3], f64, f64) {
    // Normal equations in centred coordinates (well conditioned for any map size), from each
    // row's sums (count, sum of x, of x^2, of z, of x z over its valid pixels): the rows in
    // parallel, added in row order, so the plane has the same bits whatever the thread count.
    let (cx, cy) = ((cols as f64 - 1.0) / 2.0, (rows as f64 - 1.0) / 2.0);
    let per_row: Vec<[f64; 5]> = heights
        .par_chunks(cols.max(1))
        .take(rows)
        .map(|row| {
            let mut s = [0.0f64; 5];
            for (c, &z) in row.iter().enumerate() {
                if z.is_finite() {
                    let (x, z) = (c as f64 - cx, f64::from(z));
                    s[0] += 1.0;
                    s[1] += x;
                    s[2] += x * x;
                    s[3] += z;
                    s[4] += x * z;
                }
            }
            s
        })
        .collect();
    let mut m = Matrix3::<f64>::zeros();
    let mut v = Vector3::<f64>::zeros();
    for (r, [n, sx, sxx, sz, sxz]) in per_row.into_iter().enumerate() {
        let y = r as f64 - cy;
        m += Matrix3::new(n, sx, n * y, sx, sxx, sx * y, n * y, sx * y, n * y * y);
        v += Vector3::new(sz, sxz, sz * y);
    }
    // A single valid row or column leaves the plane undetermined: level by the mean instead.
    let coef = m.lu().solve(&v).filter(|s| s.iter().all(|x| x.is_finite()));
    let coef = coef.unwrap_or_else(|| Vector3::new(v[0] / m[(0, 0)].max(1.0), 0.0, 0.0));
    ([coef[0], coef[1], coef[2]], cx, cy)
}

/// Values per part of [`height_stats`]' parallel sums: parts of a fixed size, added in order,
/// so the statistics have the same bits whatever the thread count.
const STATS_PART: usize = 1 << 16;

/// Mean, Sa, Sq, Sz of the finite values; `None` when there is none.
pub fn height_stats(heights: &[f32]) -> Option<HeightStats> {
    let counts: Vec<(usize, f64)> = heights
        .par_chunks(STATS_PART)
        .map(|part| {
            part.iter()
                .filter(|z| z.is_finite())
                .fold((0usize, 0.0f64), |(n, s), &z| (n + 1, s + f64::from(z)))
        })
        .collect();
    let (n, sum) = counts
        .into_iter()
        .fold((0usize, 0.0f64), |(n, s), (k, t)| (n + k, s + t));
    if n == 0 {
        return None;
    }
    let mean = sum / n as f64;
    let parts: Vec<[f64; 4]> = heights
        .par_chunks(STATS_PART)
        .map(|part| {
            let mut p = [0.0f64, 0.0, f64::INFINITY, f64::NEG_INFINITY];
            for &z in part.iter().filter(|z| z.is_finite()) {
                let d = f64::from(z) - mean;
                p[0] += d.abs();
                p[1] += d * d;
                p[2] = p[2].min(d);
                p[3] = p[3].max(d);
            }
            p
        })
        .collect();
    let [sa, sq, lo, hi] = parts
        .into_iter()
        .fold([0.0f64, 0.0, f64::INFINITY, f64::NEG_INFINITY], |a, p| {
            [a[0] + p[0], a[1] + p[1], a[2].min(p[2]), a[3].max(p[3])]
        });
    Some(HeightStats {
        mean_um: mean,
        sa_um: sa / n as f64,
        sq_um: (sq / n as f64).sqrt(),
        sz_um: hi - lo,
    })
}

/// Compare a map with its pooled version; `None` if either has no valid pixel.
pub fn pooling_bias(heights: &[f32], pooled: &[f32]) -> Option<PoolingBias> {
    let (b, a) = (height_stats(heights)?, height_stats(pooled)?);
    Some(PoolingBias {
        before: b,
        after: a,
        shift: HeightStats {
            mean_um: a.mean_um - b.mean_um,
            sa_um: a.sa_um - b.sa_um,
            sq_um: a.sq_um - b.sq_um,
            sz_um: a.sz_um - b.sz_um,
        },
    })
}

/// How the wavelet base is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BaseChoice {
    Named(Wavelet),
    /// Smallest reconstruction RMSE (eq. 10) among all bases.
    MinRmse,
}

/// How the decomposition level is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LevelChoice {
    /// This level, clamped to what the map supports ([`crate::default_level`]).
    Fixed(usize),
    /// [`crate::DEFAULT_LEVEL`] (8), clamped likewise and silently: the deepest level that
    /// fits when 8 does not (an explicit level that does not fit is warned about).
    Default,
    /// Minimum of the approximation's energy proportion (Fig. 13).
    MinEnergy,
}

/// Everything the separation of one map produces: the surfaces, the choices made and why.
#[derive(Debug, Clone)]
pub struct Analysis {
    pub separation: crate::Separation,
    pub pooled: crate::Pooled,
    pub wavelet: Wavelet,
    pub mode: Mode,
    /// Energy curve of the chosen base (always computed: it is the evidence for the level).
    pub energy_curve: Vec<EnergyPoint>,
    /// The level the energy rule picks (whether or not it was used).
    pub level_min_energy: Option<usize>,
    /// Eq. 10 per base, when the base was chosen by it.
    pub base_rmse: Option<Vec<BaseRmse>>,
    pub pooling_bias: Option<PoolingBias>,
    pub pool_block: usize,
    pub pool_op: crate::PoolOp,
}

/// Choose base and level as asked, separate, pool `pool_block x pool_block` with `pool_op`.
///
/// In memory, over the whole map. [`crate::separate_map`] (the node's final pass and the
/// `separate` verb) runs it only where a choice needs the whole map: the base by RMSE (every
/// base) and the level by minimum energy (every level); a named wavelet at a fixed / default
/// level streams. Otherwise it is the test oracle of the streamed pass (same datum and
/// roughness bits, the energy curve to round-off) and the Python binding's entry point.
#[allow(clippy::too_many_arguments)]
pub fn analyse(
    heights: &[f32],
    rows: usize,
    cols: usize,
    base: BaseChoice,
    level: LevelChoice,
    mode: Mode,
    pool_block: usize,
    pool_op: crate::PoolOp,
) -> Result<Analysis> {
    check_raster(heights.len(), rows, cols)?;
    let fixed = match level {
        LevelChoice::Fixed(l) => Some(l),
        _ => None,
    };
    let (wavelet, base_rmse) = match base {
        BaseChoice::Named(w) => (w, None),
        BaseChoice::MinRmse => {
            let ranking = rmse_per_base(heights, rows, cols, mode, fixed)?;
            let w = ranking
                .first()
                .and_then(|b| Wavelet::by_name(&b.wavelet))
                .ok_or(WaveletError::AllNan)?;
            (w, Some(ranking))
        }
    };
    let energy_curve = energy_curve(heights, rows, cols, &wavelet, mode)?;
    let level_min_energy = level_by_min_energy(&energy_curve);
    let level = match level {
        LevelChoice::Fixed(l) => Some(l),
        LevelChoice::Default => None,
        LevelChoice::MinEnergy => level_min_energy,
    };
    let separation = crate::separate(heights, rows, cols, &wavelet, mode, level)?;
    let pooled = crate::pool(heights, rows, cols, pool_block, pool_op)?;
    let pooling_bias = pooling_bias(heights, &pooled.heights);
    Ok(Analysis {
        separation,
        pooled,
        wavelet,
        mode,
        energy_curve,
        level_min_energy,
        base_rmse,
        pooling_bias,
        pool_block,
        pool_op,
    })
}

impl Analysis {
    /// The choices and the evidence, for run.json and the `separate` summary.
    pub fn summary(&self) -> SeparationChoices {
        SeparationChoices {
            wavelet: self.wavelet.name().into(),
            mode: self.mode.name().into(),
            level: self.separation.level,
            level_min_energy: self.level_min_energy,
            energy_curve: self.energy_curve.clone(),
            energy_curve_note: ENERGY_CURVE_NOTE.into(),
            base_rmse_note: self.base_rmse.as_ref().map(|_| BASE_RMSE_NOTE.into()),
            base_rmse: self.base_rmse.clone(),
            pool: self.pool_block,
            pool_op: self.pool_op.name().into(),
            pooling_bias: self.pooling_bias,
        }
    }

    /// [`Analysis::summary`], the separation and the pooled map, without copying the maps.
    pub fn into_parts(self) -> (SeparationChoices, crate::Separation, crate::Pooled) {
        let choices = SeparationChoices {
            wavelet: self.wavelet.name().into(),
            mode: self.mode.name().into(),
            level: self.separation.level,
            level_min_energy: self.level_min_energy,
            energy_curve: self.energy_curve,
            energy_curve_note: ENERGY_CURVE_NOTE.into(),
            base_rmse_note: self.base_rmse.as_ref().map(|_| BASE_RMSE_NOTE.into()),
            base_rmse: self.base_rmse,
            pool: self.pool_block,
            pool_op: self.pool_op.name().into(),
            pooling_bias: self.pooling_bias,
        };
        (choices, self.separation, self.pooled)
    }
}

pub(crate) const ENERGY_CURVE_NOTE: &str = "approximation energy / total energy per level, after filling holes and removing the least-squares plane (paper Fig. 13)";
const BASE_RMSE_NOTE: &str = "eq. 10: every base is orthogonal, so this RMSE is floating-point round-off, not a measure of fit";

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{pool, PoolOp};

    /// The plane from the rows' sums is the plane through the valid pixels, and the plane and
    /// the statistics have the same bits on one thread as on four.
    #[test]
    fn plane_and_stats_are_exact_and_do_not_depend_on_the_thread_count() {
        let (rows, cols) = (300, 257);
        let mut h: Vec<f32> = (0..rows * cols)
            .map(|k| {
                let (x, y) = ((k % cols) as f32, (k / cols) as f32);
                2.0 + 0.5 * x - 0.25 * y
            })
            .collect();
        for k in (0..h.len()).step_by(7) {
            h[k] = f32::NAN;
        }
        let ([a, b, c], cx, cy) = plane_coef(&h, rows, cols);
        assert!((a - (2.0 + 0.5 * cx - 0.25 * cy)).abs() < 1e-6, "{a}");
        assert!((b - 0.5).abs() < 1e-9 && (c + 0.25).abs() < 1e-9, "{b} {c}");
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| (plane_coef(&h, rows, cols), height_stats(&h)))
        };
        let (one, four) = (on(1), on(4));
        assert_eq!(format!("{one:?}"), format!("{four:?}"));
    }

    /// A plane plus a long wave plus fine texture: the energy left in the approximation drops
    /// while the levels strip texture, and rises again when the long wave leaks into details.
    fn surface(rows: usize, cols: usize) -> Vec<f32> {
        (0..rows * cols)
            .map(|i| {
                let (r, c) = ((i / cols) as f32, (i % cols) as f32);
                3.0 + 0.05 * c - 0.02 * r
                    + (c / 40.0).sin() * (r / 55.0).cos()
                    + 0.3 * ((1.7 * c).sin() * (2.3 * r).cos())
            })
            .collect()
    }

    #[test]
    fn energy_curve_is_a_fraction_per_level_and_the_rule_picks_its_minimum() {
        let (rows, cols) = (128, 160);
        let h = surface(rows, cols);
        let w = Wavelet::by_name("sym5").unwrap();
        let curve = energy_curve(&h, rows, cols, &w, Mode::Symmetric).unwrap();
        assert_eq!(curve.len(), dwt_max_level(128, 10));
        assert!(curve
            .iter()
            .all(|p| (0.0..=1.0).contains(&p.approx_energy_fraction)));
        let best = level_by_min_energy(&curve).unwrap();
        let min = curve
            .iter()
            .map(|p| p.approx_energy_fraction)
            .fold(f64::INFINITY, f64::min);
        assert_eq!(curve[best - 1].approx_energy_fraction, min);
        // Periodization is orthogonal on even sizes: energies add up exactly, so level 1's
        // fraction is E(cA_1) / E(x) of the levelled map.
        let pc = energy_curve(&h, rows, cols, &w, Mode::Periodization).unwrap();
        let x = levelled(&h, rows, cols).unwrap();
        let c = wavedec2(&x, rows, cols, &w, Mode::Periodization, 1).unwrap();
        let want = energy(c.approx.values()) / energy(&x);
        assert!((pc[0].approx_energy_fraction - want).abs() < 1e-9);
    }

    #[test]
    fn levelling_removes_the_plane() {
        let (rows, cols) = (20, 30);
        let mut h: Vec<f32> = (0..rows * cols)
            .map(|i| 7.0 + 0.5 * (i % cols) as f32 - 0.25 * (i / cols) as f32)
            .collect();
        h[33] = f32::NAN;
        let l = levelled(&h, rows, cols).unwrap();
        assert!(l.iter().all(|z| z.abs() < 1e-5), "{l:?}");
    }

    #[test]
    fn rmse_ranks_round_off_only() {
        let (rows, cols) = (64, 72);
        let mut h = surface(rows, cols);
        h[100] = f32::NAN;
        let ranking = rmse_per_base(&h, rows, cols, Mode::Symmetric, None).unwrap();
        assert_eq!(ranking.len(), 24, "a 64 px side fits every base at level 1");
        // Every orthogonal base reconstructs to round-off (PyWavelets' 12-13 digit filters
        // included): far below any height difference that matters.
        assert!(ranking.iter().all(|b| b.rmse_um < 1e-9), "{ranking:?}");
        assert!(ranking.windows(2).all(|p| p[0].rmse_um <= p[1].rmse_um));
    }

    #[test]
    fn max_pooling_lifts_the_mean_mean_pooling_keeps_it() {
        let (rows, cols) = (64, 64);
        let h = surface(rows, cols);
        let max = pool(&h, rows, cols, 4, PoolOp::Max).unwrap();
        let bias = pooling_bias(&h, &max.heights).unwrap();
        assert!(bias.shift.mean_um > 0.1, "{bias:?}");
        let mean = pool(&h, rows, cols, 4, PoolOp::Mean).unwrap();
        let bias = pooling_bias(&h, &mean.heights).unwrap();
        assert!(bias.shift.mean_um.abs() < 1e-5, "{bias:?}");
        let s = height_stats(&[1.0, 3.0, f32::NAN]).unwrap();
        assert_eq!((s.mean_um, s.sa_um, s.sq_um, s.sz_um), (2.0, 1.0, 1.0, 2.0));
        assert!(height_stats(&[f32::NAN]).is_none());
    }
}
