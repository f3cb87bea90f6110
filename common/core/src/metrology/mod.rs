//! ISO 25178-2 height and hybrid parameters, plane levelling, SIM (the reference study's
//! eq. 12) and the model-vs-measurement deviation of its Table 6.
//!
//! Conventions (the parity reference is surfalize 0.19.2, see docs/formats.md):
//! z = the valid (non-NaN) heights, N their count, c = z - mean(z); nothing is levelled or
//! filtered implicitly ([`level_plane`] is the explicit step).
//! - Sa = sum|c| / N; Sq = sqrt(sum c^2 / N); Sp = max c; Sv = |min c|; Sz = Sp + Sv;
//!   Ssk = (sum c^3 / N) / Sq^3; Sku = (sum c^4 / N) / Sq^4 (not excess).
//! - Sdq = sqrt(mean (dz/dx)^2 + mean (dz/dy)^2), forward differences, each mean over its own
//!   count; a difference takes part only when both its points are valid.
//! - Sdr = (A / A_proj - 1) * 100 %, A = the mean of the two diagonal triangulations of each
//!   grid cell. With NaN, only cells whose four corners are valid count (A_proj is theirs):
//!   Sdr and Sdq need a filled grid to mean what ISO says; on data with holes they describe
//!   the measured part only.
//!
//! Computation: two passes over the heights. The first gathers everything that does not need
//! the mean (count, sum, min, max, the squared differences and the four corner-triangle
//! normals of every cell), the second the central sums about the first mean, corrected
//! algebraically to the exact mean. Each row is summed in short vector lanes (`wide::f64x4`,
//! NaN masked out branch-free; chains of cols / 4 terms keep the error ~1e-15 relative) and
//! rows are combined in row order with Neumaier's compensated summation (naive f64 sums over
//! 1e7 points drift past 1e-9 relative). Rows run in parallel (rayon); the result does not
//! depend on the thread count, bit for bit.

use rayon::prelude::*;
use serde::Serialize;
use wide::{f64x4, CmpEq, CmpGt, CmpLt};

use crate::{ParamError, Sampling, Shape, ShapeError};

mod all;
pub mod feature;
pub mod functional;
pub mod psd;
pub mod spatial;
mod spectrum;

pub use all::{all_params, all_params_pruned, AllParams, ParamValue};
pub use feature::{feature_params, FeatureParams};
pub use functional::{abbott_curve, functional_params, AbbottCurve, FunctionalParams};
pub use psd::{radial_psd, ArealPsd};
pub use spatial::{spatial_params, Acf, SpatialParams};

/// Neumaier's compensated sum.
#[derive(Debug, Clone, Copy, Default)]
struct Compensated {
    sum: f64,
    comp: f64,
}

impl Compensated {
    fn add(&mut self, v: f64) {
        let t = self.sum + v;
        if self.sum.abs() >= v.abs() {
            self.comp += (self.sum - t) + v;
        } else {
            self.comp += (v - t) + self.sum;
        }
        self.sum = t;
    }
    fn value(self) -> f64 {
        self.sum + self.comp
    }
}

/// The nine parameters; heights in um, Sdq dimensionless, Sdr in %.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct Params {
    #[serde(rename = "Sa", deserialize_with = "crate::record::nan_if_null")]
    pub sa: f64,
    #[serde(rename = "Sq", deserialize_with = "crate::record::nan_if_null")]
    pub sq: f64,
    #[serde(rename = "Sp", deserialize_with = "crate::record::nan_if_null")]
    pub sp: f64,
    #[serde(rename = "Sv", deserialize_with = "crate::record::nan_if_null")]
    pub sv: f64,
    #[serde(rename = "Sz", deserialize_with = "crate::record::nan_if_null")]
    pub sz: f64,
    #[serde(rename = "Ssk", deserialize_with = "crate::record::nan_if_null")]
    pub ssk: f64,
    #[serde(rename = "Sku", deserialize_with = "crate::record::nan_if_null")]
    pub sku: f64,
    #[serde(rename = "Sdq", deserialize_with = "crate::record::nan_if_null")]
    pub sdq: f64,
    #[serde(rename = "Sdr", deserialize_with = "crate::record::nan_if_null")]
    pub sdr: f64,
}

