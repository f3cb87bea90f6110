//! Spatial parameters, ISO 25178-2 §4.3: Sal and Str from the autocorrelation function (ACF),
//! Std from the angular amplitude spectrum.
//!
//! ACF: f_ACF(tx, ty) = mean over the valid pairs of c(x, y) c(x + tx, y + ty), c = heights
//! minus the mean of the valid points: the linear (zero-padded, not circular) estimator with
//! each lag divided by its own number of pairs (the unbiased estimator surfalize 0.19.2 uses).
//! NaN: a pair counts only when both points are valid (the pair count is the autocorrelation of
//! the validity mask; lags with no valid pair are NaN).
//!
//! Sal and Str (threshold s = 0.2 of f_ACF(0, 0), ISO 25178-3): the region of lags connected
//! to 0 (4-neighbours) where f_ACF > s f_ACF(0); for every lag just outside it, the ray from 0
//! to that lag is followed (bilinear interpolation, 2 samples per pixel) to the first point
//! where f_ACF falls to s f_ACF(0), refined linearly between samples. Sal = the shortest of
//! these decay lengths (um), Str = shortest / longest. When the region reaches the border of
//! the lag plane the slowest decay is not inside the measurement: Str is NaN (undefined), Sal
//! is still the fastest decay. No decay anywhere: both NaN.
//!
//! Std (degrees, 0 <= Std < 180): the direction of the largest angular amplitude density
//! f_AAD(theta) = the sum of |F(fx, fy)| over the DFT samples whose frequency vector points
//! at theta (bins of `STD_STEP_DEG`, lower bin edge reported), frequencies in 1/um so the
//! angle is right for any pitch. The angle is counter-clockwise from +x towards +y in scan
//! coordinates (y grows with the row index). surfalize measures it with y pointing up the
//! displayed image (row 0 on top), i.e. towards -y: for the same array its angle is
//! 180 - ours (mod 180, within one bin). A lay of ridges along y (heights varying along x)
//! gives Std = 0. NaN: the spectrum of the mean-filled map (gaps set to the mean).

use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};

use rayon::prelude::*;
use rustfft::num_complex::Complex;
use serde::Serialize;

use super::spectrum::{
    axis_sums, correlation_half_plane, correlation_window, spectrum2_blocks, SpilledCorrelation,
    AXIS_BLOCK, SPILL_BAND_ROWS, SPILL_BLOCK_BYTES,
};
use super::{Grid, MetrologyError};

/// ISO 25178-3 default threshold of Sal / Str.
pub const ACF_THRESHOLD: f64 = 0.2;
/// Angular bin of Std (degrees).
pub const STD_STEP_DEG: f64 = 0.5;

/// Sal, Str, Std.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SpatialParams {
    /// Autocorrelation length (um).
    #[serde(rename = "Sal")]
    pub sal: f64,
    /// Texture aspect ratio (0..1]; NaN when the slowest decay leaves the measurement.
    #[serde(rename = "Str")]
    pub str_: f64,
    /// Texture direction (degrees).
    #[serde(rename = "Std")]
    pub std: f64,
}

/// The heights centred on the mean of the valid points, gaps 0, with the valid count.
pub(crate) fn centred(g: &Grid) -> Result<(Vec<f64>, usize), MetrologyError> {
    let super::HeightSummary { mean, valid, .. } = super::height_summary(g)?;
    let c: Vec<f64> = g
        .heights_um
        .par_iter()
        .map(|&z| if z.is_nan() { 0.0 } else { z - mean })
        .collect();
    Ok((c, valid))
}

/// [`centred`] without holding it: its rows written on demand, with the valid count.
struct CentredRows<'a> {
    z: &'a [f64],
    cols: usize,
    mean: f64,
    valid: usize,
}

impl<'a> CentredRows<'a> {
    fn of(g: &Grid<'a>) -> Result<Self, MetrologyError> {
        let super::HeightSummary { mean, valid, .. } = super::height_summary(g)?;
        Ok(Self {
            z: g.heights_um,
            cols: g.cols(),
            mean,
            valid,
        })
    }

    /// Row r of [`centred`]'s field into `buf` (cols values).
    fn row(&self, r: usize, buf: &mut [f64]) {
        let (cols, mean) = (self.cols, self.mean);
        for (o, &z) in buf.iter_mut().zip(&self.z[r * cols..(r + 1) * cols]) {
            *o = if z.is_nan() { 0.0 } else { z - mean };
        }
    }
}

/// The autocorrelation function over lags ty = -(rows-1)..=(rows-1), tx = -(cols-1)..=(cols-1)
/// (um^2); stored as the half plane ty >= 0 (f_ACF(-t) = f_ACF(t)), or only its lags |ty| <=
/// wy, |tx| <= wx (a window: see [`spatial_params`]).
#[derive(Debug, Clone)]
pub struct Acf {
    pub rows: usize,
    pub cols: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    /// The lags held: |ty| <= wy, |tx| <= wx (rows - 1, cols - 1: the whole plane).
    wy: usize,
    wx: usize,
    half: Vec<f64>,
}

/// The window of lags [`spatial_params`] tries first, as a fraction of the lag plane's half
/// extents: a region of f_ACF > 0.2 f_ACF(0) within an eighth of the map (Sal well below the
/// field, the usual case) is found without the whole plane.
const WINDOW_FRACTION: usize = 8;
/// Blocks of half-spectrum columns the window's transforms are made in (each row's FFT is
/// made this many times): the block is 2 x the map / this.
const WINDOW_BLOCKS: usize = 8;
/// Blocks of Std's spectrum (the map / this at a time).
const STD_BLOCKS: usize = 4;
/// When only Sal is wanted (the region reaches the plane's border), the rays to the edge lags
/// nearest to 0 followed in full before the others are followed in parallel, each only as far
/// as it can still be the shortest.
const RAYS_IN_FULL: usize = 64;
/// Below this many points the whole lag plane is made at once (its memory is small).
const WINDOW_MIN_POINTS: usize = 1 << 18;

