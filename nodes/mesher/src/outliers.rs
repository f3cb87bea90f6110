//! Spikes: isolated single samples far from their neighbours, which carry Sz on a polished
//! part (issue 22). They are always reported (count, positions, what they do to Sz); removing
//! them is an explicit option ([`OutlierPolicy::Remove`], in the spirit of ISO 25178-3's outlier
//! removal before the S-filter), never done silently: by default the model reproduces what the
//! measurement holds.
//!
//! Rule: r = height - median of the measured 8-neighbours (at least 3 of them); a sample is a
//! candidate when |r| > [`SPIKE_SIGMAS`] x 1.4826 x median |r| over the map (a robust sigma of
//! the local residual) and it stands above (below) all its neighbours by half of that; a spike is a candidate none of whose neighbours is a candidate of the
//! same sign (so a narrow scratch or ridge, whose samples are candidates side by side, is a
//! feature, not a spike).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use surfstream_core::raster::RasterView;

/// Candidates are beyond this many robust sigmas of the local residual.
pub const SPIKE_SIGMAS: f64 = 8.0;

/// Positions listed in the report (the largest first).
const LISTED: usize = 20;

/// What the mesher does with spikes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OutlierPolicy {
    /// Mesh what the measurement holds (default); spikes are reported.
    #[default]
    Keep,
    /// Treat spikes as not measured (then filled like any missing sample), and say so.
    Remove,
}

/// One spike: the report's record itself ([`surfstream_core::record::Spike`]), its layout
/// is all it is.
pub use surfstream_core::record::Spike;

/// The spikes of a map and their effect on Sz.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OutlierReport {
    pub rule: String,
    /// |height - neighbour median| beyond which a sample is a candidate, um.
    pub threshold_um: f64,
    pub count: usize,
    /// The largest spikes (at most 20), largest |excess| first.
    pub largest: Vec<Spike>,
    /// Sz of the measured samples as they are, and with every spike at its neighbours' median.
    pub sz_um: f64,
    pub sz_without_spikes_um: f64,
    /// (Sz - Sz without spikes) / Sz without spikes * 100: what the spikes add to Sz.
    pub sz_effect_pct: f64,
    pub policy: OutlierPolicy,
    /// Samples set to "not measured" before meshing (0 unless the policy is remove).
    pub removed: usize,
}

/// The median, lowest and highest of the measured 8-neighbours of (r, c), when at least 3 are
/// measured.
fn neighbours(z: &[f32], rows: usize, cols: usize, r: usize, c: usize) -> Option<(f32, f32, f32)> {
    // Inside the map all eight are there: read without the bounds arithmetic (in the order
    // of the loop below, so the same values are sorted); a missing one takes the loop.
    if r > 0 && c > 0 && r + 1 < rows && c + 1 < cols {
        let (up, at, down) = ((r - 1) * cols + c, r * cols + c, (r + 1) * cols + c);
        let mut v = [
            z[up - 1],
            z[up],
            z[up + 1],
            z[at - 1],
            z[at + 1],
            z[down - 1],
            z[down],
            z[down + 1],
        ];
        if !v.iter().any(|h| h.is_nan()) {
            sort8(&mut v);
            return Some((0.5 * (v[3] + v[4]), v[0], v[7]));
        }
    }
    let mut v = [0f32; 8];
    let mut n = 0;
    for dr in -1i64..=1 {
        for dc in -1i64..=1 {
            if dr == 0 && dc == 0 {
                continue;
            }
            let (rr, cc) = (r as i64 + dr, c as i64 + dc);
            if rr < 0 || cc < 0 || rr >= rows as i64 || cc >= cols as i64 {
                continue;
            }
            let h = z[rr as usize * cols + cc as usize];
            if !h.is_nan() {
                v[n] = h;
                n += 1;
            }
        }
    }
    if n < 3 {
        return None;
    }
    let v = &mut v[..n];
    if n == 8 {
        // Nearly every sample has all eight: a sorting network (no NaN here, so min / max
        // order them as the sort does; a -0 and a +0 may trade places, equal as heights).
        sort8(v);
    } else {
        v.sort_unstable_by(f32::total_cmp);
    }
    let median = if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    };
    Some((median, v[0], v[n - 1]))
}

/// Knuth's 19-comparator network for eight values (six layers).
const SORT8: [(usize, usize); 19] = [
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
    (0, 1),
    (2, 3),
    (4, 5),
    (6, 7),
    (2, 4),
    (3, 5),
    (1, 4),
    (3, 6),
    (1, 2),
    (3, 4),
    (5, 6),
];