impl Params {
    /// Name (ISO 25178) and value, in the order Sa Sq Sp Sv Sz Ssk Sku Sdq Sdr.
    pub fn named(&self) -> [(&'static str, f64); 9] {
        [
            ("Sa", self.sa),
            ("Sq", self.sq),
            ("Sp", self.sp),
            ("Sv", self.sv),
            ("Sz", self.sz),
            ("Ssk", self.ssk),
            ("Sku", self.sku),
            ("Sdq", self.sdq),
            ("Sdr", self.sdr),
        ]
    }

    /// One parameter by its ISO 25178 name ("Sa" .. "Sdr").
    pub fn by_name(&self, name: &str) -> Option<f64> {
        self.named()
            .into_iter()
            .find(|(n, _)| *n == name)
            .map(|(_, v)| v)
    }
}

/// Why parameters could not be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MetrologyError {
    #[error("height map: {0}")]
    Shape(#[from] ShapeError),
    #[error("no valid (non-NaN) height")]
    NoValidPoint,
    #[error(
        "feature parameters: the map has {points} points, the segmentation labels at most {max}"
    )]
    TooManyPoints { points: usize, max: usize },
    #[error(transparent)]
    Param(#[from] ParamError),
    /// The autocorrelation of a large map is made through spill files (see spatial.rs): what
    /// failed, with the folder (the error's text: this enum is `Clone` and `PartialEq`).
    #[error("autocorrelation: {0}")]
    Spill(String),
    #[error("the two maps differ in shape: {a_rows} x {a_cols} vs {b_rows} x {b_cols}")]
    ShapeMismatch {
        a_rows: usize,
        a_cols: usize,
        b_rows: usize,
        b_cols: usize,
    },
}

impl From<crate::store::StoreError> for MetrologyError {
    fn from(e: crate::store::StoreError) -> Self {
        Self::Spill(e.to_string())
    }
}

/// A height map borrowed for computing: row-major heights (um, NaN = not measured) and their
/// [`Sampling`] (the one `Grid`: a view of a surface with its pitch).
#[derive(Debug, Clone, Copy)]
pub struct Grid<'a> {
    heights_um: &'a [f64],
    sampling: Sampling,
}

/// Errors unless `len` samples fill `sampling`'s shape (an empty shape is allowed: its
/// parameters are [`MetrologyError::NoValidPoint`], unlike [`Shape::check`]).
fn fills(sampling: Sampling, len: usize) -> Result<(), MetrologyError> {
    let shape = sampling.shape();
    if shape.checked_len() == Some(len) {
        return Ok(());
    }
    Err(ShapeError::Length {
        shape,
        expected: shape.len(),
        found: len,
    }
    .into())
}

impl<'a> Grid<'a> {
    /// `rows x cols` heights at the given pitch (the pitch checked by [`Sampling::new`]).
    pub fn new(
        heights_um: &'a [f64],
        rows: usize,
        cols: usize,
        pitch_x_um: f64,
        pitch_y_um: f64,
    ) -> Result<Self, MetrologyError> {
        let sampling = Sampling::new(Shape::new(rows, cols), pitch_x_um, pitch_y_um)?;
        Self::of(heights_um, sampling)
    }

    /// Heights on `sampling`; errors unless they fill its shape (an empty map is a map: its
    /// parameters are [`MetrologyError::NoValidPoint`]).
    pub fn of(heights_um: &'a [f64], sampling: Sampling) -> Result<Self, MetrologyError> {
        fills(sampling, heights_um.len())?;
        Ok(Self {
            heights_um,
            sampling,
        })
    }

    pub fn heights_um(&self) -> &'a [f64] {
        self.heights_um
    }
    pub fn sampling(&self) -> Sampling {
        self.sampling
    }
    pub fn rows(&self) -> usize {
        self.sampling.rows()
    }
    pub fn cols(&self) -> usize {
        self.sampling.cols()
    }
    pub fn pitch_x_um(&self) -> f64 {
        self.sampling.pitch_x_um()
    }
    pub fn pitch_y_um(&self) -> f64 {
        self.sampling.pitch_y_um()
    }

    fn row(&self, r: usize) -> &'a [f64] {
        let cols = self.cols();
        &self.heights_um[r * cols..(r + 1) * cols]
    }
}

/// Lane-wise sum of a row: four independent accumulators (vectorises; short chains).
#[inline]
#[allow(clippy::needless_range_loop)] // lane-major indexing is the point here
fn lanes<const K: usize>(n: usize, mut f: impl FnMut(usize) -> [f64; K]) -> [f64; K] {
    let mut acc = [[0.0f64; 4]; K];
    let full = n / 4 * 4;
    let mut i = 0;
    while i < full {
        for l in 0..4 {
            let v = f(i + l);
            for k in 0..K {
                acc[k][l] += v[k];
            }
        }
        i += 4;
    }
    let mut out = [0.0; K];
    for k in 0..K {
        out[k] = (acc[k][0] + acc[k][1]) + (acc[k][2] + acc[k][3]);
    }
    for j in full..n {
        let v = f(j);
        for k in 0..K {
            out[k] += v[k];
        }
    }
    out
}

/// Per-row partial sums combined in row order with compensation (deterministic).
#[allow(clippy::needless_range_loop)]
fn row_sums<const K: usize>(rows: usize, f: impl Fn(usize) -> [f64; K] + Sync) -> [f64; K] {
    let per_row: Vec<[f64; K]> = (0..rows).into_par_iter().map(&f).collect();
    let mut acc = [Compensated::default(); K];
    for s in &per_row {
        for k in 0..K {
            acc[k].add(s[k]);
        }
    }
    acc.map(Compensated::value)
}