/// f_ACF at each lag of `half` (sums over the valid pairs) from its number of pairs, NaN
/// where there is none. `count` turns a held pair count into a whole number.
fn divide_by_pairs<K: Copy + Sync>(half: &mut [f64], pairs: &[K], count: impl Fn(K) -> f64 + Sync) {
    half.par_iter_mut()
        .zip(pairs.par_iter())
        .for_each(|(v, &k)| {
            let k = count(k);
            *v = if k >= 1.0 { *v / k } else { f64::NAN };
        });
}

/// f_ACF of a map without gaps at the lags of `rows_of_lags` (rows of 2 `wx` + 1, tx =
/// -wx..=wx, the first at lag row `ty0`) from their sums: each divided by its number of
/// pairs, (rows - ty) (cols - |tx|).
fn divide_by_full_pairs(
    rows_of_lags: &mut [f64],
    ty0: usize,
    wx: usize,
    (rows, cols): (usize, usize),
) {
    rows_of_lags
        .par_chunks_mut(2 * wx + 1)
        .enumerate()
        .for_each(|(j, row)| {
            for (i, v) in row.iter_mut().enumerate() {
                let tx = (i as isize - wx as isize).unsigned_abs();
                *v /= ((rows - (ty0 + j)) * (cols - tx)) as f64;
            }
        });
}

/// The rows of `g`'s validity mask (1 measured, 0 not), whose correlation counts the pairs.
fn mask_rows<'a>(g: &Grid<'a>) -> impl Fn(usize, &mut [f64]) + Sync + 'a {
    let (z, cols) = (g.heights_um, g.cols());
    move |r, buf| {
        for (o, &z) in buf.iter_mut().zip(&z[r * cols..(r + 1) * cols]) {
            *o = if z.is_nan() { 0.0 } else { 1.0 };
        }
    }
}

impl Acf {
    /// The ACF of `g` (see the module documentation), the whole lag plane.
    pub fn of(g: &Grid) -> Result<Self, MetrologyError> {
        Self::of_lags(g, &CentredRows::of(g)?, None)
    }

    /// The ACF of `g` at lags |ty| <= `wy`, |tx| <= `wx` only (`None`: all), the same values
    /// bit for bit as [`Acf::of`]'s at those lags; made in `WINDOW_BLOCKS` column blocks.
    fn of_lags(
        g: &Grid,
        c: &CentredRows,
        window: Option<(usize, usize)>,
    ) -> Result<Self, MetrologyError> {
        let n = c.valid;
        let (rows, cols) = (g.rows(), g.cols());
        let (wy, wx) = window.map_or((rows - 1, cols - 1), |(wy, wx)| {
            (wy.min(rows - 1), wx.min(cols - 1))
        });
        let sums = |row: &(dyn Fn(usize, &mut [f64]) + Sync)| match window {
            None => correlation_half_plane(&row, rows, cols),
            Some(_) => correlation_window(&row, rows, cols, (wy, wx), WINDOW_BLOCKS),
        };
        let half = if n == rows * cols {
            let mut half = sums(&|r, buf: &mut [f64]| c.row(r, buf));
            divide_by_full_pairs(&mut half, 0, wx, (rows, cols));
            half
        } else {
            // The pairs per lag first, kept as whole counts (u32 when a count, at most
            // rows x cols, fits: half the f64 plane's memory), so that two f64 planes are
            // not held at once.
            let pairs = sums(&mask_rows(g));
            let row = |r: usize, buf: &mut [f64]| c.row(r, buf);
            if rows * cols <= u32::MAX as usize {
                let counts: Vec<u32> = pairs
                    .into_par_iter()
                    .map(|k| k.round().max(0.0) as u32)
                    .collect();
                let mut half = sums(&row);
                divide_by_pairs(&mut half, &counts, f64::from);
                half
            } else {
                let mut half = sums(&row);
                divide_by_pairs(&mut half, &pairs, |k| k.round());
                half
            }
        };
        Ok(Self {
            rows,
            cols,
            pitch_x_um: g.pitch_x_um(),
            pitch_y_um: g.pitch_y_um(),
            wy,
            wx,
            half,
        })
    }

    /// Whether every lag of the plane is held.
    fn whole(&self) -> bool {
        self.wy + 1 == self.rows && self.wx + 1 == self.cols
    }

    /// f_ACF at lag (ty rows, tx cols); NaN outside the lag plane (and outside the window
    /// held, which the region search never reads: see `region_edges`).
    pub fn at(&self, ty: isize, tx: isize) -> f64 {
        let (ty, tx) = if ty < 0 { (-ty, -tx) } else { (ty, tx) };
        let (wy, wx) = (self.wy as isize, self.wx as isize);
        if ty > wy || tx < -wx || tx > wx {
            debug_assert!(self.whole(), "lag ({ty}, {tx}) read outside the window");
            return f64::NAN;
        }
        self.half[ty as usize * (2 * self.wx + 1) + (tx + wx) as usize]
    }

    fn bilinear(&self, y: f64, x: f64) -> f64 {
        let (y0, x0) = (floor_lag(y), floor_lag(x));
        let (fy, fx) = (y - y0, x - x0);
        let (y0, x0) = (y0 as isize, x0 as isize);
        let v = |dy: isize, dx: isize| self.at(y0 + dy, x0 + dx);
        let top = if fx == 0.0 {
            v(0, 0)
        } else {
            v(0, 0) * (1.0 - fx) + v(0, 1) * fx
        };
        if fy == 0.0 {
            return top;
        }
        let bot = if fx == 0.0 {
            v(1, 0)
        } else {
            v(1, 0) * (1.0 - fx) + v(1, 1) * fx
        };
        top * (1.0 - fy) + bot * fy
    }