/// Sorts eight values, none NaN, ascending.
#[inline(always)]
fn sort8(v: &mut [f32]) {
    for (i, j) in SORT8 {
        let (a, b) = (v[i], v[j]);
        v[i] = a.min(b);
        v[j] = a.max(b);
    }
}

/// The local residual (height less its neighbours' median, NaN where there is none) of one
/// sample, as [`neighbours`] gives the median.
#[inline(always)]
fn residual_at(z: &[f32], rows: usize, cols: usize, r: usize, c: usize, out: &mut f32) {
    let h = z[r * cols + c];
    if let (false, Some((m, _, _))) = (h.is_nan(), neighbours(z, rows, cols, r, c)) {
        *out = h - m;
    }
}

/// Interior samples per run of [`residual_row`]: their eight neighbours sorted lane by lane.
const RUN: usize = 8;

/// [`residual_at`] for every sample of row `r` into `out` (NaN left where there is no
/// residual). Interior samples go in runs of [`RUN`]: each neighbour position gathered for
/// the run (contiguous in its row), then [`SORT8`]'s compare-exchanges applied to all of
/// the run's samples at once, the same min / max on each sample's eight values as
/// [`sort8`] makes (so the same medians, bit for bit), which the compiler can do in SIMD
/// registers. A run with a missing neighbour takes the per-sample path.
// Lanes indexed across the eight arrays (and the rows they come from): the form that reads
// as the network and vectorizes.
#[allow(clippy::needless_range_loop)]
fn residual_row(z: &[f32], rows: usize, cols: usize, r: usize, out: &mut [f32]) {
    if r == 0 || r + 1 >= rows || cols < RUN + 2 {
        for (c, o) in out.iter_mut().enumerate() {
            residual_at(z, rows, cols, r, c, o);
        }
        return;
    }
    let up = &z[(r - 1) * cols..r * cols];
    let at = &z[r * cols..(r + 1) * cols];
    let down = &z[(r + 1) * cols..(r + 2) * cols];
    residual_at(z, rows, cols, r, 0, &mut out[0]);
    let mut c = 1;
    while c + RUN < cols {
        // The neighbours in `neighbours`' order: the row above, left and right, below.
        let mut v = [[0f32; RUN]; 8];
        for l in 0..RUN {
            let x = c + l;
            v[0][l] = up[x - 1];
            v[1][l] = up[x];
            v[2][l] = up[x + 1];
            v[3][l] = at[x - 1];
            v[4][l] = at[x + 1];
            v[5][l] = down[x - 1];
            v[6][l] = down[x];
            v[7][l] = down[x + 1];
        }
        let mut missing = false;
        for lane in &v {
            missing |= lane.iter().fold(false, |a, h| a | h.is_nan());
        }
        if missing {
            for (l, o) in out[c..c + RUN].iter_mut().enumerate() {
                residual_at(z, rows, cols, r, c + l, o);
            }
        } else {
            for (i, j) in SORT8 {
                for l in 0..RUN {
                    let (a, b) = (v[i][l], v[j][l]);
                    v[i][l] = a.min(b);
                    v[j][l] = a.max(b);
                }
            }
            for (l, o) in out[c..c + RUN].iter_mut().enumerate() {
                let h = at[c + l];
                if !h.is_nan() {
                    *o = h - 0.5 * (v[3][l] + v[4][l]);
                }
            }
        }
        c += RUN;
    }
    for (x, o) in out.iter_mut().enumerate().skip(c) {
        residual_at(z, rows, cols, r, x, o);
    }
}

