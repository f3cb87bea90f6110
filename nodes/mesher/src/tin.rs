//! Error-bounded triangulation of a height field (a TIN: triangulated irregular network) by
//! greedy insertion (Garland and Heckbert 1995, "Fast polygonal approximation of terrains and
//! height fields", algorithm III).
//!
//! Start from the two triangles spanning the grid's corners; every triangle knows its worst
//! sample (the one farthest, vertically, from the triangle's plane); a max-heap holds the
//! triangles by that error; the worst sample overall becomes a vertex, the triangulation is kept
//! Delaunay (Bowyer-Watson: the triangles whose circumcircle holds the new point are replaced by
//! a fan around it), and only the new triangles are rescanned. Stop when the worst error is at
//! most epsilon or the triangle budget is reached.
//!
//! Vertices are grid samples, so the predicates run on integer (column, row) coordinates in
//! exact integer arithmetic (orientation in i64, in-circle in i128): no epsilon-tuned geometry,
//! no degenerate triangles, and the many co-circular points of a grid are handled exactly
//! (a point on a circumcircle does not enter the cavity). The Delaunay criterion is applied in
//! index space, i.e. to the grid as if its pitches were equal; any valid triangulation bounds
//! the error the same way, this only chooses the shapes.
//!
//! Missing samples (NaN): with [`MissingSamples::Fill`] they are filled first
//! ([`crate::fill_missing`]) and covered by the mesh, but not held to the bound: nothing is
//! judged there, and a hole of filled samples then costs the triangles that cover it, not one
//! per sample along its edge. With [`MissingSamples::Holes`] a
//! triangle must never span one: a triangle whose corners are all measured but that covers a
//! missing sample is refined at that sample (it becomes a vertex, its height from the fill);
//! triangles with a missing corner are left out of the result, and refined first if they cover
//! a measured sample, so every measured sample stays inside a kept triangle.

use rayon::prelude::*;

use crate::error::{MeshError, Result};
use surfstream_core::raster::{RasterView, Shape};

use crate::field::{fill_missing, positive_finite};
use crate::geom;
use surfstream_core::ParamError;

const NONE: u32 = u32::MAX;

/// What to do with missing (NaN) samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MissingSamples {
    /// Fill them ([`crate::fill_missing`]) and mesh the filled surface; needed for a solid.
    #[default]
    Fill,
    /// Leave them out: no triangle covers a missing sample (an open sheet with holes).
    Holes,
}

/// Parameters of the error-bounded triangulation.
#[derive(Debug, Clone, PartialEq)]
pub struct TinParams {
    /// Largest allowed vertical distance between a sample and the mesh, um (> 0).
    pub epsilon_um: f64,
    /// Stop inserting once the triangulation has this many triangles (the bound may then not
    /// hold; [`Tin::budget_reached`] says so).
    pub max_triangles: Option<usize>,
    /// Missing samples: filled or left out as holes.
    pub missing: MissingSamples,
    /// Side of the blocks meshed independently, samples (None: [`DEFAULT_BLOCK_SAMPLES`];
    /// ignored with a triangle budget, which needs one block).
    pub block_samples: Option<usize>,
    /// Make each block's highest and lowest measured sample (off its shared sides) a vertex
    /// before the error-driven insertion, so that a region's peak and valley, which carry Sz,
    /// sit exactly on the mesh whatever the bound (module `tolerance`).
    pub keep_extremes: bool,
}

/// An error-bounded triangulation of a height field. Vertices are grid samples.
#[derive(Debug, Clone)]
pub struct Tin {
    /// The grid's size, samples.
    pub shape: Shape,
    /// Sample index (`row * cols + col`) of every vertex.
    pub vertex_samples: Vec<u32>,
    /// Kept triangles as vertex indices, counter-clockwise seen from +z (x = column, y = row).
    pub triangles: Vec<[u32; 3]>,
    /// The blocks in row-major order and the range of `triangles` that covers each.
    pub blocks: Vec<(Block, std::ops::Range<usize>)>,
    /// The outer rim of the kept triangles, counter-clockwise from +z, when they form one
    /// simple loop around the whole grid (always with [`MissingSamples::Fill`]).
    pub rim: Option<Vec<u32>>,
    /// The heights used for the vertices (the input with missing samples filled), um.
    pub filled_um: Vec<f32>,
    /// How many samples were missing (NaN) in the input.
    pub missing_samples: usize,
    /// True when the triangle budget stopped the insertion before the bound was met.
    pub budget_reached: bool,
    /// Triangles left out because they still span a missing sample when the budget stopped
    /// the insertion (holes mode only).
    pub dropped_spanning: usize,
}

/// The smallest interior angle every triangle must have, measured in x, y, z (um) with the
/// grid's pitches: LIGGGHTS refuses slivers at import (module `target`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AngleBound {
    pub min_angle_deg: f64,
    pub pitch: surfstream_core::Pitch,
}

/// Rounds of [`Builder::bound_angles`] at most (each treats every triangle below the bound).
const ANGLE_ROUNDS: usize = 32;

/// The vertex [`Builder::sliver_fix`] chooses.
enum SliverFix {
    /// A sample strictly inside the block.
    Inside(usize),
    /// The middle of a segment of side `0` (bottom, right, top, left): sample `1`.
    Side(usize, usize),
    /// No sample improves it (its edges are a pixel or two long).
    Stuck,
}

/// Exact orientation of (a, b, c): > 0 counter-clockwise, 0 collinear.
#[inline]
fn orient(a: (i64, i64), b: (i64, i64), c: (i64, i64)) -> i64 {
    (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0)
}

/// Exact in-circle test: > 0 when p lies strictly inside the circumcircle of the
/// counter-clockwise triangle (a, b, c).
#[inline]
fn incircle(a: (i64, i64), b: (i64, i64), c: (i64, i64), p: (i64, i64)) -> i128 {
    let (adx, ady) = ((a.0 - p.0) as i128, (a.1 - p.1) as i128);
    let (bdx, bdy) = ((b.0 - p.0) as i128, (b.1 - p.1) as i128);
    let (cdx, cdy) = ((c.0 - p.0) as i128, (c.1 - p.1) as i128);
    (adx * adx + ady * ady) * (bdx * cdy - cdx * bdy)
        + (bdx * bdx + bdy * bdy) * (cdx * ady - adx * cdy)
        + (cdx * cdx + cdy * cdy) * (adx * bdy - bdx * ady)
}

/// [`incircle`] in i64, exact while coordinate differences stay below 2^14 (every term is
/// then below 2^58): the common case inside a block, and about twice as fast as i128.
#[inline]
fn incircle_small(a: (i64, i64), b: (i64, i64), c: (i64, i64), p: (i64, i64)) -> i64 {
    let (adx, ady) = (a.0 - p.0, a.1 - p.1);
    let (bdx, bdy) = (b.0 - p.0, b.1 - p.1);
    let (cdx, cdy) = (c.0 - p.0, c.1 - p.1);
    (adx * adx + ady * ady) * (bdx * cdy - cdx * bdy)
        + (bdx * bdx + bdy * bdy) * (cdx * ady - adx * cdy)
        + (cdx * cdx + cdy * cdy) * (adx * bdy - bdx * ady)
}

/// Largest block side for which [`incircle_small`] is exact.
const SMALL_SIDE: usize = 1 << 14;

#[derive(Clone, Copy)]
struct Tri {
    /// Vertex ids, counter-clockwise.
    v: [u32; 3],
    /// `n[k]`: the neighbour across the edge opposite `v[k]`, i.e. (v[k+1], v[k+2]).
    n: [u32; 3],
    /// Bumped at every rescan: queue entries with an older stamp are stale.
    stamp: u32,
    /// The sample to insert next in this triangle (NONE: nothing to do).
    candidate: u32,
    /// The candidate's vertical distance from the triangle's plane, um (infinite: forced by
    /// a missing sample), kept so that a finer bound can requeue without a rescan.
    err: f64,
    /// Covers a missing sample although its corners are measured (holes mode).
    spans_missing: bool,
}

/// Visits every grid sample inside or on the boundary of the counter-clockwise triangle
/// (a, b, c) (integer column, row coordinates), row by row, with the row and the inclusive
/// column range. Exact: each edge bounds the columns by floor or ceiling of an integer
/// fraction, kept as quotient and remainder and stepped row by row (one division per edge
/// and triangle instead of one per edge and row: this loop runs for every new triangle).
#[inline]
pub(crate) fn for_each_row(
    a: (i64, i64),
    b: (i64, i64),
    c: (i64, i64),
    mut f: impl FnMut(i64, i64, i64) -> bool,
) {
    let y0 = a.1.min(b.1).min(c.1);
    let y1 = a.1.max(b.1).max(c.1);
    let x_lo = a.0.min(b.0).min(c.0);
    let x_hi = a.0.max(b.0).max(c.0);
    // Inside or on the edge (p, q): (q - p) x (s - p) >= 0, i.e. dy * (x - px) <= dx * (y - py).
    // dy > 0: x <= px + floor(dx (y - py) / dy); dy < 0: x >= px + ceil(dx (y - py) / dy).
    // The fraction n / d (d > 0) is kept as q + r / d; each row adds step / d to it.
    struct Edge {
        upper: bool,
        base: i64,
        q: i64,
        r: i64,
        d: i64,
        qs: i64,
        rs: i64,
    }
    let mut edges: [Option<Edge>; 3] = [None, None, None];
    let mut flat_outside = false;
    for (k, (p, q)) in [(a, b), (b, c), (c, a)].into_iter().enumerate() {
        let (dx, dy) = (q.0 - p.0, q.1 - p.1);
        if dy == 0 {
            // A horizontal edge bounds the rows, not the columns: the triangle lies on its
            // inner side unless it is degenerate.
            flat_outside |= dx * (y0 - p.1) < 0 || dx * (y1 - p.1) < 0;
            continue;
        }
        let (n, d, step) = if dy > 0 {
            (dx * (y0 - p.1), dy, dx)
        } else {
            (-dx * (y0 - p.1), -dy, -dx)
        };
        let (q, r) = div_floor(n, d);
        let (qs, rs) = div_floor(step, d);
        edges[k] = Some(Edge {
            upper: dy > 0,
            base: p.0,
            q,
            r,
            d,
            qs,
            rs,
        });
    }
    if flat_outside {
        return;
    }
    for y in y0..=y1 {
        let (mut lo, mut hi) = (x_lo, x_hi);
        for e in edges.iter_mut().flatten() {
            if e.upper {
                hi = hi.min(e.base + e.q);
            } else {
                lo = lo.max(e.base + e.q + i64::from(e.r != 0));
            }
            e.q += e.qs;
            e.r += e.rs;
            if e.r >= e.d {
                e.r -= e.d;
                e.q += 1;
            }
        }
        if lo <= hi && !f(y, lo, hi) {
            return;
        }
    }
}

/// Floor division with remainder, n = q d + r, 0 <= r < d, for d > 0. Through an f64
/// quotient, corrected (exact integers below 2^52, where the truncated, correctly rounded
/// quotient is off by at most one), because a 64-bit integer division costs several times more and this
/// runs six times per new triangle.
#[inline]
fn div_floor(n: i64, d: i64) -> (i64, i64) {
    const EXACT: i64 = 1 << 52;
    if n.abs() >= EXACT || d >= EXACT {
        return (n.div_euclid(d), n.rem_euclid(d));
    }
    // Truncation, not floor(): without SSE4.1 in the target, floor() is a libm call.
    let mut q = (n as f64 / d as f64) as i64;
    let mut r = n - q * d;
    while r < 0 {
        q -= 1;
        r += d;
    }
    while r >= d {
        q += 1;
        r -= d;
    }
    (q, r)
}

/// The plane through three (column, row, height) points as z(x, y) = z0 + gx (x - x0) +
/// gy (y - y0) around the first point.
#[derive(Clone, Copy)]
pub(crate) struct Plane {
    x0: f64,
    y0: f64,
    z0: f64,
    gx: f64,
    gy: f64,
}

impl Plane {
    pub(crate) fn through(p: [(i64, i64, f64); 3]) -> Self {
        let [a, b, c] = p;
        let (e1, e2) = (
            ((b.0 - a.0) as f64, (b.1 - a.1) as f64, b.2 - a.2),
            ((c.0 - a.0) as f64, (c.1 - a.1) as f64, c.2 - a.2),
        );
        let nx = e1.1 * e2.2 - e1.2 * e2.1;
        let ny = e1.2 * e2.0 - e1.0 * e2.2;
        let nz = e1.0 * e2.1 - e1.1 * e2.0; // > 0 for a counter-clockwise triangle
        let inv = -1.0 / nz;
        Self {
            x0: a.0 as f64,
            y0: a.1 as f64,
            z0: a.2,
            gx: nx * inv,
            gy: ny * inv,
        }
    }

    #[inline]
    pub(crate) fn at(&self, x: i64, y: i64) -> f64 {
        self.z0 + self.gx * (x as f64 - self.x0) + self.gy * (y as f64 - self.y0)
    }
}

/// The work queue: triangles by the error of their candidate, in buckets 16 to an octave
/// above epsilon. Refinement forced by missing samples goes to the bottom bucket: done
/// last, when the error-driven triangles are already small, it stays local (done first, the
/// long triangles of the first steps cascaded into many needless vertices). Taking any triangle
/// of the highest non-empty bucket is greedy insertion up to 6.25 % in the error, which changes
/// the order of refinement a little and the bound not at all, and costs O(1) per push and pop
/// where a binary heap over a million triangles spent most of the run on cache misses.
/// Entries carry the triangle's stamp at queueing time; a rescanned triangle leaves a stale
/// entry that is skipped when popped.
#[derive(Clone)]
struct BucketQueue {
    buckets: Vec<Vec<(u32, u32)>>,
    top: usize,
}