    /// (Sal um, Str) at threshold `s` (fraction of f_ACF(0)).
    pub fn sal_str(&self, s: f64) -> (f64, f64) {
        // The whole plane always holds its region.
        self.sal_str_within(s).unwrap_or((f64::NAN, f64::NAN))
    }

    /// [`Acf::sal_str`], or `None` when the region reaches the border of the window held
    /// inside the plane (the lags beyond it would be needed).
    fn sal_str_within(&self, s: f64) -> Option<(f64, f64)> {
        let thr = s * self.at(0, 0);
        if thr.is_nan() {
            return Some((f64::NAN, f64::NAN));
        }
        let (edges, touches) = self.region_edges(thr)?;
        Some(self.sal_str_of(thr, &edges, touches))
    }

    /// Sal and Str from the region's edges (see [`Acf::region_edges`]).
    fn sal_str_of(&self, thr: f64, edges: &[(isize, isize)], touches: bool) -> (f64, f64) {
        if edges.is_empty() {
            return (f64::NAN, f64::NAN);
        }
        let (px, py) = (self.pitch_x_um, self.pitch_y_um);
        let dist =
            |(ey, ex): (isize, isize)| ((ey as f64 * py).powi(2) + (ex as f64 * px).powi(2)).sqrt();
        if !touches {
            // Str needs the longest decay as well as the shortest: every ray in full.
            let lengths: Vec<f64> = edges
                .par_iter()
                .map(|&e| self.decay_length(e, dist(e), thr, f64::INFINITY))
                .collect();
            let lo = lengths.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = lengths.iter().copied().fold(0.0, f64::max);
            return (lo, lo / hi);
        }
        // Only the shortest decay is wanted (Str is undefined): the rays nearest to 0 first,
        // each left as soon as it can no longer be the shortest (see `decay_length`): the
        // same minimum as over every ray in full.
        let mut by_dist: Vec<(f64, (isize, isize))> = edges.iter().map(|&e| (dist(e), e)).collect();
        by_dist.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        let mut lo = f64::INFINITY;
        for &(d, e) in by_dist.iter().take(RAYS_IN_FULL) {
            lo = lo.min(self.decay_length(e, d, thr, lo));
        }
        // Lengths are >= 0: their bits order as they do.
        let best = AtomicU64::new(lo.to_bits());
        by_dist.par_iter().skip(RAYS_IN_FULL).for_each(|&(d, e)| {
            let bound = f64::from_bits(best.load(AtomicOrdering::Relaxed));
            let len = self.decay_length(e, d, thr, bound);
            best.fetch_min(len.to_bits(), AtomicOrdering::Relaxed);
        });
        (f64::from_bits(best.into_inner()), f64::NAN)
    }

    /// The lags just outside the region of lags connected to 0 (4-neighbours) where f_ACF >
    /// `thr`, and whether the region reaches the border of the lag plane; `None` when it
    /// reaches the border of the window held inside the plane (see [`region_edges_where`]).
    fn region_edges(&self, thr: f64) -> Option<(Vec<(isize, isize)>, bool)> {
        region_edges_where(self.rows, self.cols, (self.wy, self.wx), |y, x| {
            self.at(y, x) > thr
        })
    }

    /// The decay length (um) along the ray from lag 0 to lag `e`, `dist` um long: the first
    /// point where the bilinear f_ACF falls to `thr`, refined linearly between the samples
    /// (2 per pixel); `dist` when it does not fall. The crossing after a sample t0 above the
    /// threshold is at (t0 + f (t - t0)) dist with 0 < f <= 1, never shorter than t0 dist:
    /// once that reaches `bound` the ray is left and infinity returned (it cannot be shorter
    /// than `bound`).
    fn decay_length(&self, (ey, ex): (isize, isize), dist: f64, thr: f64, bound: f64) -> f64 {
        let n = (2 * ey.abs().max(ex.abs())).max(4) as usize;
        let mut prev = (0.0, self.at(0, 0));
        for k in 1..=n {
            if prev.0 * dist >= bound {
                return f64::INFINITY;
            }
            let t = k as f64 / n as f64;
            let v = self.bilinear(t * ey as f64, t * ex as f64);
            if v <= thr {
                let (t0, v0) = prev;
                let f = if v0 > v { (v0 - thr) / (v0 - v) } else { 1.0 };
                return (t0 + f * (t - t0)) * dist;
            }
            prev = (t, v);
        }
        dist
    }
}

/// `v.floor()` for a lag (|v| far below 2^53) without the library call the baseline x86-64
/// target makes of `floor` (no SSE4.1 round): the truncation, one down for negative
/// fractions. The same value, so the same interpolation.
#[inline(always)]
fn floor_lag(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}