/// Finds the spikes of `heights` (NaN = not measured): the report and the spikes' sample
/// indices.
pub fn find_spikes(
    heights: RasterView<'_, f32>,
    policy: OutlierPolicy,
) -> (OutlierReport, Vec<usize>) {
    let (rows, cols) = (heights.rows(), heights.cols());
    let z = heights.values();
    // Local residual of every measured sample (NaN where it has no median), written in place
    // row by row: 4 bytes per sample. (Unzipped from a parallel iterator with how far each
    // sample stands out beside it, and copied again for the median, as before, it took about
    // three times that at once: +376 MB of RSS at the 6 x 6 demo, the run's peak at 0.5 GB.)
    let mut residual = vec![f32::NAN; rows * cols];
    residual
        .par_chunks_mut(cols.max(1))
        .enumerate()
        .for_each(|(r, row)| residual_row(z, rows, cols, r, row));
    let sigma = match median_abs(&residual) {
        Some(m) => 1.4826 * f64::from(m),
        None => 0.0,
    };
    let threshold_um = SPIKE_SIGMAS * sigma;
    // The side on which a sample is beyond the threshold from its neighbours' median.
    let side = |k: usize| -> i8 {
        let r = residual[k];
        if r.is_nan() || sigma <= 0.0 || f64::from(r.abs()) <= threshold_um {
            0
        } else if r > 0.0 {
            1
        } else {
            -1
        }
    };
    // How far a sample stands out beyond all of its neighbours (above the highest or below
    // the lowest; 0 when it does not): computed for the few samples beyond the threshold
    // only, from the same neighbours.
    let beyond = |k: usize| -> f32 {
        let h = z[k];
        match (h.is_nan(), neighbours(z, rows, cols, k / cols, k % cols)) {
            (false, Some((_, lo, hi))) => (h - hi).max(lo - h).max(0.0),
            _ => 0.0,
        }
    };
    // A candidate also stands beyond every neighbour by half the threshold: the edge of a
    // scratch or a step stands out from the median, not from all.
    let candidate = |k: usize| -> i8 {
        let s = side(k);
        if s == 0 || f64::from(beyond(k)) <= 0.5 * threshold_um {
            0
        } else {
            s
        }
    };
    let mut spikes: Vec<usize> = (0..rows * cols)
        .into_par_iter()
        .filter(|&k| {
            let s = candidate(k);
            if s == 0 {
                return false;
            }
            let (r, c) = (k / cols, k % cols);
            for rr in r.saturating_sub(1)..=(r + 1).min(rows - 1) {
                for cc in c.saturating_sub(1)..=(c + 1).min(cols - 1) {
                    if (rr, cc) != (r, c) && side(rr * cols + cc) == s {
                        return false;
                    }
                }
            }
            true
        })
        .collect();
    spikes.sort_by(|&a, &b| {
        residual[b]
            .abs()
            .total_cmp(&residual[a].abs())
            .then(a.cmp(&b))
    });
    let (mut lo, mut hi, mut lo2, mut hi2) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    let is_spike = {
        let mut v = vec![false; rows * cols];
        for &k in &spikes {
            v[k] = true;
        }
        v
    };
    for (k, &h) in z.iter().enumerate() {
        if h.is_nan() {
            continue;
        }
        let h = f64::from(h);
        lo = lo.min(h);
        hi = hi.max(h);
        let h2 = if is_spike[k] {
            h - f64::from(residual[k])
        } else {
            h
        };
        lo2 = lo2.min(h2);
        hi2 = hi2.max(h2);
    }
    let (sz, sz2) = (hi - lo, hi2 - lo2);
    let report = OutlierReport {
        rule: format!(
            "isolated sample beyond {SPIKE_SIGMAS} robust sigmas (1.4826 x median |r|) of r = \
             height - median of its measured 8-neighbours, beyond all of them by half of that, \
             with no neighbour beyond it on the same side"
        ),
        threshold_um,
        count: spikes.len(),
        largest: spikes
            .iter()
            .take(LISTED)
            .map(|&k| Spike {
                row: k / cols,
                col: k % cols,
                height_um: f64::from(z[k]),
                excess_um: f64::from(residual[k]),
            })
            .collect(),
        sz_um: if sz.is_finite() { sz } else { 0.0 },
        sz_without_spikes_um: if sz2.is_finite() { sz2 } else { 0.0 },
        sz_effect_pct: if sz2 > 0.0 {
            (sz - sz2) / sz2 * 100.0
        } else {
            0.0
        },
        policy,
        removed: if policy == OutlierPolicy::Remove {
            spikes.len()
        } else {
            0
        },
    };
    (report, spikes)
}