const BUCKETS: usize = 64 * 16 + 2;

impl BucketQueue {
    /// Bucket of an error `ratio` = error / epsilon > 1: the exponent and the top four
    /// mantissa bits of the f64, i.e. 16 linear steps per octave (no logarithm in the loop).
    fn bucket(ratio: f64) -> usize {
        let b = 1 + ((ratio.to_bits() - 1f64.to_bits()) >> 48) as usize;
        b.min(BUCKETS - 1)
    }

    fn push(&mut self, b: usize, t: u32, stamp: u32) {
        self.buckets[b].push((t, stamp));
        self.top = self.top.max(b);
    }

    fn clear(&mut self) {
        self.buckets.iter_mut().for_each(Vec::clear);
        self.top = 0;
    }

    fn pop(&mut self) -> Option<(u32, u32)> {
        loop {
            if let Some(e) = self.buckets[self.top].pop() {
                return Some(e);
            }
            if self.top == 0 {
                return None;
            }
            self.top -= 1;
        }
    }
}

/// A rectangle of the grid meshed on its own: columns `x0..=x1`, rows `y0..=y1` (inclusive:
/// neighbouring blocks share their border samples).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Block {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

/// Default side of the blocks, samples: a block's working set (heights, flags, triangles)
/// stays in the L2 cache, which is what makes the greedy loop fast (with one block over a
/// 1024^2 field nearly every insertion missed the cache), while the extra vertices that the
/// fixed borders cost stay well under 1 % on rough fields.
pub const DEFAULT_BLOCK_SAMPLES: usize = 128;

#[derive(Clone)]
struct Builder<'a> {
    /// Width of the whole grid (global sample index = row * width + column).
    width: usize,
    block: Block,
    /// Width of the block (its local index = (row - y0) * bw + (column - x0)).
    bw: usize,
    z: &'a [f32],
    /// Measured (not NaN in the input), whole grid, in holes mode; None when every sample
    /// counts as measured.
    valid: Option<&'a [bool]>,
    /// Measured, whole grid, in fill mode with missing samples: the filled ones need no
    /// accuracy (nothing is judged there), only to be covered, so they are never candidates.
    measured: Option<&'a [bool]>,
    /// The mesh's height at every sample of the block (local index), kept up to date by the
    /// scans (blocks that are balanced, without holes): what the balance reads each round.
    mesh_local: Option<Vec<f64>>,
    /// Local: a vertex, or a sample on a shared border that must not become one (its error is
    /// already bounded along the border); never a candidate.
    settled: Vec<bool>,
    verts: Vec<(i64, i64)>,
    vertex_samples: Vec<u32>,
    tris: Vec<Tri>,
    queue: BucketQueue,
    epsilon_um: f64,
    /// Rescan the new triangles after an insertion (off while the fixed border is inserted).
    scanning: bool,
    /// Both sides below [`SMALL_SIDE`]: the in-circle test runs in i64.
    small: bool,
    mark: Vec<u32>,
    epoch: u32,
    // Scratch buffers reused by every insertion.
    cavity: Vec<u32>,
    rim: Vec<(u32, u32, u32)>,
    fresh: Vec<u32>,
}