/// The lags just outside the region of lags connected to 0 (4-neighbours) where `above`
/// holds, of a rows x cols map's lag plane, and whether the region reaches the border of the
/// plane; `None` when it reaches the border of the window |ty| <= `wy`, |tx| <= `wx` held
/// inside the plane (a region lag there may have neighbours beyond it). Lags inside the
/// window's border have their neighbours inside the window, so a `Some` result asked `above`
/// only of lags held.
fn region_edges_where(
    rows: usize,
    cols: usize,
    (wy, wx): (usize, usize),
    above: impl Fn(isize, isize) -> bool,
) -> Option<(Vec<(isize, isize)>, bool)> {
    let (ry, rx) = (rows as isize - 1, cols as isize - 1);
    let (wy, wx) = (wy as isize, wx as isize);
    let (h, w) = ((2 * wy + 1) as usize, (2 * wx + 1) as usize);
    let idx = |y: isize, x: isize| (y + wy) as usize * w + (x + wx) as usize;
    // Seen (in the region or on its edge), one bit per lag.
    let mut seen = vec![0u64; (h * w).div_ceil(64)];
    let mut see = |i: usize| {
        let (word, bit) = (i / 64, 1u64 << (i % 64));
        let new = seen[word] & bit == 0;
        seen[word] |= bit;
        new
    };
    // Lags to visit as i32 pairs (a lag plane's extents fit): a long correlation's region is
    // much of the plane, and so may this stack be.
    let mut stack = vec![(0i32, 0i32)];
    see(idx(0, 0));
    let mut edges = Vec::new();
    let mut touches = false;
    while let Some((y, x)) = stack.pop() {
        let (y, x) = (y as isize, x as isize);
        if (wy < ry && y.abs() >= wy) || (wx < rx && x.abs() >= wx) {
            return None;
        }
        if y.abs() == ry || x.abs() == rx {
            touches = true;
        }
        for (dy, dx) in [(-1, 0), (1, 0), (0, -1), (0, 1)] {
            let (ny, nx) = (y + dy, x + dx);
            if ny.abs() > ry || nx.abs() > rx {
                continue;
            }
            if !see(idx(ny, nx)) {
                continue;
            }
            if above(ny, nx) {
                stack.push((ny as i32, nx as i32));
            } else {
                edges.push((ny, nx));
            }
        }
    }
    Some((edges, touches))
}

/// The angular amplitude density in bins of `step_deg` (lower edges 0..180), from the DFT of
/// the centred (mean-filled) heights, made in `STD_BLOCKS` blocks of columns (the same sums:
/// each row's bins are added to in ascending kx, block after block).
pub fn angular_amplitude(g: &Grid, step_deg: f64) -> Result<Vec<(f64, f64)>, MetrologyError> {
    Ok(angular_amplitude_of(g, &CentredRows::of(g)?, step_deg))
}

/// [`angular_amplitude`] of `g`'s centred rows `c`.
fn angular_amplitude_of(g: &Grid, c: &CentredRows, step_deg: f64) -> Vec<(f64, f64)> {
    let (rows, cols) = (g.rows(), g.cols());
    let bins = angular_bins(step_deg);
    let mut per_row = vec![0.0; rows * bins];
    spectrum2_blocks(
        &|r, buf: &mut [f64]| c.row(r, buf),
        rows,
        cols,
        STD_BLOCKS,
        |k0, bw, block| {
            per_row
                .par_chunks_mut(bins)
                .zip(block.par_chunks(bw))
                .enumerate()
                .for_each(|(ky, (acc, row))| {
                    add_angular_row(g, ky, k0, row, step_deg, acc);
                });
        },
    );
    angular_total(&per_row, bins, step_deg)
}

/// The number of angular bins of `step_deg` over 180 degrees.
fn angular_bins(step_deg: f64) -> usize {
    (180.0 / step_deg).ceil() as usize
}

/// Adds |F| of the half-spectrum samples (ky, k0..k0 + row.len()) to their angular bins in
/// `acc`, in ascending kx.
fn add_angular_row(
    g: &Grid,
    ky: usize,
    k0: usize,
    row: &[Complex<f64>],
    step_deg: f64,
    acc: &mut [f64],
) {
    let cols = g.cols();
    let bins = acc.len();
    let end = k0 + row.len();
    let bin = |kx: usize| angular_bin(g, ky, kx, step_deg, bins);
    // Along a row the angle is monotone in kx (fy fixed, fx growing): a run of equal bins is
    // found by galloping and bisection, so atan2 is evaluated about twice per bin boundary
    // crossed instead of once per sample. The sums are the same, taken in the same order (kx
    // ascending within the row).
    let mut k = k0;
    while k < end {
        let b = bin(k);
        let (mut last, mut step) = (k, 1);
        let mut beyond = loop {
            let t = last + step;
            if t >= end {
                break end;
            }
            if bin(t) != b {
                break t;
            }
            last = t;
            step *= 2;
        };
        while beyond - last > 1 {
            let mid = last + (beyond - last) / 2;
            if bin(mid) == b {
                last = mid;
            } else {
                beyond = mid;
            }
        }
        for kx in k..=last {
            acc[b] += angular_weight(cols, kx) * row[kx - k0].norm();
        }
        k = last + 1;
    }
}

/// The rows' bins summed in row order, with their lower edges.
fn angular_total(per_row: &[f64], bins: usize, step_deg: f64) -> Vec<(f64, f64)> {
    let mut total = vec![0.0; bins];
    for row in per_row.chunks(bins) {
        for (t, v) in total.iter_mut().zip(row) {
            *t += v;
        }
    }
    total
        .into_iter()
        .enumerate()
        .map(|(i, v)| (i as f64 * step_deg, v))
        .collect()
}

/// The weight of half-spectrum column kx: columns 1..cols/2 stand for their conjugate mirror
/// too (same |F|, same angle mod 180); column 0 and, for even cols, column cols/2 hold both
/// signs already.
fn angular_weight(cols: usize, kx: usize) -> f64 {
    if kx == 0 || (cols.is_multiple_of(2) && kx == cols / 2) {
        1.0
    } else {
        2.0
    }
}

/// The angular bin of DFT sample (ky, kx): the direction of its frequency vector (1/um), mod
/// 180 degrees, in bins of `step_deg`.
fn angular_bin(g: &Grid, ky: usize, kx: usize, step_deg: f64, bins: usize) -> usize {
    let rows = g.rows();
    let ky_s = if ky <= rows / 2 {
        ky as f64
    } else {
        ky as f64 - rows as f64
    };
    let fy = ky_s / (rows as f64 * g.pitch_y_um());
    let fx = kx as f64 / (g.cols() as f64 * g.pitch_x_um());
    let theta = fy.atan2(fx).to_degrees().rem_euclid(180.0);
    ((theta / step_deg) as usize).min(bins - 1)
}

