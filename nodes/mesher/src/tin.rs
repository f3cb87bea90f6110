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
//! ([`crate::fill_missing`]) and meshed like measured ones. With [`MissingSamples::Holes`] a
//! triangle must never span one: a triangle whose corners are all measured but that covers a
//! missing sample is refined at that sample (it becomes a vertex, its height from the fill);
//! triangles with a missing corner are left out of the result, and refined first if they cover
//! a measured sample, so every measured sample stays inside a kept triangle.

use crate::error::{MeshError, Result};
use crate::field::{fill_missing, positive_finite, HeightFieldRef};

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
}

/// An error-bounded triangulation of a height field. Vertices are grid samples.
#[derive(Debug, Clone)]
pub struct Tin {
    /// Grid width and height (samples).
    pub width: usize,
    pub height: usize,
    /// Sample index (`row * width + col`) of every vertex.
    pub vertex_samples: Vec<u32>,
    /// Kept triangles as vertex indices, counter-clockwise seen from +z (x = column, y = row).
    pub triangles: Vec<[u32; 3]>,
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
    /// Covers a missing sample although its corners are measured (holes mode).
    spans_missing: bool,
}

/// Visits every grid sample inside or on the boundary of the counter-clockwise triangle
/// (a, b, c) (integer column, row coordinates), row by row, with the row and the inclusive
/// column range. Exact: the column bounds come from integer floor/ceil divisions.
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
    let edges = [(a, b), (b, c), (c, a)];
    for y in y0..=y1 {
        let (mut lo, mut hi) = (x_lo, x_hi);
        for &(p, q) in &edges {
            // Inside or on the edge: (q - p) x (s - p) >= 0, i.e.
            // dy * (x - px) <= dx * (y - py).
            let (dx, dy) = (q.0 - p.0, q.1 - p.1);
            let num = dx * (y - p.1);
            if dy > 0 {
                hi = hi.min(p.0 + num.div_euclid(dy));
            } else if dy < 0 {
                // x - px >= num / dy = (-num) / (-dy): a ceiling.
                lo = lo.max(p.0 + (-num).div_euclid(-dy) + ceil_fix(-num, -dy));
            } else if num < 0 {
                lo = 1;
                hi = 0;
            }
        }
        if lo <= hi && !f(y, lo, hi) {
            return;
        }
    }
}

/// ceil(n / d) - floor(n / d) for d > 0: 1 when d does not divide n.
#[inline]
fn ceil_fix(n: i64, d: i64) -> i64 {
    i64::from(n.rem_euclid(d) != 0)
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
        Self {
            x0: a.0 as f64,
            y0: a.1 as f64,
            z0: a.2,
            gx: -nx / nz,
            gy: -ny / nz,
        }
    }

    #[inline]
    pub(crate) fn at(&self, x: i64, y: i64) -> f64 {
        self.z0 + self.gx * (x as f64 - self.x0) + self.gy * (y as f64 - self.y0)
    }
}

/// The work queue: triangles by the error of their candidate, in buckets 1/16 of an octave
/// wide above epsilon. Refinement forced by missing samples goes to the bottom bucket: done
/// last, when the error-driven triangles are already small, it stays local (done first, the
/// long triangles of the first steps cascaded into many needless vertices). Taking any triangle
/// of the highest non-empty bucket is greedy insertion up to 4.4 % in the error, which changes
/// the order of refinement a little and the bound not at all, and costs O(1) per push and pop
/// where a binary heap over a million triangles spent most of the run on cache misses.
/// Entries carry the triangle's stamp at queueing time; a rescanned triangle leaves a stale
/// entry that is skipped when popped.
struct BucketQueue {
    buckets: Vec<Vec<(u32, u32)>>,
    top: usize,
}

const BUCKETS_PER_OCTAVE: f64 = 16.0;
const BUCKETS: usize = 64 * 16 + 2;

impl BucketQueue {
    /// Bucket of an error `ratio` = error / epsilon > 1.
    fn bucket(ratio: f64) -> usize {
        let b = 1 + (ratio.log2() * BUCKETS_PER_OCTAVE) as usize;
        b.min(BUCKETS - 1)
    }

    fn push(&mut self, b: usize, t: u32, stamp: u32) {
        self.buckets[b].push((t, stamp));
        self.top = self.top.max(b);
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

struct Builder<'a> {
    width: usize,
    z: &'a [f32],
    /// Measured (not NaN in the input); all true in fill mode.
    valid: Option<Vec<bool>>,
    is_vertex: Vec<bool>,
    verts: Vec<(i64, i64)>,
    vertex_samples: Vec<u32>,
    tris: Vec<Tri>,
    queue: BucketQueue,
    epsilon_um: f64,
    mark: Vec<u32>,
    epoch: u32,
    // Scratch buffers reused by every insertion.
    cavity: Vec<u32>,
    rim: Vec<(u32, u32, u32)>,
    fresh: Vec<u32>,
}

impl Builder<'_> {
    fn is_valid(&self, s: usize) -> bool {
        self.valid.as_ref().is_none_or(|v| v[s])
    }