impl Builder<'_> {
    #[inline]
    fn local(&self, x: i64, y: i64) -> usize {
        (y as usize - self.block.y0) * self.bw + (x as usize - self.block.x0)
    }

    fn add_vertex(&mut self, s: usize) -> u32 {
        let id = self.verts.len() as u32;
        let (x, y) = ((s % self.width) as i64, (s / self.width) as i64);
        self.verts.push((x, y));
        self.vertex_samples.push(s as u32);
        let l = self.local(x, y);
        self.settled[l] = true;
        id
    }

    fn corner(&self, v: u32) -> (i64, i64, f64) {
        let (x, y) = self.verts[v as usize];
        let s = self.vertex_samples[v as usize] as usize;
        (x, y, f64::from(self.z[s]))
    }

    /// Finds the triangle's next sample to insert and queues it.
    fn scan(&mut self, t: u32) {
        let tri = self.tris[t as usize];
        let c = tri.v.map(|v| self.corner(v));
        let plane = Plane::through(c);
        let (a, b, cc) = ((c[0].0, c[0].1), (c[1].0, c[1].1), (c[2].0, c[2].1));
        let w = self.width as i64;
        let (bx0, by0, bw) = (self.block.x0 as i64, self.block.y0 as i64, self.bw as i64);
        let mut best = (0.0f64, NONE);
        let mut forced = NONE;
        let mut spans_missing = false;
        match self.valid {
            None => for_each_row(a, b, cc, |y, lo, hi| {
                let row = (y * w) as usize;
                // Signed: negative on a block's rows when it starts right of column 0 (the
                // index, lrow + x with x >= bx0, is not; a usize here wrapped, which debug
                // builds refuse).
                let lrow = (y - by0) * bw - bx0;
                let mut zp = plane.at(lo, y);
                for x in lo..=hi {
                    let s = row + x as usize;
                    if let Some(m) = self.mesh_local.as_mut() {
                        m[(lrow + x) as usize] = zp;
                    }
                    let e = (f64::from(self.z[s]) - zp).abs();
                    if e > best.0
                        && !self.settled[(lrow + x) as usize]
                        && self.measured.is_none_or(|m| m[s])
                    {
                        best = (e, s as u32);
                    }
                    zp += plane.gx;
                }
                true
            }),
            Some(valid) => {
                let missing_corner = tri
                    .v
                    .iter()
                    .any(|&v| !valid[self.vertex_samples[v as usize] as usize]);
                for_each_row(a, b, cc, |y, lo, hi| {
                    let row = (y * w) as usize;
                    let lrow = (y - by0) * bw - bx0;
                    for x in lo..=hi {
                        let s = row + x as usize;
                        if self.settled[(lrow + x) as usize] {
                            continue;
                        }
                        if missing_corner {
                            // Left out of the result: refine where it covers measured data.
                            if valid[s] {
                                forced = s as u32;
                                return false;
                            }
                        } else if !valid[s] {
                            forced = s as u32;
                            spans_missing = true;
                            return false;
                        } else {
                            let e = (f64::from(self.z[s]) - plane.at(x, y)).abs();
                            if e > best.0 {
                                best = (e, s as u32);
                            }
                        }
                    }
                    true
                });
            }
        }
        let tri = &mut self.tris[t as usize];
        tri.spans_missing = spans_missing;
        tri.stamp = tri.stamp.wrapping_add(1);
        if forced != NONE {
            tri.candidate = forced;
            tri.err = f64::INFINITY;
        } else {
            tri.candidate = best.1;
            tri.err = best.0;
        }
        self.enqueue(t);
    }

    /// Queues triangle `t` when its candidate is forced or beyond the bound.
    fn enqueue(&mut self, t: u32) {
        let tri = &self.tris[t as usize];
        if tri.candidate == NONE {
            return;
        }
        if tri.err == f64::INFINITY {
            self.queue.push(0, t, tri.stamp);
        } else if tri.err > self.epsilon_um {
            self.queue
                .push(BucketQueue::bucket(tri.err / self.epsilon_um), t, tri.stamp);
        }
    }

    /// Continues the greedy insertion down to `epsilon_um` (not above the current bound: the
    /// triangles' candidates are requeued against it, no rescan) or until the block holds
    /// `max_triangles`. True when the budget stopped it.
    fn refine(&mut self, epsilon_um: f64, max_triangles: usize) -> bool {
        self.set_epsilon(epsilon_um);
        while let Some((t, stamp)) = self.queue.pop() {
            let tri = self.tris[t as usize];
            if tri.stamp != stamp || tri.candidate == NONE {
                continue;
            }
            if self.tris.len() + 2 > max_triangles {
                return true;
            }
            self.insert(tri.candidate as usize, t);
        }
        false
    }

    /// Whether grid sample `s` is measured (counts in the statistics and the bound).
    #[inline]
    fn is_measured(&self, s: usize) -> bool {
        self.valid.or(self.measured).is_none_or(|v| v[s])
    }

    /// The mesh's height at every sample of the block (local index): kept by the scans, or
    /// painted.
    fn mesh_values(&self) -> std::borrow::Cow<'_, [f64]> {
        match &self.mesh_local {
            Some(m) if self.valid.is_none() => std::borrow::Cow::Borrowed(m),
            _ => std::borrow::Cow::Owned(self.paint_local()),
        }
    }

    /// The mesh's height at every sample of the block (local index), from the triangles'
    /// planes (NaN where none covers).
    fn paint_local(&self) -> Vec<f64> {
        let mut m = vec![f64::NAN; self.settled.len()];
        let (bx0, by0, bw) = (self.block.x0 as i64, self.block.y0 as i64, self.bw as i64);
        for tri in &self.tris {
            let c = tri.v.map(|v| self.corner(v));
            let plane = Plane::through(c);
            for_each_row(
                (c[0].0, c[0].1),
                (c[1].0, c[1].1),
                (c[2].0, c[2].1),
                |y, lo, hi| {
                    let lrow = (y - by0) * bw - bx0;
                    for x in lo..=hi {
                        m[(lrow + x) as usize] = plane.at(x, y);
                    }
                    true
                },
            );
        }
        m
    }

    /// Mean, Sa, Sq of `value(local index, grid sample)` over the block's measured samples.
    fn stats(&self, value: impl Fn(usize, usize) -> f64) -> Option<BlockStats> {
        let mut v = Vec::with_capacity(self.settled.len());
        for y in self.block.y0..=self.block.y1 {
            for x in self.block.x0..=self.block.x1 {
                let s = y * self.width + x;
                if self.is_measured(s) {
                    let h = value((y - self.block.y0) * self.bw + (x - self.block.x0), s);
                    if !h.is_nan() {
                        v.push(h);
                    }
                }
            }
        }
        if v.is_empty() {
            return None;
        }
        let n = v.len() as f64;
        let mean = v.iter().sum::<f64>() / n;
        let sa = v.iter().map(|h| (h - mean).abs()).sum::<f64>() / n;
        let sq = (v.iter().map(|h| (h - mean).powi(2)).sum::<f64>() / n).sqrt();
        (sa > 0.0 && sq > 0.0).then_some(BlockStats { mean, sa, sq })
    }

    /// Per triangle, the unsettled measured sample that most reduces (`down`) or raises the
    /// mesh's spread about its mean if it became a vertex: (score, sample), score > 0. With
    /// `roughness` (the Rough pulls), the spread of the roughness the mesh carries
    /// (roughness + mesh - measurement) against the roughness's; `mean` and `mesh_mean` are
    /// then theirs.
    fn balance_candidates(
        &self,
        m: &[f64],
        roughness: Option<&[f32]>,
        mean: f64,
        mesh_mean: f64,
        mode: Pull,
    ) -> Vec<(f64, u32)> {
        let (bx0, by0, bw) = (self.block.x0 as i64, self.block.y0 as i64, self.bw as i64);
        let w = self.width as i64;
        let mut out = Vec::new();
        if mode == Pull::Pointwise {
            out.extend(
                self.tris
                    .iter()
                    .filter(|t| t.candidate != NONE && t.err.is_finite() && t.err > 0.0)
                    .map(|t| (t.err, t.candidate)),
            );
        }
        let down = matches!(mode, Pull::Down | Pull::RoughDown);
        for tri in self.tris.iter().filter(|_| mode != Pull::Pointwise) {
            let c = tri.v.map(|v| self.corner(v));
            let mut best = (0.0f64, NONE);
            for_each_row(
                (c[0].0, c[0].1),
                (c[1].0, c[1].1),
                (c[2].0, c[2].1),
                |y, lo, hi| {
                    let lrow = (y - by0) * bw - bx0;
                    for x in lo..=hi {
                        let (l, s) = ((lrow + x) as usize, (y * w + x) as usize);
                        if self.settled[l] || !self.is_measured(s) {
                            continue;
                        }
                        let z = f64::from(self.z[s]);
                        let spread = match roughness {
                            Some(g) => {
                                let g = f64::from(g[s]);
                                (m[l] - z + g - mesh_mean).abs() - (g - mean).abs()
                            }
                            None => (m[l] - mesh_mean).abs() - (z - mean).abs(),
                        };
                        if spread.is_nan() {
                            continue;
                        }
                        let score = match mode {
                            Pull::Mean { high: true } => m[l] - z,
                            Pull::Mean { high: false } => z - m[l],
                            _ if down => spread,
                            _ => -spread,
                        };
                        if score > best.0 {
                            best = (score, s as u32);
                        }
                    }
                    true
                },
            );
            if best.1 != NONE {
                out.push(best);
            }
        }
        out.sort_unstable_by_key(|c| c.1);
        out.dedup_by_key(|c| c.1);
        out
    }

    /// Makes `epsilon_um` the bound: every triangle's candidate is requeued against it.
    fn set_epsilon(&mut self, epsilon_um: f64) {
        if epsilon_um != self.epsilon_um {
            self.epsilon_um = epsilon_um;
            self.queue.clear();
            for t in 0..self.tris.len() as u32 {
                self.enqueue(t);
            }
        }
    }

    /// Inserts sample `s` (a vertex from now on) wherever it lies; `last` is where the walk
    /// starts. Returns the triangle to start the next walk from.
    fn insert_at(&mut self, s: usize, last: u32) -> u32 {
        let p = ((s % self.width) as i64, (s / self.width) as i64);
        match self.locate(p, last.min(self.tris.len() as u32 - 1)) {
            Some(t) => {
                self.insert(s, t);
                *self.fresh.last().unwrap_or(&0)
            }
            None => last, // unreachable: p lies in the block's rectangle
        }
    }

    /// A triangle that contains `p` (inside or on its boundary), by walking from `start`
    /// towards `p` (a visibility walk: it ends in a Delaunay triangulation); a full search if
    /// the walk does not end, which exact predicates should make impossible.
    fn locate(&self, p: (i64, i64), start: u32) -> Option<u32> {
        let mut t = start;
        'walk: for _ in 0..self.tris.len() + 3 {
            let tri = &self.tris[t as usize];
            for e in 0..3 {
                let (a, b) = (tri.v[(e + 1) % 3], tri.v[(e + 2) % 3]);
                if orient(self.verts[a as usize], self.verts[b as usize], p) < 0 {
                    if tri.n[e] == NONE {
                        break 'walk;
                    }
                    t = tri.n[e];
                    continue 'walk;
                }
            }
            return Some(t);
        }
        (0..self.tris.len() as u32).find(|&t| {
            let v = self.tris[t as usize].v.map(|v| self.verts[v as usize]);
            (0..3).all(|e| orient(v[e], v[(e + 1) % 3], p) >= 0)
        })
    }

    /// Bowyer-Watson insertion of sample `s`, which lies in or on triangle `start`.
    fn insert(&mut self, s: usize, start: u32) {
        let p = self.add_vertex(s);
        let pp = self.verts[p as usize];
        self.epoch = self.epoch.wrapping_add(1);
        if self.epoch == 0 {
            self.mark.iter_mut().for_each(|m| *m = 0);
            self.epoch = 1;
        }
        self.cavity.clear();
        self.rim.clear();
        self.cavity.push(start);
        self.mark[start as usize] = self.epoch;
        let mut k = 0;
        while k < self.cavity.len() {
            let t = self.cavity[k];
            k += 1;
            let tri = self.tris[t as usize];
            for e in 0..3 {
                let (a, b) = (tri.v[(e + 1) % 3], tri.v[(e + 2) % 3]);
                let nb = tri.n[e];
                if nb != NONE && self.mark[nb as usize] != self.epoch {
                    let o = self.tris[nb as usize].v.map(|v| self.verts[v as usize]);
                    let inside = if self.small {
                        incircle_small(o[0], o[1], o[2], pp) > 0
                    } else {
                        incircle(o[0], o[1], o[2], pp) > 0
                    };
                    if inside {
                        self.mark[nb as usize] = self.epoch;
                        self.cavity.push(nb);
                        continue;
                    }
                }
                if nb != NONE && self.mark[nb as usize] == self.epoch {
                    continue; // interior edge of the cavity
                }
                let (va, vb) = (self.verts[a as usize], self.verts[b as usize]);
                let o = orient(va, vb, pp);
                if o == 0 {
                    // p on a hull edge: that edge disappears, the fan stays open there.
                    debug_assert_eq!(nb, NONE);
                    continue;
                }
                debug_assert!(o > 0, "cavity not star-shaped");
                self.rim.push((a, b, nb));
            }
        }
        // One new triangle (a, b, p) per rim edge, in the cavity's slots first.
        self.fresh.clear();
        for i in 0..self.rim.len() {
            let slot = if i < self.cavity.len() {
                self.cavity[i]
            } else {
                self.tris.push(Tri {
                    v: [0; 3],
                    n: [NONE; 3],
                    stamp: 0,
                    candidate: NONE,
                    err: 0.0,
                    spans_missing: false,
                });
                self.mark.push(0);
                (self.tris.len() - 1) as u32
            };
            self.fresh.push(slot);
        }
        for i in 0..self.rim.len() {
            let (a, b, ext) = self.rim[i];
            let slot = self.fresh[i];
            // Across (b, p): the fan triangle starting at b; across (p, a): the one ending at a.
            let mut n0 = NONE;
            let mut n1 = NONE;
            for (j, &(a2, b2, _)) in self.rim.iter().enumerate() {
                if a2 == b {
                    n0 = self.fresh[j];
                }
                if b2 == a {
                    n1 = self.fresh[j];
                }
            }
            let tri = &mut self.tris[slot as usize];
            tri.v = [a, b, p];
            tri.n = [n0, n1, ext];
            tri.candidate = NONE;
            tri.spans_missing = false;
            if ext != NONE {
                let et = &mut self.tris[ext as usize];
                for e in 0..3 {
                    if et.v[(e + 1) % 3] == b && et.v[(e + 2) % 3] == a {
                        et.n[e] = slot;
                    }
                }
            }
        }
        // The cavity always yields at least as many fan triangles as it had (k + 1 or k + 2).
        debug_assert!(self.rim.len() > self.cavity.len());
        if self.scanning {
            for i in 0..self.fresh.len() {
                let t = self.fresh[i];
                self.scan(t);
            }
        }
    }

    /// The smallest interior angle of triangle `t` in physical (x, y, z), degrees.
    fn min_angle(&self, t: usize, bound: &AngleBound) -> f64 {
        let p = self.tris[t].v.map(|v| {
            let (x, y, z) = self.corner(v);
            [
                x as f64 * bound.pitch.x_um(),
                y as f64 * bound.pitch.y_um(),
                z,
            ]
        });
        geom::min_angle_deg(p)
    }

    /// The vertices on each side of the block's rectangle (bottom, right, top, left), as
    /// their coordinate along the side, sorted.
    fn side_vertices(&self) -> [Vec<i64>; 4] {
        let b = self.block;
        let (x0, x1, y0, y1) = (b.x0 as i64, b.x1 as i64, b.y0 as i64, b.y1 as i64);
        let mut sides: [Vec<i64>; 4] = Default::default();
        for &(x, y) in &self.verts {
            if y == y0 {
                sides[0].push(x);
            }
            if x == x1 {
                sides[1].push(y);
            }
            if y == y1 {
                sides[2].push(x);
            }
            if x == x0 {
                sides[3].push(y);
            }
        }
        for s in &mut sides {
            s.sort_unstable();
            s.dedup();
        }
        sides
    }

    /// Where to insert a vertex that removes the sliver `t` (Ruppert's refinement on the grid):
    /// its circumcentre, rounded to a sample, unless that lies beyond a side of the block or
    /// within the diametral circle of a side's segment: then that segment's midpoint.
    fn sliver_fix(&self, t: usize, sides: &[Vec<i64>; 4]) -> SliverFix {
        let b = self.block;
        let (x0, x1, y0, y1) = (b.x0 as i64, b.x1 as i64, b.y0 as i64, b.y1 as i64);
        let p = self.tris[t].v.map(|v| self.verts[v as usize]);
        // Circumcentre, relative to p[0] (exact integers up to the division).
        let (bx, by) = ((p[1].0 - p[0].0) as f64, (p[1].1 - p[0].1) as f64);
        let (cx, cy) = ((p[2].0 - p[0].0) as f64, (p[2].1 - p[0].1) as f64);
        let d = 2.0 * (bx * cy - by * cx);
        if d == 0.0 {
            return SliverFix::Stuck;
        }
        let (b2, c2) = (bx * bx + by * by, cx * cx + cy * cy);
        let ux = p[0].0 as f64 + (cy * b2 - by * c2) / d;
        let uy = p[0].1 as f64 + (bx * c2 - cx * b2) / d;
        // Per side: the line, the coordinate along it, the range along it, and how far the
        // centre lies beyond it (> 0: outside the block).
        let lines = [
            (uy, ux, x0, x1, y0 as f64 - uy),
            (ux, uy, y0, y1, ux - x1 as f64),
            (uy, ux, x0, x1, uy - y1 as f64),
            (ux, uy, y0, y1, x0 as f64 - ux),
        ];
        let fixed = [y0, x1, y1, x0];
        let mut split: Option<(f64, usize, i64)> = None;
        for (k, &(across, along, lo, hi, beyond)) in lines.iter().enumerate() {
            let a = along.clamp(lo as f64, hi as f64);
            let verts = &sides[k];
            // The segment [s0, s1] of the side that holds `a`.
            let i = verts.partition_point(|&v| (v as f64) <= a);
            let (s0, s1) = match (i.checked_sub(1).map(|j| verts[j]), verts.get(i)) {
                (Some(s0), Some(&s1)) => (s0, s1),
                (Some(s0), None) if i >= 2 => (verts[i - 2], s0),
                _ => continue,
            };
            let (mid, half) = ((s0 + s1) as f64 * 0.5, (s1 - s0) as f64 * 0.5);
            let dist2 = (along - mid).powi(2) + (across - fixed[k] as f64).powi(2);
            let score = if beyond > 0.0 {
                1e9 + beyond
            } else if dist2 < half * half {
                half * half - dist2
            } else {
                continue;
            };
            if s1 - s0 >= 2 && split.is_none_or(|(best, _, _)| score > best) {
                split = Some((score, k, (s0 + s1).div_euclid(2)));
            }
        }
        let at = |x: i64, y: i64| (y * self.width as i64 + x) as usize;
        if let Some((_, k, m)) = split {
            let s = match k {
                0 => at(m, y0),
                1 => at(x1, m),
                2 => at(m, y1),
                _ => at(x0, m),
            };
            return SliverFix::Side(k, s);
        }
        // Inside: the rounded centre, strictly inside the block (a side sample is only
        // inserted as a split), unless it is a vertex already; then the longest edge's middle.
        let inside = |x: f64, y: f64| {
            if x1 - x0 < 2 || y1 - y0 < 2 {
                return None;
            }
            let (x, y) = (
                (x.round() as i64).clamp(x0 + 1, x1 - 1),
                (y.round() as i64).clamp(y0 + 1, y1 - 1),
            );
            (!self.settled[self.local(x, y)]).then(|| at(x, y))
        };
        if let Some(s) = inside(ux, uy) {
            return SliverFix::Inside(s);
        }
        let (mut longest, mut mid) = (0i64, (0.0, 0.0));
        for k in 0..3 {
            let (a, c) = (p[k], p[(k + 1) % 3]);
            let len2 = (a.0 - c.0).pow(2) + (a.1 - c.1).pow(2);
            if len2 > longest {
                longest = len2;
                mid = ((a.0 + c.0) as f64 * 0.5, (a.1 + c.1) as f64 * 0.5);
            }
        }
        inside(mid.0, mid.1).map_or(SliverFix::Stuck, SliverFix::Inside)
    }

    /// Inserts grid samples until every triangle's smallest angle (in x, y, z) reaches the
    /// bound, or no sample can improve the ones left: Ruppert's refinement with the points
    /// rounded to the grid. The triangulation stays Delaunay (the insertion is Bowyer-Watson),
    /// so the flips a sliver allows are made by every insertion. Samples on a shared side
    /// (`shared`: bottom, right, top, left) are pushed to `shared_out`: the neighbour must
    /// insert them too. Returns the triangles left below the bound.
    fn bound_angles(
        &mut self,
        bound: &AngleBound,
        shared: [bool; 4],
        shared_out: &mut Vec<u32>,
    ) -> usize {
        let below = |b: &Self| {
            (0..b.tris.len())
                .filter(|&t| b.min_angle(t, bound) < bound.min_angle_deg)
                .collect::<Vec<_>>()
        };
        // Every insertion removes at least the sliver it was made for; the cap only stops a
        // pathological cascade (it is far above what the measured surfaces need).
        let mut budget = 4 * self.tris.len() + 1024;
        let mut sides = self.side_vertices();
        for _ in 0..ANGLE_ROUNDS {
            let bad = below(self);
            if bad.is_empty() {
                return 0;
            }
            let mut progress = false;
            for t in bad {
                if budget == 0 {
                    break;
                }
                if self.min_angle(t, bound) >= bound.min_angle_deg {
                    continue; // replaced by an earlier insertion of this round
                }
                let s = match self.sliver_fix(t, &sides) {
                    SliverFix::Inside(s) => s,
                    SliverFix::Side(k, s) => {
                        let along = if k % 2 == 0 {
                            s % self.width
                        } else {
                            s / self.width
                        } as i64;
                        let i = sides[k].partition_point(|&v| v < along);
                        sides[k].insert(i, along);
                        if shared[k] {
                            shared_out.push(s as u32);
                        }
                        s
                    }
                    SliverFix::Stuck => continue,
                };
                self.insert_at(s, t as u32);
                budget -= 1;
                progress = true;
            }
            if !progress || budget == 0 {
                break;
            }
        }
        below(self).len()
    }
}

/// Greedy insertion inside one block. `border` lists the samples on the block's shared sides
/// that must be vertices (from [`simplify_border`]); every other sample on a shared side is
/// settled (never inserted), so both blocks along a side end with the same vertices there.
#[allow(clippy::too_many_arguments)]
fn mesh_block(
    z: &[f32],
    valid: Option<&[bool]>,
    measured: Option<&[bool]>,
    width: usize,
    block: Block,
    shared: [bool; 4],
    border: &[u32],
    epsilon_um: f64,
    max_triangles: usize,
    keep_extremes: bool,
) -> BlockTin {
    let mut b = start_block(
        z,
        valid,
        measured,
        width,
        block,
        shared,
        border,
        epsilon_um,
        keep_extremes,
        false,
    );
    let budget_reached = b.refine(epsilon_um, max_triangles);
    BlockTin {
        vertex_samples: b.vertex_samples,
        tris: b.tris,
        budget_reached,
    }
}