/// Lanes of the vector kernels.
type V = f64x4;

#[inline(always)]
fn load(s: &[f64]) -> V {
    V::new([s[0], s[1], s[2], s[3]])
}

/// All-ones lanes where `v` is not NaN: `valid(v) & x` keeps x there and gives 0 elsewhere,
/// so NaN never reaches an accumulator (branch-free).
#[inline(always)]
fn valid(v: V) -> V {
    v.cmp_eq(v)
}

/// Lane accumulators reduced in a fixed order.
#[inline(always)]
fn fold(v: V) -> f64 {
    let a = v.to_array();
    (a[0] + a[1]) + (a[2] + a[3])
}

/// Scalar counterpart of `valid(v) & x` for the remainders.
#[inline(always)]
fn keep(ok: bool, v: f64) -> f64 {
    if ok {
        v
    } else {
        0.0
    }
}

/// What one row contributes independently of the mean: valid count, sum, min, max; and with
/// the hybrid sums: sum (dz)^2 along x (row r) and its count, along y (rows r, r+1) and its
/// count, the Sdr excess of the cells between rows r and r+1 and their count.
#[derive(Debug, Clone, Copy)]
struct RowSums {
    /// n, sum z, sum dzx^2, nx, sum dzy^2, ny, sum cell excess, cells.
    sums: [f64; 8],
    lo: f64,
    hi: f64,
}

/// Count, sum, min and max of one row's valid heights.
fn row_count_sum_min_max(a: &[f64]) -> (f64, f64, f64, f64) {
    let (mut n, mut s) = (V::ZERO, V::ZERO);
    let mut lo = V::splat(f64::INFINITY);
    let mut hi = V::splat(f64::NEG_INFINITY);
    let chunks = a.chunks_exact(4);
    let rest = chunks.remainder();
    for c in chunks {
        let z = load(c);
        let ok = valid(z);
        n += ok & V::ONE;
        s += ok & z;
        // NaN compares false: it never replaces a bound.
        lo = z.cmp_lt(lo).blend(z, lo);
        hi = z.cmp_gt(hi).blend(z, hi);
    }
    let (mut n, mut s) = (fold(n), fold(s));
    let mut lo = lo.to_array().into_iter().fold(f64::INFINITY, f64::min);
    let mut hi = hi.to_array().into_iter().fold(f64::NEG_INFINITY, f64::max);
    for &z in rest {
        if !z.is_nan() {
            n += 1.0;
            s += z;
            lo = lo.min(z);
            hi = hi.max(z);
        }
    }
    (n, s, lo, hi)
}

/// Sum and count of the squared x differences of one row (both points valid).
fn row_dx2(a: &[f64]) -> (f64, f64) {
    let (mut s, mut n) = (0.0, 0.0);
    for w in a.windows(2) {
        let d = w[1] - w[0];
        if !d.is_nan() {
            s += d * d;
            n += 1.0;
        }
    }
    (s, n)
}

/// Pitch terms of the cell kernel: py^2, px^2, (px py)^2, 4 px py.
#[derive(Debug, Clone, Copy)]
struct CellPitch {
    py2: f64,
    px2: f64,
    cell2: f64,
    four_cells: f64,
}

/// One cell (corners a0 a1 on row r, b0 b1 on row r+1), any lane type: [dzx^2 of row r,
/// dzy^2 of the left column, the cell's excess sum |n| - 4 px py].
///
/// A cell's four corner triangles (both diagonal triangulations) have normals
/// |n| = sqrt(dzx^2 py^2 + dzy^2 px^2 + (px py)^2); the cell's area is sum |n| / 4. Subtracting
/// 4 px py per cell rounds by ~1e-16 of px py per cell, i.e. ~1e-14 % absolute on Sdr, far
/// below the 1e-9 % that near-flat parity allows; without a division per triangle Sdr costs
/// four square roots per cell.
macro_rules! cell_terms {
    ($a0:expr, $a1:expr, $b0:expr, $b1:expr, $c:expr, $splat:expr) => {{
        let (a0, a1, b0, b1) = ($a0, $a1, $b0, $b1);
        let dxa = a1 - a0;
        let dxb = b1 - b0;
        let dyl = b0 - a0;
        let dyr = b1 - a1;
        let (dxa2, dyl2) = (dxa * dxa, dyl * dyl);
        let py2 = $splat($c.py2);
        let px2 = $splat($c.px2);
        let cell2 = $splat($c.cell2);
        let (bx, tx) = (dxa2 * py2, dxb * dxb * py2);
        let (ly, ry) = (dyl2 * px2, dyr * dyr * px2);
        let v = ((bx + ly + cell2).sqrt() + (bx + ry + cell2).sqrt())
            + ((tx + ry + cell2).sqrt() + (tx + ly + cell2).sqrt())
            - $splat($c.four_cells);
        (dxa2, dyl2, v)
    }};
}