/// The median of |r| over the values of `residual` that are not NaN (core's
/// [`surfstream_core::order::median_magnitude`]: no copy of the field). `None`: no value.
fn median_abs(residual: &[f32]) -> Option<f32> {
    surfstream_core::order::median_magnitude(residual.len(), |i| residual[i])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rows' runs give every sample the residual the per-sample path gives, to the bit:
    /// borders, rows narrower than a run, runs with a missing neighbour or a missing centre,
    /// ties and signed zeros.
    #[test]
    fn a_rows_runs_give_the_per_sample_residuals() {
        let mut state = 99u32;
        for &(rows, cols) in &[(5, 30), (9, 9), (7, 10), (12, 47), (3, 100), (2, 20)] {
            let z: Vec<f32> = (0..rows * cols)
                .map(|_| {
                    state = state.wrapping_mul(1_103_515_245).wrapping_add(12345);
                    match (state >> 8) % 23 {
                        0 => f32::NAN,
                        1 => 0.0,
                        2 => -0.0,
                        3 => 1.5,
                        _ => (state >> 16) as f32 / 997.0 - 30.0,
                    }
                })
                .collect();
            for r in 0..rows {
                let mut fast = vec![f32::NAN; cols];
                residual_row(&z, rows, cols, r, &mut fast);
                for (c, &f) in fast.iter().enumerate() {
                    let mut each = f32::NAN;
                    residual_at(&z, rows, cols, r, c, &mut each);
                    assert_eq!(f.to_bits(), each.to_bits(), "{rows} x {cols} at ({r}, {c})");
                }
            }
        }
    }

    #[test]
    fn every_sample_has_the_median_and_extremes_of_its_measured_neighbours() {
        // Borders, corners, missing neighbours and all-eight interiors, against a plain sort.
        let (rows, cols) = (7, 9);
        let mut state = 12345u32;
        let z: Vec<f32> = (0..rows * cols)
            .map(|k| {
                state = state.wrapping_mul(1_103_515_245).wrapping_add(12345);
                if k % 11 == 3 {
                    f32::NAN
                } else {
                    (state >> 16) as f32 / 1000.0
                }
            })
            .collect();
        for r in 0..rows {
            for c in 0..cols {
                let mut v: Vec<f32> = (-1i64..=1)
                    .flat_map(|dr| (-1i64..=1).map(move |dc| (dr, dc)))
                    .filter(|&d| d != (0, 0))
                    .map(|(dr, dc)| (r as i64 + dr, c as i64 + dc))
                    .filter(|&(y, x)| y >= 0 && x >= 0 && y < rows as i64 && x < cols as i64)
                    .map(|(y, x)| z[y as usize * cols + x as usize])
                    .filter(|h| !h.is_nan())
                    .collect();
                v.sort_unstable_by(f32::total_cmp);
                let n = v.len();
                let want = (n >= 3).then(|| {
                    let m = if n % 2 == 1 {
                        v[n / 2]
                    } else {
                        0.5 * (v[n / 2 - 1] + v[n / 2])
                    };
                    (m, v[0], v[n - 1])
                });
                assert_eq!(neighbours(&z, rows, cols, r, c), want, "({r}, {c})");
            }
        }
    }

    #[test]
    fn the_network_sorts_every_order_of_eight() {
        // The 0-1 principle: a network that sorts every 0/1 input sorts every input.
        for bits in 0u32..256 {
            let mut v: Vec<f32> = (0..8).map(|k| ((bits >> k) & 1) as f32).collect();
            let mut want = v.clone();
            want.sort_unstable_by(f32::total_cmp);
            sort8(&mut v);
            assert_eq!(v, want, "{bits:08b}");
        }
        let mut v = [3.5, -1.0, 2.25, 8.0, -7.5, 0.5, 2.25, 1e-3];
        sort8(&mut v);
        assert_eq!(v, [-7.5, -1.0, 1e-3, 0.5, 2.25, 2.25, 3.5, 8.0]);
    }
    use surfstream_core::raster::Shape;

    #[test]
    fn an_isolated_spike_is_found_and_a_scratch_is_not() {
        let (rows, cols) = (30, 40);
        let mut z: Vec<f32> = (0..rows * cols)
            .map(|k| (0.3 * (k % cols) as f32).sin() + 0.01 * ((k * 7919) % 13) as f32)
            .collect();
        z[12 * cols + 17] += 9.0;
        for c in 3..35 {
            z[22 * cols + c] -= 6.0; // a scratch along a row
        }
        let v = RasterView::new(&z, Shape::new(rows, cols)).unwrap();
        let (r, idx) = find_spikes(v, OutlierPolicy::Keep);
        assert_eq!(idx, vec![12 * cols + 17], "{r:?}");
        assert_eq!((r.largest[0].row, r.largest[0].col), (12, 17));
        assert!(r.sz_effect_pct > 0.0 && r.removed == 0);
        assert!((r.largest[0].excess_um - 9.0).abs() < 0.5, "{r:?}");
    }
}