/// A block's builder with its border (and peak and valley) inserted and every triangle
/// scanned against `epsilon_um`, ready for [`Builder::refine`].
#[allow(clippy::too_many_arguments)]
fn start_block<'a>(
    z: &'a [f32],
    valid: Option<&'a [bool]>,
    measured: Option<&'a [bool]>,
    width: usize,
    block: Block,
    shared: [bool; 4],
    border: &[u32],
    epsilon_um: f64,
    keep_extremes: bool,
    track_mesh: bool,
) -> Builder<'a> {
    let bw = block.x1 - block.x0 + 1;
    let bh = block.y1 - block.y0 + 1;
    let mut b = Builder {
        width,
        block,
        bw,
        z,
        valid,
        measured,
        settled: vec![false; bw * bh],
        mesh_local: None,
        verts: Vec::new(),
        vertex_samples: Vec::new(),
        tris: Vec::new(),
        queue: BucketQueue {
            buckets: vec![Vec::new(); BUCKETS],
            top: 0,
        },
        epsilon_um,
        scanning: false,
        small: bw < SMALL_SIDE && bh < SMALL_SIDE,
        mark: Vec::new(),
        epoch: 0,
        cavity: Vec::new(),
        rim: Vec::new(),
        fresh: Vec::new(),
    };
    // Shared sides, in the order bottom (y0), right (x1), top (y1), left (x0).
    let [bottom, right, top, left] = shared;
    for x in 0..bw {
        b.settled[x] |= bottom;
        b.settled[(bh - 1) * bw + x] |= top;
    }
    for y in 0..bh {
        b.settled[y * bw] |= left;
        b.settled[y * bw + bw - 1] |= right;
    }
    let at = |x: usize, y: usize| y * width + x;
    let c00 = b.add_vertex(at(block.x0, block.y0));
    let c10 = b.add_vertex(at(block.x1, block.y0));
    let c11 = b.add_vertex(at(block.x1, block.y1));
    let c01 = b.add_vertex(at(block.x0, block.y1));
    b.tris.push(Tri {
        v: [c00, c10, c11],
        n: [NONE, 1, NONE],
        stamp: 0,
        candidate: NONE,
        err: 0.0,
        spans_missing: false,
    });
    b.tris.push(Tri {
        v: [c00, c11, c01],
        n: [NONE, NONE, 0],
        stamp: 0,
        candidate: NONE,
        err: 0.0,
        spans_missing: false,
    });
    b.mark = vec![0; 2];
    let mut last = 0u32;
    for &s in border {
        if b.vertex_samples[..4].contains(&s) {
            continue; // a corner: the sides' ends
        }
        last = b.insert_at(s as usize, last);
    }
    if keep_extremes {
        // The block's peak and valley off the settled samples (shared sides, corners).
        let (mut hi, mut lo) = ((f32::NEG_INFINITY, usize::MAX), (f32::INFINITY, usize::MAX));
        let unmeasured = |s: usize| valid.or(measured).is_some_and(|v| !v[s]);
        for y in block.y0..=block.y1 {
            let lrow = (y - block.y0) * bw;
            for x in block.x0..=block.x1 {
                let s = y * width + x;
                if b.settled[lrow + x - block.x0] || unmeasured(s) {
                    continue;
                }
                let h = z[s];
                if h > hi.0 {
                    hi = (h, s);
                }
                if h < lo.0 {
                    lo = (h, s);
                }
            }
        }
        for s in [hi.1, lo.1] {
            if s == usize::MAX || b.settled[b.local((s % width) as i64, (s / width) as i64)] {
                continue;
            }
            last = b.insert_at(s, last);
        }
    }
    b.scanning = true;
    if track_mesh {
        b.mesh_local = Some(vec![f64::NAN; bw * bh]);
    }
    for t in 0..b.tris.len() as u32 {
        b.scan(t);
    }
    b
}

/// The vertices a shared block side needs, so that the mesh's edges along it (the same from
/// both blocks) stay within `epsilon_um` of every sample on it: the side's ends, in holes mode
/// every missing sample and the measured ones next to it (an edge along the side then never
/// spans a missing sample), and between those, the samples that a vertical-distance
/// Douglas-Peucker split picks. `line` lists the side's samples in order.
/// With `measured` (fill mode), the filled samples are not held to the bound. The split is
/// hierarchical: a smaller bound keeps every sample a larger one keeps, and more.
fn simplify_border(
    line: &[usize],
    z: &[f32],
    valid: Option<&[bool]>,
    measured: Option<&[bool]>,
    epsilon_um: f64,
    out: &mut Vec<u32>,
) {
    let n = line.len();
    let mut keep = vec![false; n];
    keep[0] = true;
    keep[n - 1] = true;
    if let Some(valid) = valid {
        for k in 0..n {
            if !valid[line[k]] {
                keep[k] = true;
                if k > 0 {
                    keep[k - 1] = true;
                }
                if k + 1 < n {
                    keep[k + 1] = true;
                }
            }
        }
    }
    // The side's peak and valley: a region's extreme on a shared side is then a vertex too
    // (the blocks' own extremes are taken off their shared sides).
    let measured_at = |k: usize| valid.or(measured).is_none_or(|m| m[line[k]]);
    let (mut hi, mut lo) = (None::<usize>, None::<usize>);
    for k in (0..n).filter(|&k| measured_at(k)) {
        if hi.is_none_or(|h| z[line[k]] > z[line[h]]) {
            hi = Some(k);
        }
        if lo.is_none_or(|l| z[line[k]] < z[line[l]]) {
            lo = Some(k);
        }
    }
    for k in [hi, lo].into_iter().flatten() {
        keep[k] = true;
    }
    // The margin keeps the bound when the triangles along the side evaluate their plane at
    // these samples with different rounding than the interpolation here.
    let limit = epsilon_um * (1.0 - 1e-9);
    let anchors: Vec<usize> = (0..n).filter(|&k| keep[k]).collect();
    let mut stack = Vec::new();
    for pair in anchors.windows(2) {
        stack.push((pair[0], pair[1]));
        while let Some((i, j)) = stack.pop() {
            let (zi, zj) = (f64::from(z[line[i]]), f64::from(z[line[j]]));
            let mut worst = (limit, usize::MAX);
            for k in i + 1..j {
                if measured.is_some_and(|m| !m[line[k]]) {
                    continue;
                }
                let t = (k - i) as f64 / (j - i) as f64;
                let e = (f64::from(z[line[k]]) - (zi + (zj - zi) * t)).abs();
                if e > worst.0 {
                    worst = (e, k);
                }
            }
            if worst.1 != usize::MAX {
                keep[worst.1] = true;
                stack.push((worst.1, j));
                stack.push((i, worst.1));
            }
        }
    }
    out.extend((0..n).filter(|&k| keep[k]).map(|k| line[k] as u32));
}

/// Splits `0..=last` into about `last / size` equal parts: the part boundaries.
fn cuts(last: usize, size: usize) -> Vec<usize> {
    let parts = ((last + size / 2) / size.max(1)).max(1);
    (0..=parts).map(|k| k * last / parts).collect()
}

/// Triangulates `map` so that every sample (every measured one with holes) lies within
/// `epsilon_um` vertically of the mesh, with greedy insertion (see the module docs), unless the
/// triangle budget stops it first.
///
/// The grid is cut into blocks ([`TinParams::block_samples`]) meshed independently and in
/// parallel; the sides that two blocks share are simplified first, once, and both blocks keep
/// exactly those vertices there, so the pieces join without a crack and the bound holds on the
/// sides too. The result does not depend on the thread count. A triangle budget needs the one
/// global order of insertion, so with `max_triangles` the grid is one block.
///
/// The four grid corners are always vertices and the rim follows the grid's rectangle exactly
/// (with holes, the corners may be missing and their triangles left out).
pub fn triangulate(heights: RasterView<'_, f32>, params: &TinParams) -> Result<Tin> {
    let plan = BlockPlan::new(heights, params)?;
    let meshed: Vec<BlockTin> = (0..plan.block_count())
        .into_par_iter()
        .map(|k| plan.mesh(k))
        .collect();
    Ok(assemble(&plan, &meshed))
}

/// The blocks' triangulations joined into one (block order), with the plan's filled heights.
pub(crate) fn assemble(plan: &BlockPlan<'_>, meshed: &[BlockTin]) -> Tin {
    // One vertex per sample across blocks (the shared sides' vertices appear in both).
    let (rows, cols) = (plan.rows, plan.cols);
    let shape = Shape::new(rows, cols);
    let valid = plan.valid.as_deref();
    let is_valid = |s: usize| valid.is_none_or(|v| v[s]);
    let mut vertex_of = vec![NONE; cols * rows];
    let mut vertex_samples = Vec::new();
    let mut triangles = Vec::new();
    let mut tin_blocks = Vec::with_capacity(meshed.len());
    let (mut dropped_spanning, mut all_kept, mut budget_reached) = (0, true, false);
    for (k, bt) in meshed.iter().enumerate() {
        budget_reached |= bt.budget_reached;
        let ids: Vec<u32> = bt
            .vertex_samples
            .iter()
            .map(|&s| {
                let v = &mut vertex_of[s as usize];
                if *v == NONE {
                    *v = vertex_samples.len() as u32;
                    vertex_samples.push(s);
                }
                *v
            })
            .collect();
        let first = triangles.len();
        // Keep the triangles whose corners are all measured and that span no missing sample.
        for t in &bt.tris {
            if !t
                .v
                .iter()
                .all(|&v| is_valid(bt.vertex_samples[v as usize] as usize))
            {
                all_kept = false;
                continue;
            }
            if t.spans_missing {
                dropped_spanning += 1;
                all_kept = false;
                continue;
            }
            triangles.push(t.v.map(|v| ids[v as usize]));
        }
        tin_blocks.push((plan.block(k).0, first..triangles.len()));
    }
    let rim = all_kept.then(|| grid_rim(|s| vertex_of[s] != NONE, shape));
    let rim = rim.map(|samples| samples.iter().map(|&s| vertex_of[s as usize]).collect());
    Tin {
        shape,
        vertex_samples,
        triangles,
        blocks: tin_blocks,
        rim,
        filled_um: plan.filled.to_vec(),
        missing_samples: plan.missing_samples,
        budget_reached,
        dropped_spanning,
    }
}

/// A triangulation cut into blocks, before the blocks are meshed: the filled heights, the
/// measured mask (holes mode), the block grid and the simplified shared sides. Every block is
/// then meshed on its own ([`BlockPlan::mesh`]), in any order and on any thread, with the same
/// result: [`triangulate`] meshes them all at once, the streaming mesher band by band.
pub(crate) struct BlockPlan<'a> {
    pub(crate) rows: usize,
    pub(crate) cols: usize,
    /// The heights with missing samples filled (borrowed when none is missing), um.
    pub(crate) filled: std::borrow::Cow<'a, [f32]>,
    /// Measured samples (holes mode with missing samples only).
    pub(crate) valid: Option<Vec<bool>>,
    /// Measured samples (fill mode with missing samples only): the others are not held to
    /// the bound.
    pub(crate) measured: Option<Vec<bool>>,
    pub(crate) missing_samples: usize,
    /// Block boundaries along x (columns) and y (rows).
    pub(crate) xs: Vec<usize>,
    pub(crate) ys: Vec<usize>,
    sides: Sides,
    epsilon_um: f64,
    max_triangles: usize,
    keep_extremes: bool,
    /// Per block (row-major), the factor its insertion bound is of the step's bound (empty:
    /// 1 everywhere): the tolerance search gives a block whose judged regions all have a
    /// larger Sq a coarser bound ([`BlockPlan::with_bound_scales`]).
    bound_scale: Vec<f64>,
}

/// The vertices of the shared block sides at one bound.
#[derive(Default)]
pub(crate) struct Sides {
    vertical: Vec<Vec<u32>>,
    horizontal: Vec<Vec<u32>>,
    pub(crate) epsilon_um: f64,
}

/// A block kept alive from one bound to the next finer one: one greedy insertion order,
/// refined step by step, so that a series of bounds costs about one mesh (module `tolerance`).
/// Cloned to bisect between two checkpoints from the coarser one's state.
#[derive(Clone)]
pub(crate) struct LiveBlock<'a> {
    b: Builder<'a>,
    /// The shared sides' vertices inserted so far, sorted.
    border: Vec<u32>,
    budget_reached: bool,
    /// The measurement's statistics over the block (computed at the first balance).
    stats_cache: Option<Option<BlockStats>>,
}

/// How close a block's Sa and Sq must come to the measurement's, as fractions
/// ([`LiveBlock::balance`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Balance<'r> {
    pub(crate) sa: f64,
    pub(crate) sq: f64,
    /// The measured roughness on the same grid and how close the Sa and Sq of the roughness
    /// the mesh carries (the roughness plus the mesh's pointwise error) must come to its own,
    /// as a fraction: the tolerance judges it too, and on a noisy surface a mesh can keep the
    /// heights' Sa and Sq by exaggerating the noise where it flattens the waviness.
    pub(crate) roughness: Option<(&'r [f32], f64)>,
}

/// What a round of [`LiveBlock::balance`] inserts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pull {
    /// Samples where the mesh is farther from its mean than the measurement from its own.
    Down,
    /// Samples where it is nearer.
    Up,
    /// The largest pointwise errors.
    Pointwise,
    /// Samples farthest below (`high`: the mesh's mean is above the measurement's) or above
    /// the mesh.
    Mean {
        high: bool,
    },
    /// Down and Up on the roughness the mesh carries against the measured roughness.
    RoughDown,
    RoughUp,
}