    fn add_vertex(&mut self, s: usize) -> u32 {
        let id = self.verts.len() as u32;
        self.verts
            .push(((s % self.width) as i64, (s / self.width) as i64));
        self.vertex_samples.push(s as u32);
        self.is_vertex[s] = true;
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
        let mut best = (0.0f64, NONE);
        let mut forced = NONE;
        let mut spans_missing = false;
        match &self.valid {
            None => for_each_row(a, b, cc, |y, lo, hi| {
                let row = (y * w) as usize;
                let mut zp = plane.at(lo, y);
                for x in lo..=hi {
                    let s = row + x as usize;
                    let e = (f64::from(self.z[s]) - zp).abs();
                    if e > best.0 && !self.is_vertex[s] {
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
                    for x in lo..=hi {
                        let s = row + x as usize;
                        if self.is_vertex[s] {
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
            self.queue.push(0, t, tri.stamp);
        } else if best.1 != NONE && best.0 > self.epsilon_um {
            tri.candidate = best.1;
            self.queue
                .push(BucketQueue::bucket(best.0 / self.epsilon_um), t, tri.stamp);
        } else {
            tri.candidate = NONE;
        }
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
                    if incircle(o[0], o[1], o[2], pp) > 0 {
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
        for i in 0..self.fresh.len() {
            let t = self.fresh[i];
            self.scan(t);
        }
    }
}

/// Triangulates `map` so that every sample (every measured one with holes) lies within
/// `epsilon_um` vertically of the mesh, with greedy insertion (see the module docs), unless the
/// triangle budget stops it first.
///
/// The four grid corners are always vertices and the rim follows the grid's rectangle exactly
/// (with holes, the corners may be missing and their triangles left out).
pub fn triangulate(map: HeightFieldRef<'_>, params: &TinParams) -> Result<Tin> {
    map.validate()?;
    positive_finite("epsilon_um", params.epsilon_um)?;
    if let Some(n) = params.max_triangles {
        if n < 2 {
            return Err(MeshError::InvalidParameter {
                name: "max_triangles",
                value: n as f64,
                expected: "at least 2 (the two triangles spanning the grid)",
            });
        }
    }
    let (width, height) = (map.width, map.height);
    if width > i32::MAX as usize || height > i32::MAX as usize || width * height >= NONE as usize {
        return Err(MeshError::TooLarge {
            what: "samples",
            count: width * height,
            limit: NONE as usize - 1,
        });
    }
    let (filled, missing_samples) = fill_missing(map.heights_um, width, height)?;
    let filled: Vec<f32> = filled.into_owned();
    let valid = (params.missing == MissingSamples::Holes && missing_samples > 0)
        .then(|| map.heights_um.iter().map(|h| !h.is_nan()).collect());
    let n = width * height;
    let mut b = Builder {
        width,
        z: &filled,
        valid,
        is_vertex: vec![false; n],
        verts: Vec::new(),
        vertex_samples: Vec::new(),
        tris: Vec::new(),
        queue: BucketQueue {
            buckets: vec![Vec::new(); BUCKETS],
            top: 0,
        },
        epsilon_um: params.epsilon_um,
        mark: Vec::new(),
        epoch: 0,
        cavity: Vec::new(),
        rim: Vec::new(),
        fresh: Vec::new(),
    };
    let c00 = b.add_vertex(0);
    let c10 = b.add_vertex(width - 1);
    let c11 = b.add_vertex(n - 1);
    let c01 = b.add_vertex(n - width);
    b.tris.push(Tri {
        v: [c00, c10, c11],
        n: [NONE, 1, NONE],
        stamp: 0,
        candidate: NONE,
        spans_missing: false,
    });
    b.tris.push(Tri {
        v: [c00, c11, c01],
        n: [NONE, NONE, 0],
        stamp: 0,
        candidate: NONE,
        spans_missing: false,
    });
    b.mark = vec![0; 2];
    b.scan(0);
    b.scan(1);

    let max_triangles = params.max_triangles.unwrap_or(usize::MAX);
    let mut budget_reached = false;
    while let Some((t, stamp)) = b.queue.pop() {
        let tri = b.tris[t as usize];
        if tri.stamp != stamp || tri.candidate == NONE {
            continue;
        }
        if b.tris.len() + 2 > max_triangles {
            budget_reached = true;
            break;
        }
        b.insert(tri.candidate as usize, t);
    }

    // Keep the triangles whose corners are all measured and that span no missing sample.
    let mut triangles = Vec::with_capacity(b.tris.len());
    let mut dropped_spanning = 0;
    let mut kept = vec![false; b.tris.len()];
    for (k, t) in b.tris.iter().enumerate() {
        let corners_valid =
            t.v.iter()
                .all(|&v| b.is_valid(b.vertex_samples[v as usize] as usize));
        if !corners_valid {
            continue;
        }
        if t.spans_missing {
            dropped_spanning += 1;
            continue;
        }
        kept[k] = true;
        triangles.push(t.v);
    }
    let rim = if triangles.len() == b.tris.len() {
        hull_rim(&b.tris)
    } else {
        None
    };
    Ok(Tin {
        width,
        height,
        vertex_samples: b.vertex_samples,
        triangles,
        rim,
        filled_um: filled,
        missing_samples,
        budget_reached,
        dropped_spanning,
    })
}

/// The hull edges (no neighbour) chained counter-clockwise into one loop.
fn hull_rim(tris: &[Tri]) -> Option<Vec<u32>> {
    let mut next = std::collections::HashMap::new();
    for t in tris {
        for e in 0..3 {
            if t.n[e] == NONE {
                next.insert(t.v[(e + 1) % 3], t.v[(e + 2) % 3]);
            }
        }
    }
    let (&first, _) = next.iter().min_by_key(|(k, _)| **k)?;
    let mut rim = vec![first];
    let mut v = next[&first];
    while v != first {
        if rim.len() > next.len() {
            return None;
        }
        rim.push(v);
        v = *next.get(&v)?;
    }
    (rim.len() == next.len()).then_some(rim)
}

/// The mesh resampled on the grid: every sample covered by a kept triangle gets the
/// triangle's plane height (um, relative to the field's z offset); uncovered samples are NaN.
pub fn resample(tin: &Tin) -> Vec<f32> {
    let mut out = vec![f32::NAN; tin.width * tin.height];
    let w = tin.width as i64;
    for tri in &tin.triangles {
        let c = tri.map(|v| {
            let s = tin.vertex_samples[v as usize] as usize;
            (
                (s % tin.width) as i64,
                (s / tin.width) as i64,
                f64::from(tin.filled_um[s]),
            )
        });
        let plane = Plane::through(c);
        for_each_row(
            (c[0].0, c[0].1),
            (c[1].0, c[1].1),
            (c[2].0, c[2].1),
            |y, lo, hi| {
                for x in lo..=hi {
                    out[(y * w + x) as usize] = plane.at(x, y) as f32;
                }
                true
            },
        );
    }
    out
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

/// Compares a resampled mesh with the measured heights (NaN = not measured). The error is
/// computed in f64 from the f32 mesh heights' source planes, so it reflects the mesh, not f32
/// rounding of large heights.
pub fn error_stats(tin: &Tin, measured_um: &[f32]) -> ErrorStats {
    let mut max_um = 0.0f64;
    let mut sum2 = 0.0f64;
    let mut covered = vec![false; tin.width * tin.height];
    let w = tin.width as i64;
    let mut samples = 0usize;
    for tri in &tin.triangles {
        let c = tri.map(|v| {
            let s = tin.vertex_samples[v as usize] as usize;
            (
                (s % tin.width) as i64,
                (s / tin.width) as i64,
                f64::from(tin.filled_um[s]),
            )
        });
        let plane = Plane::through(c);
        for_each_row(
            (c[0].0, c[0].1),
            (c[1].0, c[1].1),
            (c[2].0, c[2].1),
            |y, lo, hi| {
                for x in lo..=hi {
                    let s = (y * w + x) as usize;
                    let h = measured_um[s];
                    if covered[s] || h.is_nan() {
                        continue;
                    }
                    covered[s] = true;
                    let e = plane.at(x, y) - f64::from(h);
                    max_um = max_um.max(e.abs());
                    sum2 += e * e;
                    samples += 1;
                }
                true
            },
        );
    }
    let measured = measured_um.iter().filter(|h| !h.is_nan()).count();
    ErrorStats {
        max_um,
        rms_um: if samples > 0 {
            (sum2 / samples as f64).sqrt()
        } else {
            0.0
        },
        samples,
        uncovered: measured - samples,
    }
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
    fn incircle_is_exact_on_cocircular_grid_points() {
        assert_eq!(incircle((0, 0), (1, 0), (1, 1), (0, 1)), 0);
        assert!(incircle((0, 0), (2, 0), (2, 2), (1, 1)) > 0);
        assert!(incircle((0, 0), (2, 0), (2, 2), (3, -1)) < 0);
    }
}