/// The difference and cell sums between rows `a` (r) and `b` (r+1): sum dzx^2 of row a and
/// its count, sum dzy^2 and count, the Sdr excess of the cells and their count.
fn row_pair_sums(a: &[f64], b: &[f64], c: CellPitch) -> [f64; 6] {
    if a.is_empty() || a.len() != b.len() {
        return [0.0; 6];
    }
    let m = a.len() - 1;
    let mut acc = [V::ZERO; 6];
    let (a0, a1, b0, b1) = (&a[..m], &a[1..], &b[..m], &b[1..]);
    let chunks = a0
        .chunks_exact(4)
        .zip(a1.chunks_exact(4))
        .zip(b0.chunks_exact(4))
        .zip(b1.chunks_exact(4));
    for (((xa0, xa1), xb0), xb1) in chunks {
        let (dx2, dy2, v) = cell_terms!(load(xa0), load(xa1), load(xb0), load(xb1), c, V::splat);
        let (okx, oky, okc) = (valid(dx2), valid(dy2), valid(v));
        acc[0] += okx & dx2;
        acc[1] += okx & V::ONE;
        acc[2] += oky & dy2;
        acc[3] += oky & V::ONE;
        acc[4] += okc & v;
        acc[5] += okc & V::ONE;
    }
    let mut out = acc.map(fold);
    let id = |v: f64| v;
    for i in m / 4 * 4..m {
        let (dx2, dy2, v) = cell_terms!(a0[i], a1[i], b0[i], b1[i], c, id);
        let (okx, oky, okc) = (!dx2.is_nan(), !dy2.is_nan(), !v.is_nan());
        out[0] += keep(okx, dx2);
        out[1] += keep(okx, 1.0);
        out[2] += keep(oky, dy2);
        out[3] += keep(oky, 1.0);
        out[4] += keep(okc, v);
        out[5] += keep(okc, 1.0);
    }
    // The last column's y difference (the cells cover columns 0..m).
    if let (Some(&za), Some(&zb)) = (a.last(), b.last()) {
        let d = zb - za;
        if !d.is_nan() {
            out[2] += d * d;
            out[3] += 1.0;
        }
    }
    out
}