impl Pull {
    fn opposes(self, other: Pull) -> bool {
        matches!(
            (self, other),
            (Pull::Down, Pull::Up)
                | (Pull::Up, Pull::Down)
                | (Pull::RoughDown, Pull::RoughUp)
                | (Pull::RoughUp, Pull::RoughDown)
        ) || matches!((self, other), (Pull::Mean { high: a }, Pull::Mean { high: b }) if a != b)
    }
}

/// Rounds of [`LiveBlock::balance`] per step at most.
const BALANCE_ROUNDS: usize = 16;

/// Mean, Sa and Sq (about the mean) of values over a block's measured samples.
#[derive(Debug, Clone, Copy)]
struct BlockStats {
    mean: f64,
    sa: f64,
    sq: f64,
}

impl LiveBlock<'_> {
    /// Refines the block to the bound of `sides`: the new vertices on its shared sides, then
    /// the greedy insertion down to the bound.
    pub(crate) fn refine(&mut self, plan: &BlockPlan<'_>, sides: &Sides, k: usize) {
        let mut border = plan.border(sides, k);
        border.sort_unstable();
        border.dedup();
        let epsilon_um = plan.block_epsilon(sides, k);
        self.b.set_epsilon(epsilon_um);
        self.insert_border(&border);
        self.budget_reached |= self.b.refine(epsilon_um, plan.max_triangles);
    }

    /// Inserts the samples of `samples` that lie inside block `k`, not on its sides (a
    /// side's vertices come from its own simplification, which keeps its peak and valley).
    pub(crate) fn insert_samples(&mut self, plan: &BlockPlan<'_>, k: usize, samples: &[u32]) {
        let (b, _) = plan.block(k);
        let w = plan.cols;
        let mut inside: Vec<u32> = samples
            .iter()
            .copied()
            .filter(|&s| {
                let (x, y) = (s as usize % w, s as usize / w);
                (b.x0 + 1..b.x1).contains(&x)
                    && (b.y0 + 1..b.y1).contains(&y)
                    // Inside, settled means a vertex already (the block's own extremes).
                    && !self.b.settled[self.b.local(x as i64, y as i64)]
            })
            .collect();
        inside.sort_unstable();
        inside.dedup();
        let mut last = 0;
        for s in inside {
            last = self.b.insert_at(s as usize, last);
        }
    }

    /// Inserts the shared-side samples of `samples` the block does not have yet (kept in
    /// `border`, so that a sample is never inserted twice: the sides' simplification at a
    /// finer bound and the angle bound may both ask for it).
    fn insert_border(&mut self, samples: &[u32]) {
        let mut last = 0;
        let mut added = Vec::new();
        for &s in samples {
            // `border` stays sorted while the loop searches it; `added` is small.
            if self.border.binary_search(&s).is_err() && !added.contains(&s) {
                last = self.b.insert_at(s as usize, last);
                added.push(s);
            }
        }
        if !added.is_empty() {
            self.border.extend(added);
            self.border.sort_unstable();
        }
    }

    /// Inserts the shared-side samples its neighbours added for their angle bound
    /// (`incoming`), then, when `improve`, refines the block until every triangle's smallest
    /// angle reaches `bound` ([`Builder::bound_angles`]). Returns the shared-side samples it
    /// added (for the neighbours) and the triangles left below the bound.
    pub(crate) fn bound_angles(
        &mut self,
        plan: &BlockPlan<'_>,
        k: usize,
        incoming: &[u32],
        bound: &AngleBound,
        improve: bool,
    ) -> (Vec<u32>, usize) {
        self.insert_border(incoming);
        if !improve {
            return (Vec::new(), 0);
        }
        let (_, shared) = plan.block(k);
        let mut out = Vec::new();
        let left = self.b.bound_angles(bound, shared, &mut out);
        self.border.extend_from_slice(&out);
        self.border.sort_unstable();
        self.border.dedup();
        (out, left)
    }

    /// Balances the block's Sa and Sq (module `tolerance`): while the mesh's Sa or
    /// Sq over the block's measured samples (each about its own mean) is off the
    /// measurement's by more than `target`, inserts a batch of the samples that pull it back:
    /// where the mesh is farther from the mean than the measurement when it over-shoots (the
    /// greedy insertion's extremes, joined by long edges, exaggerate noise), nearer when it
    /// under-shoots (it smooths what it does not follow); one per triangle, the largest
    /// first, then restores the pointwise bound. Rounds are capped; the batch halves when
    /// the direction flips.
    pub(crate) fn balance(&mut self, plan: &BlockPlan<'_>, target: Balance<'_>) {
        let Some(measured) = self.measured_stats() else {
            return;
        };
        let rough = target.roughness.and_then(|(g, share)| {
            let z = self.b.z;
            // Both over the measured samples where the roughness is known.
            let stats = self.b.stats(|_, s| f64::from(g[s]))?;
            Some((g, share, stats, z))
        });
        let mut batch = (self.b.vertex_samples.len() / 16).max(4);
        // (direction, excess over the target, vertices inserted) of the last round.
        let mut last: Option<(Pull, f64, usize)> = None;
        for _ in 0..BALANCE_ROUNDS {
            let m = self.b.mesh_values();
            let Some(mesh) = self.b.stats(|l, _| m[l]) else {
                return;
            };
            let (da, dq) = (mesh.sa / measured.sa - 1.0, mesh.sq / measured.sq - 1.0);
            let (ra, rq) = (da.abs() / target.sa, dq.abs() / target.sq);
            // The block's mean: an offset between blocks is spread the regions see (a mesh
            // too coarse for the waviness flattens it between blocks while each block keeps
            // its own Sa and Sq).
            let dm = mesh.mean - measured.mean;
            let rm = dm.abs() / (target.sq * measured.sq);
            // The roughness the mesh carries: measured roughness + mesh - measurement.
            let carried = rough.and_then(|(g, share, r, z)| {
                let c = self
                    .b
                    .stats(|l, s| m[l] - f64::from(z[s]) + f64::from(g[s]))?;
                let (da, dq) = (c.sa / r.sa - 1.0, c.sq / r.sq - 1.0);
                Some((
                    da,
                    dq,
                    (da.abs() / share).max(dq.abs() / share),
                    c.mean,
                    r.mean,
                ))
            });
            let rr = carried.map_or(0.0, |c| c.2);
            if ra <= 1.0 && rq <= 1.0 && rm <= 1.0 && rr <= 1.0 {
                return;
            }
            // Sa and Sq off in opposite directions (the mesh has the spread but not the
            // shape of the distribution): neither direction helps both, the largest
            // pointwise errors do.
            let split = da * dq < 0.0 && ra.min(rq) > 1.0;
            let (mode, ratio) = if rr > rm.max(ra).max(rq) {
                // Sa and Sq of the roughness off in opposite directions are rare (it is
                // close to normal); the larger one decides.
                let (da, dq, ..) = carried.unwrap_or_default();
                let d = if da.abs() >= dq.abs() { da } else { dq };
                (
                    if d > 0.0 {
                        Pull::RoughDown
                    } else {
                        Pull::RoughUp
                    },
                    rr,
                )
            } else if rm >= ra.max(rq) {
                (Pull::Mean { high: dm > 0.0 }, rm)
            } else if split {
                (Pull::Pointwise, ra.max(rq))
            } else if ra >= rq {
                (if da > 0.0 { Pull::Down } else { Pull::Up }, ra)
            } else {
                (if dq > 0.0 { Pull::Down } else { Pull::Up }, rq)
            };
            batch = match last {
                // Flipped: the last batch went too far.
                Some((d, _, n)) if d.opposes(mode) => (n / 2).max(1),
                // Same pull: as many as the last round's progress says are needed (most of
                // them: the gain per vertex falls as the worst ones go), at most four times
                // as many.
                Some((d, before, n)) if d == mode && before > ratio => {
                    let per_vertex = (before - ratio) / n as f64;
                    (((ratio - 1.0) / per_vertex * 0.8).ceil() as usize).clamp(1, 4 * n)
                }
                Some((d, _, n)) if d == mode => 2 * n,
                Some((_, _, n)) => n,
                None => batch,
            };
            let mut cands = match (mode, rough, carried) {
                (Pull::RoughDown | Pull::RoughUp, Some((g, ..)), Some(c)) => {
                    self.b.balance_candidates(&m, Some(g), c.4, c.3, mode)
                }
                _ => self
                    .b
                    .balance_candidates(&m, None, measured.mean, mesh.mean, mode),
            };
            drop(m);
            if cands.is_empty() {
                return;
            }
            if cands.len() > batch {
                cands.select_nth_unstable_by(batch, |a, b| b.0.total_cmp(&a.0));
                cands.truncate(batch);
            }
            let inserted = cands.len();
            cands.sort_by_key(|c| c.1);
            let mut at = 0;
            for (_, s) in cands {
                at = self.b.insert_at(s as usize, at);
            }
            self.budget_reached |= self.b.refine(self.b.epsilon_um, plan.max_triangles);
            last = Some((mode, ratio, inserted));
        }
    }

    /// Mean, Sa and Sq of the measurement over the block's measured samples (cached).
    fn measured_stats(&mut self) -> Option<BlockStats> {
        if self.stats_cache.is_none() {
            let z = self.b.z;
            self.stats_cache = Some(self.b.stats(|_, s| f64::from(z[s])));
        }
        self.stats_cache.flatten()
    }

    /// The block's triangulation as it stands, the block given up (no copy).
    pub(crate) fn into_tin(self) -> BlockTin {
        BlockTin {
            vertex_samples: self.b.vertex_samples,
            tris: self.b.tris,
            budget_reached: self.budget_reached,
        }
    }

    /// The block's triangulation as it stands.
    pub(crate) fn snapshot(&self) -> BlockTin {
        BlockTin {
            vertex_samples: self.b.vertex_samples.clone(),
            tris: self.b.tris.clone(),
            budget_reached: self.budget_reached,
        }
    }
}

/// Bytes of a [`LiveBlock`] as [`LiveBlock::encode`] writes it: little-endian, private to
/// the run (the search's block store, module `tolerance`).
struct Bytes<'b> {
    b: &'b [u8],
    at: usize,
}

impl Bytes<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut a = [0u8; N];
        a.copy_from_slice(&self.b[self.at..self.at + N]);
        self.at += N;
        a
    }
    fn u8(&mut self) -> u8 {
        self.take::<1>()[0]
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn f64(&mut self) -> f64 {
        f64::from_bits(self.u64())
    }
    fn len(&mut self) -> usize {
        self.u64() as usize
    }
    fn u32s(&mut self) -> Vec<u32> {
        let n = self.len();
        (0..n).map(|_| self.u32()).collect()
    }
}