/// Std from an angular density: the lower edge of its largest bin (first on ties).
pub(crate) fn std_from_angular(a: &[(f64, f64)]) -> f64 {
    let mut best = (f64::NEG_INFINITY, f64::NAN);
    for &(t, v) in a {
        if v > best.0 {
            best = (v, t);
        }
    }
    best.1
}

/// Sal, Str and Std of `g`.
///
/// Memory: the whole lag plane is twice the map; on maps of `WINDOW_MIN_POINTS` or more the
/// lags within an eighth of the plane's extents are made first (in column blocks, below the
/// map's own size at any moment), and when the region of f_ACF > 0.2 f_ACF(0) reaches that
/// window's border (a long correlation, a strong lay, a tilt) the whole plane is made through
/// spill files in the system's temporary folder (`TMPDIR`; unnamed, gone at exit) and read
/// back in bands, never held (see [`sal_str_spilled`]). Either way the same values, bit for
/// bit.
pub fn spatial_params(g: &Grid) -> Result<SpatialParams, MetrologyError> {
    let window = (g.rows() * g.cols() >= WINDOW_MIN_POINTS).then(|| {
        (
            (g.rows() - 1) / WINDOW_FRACTION,
            (g.cols() - 1) / WINDOW_FRACTION,
        )
    });
    // The mean and valid count once for the three transforms.
    let c = CentredRows::of(g)?;
    let (sal, str_) = sal_str_in(g, &c, window)?;
    let std = std_from_angular(&angular_amplitude_of(g, &c, STD_STEP_DEG));
    Ok(SpatialParams { sal, str_, std })
}

/// Sal and Str from the lags of `window` when they hold the region, otherwise (or without a
/// window) from the whole plane.
fn sal_str_in(
    g: &Grid,
    c: &CentredRows,
    window: Option<(usize, usize)>,
) -> Result<(f64, f64), MetrologyError> {
    if let Some(w) = window {
        // A tilted or strongly laid map's region runs out of the window along an axis: known
        // from two 1-D passes, instead of the window's whole work being made and declined.
        if !axes_reach(g, c, w, ACF_THRESHOLD) {
            if let Some(v) = Acf::of_lags(g, c, Some(w))?.sal_str_within(ACF_THRESHOLD) {
                return Ok(v);
            }
        }
    }
    match window {
        // The whole plane is twice the map: not held on a large map.
        Some(_) => sal_str_spilled(g, c, ACF_THRESHOLD, spill_block_cols(g.rows())),
        None => Ok(Acf::of_lags(g, c, None)?.sal_str(ACF_THRESHOLD)),
    }
}

/// Spectrum columns per block of [`SpilledCorrelation`] for a map of `rows` rows: a block
/// of about `SPILL_BLOCK_BYTES`.
fn spill_block_cols(rows: usize) -> usize {
    let p = crate::fft::fast_len(2 * rows - 1);
    (SPILL_BLOCK_BYTES / (p * std::mem::size_of::<Complex<f64>>())).max(1)
}

/// [`Acf::of`]`(g)?.sal_str(s)` (the same values, bit for bit) without the lag plane in
/// memory: its sums are made through spill files (see [`SpilledCorrelation`]) and read back
/// twice, a band of lag rows at a time: once for which lags are above the threshold (a bit
/// each), whose region and edges are then found as on the plane itself, and once for the
/// lags the rays to those edges can read (see [`rays_window`]). Memory: the bits, a band,
/// a block of columns and that window (an eighth of the plane or less unless a long,
/// isotropic correlation fills the plane without reaching its border).
fn sal_str_spilled(
    g: &Grid,
    c: &CentredRows,
    s: f64,
    block_cols: usize,
) -> Result<(f64, f64), MetrologyError> {
    let (rows, cols) = (g.rows(), g.cols());
    let sums = SpilledCorrelation::new(
        &|r, buf: &mut [f64]| c.row(r, buf),
        rows,
        cols,
        block_cols,
        None,
    )?;
    let pairs = if c.valid == rows * cols {
        None
    } else {
        let mask = mask_rows(g);
        Some(SpilledCorrelation::new(
            &mask, rows, cols, block_cols, None,
        )?)
    };
    // f_ACF at the lags ty = 0..=wy, tx = -wx..=wx, handed to `take(ty0, band)` a band of
    // rows at a time (the division of `Acf::of_lags`).
    let acf_bands = |(wy, wx): (usize, usize),
                     take: &mut dyn FnMut(usize, &[f64])|
     -> Result<(), MetrologyError> {
        let mut sum_bands = sums.lag_bands(wx);
        let mut pair_bands = pairs.as_ref().map(|p| p.lag_bands(wx));
        for ty0 in (0..=wy).step_by(SPILL_BAND_ROWS) {
            let nb = SPILL_BAND_ROWS.min(wy + 1 - ty0);
            let band = sum_bands.read(ty0, nb)?;
            match pair_bands.as_mut() {
                None => divide_by_full_pairs(band, ty0, wx, (rows, cols)),
                Some(pair_bands) => {
                    let k = pair_bands.read(ty0, nb)?;
                    divide_by_pairs(band, &*k, |k| k.round());
                }
            }
            take(ty0, band);
        }
        Ok(())
    };
    // Pass 1: the lags of the half plane above the threshold.
    let (ry, rx) = (rows - 1, cols - 1);
    let w = 2 * cols - 1;
    let mut above = vec![0u64; (rows * w).div_ceil(64)];
    let mut thr = f64::NAN;
    acf_bands((ry, rx), &mut |ty0, band| {
        if ty0 == 0 {
            thr = s * band[rx];
        }
        for (k, &v) in band.iter().enumerate() {
            if v > thr {
                let i = ty0 * w + k;
                above[i / 64] |= 1 << (i % 64);
            }
        }
    })?;
    if thr.is_nan() {
        return Ok((f64::NAN, f64::NAN));
    }
    let is_above = |y: isize, x: isize| {
        let (y, x) = if y < 0 { (-y, -x) } else { (y, x) };
        let i = y as usize * w + (x + rx as isize) as usize;
        above[i / 64] & (1 << (i % 64)) != 0
    };
    let Some((edges, touches)) = region_edges_where(rows, cols, (ry, rx), is_above) else {
        // The window is the whole plane: its border is the plane's.
        return Ok((f64::NAN, f64::NAN));
    };
    drop(above);
    // Pass 2: the lags the rays read.
    let (px, py) = (g.pitch_x_um(), g.pitch_y_um());
    let (wy, wx) = rays_window(&edges, touches, (px, py), (rows, cols));
    let ww = 2 * wx + 1;
    let mut half = vec![0.0; (wy + 1) * ww];
    acf_bands((wy, wx), &mut |ty0, band| {
        half[ty0 * ww..ty0 * ww + band.len()].copy_from_slice(band);
    })?;
    let acf = Acf {
        rows,
        cols,
        pitch_x_um: px,
        pitch_y_um: py,
        wy,
        wx,
        half,
    };
    Ok(acf.sal_str_of(thr, &edges, touches))
}