/// Everything that does not need the mean, one pass: the sums of row r and of the cells
/// between rows r and r+1 (`hybrid` = false skips the difference and cell sums).
fn pass_independent(g: &Grid, hybrid: bool) -> RowSums {
    let (px, py) = (g.pitch_x_um(), g.pitch_y_um());
    let c = CellPitch {
        py2: py * py,
        px2: px * px,
        cell2: (px * py) * (px * py),
        four_cells: 4.0 * (px * py),
    };
    let per_row: Vec<RowSums> = (0..g.rows())
        .into_par_iter()
        .map(|r| {
            let a = g.row(r);
            let (n, s, lo, hi) = row_count_sum_min_max(a);
            let mut sums = [n, s, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
            if hybrid {
                let pair = if r + 1 < g.rows() {
                    row_pair_sums(a, g.row(r + 1), c)
                } else {
                    let (sx, nx) = row_dx2(a);
                    [sx, nx, 0.0, 0.0, 0.0, 0.0]
                };
                sums[2..].copy_from_slice(&pair);
            }
            RowSums { sums, lo, hi }
        })
        .collect();
    // Rows combined in row order with compensation: the result is the same for any thread count.
    let mut acc = [Compensated::default(); 8];
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for row in &per_row {
        for (a, &v) in acc.iter_mut().zip(&row.sums) {
            a.add(v);
        }
        lo = lo.min(row.lo);
        hi = hi.max(row.hi);
    }
    RowSums {
        sums: acc.map(Compensated::value),
        lo,
        hi,
    }
}

/// The central sums about the exact mean of the valid heights: sum |c|, c^2, c^3, c^4, from
/// one pass about `mean0` (the first, rounded mean) corrected algebraically by the mean of
/// the residuals d (so no third pass is needed to refine the mean).
fn pass_central(g: &Grid, n: f64, mean0: f64) -> (f64, [f64; 4]) {
    central_about_mean(
        n,
        mean0,
        row_sums(g.rows(), |r| row_central(g.row(r), mean0)),
    )
}

/// One row's sums about `mean0`: sum |c|, c, c^2, c^3, c^4 and sum sign(c).
fn row_central(row: &[f64], mean0: f64) -> [f64; 6] {
    let mut acc = [V::ZERO; 6];
    let m0 = V::splat(mean0);
    let chunks = row.chunks_exact(4);
    let rest = chunks.remainder();
    for ch in chunks {
        let z = load(ch);
        let c = valid(z) & (z - m0);
        let c2 = c * c;
        acc[0] += c.abs();
        acc[1] += c;
        acc[2] += c2;
        acc[3] += c2 * c;
        acc[4] += c2 * c2;
        acc[5] += (c.cmp_gt(V::ZERO) & V::ONE) - (c.cmp_lt(V::ZERO) & V::ONE);
    }
    let mut out = acc.map(fold);
    for &z in rest {
        if !z.is_nan() {
            let c = z - mean0;
            let c2 = c * c;
            out[0] += c.abs();
            out[1] += c;
            out[2] += c2;
            out[3] += c2 * c;
            out[4] += c2 * c2;
            out[5] += if c > 0.0 {
                1.0
            } else if c < 0.0 {
                -1.0
            } else {
                0.0
            };
        }
    }
    out
}

/// The exact mean and the central sums (|c|, c^2, c^3, c^4) from the sums about `mean0`.
fn central_about_mean(n: f64, mean0: f64, sums: [f64; 6]) -> (f64, [f64; 4]) {
    let [s_abs, s1, s2, s3, s4, sgn] = sums;
    let d = s1 / n;
    let mean = mean0 + d;
    // Moments about mean0 + d from those about mean0 (binomial expansion, s1 = n d). For Sa,
    // |c - d| = |c| - d sign(c) wherever |c| > |d|; d is a rounding residue (~1e-16 of the
    // heights), so the points where that does not hold change Sa by less than |d| / n each.
    let sa_sum = s_abs - d * sgn;
    let c2 = s2 - n * d * d;
    let c3 = s3 - 3.0 * d * s2 + 2.0 * n * d * d * d;
    let c4 = s4 - 4.0 * d * s3 + 6.0 * d * d * s2 - 3.0 * n * d * d * d * d;
    (mean, [sa_sum, c2, c3, c4])
}

fn heights_from(g: &Grid, p1: &RowSums) -> Result<[f64; 7], MetrologyError> {
    let (n, sum) = (p1.sums[0], p1.sums[1]);
    if n == 0.0 {
        return Err(MetrologyError::NoValidPoint);
    }
    Ok(heights_of(p1, pass_central(g, n, sum / n)))
}

/// Sa..Sku from the first pass (count, bounds) and the central sums about the exact mean.
fn heights_of(p1: &RowSums, (mean, [s1, s2, s3, s4]): (f64, [f64; 4])) -> [f64; 7] {
    let n = p1.sums[0];
    let sq = (s2 / n).sqrt();
    let (sp, sv) = (p1.hi - mean, (p1.lo - mean).abs());
    // A constant surface has Sq = 0: skewness and kurtosis are undefined (NaN), as in surfalize.
    [
        s1 / n,
        sq,
        sp,
        sv,
        sp + sv,
        (s3 / n) / (sq * sq * sq),
        (s4 / n) / (sq * sq * sq * sq),
    ]
}

fn hybrid_from(g: &Grid, p1: &RowSums) -> (f64, f64) {
    hybrid_of(g.pitch_x_um(), g.pitch_y_um(), p1)
}

fn hybrid_of(px: f64, py: f64, p1: &RowSums) -> (f64, f64) {
    let [_, _, sx, nx, sy, ny, excess, cells] = p1.sums;
    let sdq = if nx + ny == 0.0 {
        f64::NAN
    } else {
        // The sums are of height differences; the slopes divide by the pitch once here.
        let mx = if nx > 0.0 { sx / nx / (px * px) } else { 0.0 };
        let my = if ny > 0.0 { sy / ny / (py * py) } else { 0.0 };
        (mx + my).sqrt()
    };
    // Each cell's area ratio - 1 = (sum of its four normals' excess / 4) / (px py).
    let sdr = if cells == 0.0 {
        f64::NAN
    } else {
        excess / (4.0 * px * py) / cells * 100.0
    };
    (sdq, sdr)
}

/// The height parameters Sa Sq Sp Sv Sz Ssk Sku (um; Ssk, Sku dimensionless) over the valid
/// points, about their mean.
pub fn height_params(g: &Grid) -> Result<[f64; 7], MetrologyError> {
    heights_from(g, &pass_independent(g, false))
}

/// The valid heights' count, lowest and highest (um) and mean (um, exactly as the height
/// parameters take it).
#[derive(Debug, Clone, Copy)]
pub(crate) struct HeightSummary {
    pub valid: usize,
    pub lo: f64,
    pub hi: f64,
    pub mean: f64,
}

/// [`HeightSummary`] of `g`: the height parameters' two passes, without their moments.
pub(crate) fn height_summary(g: &Grid) -> Result<HeightSummary, MetrologyError> {
    let p1 = pass_independent(g, false);
    let (n, sum) = (p1.sums[0], p1.sums[1]);
    if n == 0.0 {
        return Err(MetrologyError::NoValidPoint);
    }
    Ok(HeightSummary {
        // A count of at most the map's points, exact in f64.
        valid: n as usize,
        lo: p1.lo,
        hi: p1.hi,
        mean: pass_central(g, n, sum / n).0,
    })
}

/// The mean of the valid heights, exactly as the height parameters take it.
pub(crate) fn height_params_mean(g: &Grid) -> Result<f64, MetrologyError> {
    Ok(height_summary(g)?.mean)
}

/// Sdq and Sdr (%). NaN when no difference / no whole cell is valid.
pub fn hybrid_params(g: &Grid) -> (f64, f64) {
    hybrid_from(g, &pass_independent(g, true))
}

/// All nine parameters: two passes over the heights (the mean-independent sums, including
/// the slope and area sums, then the central moments).
pub fn params(g: &Grid) -> Result<Params, MetrologyError> {
    let p1 = pass_independent(g, true);
    let [sa, sq, sp, sv, sz, ssk, sku] = heights_from(g, &p1)?;
    let (sdq, sdr) = hybrid_from(g, &p1);
    Ok(Params {
        sa,
        sq,
        sp,
        sv,
        sz,
        ssk,
        sku,
        sdq,
        sdr,
    })
}

/// The least-squares plane z = a + b x + c y through the valid points (x = col * pitch_x,
/// y = row * pitch_y, um), as (a, b, c); fitted on centred coordinates for conditioning.
pub fn fit_plane(g: &Grid) -> Result<(f64, f64, f64), MetrologyError> {
    fit_plane_rows(g.heights_um, g.sampling)
}

/// [`fit_plane`] of float32 heights on `sampling`, without a float64 copy of the map (the
/// mesher fits the whole panorama's plane). The same sums in the same order: each height is
/// widened exactly, so the plane is the one [`fit_plane`] gives the widened map, to the bit.
pub fn fit_plane_f32(
    heights_um: &[f32],
    sampling: Sampling,
) -> Result<(f64, f64, f64), MetrologyError> {
    fills(sampling, heights_um.len())?;
    fit_plane_rows(heights_um, sampling)
}

fn fit_plane_rows<T: Copy + Into<f64> + Sync>(
    heights_um: &[T],
    sampling: Sampling,
) -> Result<(f64, f64, f64), MetrologyError> {
    let cols = sampling.cols();
    let row_of = |r: usize| &heights_um[r * cols..(r + 1) * cols];
    // Pass 1: count and the sums of z, x, y over the valid points.
    let [n, sz, sx, sy] = row_sums(sampling.rows(), |r| {
        let row = row_of(r);
        let [n, sz, sx] = lanes(row.len(), |i| {
            let z: f64 = row[i].into();
            let ok = !z.is_nan();
            [keep(ok, 1.0), keep(ok, z), keep(ok, i as f64)]
        });
        [n, sz, sx, n * r as f64]
    });
    if n == 0.0 {
        return Err(MetrologyError::NoValidPoint);
    }
    let (zmean, xm, ym) = (sz / n, sx / n, sy / n);
    // Pass 2: centred second moments and cross products.
    let [sxx, sxy, syy, sxz, syz] = row_sums(sampling.rows(), |r| {
        let row = row_of(r);
        let y = r as f64 - ym;
        lanes(row.len(), |i| {
            let z: f64 = row[i].into();
            let ok = !z.is_nan();
            let x = keep(ok, i as f64 - xm);
            let yv = keep(ok, y);
            let dz = keep(ok, z - zmean);
            [x * x, x * yv, yv * yv, x * dz, yv * dz]
        })
    });
    let det = sxx * syy - sxy * sxy;
    // Points on one line (or one point): the plane's slope across the line is undetermined;
    // take the least-squares fit along the direction that has extent.
    let (bx, by) = if det.abs() > 1e-12 * (sxx * syy).max(f64::MIN_POSITIVE) {
        ((sxz * syy - syz * sxy) / det, (syz * sxx - sxz * sxy) / det)
    } else if sxx > 0.0 {
        (sxz / sxx, 0.0)
    } else if syy > 0.0 {
        (0.0, syz / syy)
    } else {
        (0.0, 0.0)
    };
    // Per-pixel slopes to per-um slopes; intercept at pixel (0, 0).
    let (b, c) = (bx / sampling.pitch_x_um(), by / sampling.pitch_y_um());
    let a = zmean - bx * xm - by * ym;
    Ok((a, b, c))
}

/// The heights minus their least-squares plane (NaN stays NaN).
pub fn level_plane(g: &Grid) -> Result<Vec<f64>, MetrologyError> {
    let (a, b, c) = fit_plane(g)?;
    let (bx, by) = (b * g.pitch_x_um(), c * g.pitch_y_um());
    let mut out = vec![0.0; g.heights_um.len()];
    out.par_chunks_mut(g.cols().max(1))
        .enumerate()
        .for_each(|(r, o)| {
            let row = g.row(r);
            let base = a + by * r as f64;
            for (i, (o, &z)) in o.iter_mut().zip(row).enumerate() {
                *o = z - (base + bx * i as f64);
            }
        });
    Ok(out)
}

/// SIM, the reference study's eq. 12 as we read it: the normalised (zero-mean) cross-correlation
/// of two maps of the same shape, sum (a - mean a)(b - mean b) / sqrt(sum (a - mean a)^2 *
/// sum (b - mean b)^2), over the pixels valid in both; 1 = identical up to offset and scale.
/// NaN when either map is constant there.
pub fn sim(a: &[f64], b: &[f64]) -> Result<f64, MetrologyError> {
    if a.len() != b.len() {
        return Err(MetrologyError::ShapeMismatch {
            a_rows: 1,
            a_cols: a.len(),
            b_rows: 1,
            b_cols: b.len(),
        });
    }
    let both = |i: usize| !a[i].is_nan() && !b[i].is_nan();
    let chunk = 4096;
    let chunks = a.len().div_ceil(chunk);
    let range = |c: usize| c * chunk..((c + 1) * chunk).min(a.len());
    let [n, sa, sb] = row_sums(chunks, |c| {
        let mut s = [0.0; 3];
        for i in range(c) {
            if both(i) {
                s[0] += 1.0;
                s[1] += a[i];
                s[2] += b[i];
            }
        }
        s
    });
    if n == 0.0 {
        return Err(MetrologyError::NoValidPoint);
    }
    let (ma, mb) = (sa / n, sb / n);
    let [sab, saa, sbb] = row_sums(chunks, |c| {
        let mut s = [0.0; 3];
        for i in range(c) {
            if both(i) {
                let (x, y) = (a[i] - ma, b[i] - mb);
                s[0] += x * y;
                s[1] += x * x;
                s[2] += y * y;
            }
        }
        s
    });
    Ok(sab / (saa * sbb).sqrt())
}

/// RMS of a - b over the pixels valid in both (um), with the number of such pixels.
pub fn rms_difference(a: &[f64], b: &[f64]) -> Result<(f64, usize), MetrologyError> {
    if a.len() != b.len() {
        return Err(MetrologyError::ShapeMismatch {
            a_rows: 1,
            a_cols: a.len(),
            b_rows: 1,
            b_cols: b.len(),
        });
    }
    let chunk = 4096;
    let [n, s] = row_sums(a.len().div_ceil(chunk), |c| {
        let mut s = [0.0; 2];
        for i in c * chunk..((c + 1) * chunk).min(a.len()) {
            let d = a[i] - b[i];
            if !d.is_nan() {
                s[0] += 1.0;
                s[1] += d * d;
            }
        }
        s
    });
    if n == 0.0 {
        return Err(MetrologyError::NoValidPoint);
    }
    Ok(((s / n).sqrt(), n as usize))
}

// ---------------------------------------------------------------------------------------------
// The nine parameters of a map too large to hold: rows pushed twice (issue 17).

/// [`params`] of a height map fed row by row, twice: every row in order through
/// [`ParamsByRows::push_first`], then [`ParamsByRows::end_first`], then every row again, in
/// the same order, through [`ParamsByRows::push_second`], then [`ParamsByRows::finish`]. It
/// holds one row; the result equals [`params`] on the whole map bit for bit (the same per-row
/// kernels, rows combined in the same order).
#[derive(Debug, Clone)]
pub struct ParamsByRows {
    cols: usize,
    pitch_um: (f64, f64),
    cell: CellPitch,
    /// The previous row of the first pass and its count, sum, min, max.
    prev: Vec<f64>,
    prev_sums: Option<(f64, f64, f64, f64)>,
    first: [Compensated; 8],
    lo: f64,
    hi: f64,
    /// The first pass's result, once ended.
    p1: Option<RowSums>,
    /// The second pass's sums about the first pass's mean.
    second: [Compensated; 6],
}

impl ParamsByRows {
    /// For rows of `cols` heights at the given pitch (um, finite and positive).
    pub fn new(cols: usize, pitch_x_um: f64, pitch_y_um: f64) -> Result<Self, MetrologyError> {
        Sampling::new(Shape::new(0, cols), pitch_x_um, pitch_y_um)?;
        let (px, py) = (pitch_x_um, pitch_y_um);
        Ok(Self {
            cols,
            pitch_um: (px, py),
            cell: CellPitch {
                py2: py * py,
                px2: px * px,
                cell2: (px * py) * (px * py),
                four_cells: 4.0 * (px * py),
            },
            prev: Vec::with_capacity(cols),
            prev_sums: None,
            first: [Compensated::default(); 8],
            lo: f64::INFINITY,
            hi: f64::NEG_INFINITY,
            p1: None,
            second: [Compensated::default(); 6],
        })
    }

    fn check(&self, row: &[f64]) -> Result<(), MetrologyError> {
        if row.len() != self.cols {
            return Err(ShapeError::Length {
                shape: Shape::new(1, self.cols),
                expected: self.cols,
                found: row.len(),
            }
            .into());
        }
        Ok(())
    }

    /// Adds the previous row's sums: its pair with `next`, or its x differences when last.
    fn close_prev(&mut self, next: Option<&[f64]>) {
        let Some((n, s, lo, hi)) = self.prev_sums.take() else {
            return;
        };
        let pair = match next {
            Some(b) => row_pair_sums(&self.prev, b, self.cell),
            None => {
                let (sx, nx) = row_dx2(&self.prev);
                [sx, nx, 0.0, 0.0, 0.0, 0.0]
            }
        };
        let sums = [n, s, pair[0], pair[1], pair[2], pair[3], pair[4], pair[5]];
        for (a, &v) in self.first.iter_mut().zip(&sums) {
            a.add(v);
        }
        self.lo = self.lo.min(lo);
        self.hi = self.hi.max(hi);
    }

    /// The next row of the first pass.
    pub fn push_first(&mut self, row: &[f64]) -> Result<(), MetrologyError> {
        self.check(row)?;
        self.close_prev(Some(row));
        self.prev.clear();
        self.prev.extend_from_slice(row);
        self.prev_sums = Some(row_count_sum_min_max(row));
        Ok(())
    }

    /// Ends the first pass.
    pub fn end_first(&mut self) {
        self.close_prev(None);
        self.prev = Vec::new();
        self.p1 = Some(RowSums {
            sums: self.first.map(Compensated::value),
            lo: self.lo,
            hi: self.hi,
        });
    }

    /// The next row of the second pass; a row before [`ParamsByRows::end_first`] is a shape
    /// error (no first pass has ended).
    pub fn push_second(&mut self, row: &[f64]) -> Result<(), MetrologyError> {
        self.check(row)?;
        let Some(p1) = &self.p1 else {
            return Err(ShapeError::Length {
                shape: Shape::new(0, self.cols),
                expected: 0,
                found: row.len(),
            }
            .into());
        };
        let mean0 = p1.sums[1] / p1.sums[0];
        for (a, v) in self.second.iter_mut().zip(row_central(row, mean0)) {
            a.add(v);
        }
        Ok(())
    }

    /// The nine parameters.
    pub fn finish(self) -> Result<Params, MetrologyError> {
        let p1 = self.p1.ok_or(MetrologyError::NoValidPoint)?;
        let (n, sum) = (p1.sums[0], p1.sums[1]);
        if n == 0.0 {
            return Err(MetrologyError::NoValidPoint);
        }
        let central = central_about_mean(n, sum / n, self.second.map(Compensated::value));
        let [sa, sq, sp, sv, sz, ssk, sku] = heights_of(&p1, central);
        let (sdq, sdr) = hybrid_of(self.pitch_um.0, self.pitch_um.1, &p1);
        Ok(Params {
            sa,
            sq,
            sp,
            sv,
            sz,
            ssk,
            sku,
            sdq,
            sdr,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The mesher fits the panorama's plane on its float32 heights: the same plane, to the
    /// bit, as the float64 fit of the widened map (NaN holes and an odd width included).
    #[test]
    fn the_float32_plane_is_the_widened_maps_plane() {
        let (rows, cols) = (37, 53);
        let heights: Vec<f32> = (0..rows * cols)
            .map(|k| {
                let (r, c) = ((k / cols) as f32, (k % cols) as f32);
                if k % 17 == 3 {
                    f32::NAN
                } else {
                    0.3 + 0.011 * c - 0.007 * r + (0.9 * c).sin() * (0.4 * r).cos()
                }
            })
            .collect();
        let sampling = Sampling::new(Shape::new(rows, cols), 0.8148, 0.75).unwrap();
        let widened: Vec<f64> = heights.iter().map(|&h| f64::from(h)).collect();
        let wide = fit_plane(&Grid::of(&widened, sampling).unwrap()).unwrap();
        let narrow = fit_plane_f32(&heights, sampling).unwrap();
        assert_eq!(wide.0.to_bits(), narrow.0.to_bits());
        assert_eq!(wide.1.to_bits(), narrow.1.to_bits());
        assert_eq!(wide.2.to_bits(), narrow.2.to_bits());
        assert!((wide.1 - 0.011 / 0.8148).abs() < 2e-3, "{wide:?}");
        // A length that does not fill the sampling is refused, not read past.
        assert!(fit_plane_f32(&heights[1..], sampling).is_err());
    }
}