fn put_u32s(out: &mut Vec<u8>, v: &[u32]) {
    out.extend_from_slice(&(v.len() as u64).to_le_bytes());
    for x in v {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

impl LiveBlock<'_> {
    /// The block's whole state as bytes, for [`BlockPlan::decode`]: what the next refinement
    /// reads (triangles with their candidates and stamps, the queue in its order, the settled
    /// samples, the mesh on the block's samples, the shared sides' vertices, the cached
    /// statistics), so that a decoded block refines to the same triangles, bit for bit, as
    /// the block kept in memory. The vertices' coordinates are derived from their samples;
    /// scratch buffers are not kept (every insertion clears them).
    pub(crate) fn encode(&self, out: &mut Vec<u8>) {
        let b = &self.b;
        out.extend_from_slice(&b.epsilon_um.to_bits().to_le_bytes());
        out.push(u8::from(b.scanning));
        out.push(u8::from(self.budget_reached));
        out.extend_from_slice(&b.epoch.to_le_bytes());
        match &b.mesh_local {
            None => out.push(0),
            Some(m) => {
                out.push(1);
                out.extend_from_slice(&(m.len() as u64).to_le_bytes());
                for v in m {
                    out.extend_from_slice(&v.to_bits().to_le_bytes());
                }
            }
        }
        out.extend_from_slice(&(b.settled.len() as u64).to_le_bytes());
        for chunk in b.settled.chunks(8) {
            let byte = chunk
                .iter()
                .enumerate()
                .fold(0u8, |a, (i, &s)| a | (u8::from(s) << i));
            out.push(byte);
        }
        put_u32s(out, &b.vertex_samples);
        out.extend_from_slice(&(b.tris.len() as u64).to_le_bytes());
        for t in &b.tris {
            for x in t.v.iter().chain(&t.n) {
                out.extend_from_slice(&x.to_le_bytes());
            }
            out.extend_from_slice(&t.stamp.to_le_bytes());
            out.extend_from_slice(&t.candidate.to_le_bytes());
            out.extend_from_slice(&t.err.to_bits().to_le_bytes());
            out.push(u8::from(t.spans_missing));
        }
        put_u32s(out, &b.mark);
        out.extend_from_slice(&(b.queue.top as u64).to_le_bytes());
        let used: Vec<(usize, &Vec<(u32, u32)>)> = b
            .queue
            .buckets
            .iter()
            .enumerate()
            .filter(|(_, q)| !q.is_empty())
            .collect();
        out.extend_from_slice(&(used.len() as u64).to_le_bytes());
        for (i, q) in used {
            out.extend_from_slice(&(i as u64).to_le_bytes());
            out.extend_from_slice(&(q.len() as u64).to_le_bytes());
            for (t, stamp) in q {
                out.extend_from_slice(&t.to_le_bytes());
                out.extend_from_slice(&stamp.to_le_bytes());
            }
        }
        put_u32s(out, &self.border);
        match self.stats_cache {
            None => out.push(0),
            Some(None) => out.push(1),
            Some(Some(s)) => {
                out.push(2);
                for v in [s.mean, s.sa, s.sq] {
                    out.extend_from_slice(&v.to_bits().to_le_bytes());
                }
            }
        }
    }
}

/// What the angle bound did to a mesh ([`bound_block_angles`]): the report's record itself.
pub use surfstream_core::record::AngleRecord as AngleStats;

/// Rounds between the blocks at most: each round every block refines its slivers and its
/// neighbours then insert the samples it added on their shared sides.
const ANGLE_BLOCK_ROUNDS: usize = 64;

/// Refines every live block until no triangle's smallest angle is below `bound`, keeping the
/// shared sides exact: a sample one block adds on a side is inserted by the block across it
/// in the next round, which may refine in turn. Side segments only get shorter, so the rounds
/// end; the last one only inserts the neighbours' samples (the mesh stays conforming whatever
/// the cap).
pub(crate) fn bound_block_angles(
    plan: &BlockPlan<'_>,
    live: &mut [LiveBlock<'_>],
    bound: &AngleBound,
) -> AngleStats {
    let stats = |live: &[LiveBlock<'_>]| {
        live.par_iter()
            .map(|b| {
                let angles: Vec<f64> = (0..b.b.tris.len())
                    .map(|t| b.b.min_angle(t, bound))
                    .collect();
                let below = angles.iter().filter(|&&a| a < bound.min_angle_deg).count();
                let min = angles.into_iter().fold(f64::INFINITY, f64::min);
                (b.b.tris.len(), min, below)
            })
            .reduce(
                || (0, f64::INFINITY, 0),
                |a, b| (a.0 + b.0, a.1.min(b.1), a.2 + b.2),
            )
    };
    let before = stats(live);
    let mut incoming: Vec<Vec<u32>> = vec![Vec::new(); live.len()];
    for round in 0..=ANGLE_BLOCK_ROUNDS {
        let improve = round < ANGLE_BLOCK_ROUNDS;
        let added: Vec<Vec<u32>> = live
            .par_iter_mut()
            .zip(incoming.par_iter())
            .enumerate()
            .map(|(k, (b, inc))| b.bound_angles(plan, k, inc, bound, improve).0)
            .collect();
        incoming.iter_mut().for_each(Vec::clear);
        let mut any = false;
        for (k, samples) in added.iter().enumerate() {
            for &s in samples {
                if let Some(j) = plan.across(k, s) {
                    incoming[j].push(s);
                    any = true;
                }
            }
        }
        if !any {
            break;
        }
    }
    let after = stats(live);
    AngleStats {
        bound_deg: bound.min_angle_deg,
        min_angle_before_deg: before.1,
        min_angle_deg: after.1,
        below_bound_before: before.2 as u64,
        below_bound: after.2 as u64,
        triangles_before: before.0 as u64,
        triangles: after.0 as u64,
    }
}

/// One block's triangulation: its vertices (grid samples) and triangles over them.
pub(crate) struct BlockTin {
    vertex_samples: Vec<u32>,
    tris: Vec<Tri>,
    pub(crate) budget_reached: bool,
}

/// The triangles of one block that the result keeps, as grid sample indices.
pub(crate) struct KeptTriangles {
    pub(crate) triangles: Vec<[u32; 3]>,
    /// Left out because they still span a missing sample (see [`Tin::dropped_spanning`]).
    pub(crate) dropped_spanning: usize,
    /// No triangle was left out.
    pub(crate) all_kept: bool,
}

impl BlockTin {
    /// The triangles whose corners are all measured and that span no missing sample, with
    /// their corners as grid sample indices, in the block's order.
    pub(crate) fn kept(&self, valid: Option<&[bool]>) -> KeptTriangles {
        let is_valid = |s: u32| valid.is_none_or(|v| v[s as usize]);
        let mut kept = KeptTriangles {
            triangles: Vec::with_capacity(self.tris.len()),
            dropped_spanning: 0,
            all_kept: true,
        };
        for t in &self.tris {
            let corners = t.v.map(|v| self.vertex_samples[v as usize]);
            if !corners.iter().all(|&s| is_valid(s)) {
                kept.all_kept = false;
            } else if t.spans_missing {
                kept.dropped_spanning += 1;
                kept.all_kept = false;
            } else {
                kept.triangles.push(corners);
            }
        }
        kept
    }
}

impl<'a> BlockPlan<'a> {
    /// Checks the parameters, fills the missing samples, cuts the grid into blocks and
    /// simplifies the sides they share (errors as [`triangulate`]).
    pub(crate) fn new(heights: RasterView<'a, f32>, params: &TinParams) -> Result<Self> {
        if heights.rows() < 2 || heights.cols() < 2 {
            return Err(MeshError::TooSmall {
                rows: heights.rows(),
                cols: heights.cols(),
            });
        }
        positive_finite("epsilon_um", params.epsilon_um)?;
        if let Some(n) = params.max_triangles {
            if n < 2 {
                return Err(MeshError::from(ParamError::new(
                    "max_triangles",
                    n,
                    "at least 2 (the two triangles spanning the grid)",
                )));
            }
        }
        if params.block_samples == Some(0) {
            return Err(MeshError::from(ParamError::new(
                "block_samples",
                0.0,
                "at least 1 (samples per block side)",
            )));
        }
        let (rows, cols) = (heights.rows(), heights.cols());
        if cols > i32::MAX as usize || rows > i32::MAX as usize || cols * rows >= NONE as usize {
            return Err(MeshError::TooLarge {
                what: "samples",
                count: cols * rows,
                limit: NONE as usize - 1,
            });
        }
        let (filled, missing_samples) = fill_missing(heights)?;
        let valid: Option<Vec<bool>> = (params.missing == MissingSamples::Holes
            && missing_samples > 0)
            .then(|| heights.values().iter().map(|h| !h.is_nan()).collect());

        let block_samples = match params.max_triangles {
            Some(_) => usize::MAX,
            None => params.block_samples.unwrap_or(DEFAULT_BLOCK_SAMPLES),
        };
        let xs = cuts(cols - 1, block_samples);
        let ys = cuts(rows - 1, block_samples);
        let measured: Option<Vec<bool>> = (params.missing == MissingSamples::Fill
            && missing_samples > 0)
            .then(|| heights.values().iter().map(|h| !h.is_nan()).collect());
        let mut plan = Self {
            rows,
            cols,
            filled,
            valid,
            measured,
            missing_samples,
            xs,
            ys,
            sides: Sides::default(),
            epsilon_um: params.epsilon_um,
            max_triangles: params.max_triangles.unwrap_or(usize::MAX),
            keep_extremes: params.keep_extremes,
            bound_scale: Vec::new(),
        };
        plan.sides = plan.sides_at(params.epsilon_um);
        Ok(plan)
    }

    /// The plan with block `k`'s insertion bound `scales[k]` times the step's bound, and
    /// every shared side's the smaller of its two blocks' (so that both blocks keep their
    /// bound along it). Errors: not one finite factor > 0 per block.
    pub(crate) fn with_bound_scales(mut self, scales: Vec<f64>) -> Result<Self> {
        if scales.len() != self.block_count() || !scales.iter().all(|s| s.is_finite() && *s > 0.0) {
            return Err(MeshError::Incompatible(format!(
                "expected {} finite bound factors > 0, one per block, got {}",
                self.block_count(),
                scales.len()
            )));
        }
        self.bound_scale = scales;
        self.sides = self.sides_at(self.epsilon_um);
        Ok(self)
    }

    /// Block `k`'s factor of the step's bound.
    fn bound_scale(&self, k: usize) -> f64 {
        self.bound_scale.get(k).copied().unwrap_or(1.0)
    }

    /// Block `k`'s insertion bound at the step of `sides`, um.
    pub(crate) fn block_epsilon(&self, sides: &Sides, k: usize) -> f64 {
        sides.epsilon_um * self.bound_scale(k)
    }

    /// The largest factor of the step's bound any block has (1 without factors): every
    /// sample is within that times the step's bound.
    pub(crate) fn largest_bound_scale(&self) -> f64 {
        self.bound_scale.iter().copied().fold(1.0, f64::max)
    }

    /// The shared sides simplified at `epsilon_um` (times the smaller bound factor of the
    /// two blocks each one separates): vertical ones (x = xs[i], 0 < i < nbx) per block row,
    /// horizontal ones (y = ys[j]) per block column. A smaller bound keeps every vertex a
    /// larger one kept ([`simplify_border`]).
    pub(crate) fn sides_at(&self, epsilon_um: f64) -> Sides {
        let (nbx, nby) = self.blocks_x_y();
        let (xs, ys, cols) = (&self.xs, &self.ys, self.cols);
        let mut vertical = vec![Vec::new(); (nbx + 1) * nby];
        let mut horizontal = vec![Vec::new(); nbx * (nby + 1)];
        for j in 0..nby {
            for i in 1..nbx {
                let line: Vec<usize> = (ys[j]..=ys[j + 1]).map(|y| y * cols + xs[i]).collect();
                let k = j * nbx + i;
                let scale = self.bound_scale(k - 1).min(self.bound_scale(k));
                simplify_border(
                    &line,
                    &self.filled,
                    self.valid.as_deref(),
                    self.measured.as_deref(),
                    epsilon_um * scale,
                    &mut vertical[j * (nbx + 1) + i],
                );
            }
        }
        for j in 1..nby {
            for i in 0..nbx {
                let line: Vec<usize> = (xs[i]..=xs[i + 1]).map(|x| ys[j] * cols + x).collect();
                let k = j * nbx + i;
                let scale = self.bound_scale(k - nbx).min(self.bound_scale(k));
                simplify_border(
                    &line,
                    &self.filled,
                    self.valid.as_deref(),
                    self.measured.as_deref(),
                    epsilon_um * scale,
                    &mut horizontal[j * nbx + i],
                );
            }
        }
        Sides {
            vertical,
            horizontal,
            epsilon_um,
        }
    }

    /// Blocks per row of blocks, and rows of blocks.
    pub(crate) fn blocks_x_y(&self) -> (usize, usize) {
        (self.xs.len() - 1, self.ys.len() - 1)
    }

    pub(crate) fn block_count(&self) -> usize {
        let (nbx, nby) = self.blocks_x_y();
        nbx * nby
    }

    /// Block `k` (row-major) and which of its sides it shares (bottom, right, top, left).
    pub(crate) fn block(&self, k: usize) -> (Block, [bool; 4]) {
        let (nbx, nby) = self.blocks_x_y();
        let (i, j) = (k % nbx, k / nbx);
        let (xs, ys) = (&self.xs, &self.ys);
        let block = Block {
            x0: xs[i],
            y0: ys[j],
            x1: xs[i + 1],
            y1: ys[j + 1],
        };
        (block, [j > 0, i + 1 < nbx, j + 1 < nby, i > 0])
    }

    /// The other block that holds sample `s`, which lies on a shared side of block `k` (not
    /// at a corner); None when it lies on the grid's rim or inside the block.
    pub(crate) fn across(&self, k: usize, s: u32) -> Option<usize> {
        let (nbx, _) = self.blocks_x_y();
        let (block, [bottom, right, top, left]) = self.block(k);
        let (x, y) = (s as usize % self.cols, s as usize / self.cols);
        if x == block.x0 && left {
            Some(k - 1)
        } else if x == block.x1 && right {
            Some(k + 1)
        } else if y == block.y0 && bottom {
            Some(k - nbx)
        } else if y == block.y1 && top {
            Some(k + nbx)
        } else {
            None
        }
    }

    /// The vertices block `k` must have on its shared sides simplified as `sides`.
    fn border(&self, sides: &Sides, k: usize) -> Vec<u32> {
        let (nbx, _) = self.blocks_x_y();
        let (i, j) = (k % nbx, k / nbx);
        let (_, shared) = self.block(k);
        let mut border = Vec::new();
        for (side, list) in [
            (shared[0], &sides.horizontal[j * nbx + i]),
            (shared[1], &sides.vertical[j * (nbx + 1) + i + 1]),
            (shared[2], &sides.horizontal[(j + 1) * nbx + i]),
            (shared[3], &sides.vertical[j * (nbx + 1) + i]),
        ] {
            if side {
                border.extend_from_slice(list);
            }
        }
        border
    }

    /// Starts block `k` for step-by-step refinement at the bound of `sides` (the first step:
    /// border, peak and valley, every triangle scanned; then [`LiveBlock::refine`]);
    /// `track_mesh`: its scans keep the mesh's height at every sample, which
    /// [`LiveBlock::balance`] reads (an order never balanced need not: the same triangles).
    pub(crate) fn start(&self, sides: &Sides, k: usize, track_mesh: bool) -> LiveBlock<'_> {
        let (block, shared) = self.block(k);
        let mut border = self.border(sides, k);
        let b = start_block(
            &self.filled,
            self.valid.as_deref(),
            self.measured.as_deref(),
            self.cols,
            block,
            shared,
            &border,
            self.block_epsilon(sides, k),
            self.keep_extremes,
            track_mesh,
        );
        border.sort_unstable();
        border.dedup();
        LiveBlock {
            b,
            border,
            budget_reached: false,
            stats_cache: None,
        }
    }

    /// Block `k` as [`LiveBlock::encode`] wrote it (`bytes` from this plan's block `k`).
    pub(crate) fn decode(&self, k: usize, bytes: &[u8]) -> LiveBlock<'_> {
        let (block, _) = self.block(k);
        let bw = block.x1 - block.x0 + 1;
        let bh = block.y1 - block.y0 + 1;
        let mut r = Bytes { b: bytes, at: 0 };
        let epsilon_um = r.f64();
        let scanning = r.u8() == 1;
        let budget_reached = r.u8() == 1;
        let epoch = r.u32();
        let mesh_local = (r.u8() == 1).then(|| {
            let n = r.len();
            (0..n).map(|_| r.f64()).collect::<Vec<f64>>()
        });
        let n = r.len();
        let packed: Vec<u8> = (0..n.div_ceil(8)).map(|_| r.u8()).collect();
        let settled: Vec<bool> = (0..n).map(|i| packed[i / 8] >> (i % 8) & 1 == 1).collect();
        let vertex_samples = r.u32s();
        let verts = vertex_samples
            .iter()
            .map(|&s| {
                (
                    (s as usize % self.cols) as i64,
                    (s as usize / self.cols) as i64,
                )
            })
            .collect();
        let n = r.len();
        let tris = (0..n)
            .map(|_| {
                let v = [r.u32(), r.u32(), r.u32()];
                let nb = [r.u32(), r.u32(), r.u32()];
                Tri {
                    v,
                    n: nb,
                    stamp: r.u32(),
                    candidate: r.u32(),
                    err: r.f64(),
                    spans_missing: r.u8() == 1,
                }
            })
            .collect();
        let mark = r.u32s();
        let top = r.len();
        let mut buckets = vec![Vec::new(); BUCKETS];
        for _ in 0..r.len() {
            let i = r.len();
            let n = r.len();
            buckets[i] = (0..n).map(|_| (r.u32(), r.u32())).collect();
        }
        let border = r.u32s();
        let stats_cache = match r.u8() {
            0 => None,
            1 => Some(None),
            _ => Some(Some(BlockStats {
                mean: r.f64(),
                sa: r.f64(),
                sq: r.f64(),
            })),
        };
        debug_assert_eq!(r.at, bytes.len());
        LiveBlock {
            b: Builder {
                width: self.cols,
                block,
                bw,
                z: &self.filled,
                valid: self.valid.as_deref(),
                measured: self.measured.as_deref(),
                mesh_local,
                settled,
                verts,
                vertex_samples,
                tris,
                queue: BucketQueue { buckets, top },
                epsilon_um,
                scanning,
                small: bw < SMALL_SIDE && bh < SMALL_SIDE,
                mark,
                epoch,
                cavity: Vec::new(),
                rim: Vec::new(),
                fresh: Vec::new(),
            },
            border,
            budget_reached,
            stats_cache,
        }
    }

    /// Meshes block `k` (row-major) with the shared sides' vertices fixed.
    pub(crate) fn mesh(&self, k: usize) -> BlockTin {
        let (block, shared) = self.block(k);
        let border = self.border(&self.sides, k);
        mesh_block(
            &self.filled,
            self.valid.as_deref(),
            self.measured.as_deref(),
            self.cols,
            block,
            shared,
            &border,
            self.epsilon_um * self.bound_scale(k),
            self.max_triangles,
            self.keep_extremes,
        )
    }
}