/// The window |ty| <= wy, |tx| <= wx of the lags [`Acf::sal_str_of`]'s rays to `edges` can
/// read. Every ray in full (`!touches`): a ray to e samples the segment from 0 to e, its
/// bilinear corners within |ty| <= max(|ey|, 1). Only the shortest (`touches`): the
/// `RAYS_IN_FULL` nearest rays in full, within the `RAYS_IN_FULL`-th smallest distance d of
/// 0; every other ray is left once a sample is at or beyond the bound, which is at most the
/// nearest ray's length (<= its distance <= d), so its samples lie within d plus one step
/// (half a diagonal pitch) of 0, their corners one lag further.
fn rays_window(
    edges: &[(isize, isize)],
    touches: bool,
    (px, py): (f64, f64),
    (rows, cols): (usize, usize),
) -> (usize, usize) {
    let clamp = |wy: usize, wx: usize| (wy.min(rows - 1), wx.min(cols - 1));
    if edges.is_empty() {
        return clamp(1, 1);
    }
    if !touches {
        let reach = |f: fn(&(isize, isize)) -> isize| {
            edges
                .iter()
                .map(|e| f(e).unsigned_abs())
                .max()
                .unwrap_or(0)
                .max(1)
        };
        return clamp(reach(|e| e.0), reach(|e| e.1));
    }
    let mut d: Vec<f64> = edges
        .iter()
        .map(|&(ey, ex)| ((ey as f64 * py).powi(2) + (ex as f64 * px).powi(2)).sqrt())
        .collect();
    let k = RAYS_IN_FULL.min(d.len()) - 1;
    let (_, &mut dk, _) = d.select_nth_unstable_by(k, f64::total_cmp);
    let r_um = dk + px.max(py);
    clamp((r_um / py) as usize + 2, (r_um / px) as usize + 2)
}