/// The samples on the grid's outer rectangle that are vertices (`is_vertex`),
/// counter-clockwise from +z starting at sample 0: the rim of a triangulation that covers the
/// whole rectangle.
pub(crate) fn grid_rim(is_vertex: impl Fn(usize) -> bool, shape: Shape) -> Vec<u32> {
    let Shape { rows, cols } = shape;
    let at = |x: usize, y: usize| y * cols + x;
    let mut rim = Vec::new();
    rim.extend((0..cols - 1).map(|x| at(x, 0)));
    rim.extend((0..rows - 1).map(|y| at(cols - 1, y)));
    rim.extend((1..cols).rev().map(|x| at(x, rows - 1)));
    rim.extend((1..rows).rev().map(|y| at(0, y)));
    rim.retain(|&s| is_vertex(s));
    rim.dedup();
    rim.into_iter().map(|s| s as u32).collect()
}

/// The mesh resampled on the grid, and its vertical error against the measured samples
/// (`measured_um`, NaN = not measured). Every sample covered by a kept triangle gets the
/// triangle's plane height (um, relative to the field's z offset; uncovered samples are NaN);
/// the error is computed in f64 from the planes, so it reflects the mesh, not the f32 rounding
/// of large heights. Rows of blocks run in parallel; the sums are combined in row order, so
/// the result does not depend on the thread count.
pub fn resample_with_error(tin: &Tin, measured_um: &[f32]) -> (Vec<f32>, ErrorStats) {
    let (w, h) = (tin.shape.cols, tin.shape.rows);
    let mut resampled = vec![f32::NAN; w * h];
    // Bands of block rows: band k owns rows y0..y1 (the last one also row y1 = h - 1).
    let mut bands: Vec<(usize, usize, Vec<usize>)> = Vec::new();
    for (k, (b, _)) in tin.blocks.iter().enumerate() {
        match bands.last_mut() {
            Some(band) if band.0 == b.y0 => band.2.push(k),
            _ => bands.push((b.y0, b.y1, vec![k])),
        }
    }
    let as_samples = |members: &[usize]| -> Vec<[u32; 3]> {
        members
            .iter()
            .flat_map(|&k| &tin.triangles[tin.blocks[k].1.clone()])
            .map(|t| t.map(|v| tin.vertex_samples[v as usize]))
            .collect()
    };
    let mut chunks = Vec::with_capacity(bands.len());
    let mut rest: &mut [f32] = &mut resampled;
    for (k, band) in bands.iter().enumerate() {
        let end = if k + 1 == bands.len() { h } else { band.1 };
        let (this, next) = rest.split_at_mut((end - band.0) * w);
        // The band below shares row y0; with holes its triangles may be the only ones there.
        let below: &[usize] = if k > 0 { &bands[k - 1].2 } else { &[] };
        chunks.push((band, below, this));
        rest = next;
    }
    let stats: Vec<ErrorStats> = chunks
        .into_par_iter()
        .map(|((y0, _, members), below, out)| {
            let below = on_row(&as_samples(below), *y0, w);
            paint_band(
                &tin.filled_um,
                measured_um,
                w,
                *y0,
                &below,
                &as_samples(members),
                out,
            )
        })
        .collect();
    (resampled, ErrorStats::combine(&stats))
}

/// The triangles (as sample triples) with a corner on row `y` of a grid `w` samples wide: what
/// a band of blocks paints on the row it shares with the band above.
pub(crate) fn on_row(tris: &[[u32; 3]], y: usize, w: usize) -> Vec<[u32; 3]> {
    tris.iter()
        .filter(|t| t.iter().any(|&s| s as usize / w == y))
        .copied()
        .collect()
}

/// Paints the triangles of one band of blocks on its rows (`out`: rows `y0..`, `w` wide, f32
/// of the f64 plane heights, um relative to the z offset; NaN where no triangle covers), first
/// the triangles of the band below that touch the shared row `y0`, then the band's own, in
/// order (a later triangle wins on a shared edge), and returns the vertical error of the
/// band's rows against `measured_um` (the whole grid's). Corners are grid sample indices;
/// `filled_um` gives their heights.
pub(crate) fn paint_band(
    filled_um: &[f32],
    measured_um: &[f32],
    w: usize,
    y0: usize,
    below: &[[u32; 3]],
    own: &[[u32; 3]],
    out: &mut [f32],
) -> ErrorStats {
    let end = (y0 + out.len() / w) as i64;
    let (y0, wi) = (y0 as i64, w as i64);
    // f64 while painting, so the error below is that of the planes themselves.
    let mut mesh_um = vec![f64::NAN; out.len()];
    for tri in below.iter().chain(own) {
        let c = tri.map(|s| {
            let s = s as usize;
            ((s % w) as i64, (s / w) as i64, f64::from(filled_um[s]))
        });
        let plane = Plane::through(c);
        for_each_row(
            (c[0].0, c[0].1),
            (c[1].0, c[1].1),
            (c[2].0, c[2].1),
            |y, lo, hi| {
                if y >= y0 && y < end {
                    let row = ((y - y0) * wi) as usize;
                    for x in lo..=hi {
                        mesh_um[row + x as usize] = plane.at(x, y);
                    }
                }
                true
            },
        );
    }
    let (mut max_um, mut sum2, mut samples, mut uncovered) = (0.0f64, 0.0f64, 0, 0);
    let first = (y0 * wi) as usize;
    for (k, &m) in mesh_um.iter().enumerate() {
        out[k] = m as f32;
        let s = measured_um[first + k];
        if s.is_nan() {
            continue;
        }
        if m.is_nan() {
            uncovered += 1;
            continue;
        }
        let e = m - f64::from(s);
        max_um = max_um.max(e.abs());
        sum2 += e * e;
        samples += 1;
    }
    ErrorStats {
        max_um,
        rms_um: sum2,
        samples,
        uncovered,
    }
}

impl ErrorStats {
    /// The bands' statistics (from [`paint_band`], `rms_um` holding the band's sum of
    /// squares) combined in band order.
    pub(crate) fn combine(bands: &[ErrorStats]) -> ErrorStats {
        let (mut max_um, mut sum2, mut samples, mut uncovered) = (0.0f64, 0.0f64, 0, 0);
        for s in bands {
            max_um = max_um.max(s.max_um);
            sum2 += s.rms_um;
            samples += s.samples;
            uncovered += s.uncovered;
        }
        ErrorStats {
            max_um,
            rms_um: if samples > 0 {
                (sum2 / samples as f64).sqrt()
            } else {
                0.0
            },
            samples,
            uncovered,
        }
    }
}

/// Vertical error of a mesh against the measured samples.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ErrorStats {
    /// Largest |mesh - sample| over the measured samples, um.
    pub max_um: f64,
    /// Root mean square of (mesh - sample) over the measured samples, um.
    pub rms_um: f64,
    /// Measured samples compared.
    pub samples: usize,
    /// Measured samples no triangle covers (0 unless a budget stopped a holes mesh).
    pub uncovered: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute(a: (i64, i64), b: (i64, i64), c: (i64, i64)) -> Vec<(i64, i64)> {
        let mut v = Vec::new();
        for y in -3..12 {
            for x in -3..12 {
                if orient(a, b, (x, y)) >= 0
                    && orient(b, c, (x, y)) >= 0
                    && orient(c, a, (x, y)) >= 0
                {
                    v.push((x, y));
                }
            }
        }
        v
    }

    #[test]
    fn rows_cover_exactly_the_closed_triangle() {
        let cases = [
            ((0, 0), (9, 0), (9, 7)),
            ((0, 0), (9, 7), (0, 7)),
            ((1, 2), (8, 5), (3, 9)),
            ((5, 0), (6, 9), (0, 4)),
            ((0, 0), (1, 0), (0, 1)),
        ];
        for (a, b, c) in cases {
            let mut got = Vec::new();
            for_each_row(a, b, c, |y, lo, hi| {
                got.extend((lo..=hi).map(|x| (x, y)));
                true
            });
            got.sort_by_key(|&(x, y)| (y, x));
            let mut want = brute(a, b, c);
            want.sort_by_key(|&(x, y)| (y, x));
            assert_eq!(got, want, "{a:?} {b:?} {c:?}");
        }
    }

    #[test]
    fn small_incircle_agrees_with_the_wide_one() {
        let mut state = 7u64;
        let mut next = |m: i64| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            ((state >> 33) as i64).rem_euclid(m)
        };
        let m = SMALL_SIDE as i64;
        for _ in 0..20_000 {
            let p = [(); 4].map(|_| (next(m), next(m)));
            let (a, b, c) = (p[0], p[1], p[2]);
            if orient(a, b, c) <= 0 {
                continue;
            }
            let wide = incircle(a, b, c, p[3]);
            assert_eq!(i128::from(incircle_small(a, b, c, p[3])), wide);
        }
        // The extreme corners of a block.
        let (a, b, c, d) = ((0, 0), (m - 1, 0), (m - 1, m - 1), (0, m - 1));
        assert_eq!(incircle_small(a, b, c, d), 0);
        assert_eq!(
            i128::from(incircle_small(a, b, (0, m - 1), (1, 1))),
            incircle(a, b, (0, m - 1), (1, 1))
        );
    }

    #[test]
    fn div_floor_matches_euclid() {
        for n in -300i64..300 {
            for d in 1i64..40 {
                assert_eq!(
                    div_floor(n, d),
                    (n.div_euclid(d), n.rem_euclid(d)),
                    "{n} / {d}"
                );
            }
        }
        for (n, d) in [
            ((1i64 << 52) - 1, 3),
            (-(1i64 << 52) + 1, 7),
            (1i64 << 60, 12_345),
            (-(1i64 << 61) - 17, 1 << 30),
            (9_007_199_254_740_991, 9_007_199_254_740_990),
        ] {
            assert_eq!(
                div_floor(n, d),
                (n.div_euclid(d), n.rem_euclid(d)),
                "{n} / {d}"
            );
        }
    }

    fn lcg_field(rows: usize, cols: usize, seed: u64) -> Vec<f32> {
        let mut state = seed;
        (0..rows * cols)
            .map(|k| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                let r = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
                let (x, y) = ((k % cols) as f64, (k / cols) as f64);
                ((x / 7.0).sin() * (y / 5.0).cos() + 0.5 * r) as f32
            })
            .collect()
    }

    fn params_at(epsilon_um: f64, block: usize) -> TinParams {
        TinParams {
            epsilon_um,
            max_triangles: None,
            missing: MissingSamples::Fill,
            block_samples: Some(block),
            keep_extremes: true,
        }
    }

    #[test]
    fn a_finer_side_simplification_keeps_every_coarser_vertex() {
        let z = lcg_field(1, 300, 3);
        let line: Vec<usize> = (0..300).collect();
        let (mut coarse, mut fine) = (Vec::new(), Vec::new());
        simplify_border(&line, &z, None, None, 0.4, &mut coarse);
        simplify_border(&line, &z, None, None, 0.1, &mut fine);
        assert!(fine.len() > coarse.len());
        assert!(coarse.iter().all(|v| fine.contains(v)));
    }

    /// Refines every block of `plan` through `bounds`, balancing with `balance`, and joins
    /// them.
    fn refined(plan: &BlockPlan<'_>, bounds: &[f64], balance: Option<Balance>) -> Tin {
        let mut live: Vec<LiveBlock<'_>> = Vec::new();
        for &e in bounds {
            let sides = plan.sides_at(e);
            if live.is_empty() {
                live = (0..plan.block_count())
                    .map(|k| plan.start(&sides, k, true))
                    .collect();
            }
            for (k, b) in live.iter_mut().enumerate() {
                b.refine(plan, &sides, k);
                if let Some(t) = balance {
                    b.balance(plan, t);
                }
            }
        }
        // The heights the scans keep are the triangles' planes, painted afresh.
        for b in &live {
            if let (Some(kept), None) = (&b.b.mesh_local, b.b.valid) {
                let painted = b.b.paint_local();
                assert!(kept
                    .iter()
                    .zip(&painted)
                    .all(|(a, p)| (a - p).abs() <= 1e-9 * (1.0 + p.abs())));
            }
        }
        let meshed: Vec<BlockTin> = live.iter().map(LiveBlock::snapshot).collect();
        assemble(plan, &meshed)
    }

    #[test]
    fn one_order_refined_in_steps_meets_the_last_bound_without_cracks() {
        let (rows, cols) = (50, 61);
        let z = lcg_field(rows, cols, 11);
        let view = RasterView::new(&z, Shape::new(rows, cols)).unwrap();
        let plan = BlockPlan::new(view, &params_at(0.8, 16)).unwrap();
        let tin = refined(&plan, &[0.8, 0.4, 0.15], None);
        let (_, err) = resample_with_error(&tin, &z);
        assert_eq!(err.uncovered, 0);
        assert!(err.max_um <= 0.15, "{}", err.max_um);
        // Every grid cell is covered exactly once: the triangles' areas sum to the grid's.
        let area2: i64 = tin
            .triangles
            .iter()
            .map(|t| {
                let p = t.map(|v| {
                    let s = tin.vertex_samples[v as usize] as i64;
                    (s % cols as i64, s / cols as i64)
                });
                orient(p[0], p[1], p[2])
            })
            .sum();
        assert_eq!(area2, 2 * (rows as i64 - 1) * (cols as i64 - 1));
    }

    /// Per-block bounds: every sample within its own block's bound (the shared sides within
    /// the smaller of their two), the mesh still conforming (the grid covered exactly once),
    /// fewer triangles where the bound is coarser, and a factor per block or an error.
    #[test]
    fn each_block_meets_its_own_bound_and_the_mesh_stays_conforming() {
        let (rows, cols) = (50, 61);
        let z = lcg_field(rows, cols, 11);
        let view = RasterView::new(&z, Shape::new(rows, cols)).unwrap();
        let uniform = BlockPlan::new(view, &params_at(0.8, 16)).unwrap();
        let n = uniform.block_count();
        assert!(BlockPlan::new(view, &params_at(0.8, 16))
            .unwrap()
            .with_bound_scales(vec![1.0; n + 1])
            .is_err());
        assert!(BlockPlan::new(view, &params_at(0.8, 16))
            .unwrap()
            .with_bound_scales(vec![0.0; n])
            .is_err());
        // The right half of the blocks at three times the bound.
        let (nbx, _) = uniform.blocks_x_y();
        let scales: Vec<f64> = (0..n)
            .map(|k| if k % nbx >= nbx / 2 { 3.0 } else { 1.0 })
            .collect();
        let scaled = BlockPlan::new(view, &params_at(0.8, 16))
            .unwrap()
            .with_bound_scales(scales.clone())
            .unwrap();
        assert_eq!(scaled.largest_bound_scale(), 3.0);
        let bounds = [0.8, 0.3, 0.1];
        let (fine, coarse) = (
            refined(&uniform, &bounds, None),
            refined(&scaled, &bounds, None),
        );
        let (mesh, err) = resample_with_error(&coarse, &z);
        assert_eq!(err.uncovered, 0);
        assert!(err.max_um <= 0.3, "{}", err.max_um);
        // Each sample within the bound of every block that holds it (a side: the smaller).
        let mut coarser_used = 0.0f64;
        for y in 0..rows {
            for x in 0..cols {
                let s = y * cols + x;
                let bound = (0..n)
                    .filter(|&k| {
                        let (b, _) = scaled.block(k);
                        (b.x0..=b.x1).contains(&x) && (b.y0..=b.y1).contains(&y)
                    })
                    .map(|k| 0.1 * scales[k])
                    .fold(f64::INFINITY, f64::min);
                let e = (f64::from(mesh[s]) - f64::from(z[s])).abs();
                assert!(e <= bound * (1.0 + 1e-6), "sample {s}: {e} > {bound}");
                if bound > 0.1 {
                    coarser_used = coarser_used.max(e);
                }
            }
        }
        assert!(coarser_used > 0.1, "{coarser_used}");
        assert!(coarse.triangles.len() < fine.triangles.len());
        let area2: i64 = coarse
            .triangles
            .iter()
            .map(|t| {
                let p = t.map(|v| {
                    let s = coarse.vertex_samples[v as usize] as i64;
                    (s % cols as i64, s / cols as i64)
                });
                orient(p[0], p[1], p[2])
            })
            .sum();
        assert_eq!(area2, 2 * (rows as i64 - 1) * (cols as i64 - 1));
    }

    #[test]
    fn filled_samples_are_covered_but_never_inserted() {
        let (rows, cols) = (48, 48);
        let mut z = lcg_field(rows, cols, 5);
        for y in 10..30 {
            for x in 12..34 {
                z[y * cols + x] = f32::NAN;
            }
        }
        let view = RasterView::new(&z, Shape::new(rows, cols)).unwrap();
        let plan = BlockPlan::new(view, &params_at(0.05, 16)).unwrap();
        let tin = refined(&plan, &[0.05], None);
        let on_side = |s: usize| plan.xs.contains(&(s % cols)) || plan.ys.contains(&(s / cols));
        let inside: Vec<u32> = tin
            .vertex_samples
            .iter()
            .copied()
            .filter(|&s| z[s as usize].is_nan() && !on_side(s as usize))
            .collect();
        assert!(inside.is_empty(), "{inside:?}");
        let (_, err) = resample_with_error(&tin, &z);
        assert!(err.max_um <= 0.05 && err.uncovered == 0, "{err:?}");
    }

    #[test]
    fn a_balanced_block_matches_the_measured_sa_and_sq() {
        let n = 64;
        let z = lcg_field(n, n, 9);
        let view = RasterView::new(&z, Shape::new(n, n)).unwrap();
        let plan = BlockPlan::new(view, &params_at(0.9, 64)).unwrap();
        let stats = |v: &[f32]| {
            let v: Vec<f64> = v.iter().map(|&h| f64::from(h)).collect();
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            let sa = v.iter().map(|h| (h - mean).abs()).sum::<f64>() / v.len() as f64;
            let sq = (v.iter().map(|h| (h - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
            (sa, sq)
        };
        let (sa, sq) = stats(&z);
        let greedy = refined(&plan, &[0.9], None);
        let (gm, _) = resample_with_error(&greedy, &z);
        let (ga, gq) = stats(&gm);
        // The greedy mesh at this bound is off by more than the target ...
        assert!((ga / sa - 1.0).abs() > 0.01 || (gq / sq - 1.0).abs() > 0.01);
        let target = Balance {
            sa: 0.005,
            sq: 0.005,
            roughness: None,
        };
        let balanced = refined(&plan, &[0.9], Some(target));
        let (bm, err) = resample_with_error(&balanced, &z);
        let (ba, bq) = stats(&bm);
        // ... the balanced one within it, with the bound still held.
        assert!((ba / sa - 1.0).abs() <= 0.005, "Sa {ba} vs {sa}");
        assert!((bq / sq - 1.0).abs() <= 0.005, "Sq {bq} vs {sq}");
        assert!(err.max_um <= 0.9);
        assert!(balanced.triangles.len() > greedy.triangles.len());
    }

    /// Triangles of the block whose circumcircle holds a vertex strictly inside.
    fn not_delaunay(b: &Builder<'_>) -> usize {
        b.tris
            .iter()
            .filter(|t| {
                let p = t.v.map(|v| b.verts[v as usize]);
                b.verts.iter().any(|&q| incircle(p[0], p[1], p[2], q) > 0)
            })
            .count()
    }

    #[test]
    fn the_balance_holds_the_roughness_the_mesh_carries_when_given() {
        let n = 64;
        let z = lcg_field(n, n, 9);
        // The roughness: the field minus its waviness (what lcg_field adds as noise).
        let g: Vec<f32> = z
            .iter()
            .enumerate()
            .map(|(k, &h)| {
                let (x, y) = ((k % n) as f64, (k / n) as f64);
                (f64::from(h) - (x / 7.0).sin() * (y / 5.0).cos()) as f32
            })
            .collect();
        let view = RasterView::new(&z, Shape::new(n, n)).unwrap();
        let plan = BlockPlan::new(view, &params_at(0.6, 64)).unwrap();
        let stats = |v: &[f64]| {
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            let sa = v.iter().map(|h| (h - mean).abs()).sum::<f64>() / v.len() as f64;
            let sq = (v.iter().map(|h| (h - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
            (sa, sq)
        };
        let (ra, rq) = stats(&g.iter().map(|&v| f64::from(v)).collect::<Vec<_>>());
        // Sa and Sq of the roughness a mesh carries (roughness + mesh - measurement), as
        // fractions off the measured roughness's.
        let carried = |tin: &Tin| {
            let (m, _) = resample_with_error(tin, &z);
            let c: Vec<f64> = (0..z.len())
                .map(|k| f64::from(g[k]) + f64::from(m[k]) - f64::from(z[k]))
                .collect();
            let (ca, cq) = stats(&c);
            (ca / ra - 1.0, cq / rq - 1.0)
        };
        let heights_only = Balance {
            sa: 0.005,
            sq: 0.005,
            roughness: None,
        };
        let (ha, hq) = carried(&refined(&plan, &[0.6], Some(heights_only)));
        let both = Balance {
            roughness: Some((&g, 0.025)),
            ..heights_only
        };
        let balanced = refined(&plan, &[0.6], Some(both));
        let (ba, bq) = carried(&balanced);
        // The heights' balance alone leaves the roughness off by more than the target ...
        assert!(ha.abs().max(hq.abs()) > 0.025, "{ha} {hq}");
        // ... the balance given the roughness brings it within.
        assert!(ba.abs() <= 0.025 && bq.abs() <= 0.025, "{ba} {bq}");
    }

    #[test]
    fn a_live_block_stays_delaunay_and_the_angle_bound_holds_in_it() {
        let (rows, cols) = (130, 130);
        let z = lcg_field(rows, cols, 5);
        let heights = RasterView::new(&z, Shape::new(rows, cols)).unwrap();
        let plan = BlockPlan::new(heights, &params_at(0.5, 64)).unwrap();
        let mut b = plan.start(&plan.sides_at(0.5), 0, true);
        // Finer bounds insert more vertices on the shared sides, several per call.
        for e in [0.4, 0.3, 0.2, 0.1] {
            b.refine(&plan, &plan.sides_at(e), 0);
            b.balance(
                &plan,
                Balance {
                    sa: 0.005,
                    sq: 0.005,
                    roughness: None,
                },
            );
            assert_eq!(not_delaunay(&b.b), 0, "bound {e}");
        }
        let bound = AngleBound {
            min_angle_deg: 12.0,
            pitch: surfstream_core::Pitch::new(1.0, 1.2).unwrap(),
        };
        let before = b.b.tris.len();
        let (added, left) = b.bound_angles(&plan, 0, &[], &bound, true);
        assert_eq!(left, 0);
        assert_eq!(not_delaunay(&b.b), 0);
        assert!(b.b.tris.len() > before, "12 deg needs some refinement here");
        let smallest = (0..b.b.tris.len())
            .map(|t| b.b.min_angle(t, &bound))
            .fold(f64::INFINITY, f64::min);
        assert!(smallest >= 12.0, "{smallest}");
        // What it added on its shared sides (right and top) is for the blocks across.
        for &s in &added {
            let (x, y) = (s as usize % cols, s as usize / cols);
            assert!(x == b.b.block.x1 || y == b.b.block.y1, "({x}, {y})");
            assert!(plan.across(0, s).is_some());
        }
    }

    #[test]
    fn incircle_is_exact_on_cocircular_grid_points() {
        assert_eq!(incircle((0, 0), (1, 0), (1, 1), (0, 1)), 0);
        assert!(incircle((0, 0), (2, 0), (2, 2), (1, 1)) > 0);
        assert!(incircle((0, 0), (2, 0), (2, 2), (3, -1)) < 0);
    }
}