/// Whether f_ACF stays above `s` f_ACF(0) along the tx axis out to lag `wx` or along the ty
/// axis out to `wy`: then the region reaches the window's border and the window would
/// decline. Only a hint (its sums are made in another order than the ACF's own, so a lag
/// within rounding of the threshold may go either way, and a region leaving the window off
/// the axes is not seen): it picks the path, never the values. Maps with gaps: false.
fn axes_reach(g: &Grid, c: &CentredRows, (wy, wx): (usize, usize), s: f64) -> bool {
    let (rows, cols) = (g.rows(), g.cols());
    if c.valid != rows * cols {
        return false;
    }
    // f_ACF(lag) = S(lag) / pairs, S from the summed power of the 1-D transforms.
    let reaches = |sums: Vec<f64>, n: usize, other: usize, w: usize| {
        let f = |t: usize| sums[t] / ((n - t) * other) as f64;
        let thr = s * f(0);
        w > 0 && (1..=w.min(n - 1)).all(|t| f(t) > thr)
    };
    let along_x = axis_sums(rows.div_ceil(AXIS_BLOCK), cols, |b, lines| {
        let r0 = b * AXIS_BLOCK;
        let n = AXIS_BLOCK.min(rows - r0);
        for (j, line) in lines.chunks_mut(cols).take(n).enumerate() {
            c.row(r0 + j, line);
        }
        n
    });
    if reaches(along_x, cols, rows, wx) {
        return true;
    }
    // Columns in blocks too: each row's few adjacent values read together.
    let z = g.heights_um;
    let along_y = axis_sums(cols.div_ceil(AXIS_BLOCK), rows, |b, lines| {
        let k0 = b * AXIS_BLOCK;
        let n = AXIS_BLOCK.min(cols - k0);
        for r in 0..rows {
            for (j, &v) in z[r * cols + k0..r * cols + k0 + n].iter().enumerate() {
                lines[j * rows + r] = v - c.mean;
            }
        }
        n
    });
    reaches(along_y, rows, cols, wy)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrology::spectrum::spectrum2_of;

    /// Heights of a wavy, tilted surface with noise (xorshift), rows x cols.
    fn surface(rows: usize, cols: usize, tilt: f64, seed: u64) -> Vec<f64> {
        let mut state = seed | 1;
        (0..rows * cols)
            .map(|k| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let noise = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
                let (r, c) = ((k / cols) as f64, (k % cols) as f64);
                (0.21 * c + 0.05 * r).sin()
                    + 0.6 * (0.07 * c - 0.13 * r).cos()
                    + tilt * (c + 0.3 * r)
                    + 0.3 * noise
            })
            .collect()
    }

    /// The angular density, one atan2 per DFT sample: the reference the run search must equal.
    fn angular_per_sample(g: &Grid, step_deg: f64) -> Vec<f64> {
        let c = CentredRows::of(g).unwrap();
        let spec = spectrum2_of(&|r, buf: &mut [f64]| c.row(r, buf), g.rows(), g.cols());
        let (rows, cols) = (g.rows(), g.cols());
        let h = cols / 2 + 1;
        let bins = (180.0 / step_deg).ceil() as usize;
        let mut total = vec![0.0; bins];
        for ky in 0..rows {
            let mut acc = vec![0.0; bins];
            for kx in 0..h {
                let b = angular_bin(g, ky, kx, step_deg, bins);
                acc[b] += angular_weight(cols, kx) * spec[ky * h + kx].norm();
            }
            for (t, v) in total.iter_mut().zip(&acc) {
                *t += v;
            }
        }
        total
    }

    /// Bin runs found by bisection give the per-sample sums bit for bit: odd and even sizes,
    /// square and non-square pitches, a coarse and the default step.
    #[test]
    fn angular_runs_equal_per_sample_bins() {
        for &(rows, cols, px, py) in &[(64, 64, 1.0, 1.0), (61, 90, 0.4, 1.3), (128, 37, 2.0, 0.5)]
        {
            let z = surface(rows, cols, 0.0, (rows * cols) as u64);
            let g = Grid::new(&z, rows, cols, px, py).unwrap();
            for step in [STD_STEP_DEG, 7.0] {
                let fast: Vec<u64> = angular_amplitude(&g, step)
                    .unwrap()
                    .iter()
                    .map(|p| p.1.to_bits())
                    .collect();
                let each: Vec<u64> = angular_per_sample(&g, step)
                    .iter()
                    .map(|v| v.to_bits())
                    .collect();
                assert_eq!(
                    fast, each,
                    "{rows} x {cols}, pitch {px} x {py}, step {step}"
                );
            }
        }
    }

    /// Sal from rays left early (Str undefined) is the minimum over every ray in full, to the
    /// bit; and a region inside the plane still gives Str from every ray.
    #[test]
    fn early_left_rays_give_the_full_minimum() {
        let mut touched = 0;
        for &(rows, cols, px, py, tilt) in &[
            (96, 96, 1.0, 1.0, 0.08),
            (70, 120, 0.5, 1.5, 0.05),
            (96, 96, 1.0, 1.0, 0.0),
        ] {
            let z = surface(rows, cols, tilt, 7 + rows as u64);
            let g = Grid::new(&z, rows, cols, px, py).unwrap();
            let acf = Acf::of(&g).unwrap();
            let thr = ACF_THRESHOLD * acf.at(0, 0);
            let (edges, touches) = acf.region_edges(thr).unwrap();
            assert!(!edges.is_empty());
            let full: Vec<f64> = edges
                .iter()
                .map(|&(ey, ex)| {
                    let d = ((ey as f64 * py).powi(2) + (ex as f64 * px).powi(2)).sqrt();
                    acf.decay_length((ey, ex), d, thr, f64::INFINITY)
                })
                .collect();
            let lo = full.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = full.iter().copied().fold(0.0, f64::max);
            let (sal, str_) = acf.sal_str(ACF_THRESHOLD);
            assert_eq!(sal.to_bits(), lo.to_bits(), "{rows} x {cols} tilt {tilt}");
            if touches {
                touched += 1;
                assert!(str_.is_nan());
            } else {
                assert_eq!(str_.to_bits(), (lo / hi).to_bits());
            }
        }
        assert!(
            touched >= 1,
            "no case reached the border: the early exit went untested"
        );
    }

    /// Sal and Str through the spill files are the whole plane's in memory, to the bit: on
    /// regions that reach the border (tilted) and that do not, short and long correlations,
    /// maps with gaps, bands and column blocks that do not divide the plane, and a flat map
    /// (no threshold). The rays read only the window they were given (`Acf::at` asserts it in
    /// debug builds).
    #[test]
    fn spilled_sal_str_is_the_whole_planes() {
        let mut kinds = (0, 0);
        let flat = vec![2.5; 70 * 90];
        let cases: Vec<(usize, usize, f64, f64, Vec<f64>)> = vec![
            (150, 97, 1.0, 0.7, surface(150, 97, 0.08, 3)),
            (97, 150, 0.5, 1.5, surface(97, 150, 0.0, 5)),
            (130, 130, 0.8, 0.8, short_correlation(130, 130, 9)),
            (
                129,
                71,
                1.0,
                1.0,
                with_gaps(surface(129, 71, 0.05, 11), 129, 71, 7),
            ),
            (
                80,
                140,
                1.2,
                0.9,
                with_gaps(short_correlation(80, 140, 13), 80, 140, 5),
            ),
            (70, 90, 1.0, 1.0, flat),
        ];
        for (rows, cols, px, py, z) in &cases {
            let (rows, cols) = (*rows, *cols);
            let g = Grid::new(z, rows, cols, *px, *py).unwrap();
            let acf = Acf::of(&g).unwrap();
            let whole = acf.sal_str(ACF_THRESHOLD);
            let c = CentredRows::of(&g).unwrap();
            for block_cols in [8, 24, 1 << 20] {
                let spilled = sal_str_spilled(&g, &c, ACF_THRESHOLD, block_cols).unwrap();
                assert_eq!(
                    (spilled.0.to_bits(), spilled.1.to_bits()),
                    (whole.0.to_bits(), whole.1.to_bits()),
                    "{rows} x {cols}, blocks of {block_cols}: {spilled:?} vs {whole:?}"
                );
            }
            let thr = ACF_THRESHOLD * acf.at(0, 0);
            if let Some((edges, touches)) = acf.region_edges(thr) {
                if !edges.is_empty() {
                    if touches {
                        kinds.0 += 1
                    } else {
                        kinds.1 += 1
                    }
                }
            }
        }
        assert!(
            kinds.0 >= 1 && kinds.1 >= 1,
            "regions reaching the border and not: {kinds:?}"
        );
    }

    /// White noise smoothed by a 5 x 5 box (correlated over a few points only).
    fn short_correlation(rows: usize, cols: usize, seed: u64) -> Vec<f64> {
        let noise = surface(rows, cols, 0.0, seed)
            .iter()
            .enumerate()
            .map(|(k, v)| (v * 1e4 + k as f64 * 0.618).sin())
            .collect::<Vec<_>>();
        (0..rows * cols)
            .map(|k| {
                let (r, c) = ((k / cols) as isize, (k % cols) as isize);
                let mut sum = 0.0;
                for dy in -2..=2 {
                    for dx in -2..=2 {
                        let (y, x) = (
                            (r + dy).clamp(0, rows as isize - 1),
                            (c + dx).clamp(0, cols as isize - 1),
                        );
                        sum += noise[y as usize * cols + x as usize];
                    }
                }
                sum
            })
            .collect()
    }

    /// A surface with gaps: every `every`-th point NaN, and a hole.
    fn with_gaps(mut z: Vec<f64>, rows: usize, cols: usize, every: usize) -> Vec<f64> {
        for (k, v) in z.iter_mut().enumerate() {
            let (r, c) = (k / cols, k % cols);
            if k % every == 3 || (r > rows / 3 && r < rows / 2 && c > cols / 4 && c < cols / 3) {
                *v = f64::NAN;
            }
        }
        z
    }

    /// The windowed ACF holds the whole plane's values at its lags, bit for bit: full and
    /// gappy maps, odd and even sizes, windows of one lag up to beyond the plane, 1 to 9
    /// column blocks.
    #[test]
    fn window_lags_are_the_whole_planes() {
        for &(rows, cols, gaps) in &[
            (40, 52, false),
            (37, 29, true),
            (64, 64, false),
            (33, 80, true),
        ] {
            let z = surface(rows, cols, 0.01, (rows + cols) as u64);
            let z = if gaps { with_gaps(z, rows, cols, 7) } else { z };
            let g = Grid::new(&z, rows, cols, 0.8, 1.1).unwrap();
            let whole = Acf::of(&g).unwrap();
            for (wy, wx) in [
                (0, 0),
                (3, 5),
                (rows / 8, cols / 8),
                (rows - 2, 1),
                (rows + 4, cols + 4),
            ] {
                let win = Acf::of_lags(&g, &CentredRows::of(&g).unwrap(), Some((wy, wx))).unwrap();
                let (wy, wx) = (wy.min(rows - 1) as isize, wx.min(cols - 1) as isize);
                for ty in -wy..=wy {
                    for tx in -wx..=wx {
                        assert_eq!(
                            win.at(ty, tx).to_bits(),
                            whole.at(ty, tx).to_bits(),
                            "{rows} x {cols} gaps {gaps}, window {wy} x {wx}, lag ({ty}, {tx})"
                        );
                    }
                }
            }
            let c = CentredRows::of(&g).unwrap();
            let row = |r: usize, buf: &mut [f64]| c.row(r, buf);
            let plane = correlation_half_plane(&row, rows, cols);
            for blocks in [1, 3, 9] {
                let win = correlation_window(&row, rows, cols, (rows - 1, cols - 1), blocks);
                let same = win
                    .iter()
                    .zip(&plane)
                    .all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(
                    same && win.len() == plane.len(),
                    "{rows} x {cols}, {blocks} blocks"
                );
            }
        }
    }

    /// Sal and Str from a window that holds the region are the whole plane's, bit for bit; a
    /// window the region reaches the border of declines, and `sal_str_in` then gives the
    /// whole plane's.
    #[test]
    fn window_sal_str_is_the_whole_planes_or_declines() {
        let (mut held, mut declined) = (0, 0);
        for &(rows, cols, tilt, gaps) in &[
            (96, 96, -1.0, false),
            (90, 120, -1.0, true),
            (96, 96, 0.0, false),
            (96, 96, 0.08, false),
            (80, 64, 0.05, true),
        ] {
            // tilt -1: the short correlation.
            let z = if tilt < 0.0 {
                short_correlation(rows, cols, 5 + cols as u64)
            } else {
                surface(rows, cols, tilt, 11 + rows as u64)
            };
            let z = if gaps {
                with_gaps(z, rows, cols, 11)
            } else {
                z
            };
            let g = Grid::new(&z, rows, cols, 1.0, 0.7).unwrap();
            let (sal, str_) = Acf::of(&g).unwrap().sal_str(ACF_THRESHOLD);
            let window = ((rows - 1) / WINDOW_FRACTION, (cols - 1) / WINDOW_FRACTION);
            match Acf::of_lags(&g, &CentredRows::of(&g).unwrap(), Some(window))
                .unwrap()
                .sal_str_within(ACF_THRESHOLD)
            {
                Some((a, b)) => {
                    held += 1;
                    assert_eq!((a.to_bits(), b.to_bits()), (sal.to_bits(), str_.to_bits()));
                }
                None => declined += 1,
            }
            let (a, b) = sal_str_in(&g, &CentredRows::of(&g).unwrap(), Some(window)).unwrap();
            assert_eq!(
                (a.to_bits(), b.to_bits()),
                (sal.to_bits(), str_.to_bits()),
                "{rows} x {cols} tilt {tilt} gaps {gaps}"
            );
        }
        assert!(
            held >= 1 && declined >= 1,
            "held {held}, declined {declined}"
        );
    }

    /// The floor without the library call is floor.
    #[test]
    fn floor_lag_is_floor() {
        for v in [
            -3.5,
            -3.0,
            -0.25,
            -0.0,
            0.0,
            0.25,
            1.0,
            2.999,
            1e6 + 0.5,
            -1e6 - 0.5,
        ] {
            assert_eq!(floor_lag(v), v.floor(), "{v}");
        }
    }
}
