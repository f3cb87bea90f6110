//! The global solve over the whole tile graph: tile positions by weighted least squares over all
//! pair offsets with the stage positions as a weak prior and iterative removal of inconsistent
//! links ([`solve_positions`]), and per-tile piston and tilt by least squares over all overlaps
//! ([`solve_planes`]).
//!
//! Positions are solved separately along x and along y (the equations do not couple them):
//! minimise `sum_links w_l |(p_b - p_a) - d_ab|^2 + sum_tiles w_s |p_i - s_i|^2` with `d_ab` the
//! measured offset, `s_i` the stage position and `w_s = 1 / stage_sigma_px^2` small next to the
//! link weights. The prior fixes the one global translation the links cannot know and places a
//! tile that has no trustworthy link at its stage position; it pulls the linked tiles by a
//! negligible amount (a fraction `w_s / w_l`, about 1e-4 with the defaults, of their stage error).
//!
//! Inconsistent links (a wrong answer that passed the pairwise checks, e.g. one period off on a
//! periodic texture) show up as residuals after the solve. While any link's residual exceeds
//! `outlier_px`, each such link is tried out in turn (solve without it) and the one whose
//! removal leaves the smallest total cost, links and prior together, is dropped. In a single
//! loop every link carries the same residual; the prior then decides, since removing the wrong
//! link leaves positions that agree with the stage and removing a right one does not.
//!
//! One-direction links ([`AnisotropicLink`], [`solve_positions_anisotropic`]): a pair whose NCC
//! peak is a ridge (a lone scratch, a straight flank across a featureless strip) knows its
//! offset across the ridge only. Its residual costs `r^T I r` with `I` its 2 x 2 information
//! (rank 1 for a ridge), which couples x and y: with such links the solve is one system over
//! (x, y) of every tile. A tile whose kept links fix one direction only is placed along the
//! other by the prior alone and is reported so ([`GlobalSolution::registered_directions`],
//! [`GlobalSolution::stage_direction`]); the outlier test uses a one-direction link's residual
//! across its ridge only.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use surfstream_core::raster::{RasterView, Shape};

use crate::plane::PlaneCorrection;
use crate::raster::InputError;

/// One measured pair offset: `position(b) - position(a) = offset_px`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Link {
    /// Tile indices into the stage-position slice.
    pub a: usize,
    pub b: usize,
    /// Measured offset of b's pixel (0, 0) from a's, px, (x, y).
    pub offset_px: [f64; 2],
    /// Standard deviation (px) the offset is trusted to; its weight is `1 / sigma^2`.
    pub sigma_px: f64,
}

/// A pair offset known in one direction better than in the other: `position(b) -
/// position(a) = offset_px` with the residual `r` costing `r^T I r`, `I` the offset's
/// information (inverse covariance). A ridge of the NCC (a lone scratch, a straight flank)
/// fixes the offset across it only: `I` has rank 1 ([`AnisotropicLink::across`]) and the solve
/// takes nothing from it along the ridge, where the tile's other links (or, failing those,
/// its stage position) place it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AnisotropicLink {
    /// Tile indices into the stage-position slice.
    pub a: usize,
    pub b: usize,
    /// Measured offset of b's pixel (0, 0) from a's, px, (x, y); only its components in the
    /// directions `information_per_px2` weights are used.
    pub offset_px: [f64; 2],
    /// Symmetric positive semi-definite 2 x 2 information matrix, 1/px^2, rows (x, y).
    pub information_per_px2: [[f64; 2]; 2],
}

impl AnisotropicLink {
    /// The one-direction link `normal . (p_b - p_a) = normal . offset_px` trusted to
    /// `sigma_px` across (`normal` need not be of unit length) and not at all along.
    pub fn across(
        a: usize,
        b: usize,
        offset_px: [f64; 2],
        normal: [f64; 2],
        sigma_px: f64,
    ) -> Self {
        let len = normal[0].hypot(normal[1]);
        let n = [normal[0] / len, normal[1] / len];
        let w = 1.0 / (sigma_px * sigma_px);
        AnisotropicLink {
            a,
            b,
            offset_px,
            information_per_px2: [
                [w * n[0] * n[0], w * n[0] * n[1]],
                [w * n[0] * n[1], w * n[1] * n[1]],
            ],
        }
    }
}

/// Eigenvalues (larger first) and the unit eigenvector of the larger one of a symmetric 2 x 2
/// matrix.
fn eigen2(m: [[f64; 2]; 2]) -> ([f64; 2], [f64; 2]) {
    let (p, q, r) = (m[0][0], m[1][1], 0.5 * (m[0][1] + m[1][0]));
    let mean = 0.5 * (p + q);
    let disc = (0.25 * (p - q) * (p - q) + r * r).sqrt();
    let (hi, lo) = (mean + disc, mean - disc);
    let v = if r.abs() > 1e-12 * hi.abs().max(1e-300) {
        [hi - q, r]
    } else if p >= q {
        [1.0, 0.0]
    } else {
        [0.0, 1.0]
    };
    let len = v[0].hypot(v[1]);
    ([hi, lo], [v[0] / len, v[1] / len])
}

/// Parameters of [`solve_positions`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SolveParams {
    /// Standard deviation of the stage positions, px (the prior's weight is `1 / sigma^2`).
    pub stage_sigma_px: f64,
    /// A link whose residual (Euclidean, px) after the solve exceeds this is inconsistent.
    pub outlier_px: f64,
}

impl Default for SolveParams {
    fn default() -> Self {
        SolveParams {
            stage_sigma_px: 5.0,
            outlier_px: 1.0,
        }
    }
}

/// What became of one link in [`solve_positions`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LinkOutcome {
    /// Whether the link is part of the final solve (false: removed as inconsistent).
    pub kept: bool,
    /// `(p_b - p_a) - offset_px` in the final solution, px.
    pub residual_px: [f64; 2],
}

/// The answer of [`solve_positions`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GlobalSolution {
    /// Position of every tile's pixel (0, 0), px, in the frame of the stage positions.
    pub positions_px: Vec<[f64; 2]>,
    /// Whether the tile has at least one kept link (false: placed by the stage prior alone).
    pub linked: Vec<bool>,
    /// One outcome per input link, in input order.
    pub links: Vec<LinkOutcome>,
    /// Largest residual of a kept link, px (0 without links); for an anisotropic link, its
    /// residual in the direction it measures.
    pub max_residual_px: f64,
    /// One outcome per anisotropic link, in input order; the residual is its component in the
    /// direction the link measures (the one of its largest information).
    #[serde(default)]
    pub anisotropic_links: Vec<LinkOutcome>,
    /// Per tile, how many independent directions its kept links fix: 2 (placed by links), 1
    /// (one direction from links, the other from the stage prior, see `stage_direction`) or 0
    /// (placed by the stage prior alone).
    #[serde(default)]
    pub registered_directions: Vec<u8>,
    /// Per tile with `registered_directions` 1: the unit direction (x, y) along which the stage
    /// prior alone placed it (the links fix the perpendicular one).
    #[serde(default)]
    pub stage_direction: Vec<Option<[f64; 2]>>,
}

/// Smallest eigenvalue, per unit of a link, of a tile's summed link directions for a
/// direction to count as fixed by its links ([`GlobalSolution::registered_directions`]): two
/// ridge links fix a tile fully once their normals are at least 26 degrees apart
/// (1 - cos 26 deg = 0.1); closer, the position along their common ridge is a division by
/// almost nothing.
const MIN_DIRECTION_STRENGTH: f64 = 0.1;

/// Why there is no global solution.
#[derive(Debug, Clone, PartialEq, Error, Serialize, Deserialize)]
pub enum SolveError {
    #[error("invalid input: {0}")]
    Input(#[from] InputError),
    #[error("link {link}: tile index {tile} is out of range (there are {tiles} tiles)")]
    TileOutOfRange {
        link: usize,
        tile: usize,
        tiles: usize,
    },
    #[error("link {link} joins tile {tile} to itself")]
    SelfLink { link: usize, tile: usize },
    #[error("link {link}: offset or sigma is not finite and positive")]
    BadLink { link: usize },
    #[error("tile {tile}: stage position is not finite")]
    BadStage { tile: usize },
    #[error("the normal equations are not positive definite")]
    Singular,
    #[error("tile {tile}: {what} differs from tile 0 ({got} vs {expected})")]
    Mismatch {
        tile: usize,
        what: &'static str,
        got: f64,
        expected: f64,
    },
}

fn bad(name: &str, reason: &str) -> SolveError {
    SolveError::Input(InputError::InvalidParameter {
        name: name.into(),
        reason: reason.into(),
    })
}

/// Solves the tile positions; see the module documentation.
pub fn solve_positions(
    stage_px: &[[f64; 2]],
    links: &[Link],
    params: &SolveParams,
) -> Result<GlobalSolution, SolveError> {
    solve_positions_anisotropic(stage_px, links, &[], params)
}

/// One link of the solve: an isotropic [`Link`] (weight `w` in x and y) or an
/// [`AnisotropicLink`] (information `info`).
#[derive(Debug, Clone, Copy)]
struct Edge {
    a: usize,
    b: usize,
    d: [f64; 2],
    /// Information matrix, 1/px^2 (`w` times the identity for an isotropic link).
    info: [[f64; 2]; 2],
    /// The direction the link measures best (unit) and its information there.
    strong: [f64; 2],
    w_strong: f64,
    isotropic: bool,
}

impl Edge {
    fn iso(l: &Link) -> Edge {
        let w = 1.0 / (l.sigma_px * l.sigma_px);
        Edge {
            a: l.a,
            b: l.b,
            d: l.offset_px,
            info: [[w, 0.0], [0.0, w]],
            strong: [1.0, 0.0],
            w_strong: w,
            isotropic: true,
        }
    }

    fn aniso(l: &AnisotropicLink) -> Edge {
        let ([hi, _], v) = eigen2(l.information_per_px2);
        Edge {
            a: l.a,
            b: l.b,
            d: l.offset_px,
            info: l.information_per_px2,
            strong: v,
            w_strong: hi,
            isotropic: false,
        }
    }

    /// `(p_b - p_a) - d`, px.
    fn residual(&self, pos: &[[f64; 2]]) -> [f64; 2] {
        [
            pos[self.b][0] - pos[self.a][0] - self.d[0],
            pos[self.b][1] - pos[self.a][1] - self.d[1],
        ]
    }

    /// The residual as reported and tested against `outlier_px`: the whole vector for an
    /// isotropic link, its component along the measured direction for an anisotropic one
    /// (along a ridge the link says nothing, so a misfit there is no inconsistency).
    fn reported_residual(&self, pos: &[[f64; 2]]) -> [f64; 2] {
        let r = self.residual(pos);
        if self.isotropic {
            return r;
        }
        let s = r[0] * self.strong[0] + r[1] * self.strong[1];
        [s * self.strong[0], s * self.strong[1]]
    }

    /// For an anisotropic link with an end tile whose links fix one direction only (`free`:
    /// the unit direction left to the stage, per tile), the same link measuring exactly that
    /// tile's fixed direction `v`: `v . (p_b - p_a) = alpha` with `alpha` what the link
    /// measures across when the tiles sit at their stage positions along `free`. Other links
    /// unchanged.
    fn turned_to_fixed_direction(&self, stage: &[[f64; 2]], free: &[Option<[f64; 2]>]) -> Edge {
        let Some(t) = (if self.isotropic {
            None
        } else {
            free[self.a].or(free[self.b])
        }) else {
            return *self;
        };
        let v = [-t[1], t[0]];
        let n = self.strong;
        let nv = n[0] * v[0] + n[1] * v[1];
        if nv.abs() < 0.5 {
            return *self;
        }
        let nt = n[0] * t[0] + n[1] * t[1];
        let along_stage = t[0] * (stage[self.b][0] - stage[self.a][0])
            + t[1] * (stage[self.b][1] - stage[self.a][1]);
        let nd = n[0] * self.d[0] + n[1] * self.d[1];
        let alpha = (nd - nt * along_stage) / nv;
        let w = self.w_strong;
        Edge {
            d: [
                alpha * v[0] + along_stage * t[0],
                alpha * v[1] + along_stage * t[1],
            ],
            info: [
                [w * v[0] * v[0], w * v[0] * v[1]],
                [w * v[0] * v[1], w * v[1] * v[1]],
            ],
            strong: v,
            ..*self
        }
    }

    /// `r^T I r`.
    fn cost(&self, pos: &[[f64; 2]]) -> f64 {
        let r = self.residual(pos);
        let i = &self.info;
        r[0] * (i[0][0] * r[0] + i[0][1] * r[1]) + r[1] * (i[1][0] * r[0] + i[1][1] * r[1])
    }
}

/// [`solve_positions`] with anisotropic links besides the isotropic ones (see
/// [`AnisotropicLink`]). A tile whose kept links fix one direction only is placed along the
/// other by the stage prior alone, and says so ([`GlobalSolution::registered_directions`],
/// [`GlobalSolution::stage_direction`]). Without anisotropic links this is exactly
/// [`solve_positions`].
pub fn solve_positions_anisotropic(
    stage_px: &[[f64; 2]],
    links: &[Link],
    anisotropic: &[AnisotropicLink],
    params: &SolveParams,
) -> Result<GlobalSolution, SolveError> {
    if !(params.stage_sigma_px.is_finite() && params.stage_sigma_px > 0.0) {
        return Err(bad("stage_sigma_px", "must be finite and > 0"));
    }
    if !(params.outlier_px.is_finite() && params.outlier_px > 0.0) {
        return Err(bad("outlier_px", "must be finite and > 0"));
    }
    let n = stage_px.len();
    for (tile, s) in stage_px.iter().enumerate() {
        if !(s[0].is_finite() && s[1].is_finite()) {
            return Err(SolveError::BadStage { tile });
        }
    }
    let ends = links
        .iter()
        .map(|l| (l.a, l.b))
        .chain(anisotropic.iter().map(|l| (l.a, l.b)));
    for (i, (a, b)) in ends.enumerate() {
        for tile in [a, b] {
            if tile >= n {
                return Err(SolveError::TileOutOfRange {
                    link: i,
                    tile,
                    tiles: n,
                });
            }
        }
        if a == b {
            return Err(SolveError::SelfLink { link: i, tile: a });
        }
    }
    for (i, l) in links.iter().enumerate() {
        let finite = l.offset_px.iter().all(|v| v.is_finite());
        if !(finite && l.sigma_px.is_finite() && l.sigma_px > 0.0) {
            return Err(SolveError::BadLink { link: i });
        }
    }
    for (i, l) in anisotropic.iter().enumerate() {
        let m = l.information_per_px2;
        let finite = l
            .offset_px
            .iter()
            .chain(m.iter().flatten())
            .all(|v| v.is_finite());
        // Symmetric, positive semi-definite and not zero.
        let psd = finite
            && (m[0][1] - m[1][0]).abs() <= 1e-9 * (m[0][0] + m[1][1]).abs()
            && m[0][0] >= 0.0
            && m[1][1] >= 0.0
            && m[0][0] * m[1][1] - m[0][1] * m[1][0] >= -1e-9 * (m[0][0] + m[1][1]).powi(2)
            && m[0][0] + m[1][1] > 0.0;
        if !psd {
            return Err(SolveError::BadLink {
                link: links.len() + i,
            });
        }
    }
    if n == 0 {
        return Ok(GlobalSolution {
            positions_px: Vec::new(),
            linked: Vec::new(),
            links: Vec::new(),
            max_residual_px: 0.0,
            anisotropic_links: Vec::new(),
            registered_directions: Vec::new(),
            stage_direction: Vec::new(),
        });
    }
    let edges: Vec<Edge> = links
        .iter()
        .map(Edge::iso)
        .chain(anisotropic.iter().map(Edge::aniso))
        .collect();
    // Relative to the mean stage position: small numbers, well conditioned.
    let mean = [0, 1].map(|k| stage_px.iter().map(|s| s[k]).sum::<f64>() / n as f64);
    let stage: Vec<[f64; 2]> = stage_px
        .iter()
        .map(|s| [s[0] - mean[0], s[1] - mean[1]])
        .collect();
    let w_stage = 1.0 / (params.stage_sigma_px * params.stage_sigma_px);
    let mut kept = vec![true; edges.len()];
    let mut sol = solve_once(&stage, &edges, &kept, w_stage)?;
    loop {
        let suspects: Vec<usize> = (0..edges.len())
            .filter(|&i| kept[i] && norm(edges[i].reported_residual(&sol.0)) > params.outlier_px)
            .collect();
        if suspects.is_empty() {
            break;
        }
        let mut best: Option<(usize, Trial)> = None;
        for &i in &suspects {
            kept[i] = false;
            let trial = solve_once(&stage, &edges, &kept, w_stage)?;
            kept[i] = true;
            if best.as_ref().is_none_or(|b| trial.1 < b.1 .1) {
                best = Some((i, trial));
            }
        }
        let Some((i, trial)) = best else { break };
        kept[i] = false;
        sol = trial;
    }
    let (registered_directions, stage_direction) = directions(n, &edges, &kept);
    if stage_direction.iter().any(Option::is_some) {
        // Two ridge links of one tile whose normals are a degree or two apart (one scratch
        // seen in both its strips, the normals differing by estimation noise) would place
        // the tile along the ridge where the two nearly parallel lines cross: a 0.05 px
        // misfit across becomes 3 px along. Each such link is turned to the tile's fixed
        // direction, so that the stage alone places the tile along it, as reported.
        let turned: Vec<Edge> = edges
            .iter()
            .map(|e| e.turned_to_fixed_direction(&stage, &stage_direction))
            .collect();
        sol = solve_once(&stage, &turned, &kept, w_stage)?;
    }
    let linked: Vec<bool> = registered_directions.iter().map(|&d| d == 2).collect();
    let mut max_residual_px: f64 = 0.0;
    let mut outcomes: Vec<LinkOutcome> = edges
        .iter()
        .zip(&kept)
        .map(|(e, &k)| {
            let r = e.reported_residual(&sol.0);
            if k {
                max_residual_px = max_residual_px.max(norm(r));
            }
            LinkOutcome {
                kept: k,
                residual_px: r,
            }
        })
        .collect();
    let anisotropic_links = outcomes.split_off(links.len());
    Ok(GlobalSolution {
        positions_px: sol
            .0
            .iter()
            .map(|p| [p[0] + mean[0], p[1] + mean[1]])
            .collect(),
        linked,
        links: outcomes,
        max_residual_px,
        anisotropic_links,
        registered_directions,
        stage_direction,
    })
}

/// Per tile, the directions its kept links fix (2, 1 or 0) and, with 1, the unit direction
/// left to the stage. Each link counts with unit strength: an isotropic one in every
/// direction, an anisotropic one along its measured direction in proportion to its
/// information there (a rank-1 link adds `n n^T`).
fn directions(n: usize, edges: &[Edge], kept: &[bool]) -> (Vec<u8>, Vec<Option<[f64; 2]>>) {
    // Tiles joined by kept full links move as one group: a full link to a partner that is
    // itself free fixes nothing relative to the scan (two tiles linked to each other, hanging
    // from the rest by ridges of one direction, are free along them together). So the
    // directions are counted per group, from the ridge links that leave it; the largest group
    // (of two or more tiles; ties: the one holding the lowest tile) is the scan's frame.
    let group = full_link_groups(n, edges, kept);
    let mut size = vec![0usize; n];
    for &g in &group {
        size[g] += 1;
    }
    let frame = (0..n)
        .filter(|&t| size[group[t]] >= 2)
        .max_by(|&a, &b| size[group[a]].cmp(&size[group[b]]).then(b.cmp(&a)))
        .map(|t| group[t]);
    let mut sum = vec![[[0.0f64; 2]; 2]; n];
    for (e, _) in edges.iter().zip(kept).filter(|(e, &k)| k && !e.isotropic) {
        if group[e.a] == group[e.b] {
            continue;
        }
        for g in [group[e.a], group[e.b]] {
            for (row, info) in sum[g].iter_mut().zip(&e.info) {
                for (v, i) in row.iter_mut().zip(info) {
                    *v += i / e.w_strong;
                }
            }
        }
    }
    let mut dirs = Vec::with_capacity(n);
    let mut stage_dir = Vec::with_capacity(n);
    for t in 0..n {
        if Some(group[t]) == frame {
            dirs.push(2);
            stage_dir.push(None);
            continue;
        }
        let ([hi, lo], v) = eigen2(sum[group[t]]);
        if lo >= MIN_DIRECTION_STRENGTH {
            dirs.push(2);
            stage_dir.push(None);
        } else if hi >= MIN_DIRECTION_STRENGTH {
            dirs.push(1);
            // Perpendicular to the fixed direction.
            stage_dir.push(Some([-v[1], v[0]]));
        } else {
            dirs.push(0);
            stage_dir.push(None);
        }
    }
    (dirs, stage_dir)
}

/// Per tile, the smallest tile index of its group: the tiles joined by kept full links.
fn full_link_groups(n: usize, edges: &[Edge], kept: &[bool]) -> Vec<usize> {
    fn root(parent: &mut [usize], mut t: usize) -> usize {
        while parent[t] != t {
            parent[t] = parent[parent[t]];
            t = parent[t];
        }
        t
    }
    let mut parent: Vec<usize> = (0..n).collect();
    for (e, _) in edges.iter().zip(kept).filter(|(e, &k)| k && e.isotropic) {
        let (a, b) = (root(&mut parent, e.a), root(&mut parent, e.b));
        // The smaller index is the root, so a group is named by its lowest tile.
        parent[a.max(b)] = a.min(b);
    }
    (0..n).map(|t| root(&mut parent, t)).collect()
}

/// A pair the pairwise test found ambiguous (several distinct, equally good NCC maxima, as on
/// periodic or lay-dominated textures), with the offsets it could not choose between.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AmbiguousLink {
    pub a: usize,
    pub b: usize,
    /// The candidate offsets (b's pixel (0, 0) minus a's, px), best NCC first.
    pub offsets_px: Vec<[f64; 2]>,
    /// Standard deviation of a chosen offset, px (as [`Link::sigma_px`]).
    pub sigma_px: f64,
}

/// [`solve_positions`] that also resolves ambiguous pairs by consistency with the rest of the
/// scan, the way ASHLAR and MIST let the tile graph decide between correlation peaks. Returns
/// the solution over `links` followed by the chosen ambiguous links (in input order), and
/// per ambiguous link the index of the chosen offset (`None`: left out).
///
/// Repeated until nothing changes:
/// - an ambiguous pair whose two tiles are both placed by kept links takes the one offset
///   within `outlier_px` of their solved relative position, when exactly one is;
/// - a tile not placed by any kept link, with ambiguous pairs to two or more placed tiles,
///   takes the position on which offsets of two or more of those pairs agree (within
///   `outlier_px`), when exactly one such position exists (a wrong peak of one pair rarely
///   lands where a wrong peak of another does).
///
/// A tile with a single ambiguous pair stays unplaced (stage placement): the stage error is of
/// the same size as the spacing of the peaks, so the prior cannot choose honestly.
pub fn solve_positions_with_alternatives(
    stage_px: &[[f64; 2]],
    links: &[Link],
    ambiguous: &[AmbiguousLink],
    params: &SolveParams,
) -> Result<(GlobalSolution, Vec<Option<usize>>), SolveError> {
    solve_scan_positions(stage_px, links, &[], ambiguous, params)
}

/// [`solve_positions_with_alternatives`] with anisotropic links as well
/// ([`solve_positions_anisotropic`]); a tile counts as placed (for resolving ambiguous pairs)
/// when its links fix both directions. Link numbers in errors count `links`, then
/// `anisotropic`, then `ambiguous`.
pub fn solve_scan_positions(
    stage_px: &[[f64; 2]],
    links: &[Link],
    anisotropic: &[AnisotropicLink],
    ambiguous: &[AmbiguousLink],
    params: &SolveParams,
) -> Result<(GlobalSolution, Vec<Option<usize>>), SolveError> {
    let first = links.len() + anisotropic.len();
    for (i, l) in ambiguous.iter().enumerate() {
        let n = stage_px.len();
        for tile in [l.a, l.b] {
            if tile >= n {
                return Err(SolveError::TileOutOfRange {
                    link: first + i,
                    tile,
                    tiles: n,
                });
            }
        }
        if l.a == l.b {
            return Err(SolveError::SelfLink {
                link: first + i,
                tile: l.a,
            });
        }
        let finite = l.offsets_px.iter().flatten().all(|v| v.is_finite());
        if !(finite && l.sigma_px.is_finite() && l.sigma_px > 0.0) {
            return Err(SolveError::BadLink { link: first + i });
        }
    }
    let mut chosen: Vec<Option<usize>> = vec![None; ambiguous.len()];
    let all_links = |chosen: &[Option<usize>]| -> Vec<Link> {
        let mut v = links.to_vec();
        for (k, ch) in chosen.iter().enumerate() {
            if let Some(c) = *ch {
                let l = &ambiguous[k];
                v.push(Link {
                    a: l.a,
                    b: l.b,
                    offset_px: l.offsets_px[c],
                    sigma_px: l.sigma_px,
                });
            }
        }
        v
    };
    loop {
        let sol = solve_positions_anisotropic(stage_px, &all_links(&chosen), anisotropic, params)?;
        let pos = &sol.positions_px;
        let mut progress = false;
        // Pairs between placed tiles: the one consistent offset.
        for (k, l) in ambiguous.iter().enumerate() {
            if chosen[k].is_some() || !(sol.linked[l.a] && sol.linked[l.b]) {
                continue;
            }
            let consistent: Vec<usize> = (0..l.offsets_px.len())
                .filter(|&c| {
                    let o = l.offsets_px[c];
                    let r = [
                        pos[l.b][0] - pos[l.a][0] - o[0],
                        pos[l.b][1] - pos[l.a][1] - o[1],
                    ];
                    norm(r) <= params.outlier_px
                })
                .collect();
            if let [c] = consistent[..] {
                chosen[k] = Some(c);
                progress = true;
            }
        }
        if !progress {
            // One unplaced tile at a time, then solve again.
            for t in (0..stage_px.len()).filter(|&t| !sol.linked[t]) {
                if let Some(picks) = agreeing_position(t, &sol, ambiguous, &chosen, params) {
                    for (k, c) in picks {
                        chosen[k] = Some(c);
                    }
                    progress = true;
                    break;
                }
            }
        }
        if !progress {
            // A pair with a half-placed tile (its links fix one direction): the one offset
            // that agrees with that tile's ridge links across.
            for (k, l) in ambiguous.iter().enumerate() {
                if chosen[k].is_some() || (sol.linked[l.a] && sol.linked[l.b]) {
                    continue;
                }
                let half_placed = |t: usize| sol.registered_directions[t] == 1;
                if !(half_placed(l.a) || half_placed(l.b)) {
                    continue;
                }
                let misfit = |c: usize| -> Result<f64, SolveError> {
                    let mut trial = chosen.clone();
                    trial[k] = Some(c);
                    let with = all_links(&trial);
                    let s = solve_positions_anisotropic(stage_px, &with, anisotropic, params)?;
                    let own = s.links[with.len() - 1];
                    let mut worst = if own.kept {
                        norm(own.residual_px)
                    } else {
                        f64::INFINITY
                    };
                    for (r, o) in anisotropic.iter().zip(&s.anisotropic_links) {
                        if [r.a, r.b].iter().any(|t| [l.a, l.b].contains(t)) {
                            worst = worst.max(if o.kept {
                                norm(o.residual_px)
                            } else {
                                f64::INFINITY
                            });
                        }
                    }
                    Ok(worst)
                };
                let m: Vec<f64> = (0..l.offsets_px.len())
                    .map(misfit)
                    .collect::<Result<_, _>>()?;
                if let Some(c) = consistent_across(&m) {
                    chosen[k] = Some(c);
                    progress = true;
                    break;
                }
            }
        }
        if !progress {
            return Ok((sol, chosen));
        }
    }
}

/// Largest misfit (px) of an ambiguous pair's offset with the ridge links of its half-placed
/// tile for that offset to be taken, and smallest misfit of every other offset
/// ([`solve_scan_positions`]): the 32 one-direction answers of `scripts/bench_sparse.py` are
/// within 0.088 px across (RMS 0.026 px), so 0.1 px is 4 standard deviations.
const RIDGE_CONSISTENT_PX: f64 = 0.1;

/// Of an ambiguous pair's offsets with misfits `m` (the largest residual of the offset and
/// of the ridge links it meets, px), the one within [`RIDGE_CONSISTENT_PX`] when every other
/// misfits by at least twice as much and by more than [`RIDGE_CONSISTENT_PX`].
fn consistent_across(m: &[f64]) -> Option<usize> {
    let (best, &mb) = m.iter().enumerate().min_by(|p, q| p.1.total_cmp(q.1))?;
    let clear = m
        .iter()
        .enumerate()
        .all(|(i, &v)| i == best || v >= (2.0 * mb).max(RIDGE_CONSISTENT_PX));
    (mb <= RIDGE_CONSISTENT_PX && clear).then_some(best)
}

/// Hypotheses that agree on one position: (ambiguous link, offset index) pairs and the position.
type Cluster = (Vec<(usize, usize)>, [f64; 2]);

/// For the unplaced tile `t`: the offsets (ambiguous link, offset index) of its pairs to placed
/// tiles that agree on one position of `t`, when exactly one position has the support of two
/// or more pairs.
fn agreeing_position(
    t: usize,
    sol: &GlobalSolution,
    ambiguous: &[AmbiguousLink],
    chosen: &[Option<usize>],
    params: &SolveParams,
) -> Option<Vec<(usize, usize)>> {
    // Every hypothesis for t's position: (link, offset index, position).
    let mut hyp: Vec<(usize, usize, [f64; 2])> = Vec::new();
    for (k, l) in ambiguous.iter().enumerate() {
        if chosen[k].is_some() {
            continue;
        }
        let (other, sign) = if l.b == t && l.a != t {
            (l.a, 1.0)
        } else if l.a == t && l.b != t {
            (l.b, -1.0)
        } else {
            continue;
        };
        if !sol.linked[other] {
            continue;
        }
        let p = sol.positions_px[other];
        for (c, o) in l.offsets_px.iter().enumerate() {
            hyp.push((k, c, [p[0] + sign * o[0], p[1] + sign * o[1]]));
        }
    }
    // Clusters seeded by each hypothesis: the hypotheses of other links within outlier_px.
    // The supported position found so far and its members.
    let mut found: Option<Cluster> = None;
    for &(k, c, p) in &hyp {
        let mut members = vec![(k, c)];
        for &(k2, c2, p2) in &hyp {
            if k2 != k
                && norm([p2[0] - p[0], p2[1] - p[1]]) <= params.outlier_px
                && !members.iter().any(|m| m.0 == k2)
            {
                members.push((k2, c2));
            }
        }
        if members.len() < 2 {
            continue;
        }
        match &found {
            None => found = Some((members, p)),
            Some((_, q)) => {
                if norm([p[0] - q[0], p[1] - q[1]]) > params.outlier_px {
                    // Two distinct supported positions: no honest choice.
                    return None;
                }
            }
        }
    }
    found.map(|(m, _)| m)
}

fn norm(v: [f64; 2]) -> f64 {
    v[0].hypot(v[1])
}

/// Positions and the total cost (links and prior) of one solve.
type Trial = (Vec<[f64; 2]>, f64);

/// One weighted least-squares solve with the links marked `kept`.
fn solve_once(
    stage: &[[f64; 2]],
    edges: &[Edge],
    kept: &[bool],
    w_stage: f64,
) -> Result<Trial, SolveError> {
    let kept_edges = || edges.iter().zip(kept).filter(|(_, &k)| k).map(|(e, _)| e);
    let pos = if kept_edges().all(|e| e.isotropic) {
        solve_separable(stage, kept_edges(), w_stage)?
    } else {
        solve_coupled(stage, kept_edges(), w_stage)?
    };
    let mut cost = 0.0;
    for (i, p) in pos.iter().enumerate() {
        cost += w_stage * ((p[0] - stage[i][0]).powi(2) + (p[1] - stage[i][1]).powi(2));
    }
    for e in kept_edges() {
        cost += e.cost(&pos);
    }
    Ok((pos, cost))
}

/// Isotropic links only: x and y do not couple, and the normal matrix (a weighted graph
/// Laplacian plus the prior's diagonal) is the same for both: one factorisation, two
/// right-hand sides.
fn solve_separable<'a>(
    stage: &[[f64; 2]],
    edges: impl Iterator<Item = &'a Edge>,
    w_stage: f64,
) -> Result<Vec<[f64; 2]>, SolveError> {
    let n = stage.len();
    let mut m = DMatrix::<f64>::from_diagonal_element(n, n, w_stage);
    let mut rhs = DMatrix::<f64>::zeros(n, 2);
    for i in 0..n {
        rhs[(i, 0)] = w_stage * stage[i][0];
        rhs[(i, 1)] = w_stage * stage[i][1];
    }
    for e in edges {
        let w = e.info[0][0];
        m[(e.a, e.a)] += w;
        m[(e.b, e.b)] += w;
        m[(e.a, e.b)] -= w;
        m[(e.b, e.a)] -= w;
        for k in 0..2 {
            rhs[(e.b, k)] += w * e.d[k];
            rhs[(e.a, k)] -= w * e.d[k];
        }
    }
    let chol = m.cholesky().ok_or(SolveError::Singular)?;
    let x = chol.solve(&rhs);
    Ok((0..n).map(|i| [x[(i, 0)], x[(i, 1)]]).collect())
}

/// With anisotropic links x and y couple: one system over (x_0, y_0, x_1, y_1, ...), each link
/// adding its 2 x 2 information in the Laplacian's four blocks.
fn solve_coupled<'a>(
    stage: &[[f64; 2]],
    edges: impl Iterator<Item = &'a Edge>,
    w_stage: f64,
) -> Result<Vec<[f64; 2]>, SolveError> {
    let n = stage.len();
    let mut m = DMatrix::<f64>::from_diagonal_element(2 * n, 2 * n, w_stage);
    let mut rhs = DVector::<f64>::zeros(2 * n);
    for i in 0..n {
        rhs[2 * i] = w_stage * stage[i][0];
        rhs[2 * i + 1] = w_stage * stage[i][1];
    }
    for e in edges {
        let (a, b) = (2 * e.a, 2 * e.b);
        for r in 0..2 {
            for c in 0..2 {
                let w = e.info[r][c];
                m[(a + r, a + c)] += w;
                m[(b + r, b + c)] += w;
                m[(a + r, b + c)] -= w;
                m[(b + r, a + c)] -= w;
            }
            let id = e.info[r][0] * e.d[0] + e.info[r][1] * e.d[1];
            rhs[b + r] += id;
            rhs[a + r] -= id;
        }
    }
    let chol = m.cholesky().ok_or(SolveError::Singular)?;
    let x = chol.solve(&rhs);
    Ok((0..n).map(|i| [x[2 * i], x[2 * i + 1]]).collect())
}

/// One overlap's normal block over (p_a, tx_a, ty_a, p_b, tx_b, ty_b): A^T A, A^T d, d^T d and
/// the sample count.
type PairBlock = ([[f64; 6]; 6], [f64; 6], f64, usize);

/// The answer of [`solve_planes`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlaneSolution {
    /// The correction of every tile (subtract it from the raw heights), same convention as
    /// [`PlaneCorrection`]; the gauge tile's is zero.
    pub corrections: Vec<PlaneCorrection>,
    /// Height-difference samples used, per overlap pair (input order).
    pub samples: Vec<usize>,
    /// RMS of the corrected height differences over all samples, um (before: `rms_before_um`).
    pub rms_residual_um: f64,
    pub rms_before_um: f64,
}

/// Per-tile piston and tilt over the whole tile graph: minimises the squared differences of
/// corrected heights over every overlapping valid pixel of every pair in `pairs` (b's pixels,
/// every `stride`-th row and column, a sampled by cubic convolution at the tiles' relative
/// position, NaN-aware), with tile `gauge` held at zero correction (the one piston and tilt no overlap
/// can know). A tile that overlaps no other keeps zero correction.
///
/// All tiles must share one size (the tilt is about the tile centre).
pub fn solve_planes(
    tiles: &[RasterView<'_, f32>],
    positions_px: &[[f64; 2]],
    pairs: &[(usize, usize)],
    gauge: usize,
    stride: usize,
) -> Result<PlaneSolution, SolveError> {
    solve_planes_in(
        &mut TilesInMemory(tiles),
        positions_px,
        pairs,
        gauge,
        stride,
    )
}

/// Where [`solve_planes_in`] finds the tiles: their number and sizes, and a pair of them at a
/// time (so they need not all be in memory at once).
pub trait PlaneTiles {
    /// What reading a tile can fail with.
    type Error: From<SolveError>;
    /// Number of tiles.
    fn len(&self) -> usize;
    /// Whether there are no tiles.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Rows x columns of tile `i`.
    fn shape(&self, i: usize) -> Shape;
    /// Calls `f` with tiles `a` and `b`.
    fn with_pair(
        &mut self,
        a: usize,
        b: usize,
        f: &mut dyn FnMut(RasterView<'_, f32>, RasterView<'_, f32>),
    ) -> Result<(), Self::Error>;
}

/// Tiles held in memory.
struct TilesInMemory<'a, 'b>(&'a [RasterView<'b, f32>]);

impl PlaneTiles for TilesInMemory<'_, '_> {
    type Error = SolveError;
    fn len(&self) -> usize {
        self.0.len()
    }
    fn shape(&self, i: usize) -> Shape {
        self.0[i].shape()
    }
    fn with_pair(
        &mut self,
        a: usize,
        b: usize,
        f: &mut dyn FnMut(RasterView<'_, f32>, RasterView<'_, f32>),
    ) -> Result<(), SolveError> {
        f(self.0[a], self.0[b]);
        Ok(())
    }
}

/// [`solve_planes`] over tiles read a pair at a time ([`PlaneTiles`]): the same solution, bit
/// for bit.
pub fn solve_planes_in<T: PlaneTiles>(
    tiles: &mut T,
    positions_px: &[[f64; 2]],
    pairs: &[(usize, usize)],
    gauge: usize,
    stride: usize,
) -> Result<PlaneSolution, T::Error> {
    let n = tiles.len();
    if positions_px.len() != n {
        return Err(bad("positions_px", "must have one position per tile").into());
    }
    if stride == 0 {
        return Err(bad("stride", "must be >= 1").into());
    }
    if n == 0 {
        return Ok(PlaneSolution {
            corrections: Vec::new(),
            samples: Vec::new(),
            rms_residual_um: 0.0,
            rms_before_um: 0.0,
        });
    }
    if gauge >= n {
        return Err(bad("gauge", "must be a tile index").into());
    }
    let shapes: Vec<Shape> = (0..n).map(|i| tiles.shape(i)).collect();
    check_plane_inputs(&shapes, positions_px, pairs)?;
    let centre = shapes[0].centre_px();
    // Tilts are solved per half tile (x / half) so that all unknowns have similar scales: the
    // normal matrix stays well conditioned.
    let half = centre.0.max(centre.1).max(1.0);
    let mut blocks: Vec<PairBlock> = Vec::with_capacity(pairs.len());
    for &(a, b) in pairs {
        surfstream_core::liveness::beat();
        let offset = [
            positions_px[b][0] - positions_px[a][0],
            positions_px[b][1] - positions_px[a][1],
        ];
        let mut block = None;
        tiles.with_pair(a, b, &mut |ta, tb| {
            block = Some(overlap_normal_block(&ta, &tb, offset, centre, half, stride));
        })?;
        blocks.push(block.ok_or_else(|| bad("tiles", "with_pair did not give the pair"))?);
    }
    let (m, rhs, zz_total, count_total) = normal_equations(n, gauge, pairs, &blocks);
    let corrections = solve_corrections(m, rhs, n, gauge, half)?;
    let ssr = residual_sum_of_squares(pairs, &blocks, &corrections, half, zz_total);
    let denom = count_total.max(1) as f64;
    Ok(PlaneSolution {
        corrections,
        samples: blocks.iter().map(|b| b.3).collect(),
        rms_residual_um: (ssr.max(0.0) / denom).sqrt(),
        rms_before_um: (zz_total / denom).sqrt(),
    })
}

/// [`solve_planes`]' input checks: tiles of one size, finite positions, pairs of two
/// distinct tiles.
fn check_plane_inputs(
    shapes: &[Shape],
    positions_px: &[[f64; 2]],
    pairs: &[(usize, usize)],
) -> Result<(), SolveError> {
    let n = shapes.len();
    for (i, t) in shapes.iter().enumerate() {
        if *t != shapes[0] {
            return Err(SolveError::Mismatch {
                tile: i,
                what: "tile width x height",
                got: (t.cols * 100_000 + t.rows) as f64,
                expected: (shapes[0].cols * 100_000 + shapes[0].rows) as f64,
            });
        }
        if !positions_px[i].iter().all(|v| v.is_finite()) {
            return Err(SolveError::BadStage { tile: i });
        }
    }
    for (k, &(a, b)) in pairs.iter().enumerate() {
        for tile in [a, b] {
            if tile >= n {
                return Err(SolveError::TileOutOfRange {
                    link: k,
                    tile,
                    tiles: n,
                });
            }
        }
        if a == b {
            return Err(SolveError::SelfLink { link: k, tile: a });
        }
    }
    Ok(())
}

/// One overlap's 6 x 6 normal block over (p_a, tx_a, ty_a, p_b, tx_b, ty_b) and its rhs, from
/// b's pixels (every `stride`-th row and column) and a sampled at `offset` (b's origin in a's
/// pixels). A sample says c_b(x_b) - c_a(x_a) = z_b - z_a, with c = p + tx * x + ty * y about
/// the tile centre `(cx, cy)`, x and y in units of `half`.
fn overlap_normal_block(
    ta: &RasterView<'_, f32>,
    tb: &RasterView<'_, f32>,
    [ox, oy]: [f64; 2],
    (cx, cy): (f64, f64),
    half: f64,
    stride: usize,
) -> PairBlock {
    let mut ata = [[0.0; 6]; 6];
    let mut atb = [0.0; 6];
    let mut zz = 0.0;
    let mut count = 0;
    let c_lo = (-ox).ceil().max(0.0);
    let c_hi = ((ta.cols() - 1) as f64 - ox)
        .floor()
        .min((tb.cols() - 1) as f64);
    let r_lo = (-oy).ceil().max(0.0);
    let r_hi = ((ta.rows() - 1) as f64 - oy)
        .floor()
        .min((tb.rows() - 1) as f64);
    if c_lo > c_hi || r_lo > r_hi {
        return (ata, atb, zz, count);
    }
    for r in (r_lo as usize..=r_hi as usize).step_by(stride) {
        let yb = (r as f64 - cy) / half;
        let ya = (r as f64 + oy - cy) / half;
        for c in (c_lo as usize..=c_hi as usize).step_by(stride) {
            let zb = tb.values()[r * tb.cols() + c];
            if !zb.is_finite() {
                continue;
            }
            let Some(za) = sample_cubic(ta, c as f64 + ox, r as f64 + oy) else {
                continue;
            };
            let xb = (c as f64 - cx) / half;
            let xa = (c as f64 + ox - cx) / half;
            let g = [-1.0, -xa, -ya, 1.0, xb, yb];
            let d = zb as f64 - za;
            for i in 0..6 {
                for j in 0..6 {
                    ata[i][j] += g[i] * g[j];
                }
                atb[i] += g[i] * d;
            }
            zz += d * d;
            count += 1;
        }
    }
    (ata, atb, zz, count)
}

/// The unknowns' slot of tile `i`: the gauge tile's are eliminated (held at zero).
fn gauge_slot(i: usize, gauge: usize) -> Option<usize> {
    match i.cmp(&gauge) {
        std::cmp::Ordering::Less => Some(3 * i),
        std::cmp::Ordering::Equal => None,
        std::cmp::Ordering::Greater => Some(3 * (i - 1)),
    }
}

/// The scan's normal equations from the overlaps' blocks (gauge eliminated, a tiny ridge
/// added), and the data's sum of squares and sample count.
fn normal_equations(
    n: usize,
    gauge: usize,
    pairs: &[(usize, usize)],
    blocks: &[PairBlock],
) -> (DMatrix<f64>, DVector<f64>, f64, usize) {
    let slot = |i: usize| gauge_slot(i, gauge);
    let dim = 3 * (n - 1);
    let mut m = DMatrix::<f64>::zeros(dim, dim);
    let mut rhs = DVector::<f64>::zeros(dim);
    let mut zz_total = 0.0;
    let mut count_total = 0usize;
    for (&(a, b), (ata, atb, zz, count)) in pairs.iter().zip(blocks) {
        let idx: [Option<usize>; 6] = {
            let (sa, sb) = (slot(a), slot(b));
            [
                sa,
                sa.map(|v| v + 1),
                sa.map(|v| v + 2),
                sb,
                sb.map(|v| v + 1),
                sb.map(|v| v + 2),
            ]
        };
        for i in 0..6 {
            let Some(ii) = idx[i] else { continue };
            for j in 0..6 {
                if let Some(jj) = idx[j] {
                    m[(ii, jj)] += ata[i][j];
                }
            }
            rhs[ii] += atb[i];
        }
        zz_total += zz;
        count_total += count;
    }
    // A tiny ridge keeps tiles (or tilts) that no overlap determines at zero instead of
    // making the system singular; it is far below any overlap's weight.
    let scale = (0..dim).map(|i| m[(i, i)]).fold(1.0, f64::max);
    for i in 0..dim {
        m[(i, i)] += 1e-9 * scale;
    }
    (m, rhs, zz_total, count_total)
}

/// Every tile's correction from the normal equations (Cholesky); the gauge's is zero.
fn solve_corrections(
    m: DMatrix<f64>,
    rhs: DVector<f64>,
    n: usize,
    gauge: usize,
    half: f64,
) -> Result<Vec<PlaneCorrection>, SolveError> {
    let x = if rhs.is_empty() {
        DVector::<f64>::zeros(0)
    } else {
        m.cholesky().ok_or(SolveError::Singular)?.solve(&rhs)
    };
    Ok((0..n)
        .map(|i| match gauge_slot(i, gauge) {
            Some(k) => PlaneCorrection {
                piston_um: x[k],
                tilt_x_um_per_px: x[k + 1] / half,
                tilt_y_um_per_px: x[k + 2] / half,
            },
            None => PlaneCorrection::ZERO,
        })
        .collect())
}

/// Residual sum of squares = zz - 2 x.atb + x.M.x, with the pure data matrix.
fn residual_sum_of_squares(
    pairs: &[(usize, usize)],
    blocks: &[PairBlock],
    corrections: &[PlaneCorrection],
    half: f64,
    zz_total: f64,
) -> f64 {
    let mut ssr = zz_total;
    for (&(a, b), (ata, atb, _, _)) in pairs.iter().zip(blocks) {
        let u = [
            corrections[a].piston_um,
            corrections[a].tilt_x_um_per_px * half,
            corrections[a].tilt_y_um_per_px * half,
            corrections[b].piston_um,
            corrections[b].tilt_x_um_per_px * half,
            corrections[b].tilt_y_um_per_px * half,
        ];
        for i in 0..6 {
            ssr -= 2.0 * u[i] * atb[i];
            for j in 0..6 {
                ssr += u[i] * ata[i][j] * u[j];
            }
        }
    }
    ssr
}

/// Cubic-convolution (Keys, a = -0.5) sample of `r` at (x, y) px; `None` when the 4 x 4
/// stencil leaves the raster or a pixel with non-zero weight is NaN. Bilinear sampling would
/// leave a resampling error of a few percent of the roughness on surfaces with detail at a few
/// pixels, spatially correlated, and that error (not the noise) then limits the tilt fitted
/// across a narrow overlap.
fn sample_cubic(r: &RasterView<'_, f32>, x: f64, y: f64) -> Option<f64> {
    let (x0, y0) = (x.floor(), y.floor());
    if !(x0 >= 1.0 && y0 >= 1.0 && x0 + 2.0 < r.cols() as f64 && y0 + 2.0 < r.rows() as f64) {
        return None;
    }
    let weights = |t: f64| -> [f64; 4] {
        let (t2, t3) = (t * t, t * t * t);
        [
            0.5 * (-t3 + 2.0 * t2 - t),
            0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
            0.5 * (-3.0 * t3 + 4.0 * t2 + t),
            0.5 * (t3 - t2),
        ]
    };
    let (wx, wy) = (weights(x - x0), weights(y - y0));
    let (xi, yi) = (x0 as usize - 1, y0 as usize - 1);
    let mut acc = 0.0;
    for (j, &wyj) in wy.iter().enumerate() {
        if wyj == 0.0 {
            continue;
        }
        let row = &r.values()[(yi + j) * r.cols() + xi..(yi + j) * r.cols() + xi + 4];
        let mut line = 0.0;
        for (&v, &wxi) in row.iter().zip(&wx) {
            if wxi != 0.0 {
                if !v.is_finite() {
                    return None;
                }
                line += wxi * v as f64;
            }
        }
        acc += wyj * line;
    }
    Some(acc)
}

#[cfg(test)]
mod tests {
    #[test]
    fn cubic_sampling_is_exact_on_quadratics_and_nan_aware() {
        let (w, h) = (8usize, 7usize);
        let f = |x: f64, y: f64| 0.5 + 0.2 * x - 0.1 * y + 0.03 * x * y + 0.01 * x * x;
        let mut z: Vec<f32> = (0..w * h)
            .map(|i| f((i % w) as f64, (i / w) as f64) as f32)
            .collect();
        let r = RasterView::new(&z, Shape::new(h, w)).unwrap();
        let v = sample_cubic(&r, 3.3, 2.6).unwrap();
        assert!((v - f(3.3, 2.6)).abs() < 1e-5, "{v}");
        assert!(sample_cubic(&r, 0.5, 3.0).is_none());
        assert!(sample_cubic(&r, 3.0, 5.5).is_none());
        z[3 * w + 4] = f32::NAN;
        let r = RasterView::new(&z, Shape::new(h, w)).unwrap();
        assert!(sample_cubic(&r, 3.5, 2.5).is_none());
        assert!(sample_cubic(&r, 2.0, 2.0).is_some());
    }

    use super::*;

    fn grid(rows: usize, cols: usize, step: f64) -> Vec<[f64; 2]> {
        (0..rows * cols)
            .map(|i| [(i % cols) as f64 * step, (i / cols) as f64 * step])
            .collect()
    }

    #[test]
    fn recovers_positions_and_removes_an_injected_outlier() {
        let truth = grid(3, 3, 100.0)
            .iter()
            .enumerate()
            .map(|(i, p)| [p[0] + 0.37 * i as f64, p[1] - 0.21 * i as f64])
            .collect::<Vec<_>>();
        // Stage positions off by a few px.
        let stage: Vec<[f64; 2]> = truth
            .iter()
            .enumerate()
            .map(|(i, p)| {
                [
                    p[0] + [3.0, -2.0, 1.5][i % 3],
                    p[1] + [-2.5, 2.0, 0.5][i % 3],
                ]
            })
            .collect();
        let mut links = Vec::new();
        for r in 0..3 {
            for c in 0..3 {
                let i = r * 3 + c;
                for j in [(c + 1 < 3).then_some(i + 1), (r + 1 < 3).then_some(i + 3)]
                    .into_iter()
                    .flatten()
                {
                    links.push(Link {
                        a: i,
                        b: j,
                        offset_px: [truth[j][0] - truth[i][0], truth[j][1] - truth[i][1]],
                        sigma_px: 0.05,
                    });
                }
            }
        }
        // One link one period (12 px) off.
        links[4].offset_px[0] += 12.0;
        let sol = solve_positions(&stage, &links, &SolveParams::default()).unwrap();
        assert!(!sol.links[4].kept, "{:?}", sol.links);
        assert_eq!(sol.links.iter().filter(|l| !l.kept).count(), 1);
        // Relative positions exact up to one translation.
        let d = [
            sol.positions_px[0][0] - truth[0][0],
            sol.positions_px[0][1] - truth[0][1],
        ];
        for (p, t) in sol.positions_px.iter().zip(&truth) {
            assert!((p[0] - t[0] - d[0]).abs() < 1e-3, "{p:?} {t:?}");
            assert!((p[1] - t[1] - d[1]).abs() < 1e-3, "{p:?} {t:?}");
        }
        assert!(sol.linked.iter().all(|&l| l));
    }

    #[test]
    fn outlier_in_a_single_loop_is_found_by_the_prior() {
        let truth = grid(2, 2, 200.0);
        let stage: Vec<[f64; 2]> = truth
            .iter()
            .zip([[2.0, -1.0], [-3.0, 2.0], [1.0, 3.0], [-2.0, -2.5]])
            .map(|(p, e)| [p[0] + e[0], p[1] + e[1]])
            .collect();
        let pairs = [(0, 1), (0, 2), (1, 3), (2, 3)];
        for wrong in 0..4 {
            let links: Vec<Link> = pairs
                .iter()
                .enumerate()
                .map(|(k, &(a, b))| Link {
                    a,
                    b,
                    offset_px: [
                        truth[b][0] - truth[a][0] + if k == wrong { 15.0 } else { 0.0 },
                        truth[b][1] - truth[a][1],
                    ],
                    sigma_px: 0.05,
                })
                .collect();
            let sol = solve_positions(&stage, &links, &SolveParams::default()).unwrap();
            let removed: Vec<usize> = (0..4).filter(|&k| !sol.links[k].kept).collect();
            assert_eq!(removed, vec![wrong]);
        }
    }

    #[test]
    fn unlinked_tile_sits_at_its_stage_position() {
        let stage = grid(1, 3, 100.0);
        let links = [Link {
            a: 0,
            b: 1,
            offset_px: [98.0, 1.0],
            sigma_px: 0.05,
        }];
        let sol = solve_positions(&stage, &links, &SolveParams::default()).unwrap();
        assert_eq!(sol.linked, vec![true, true, false]);
        let p = &sol.positions_px;
        assert!((p[1][0] - p[0][0] - 98.0).abs() < 1e-3);
        assert!((p[2][0] - 200.0).abs() < 1e-9 && (p[2][1]).abs() < 1e-9);
    }

    /// Tiles 100 px apart in a row, the stage off by a few px: the truth, the stage.
    fn row_with_stage_error() -> (Vec<[f64; 2]>, Vec<[f64; 2]>) {
        let truth = vec![[0.0, 0.0], [97.3, 1.6], [195.1, -0.7]];
        let stage = grid(1, 3, 100.0);
        (truth, stage)
    }

    fn rel(p: &[[f64; 2]], a: usize, b: usize) -> [f64; 2] {
        [p[b][0] - p[a][0], p[b][1] - p[a][1]]
    }

    #[test]
    fn a_ridge_link_fixes_the_across_offset_and_leaves_the_along_one_to_the_stage() {
        let (truth, stage) = row_with_stage_error();
        // A scratch along x: the pair's offset is known in y only; the point given on the
        // ridge is 6 px off along it (where the NCC climb happened to stop).
        let t = rel(&truth, 0, 1);
        let ridge = AnisotropicLink::across(0, 1, [t[0] + 6.0, t[1]], [0.0, 1.0], 0.05);
        let sol =
            solve_positions_anisotropic(&stage, &[], &[ridge], &SolveParams::default()).unwrap();
        let r = rel(&sol.positions_px, 0, 1);
        assert!((r[1] - t[1]).abs() < 1e-3, "across: {r:?} vs {t:?}");
        // Along the ridge the link says nothing: the stage's relative offset stays.
        assert!((r[0] - 100.0).abs() < 1e-3, "along: {r:?}");
        assert_eq!(sol.registered_directions, vec![1, 1, 0]);
        let d = sol.stage_direction[0].unwrap();
        assert!(d[0].abs() > 0.999 && d[1].abs() < 1e-6, "{d:?}");
        assert_eq!(sol.linked, vec![false, false, false]);
        assert!(sol.anisotropic_links[0].kept);
        assert!(norm(sol.anisotropic_links[0].residual_px) < 1e-3);
    }

    #[test]
    fn a_slanted_ridge_fixes_its_normal_component_only() {
        let (truth, stage) = row_with_stage_error();
        let t = rel(&truth, 1, 2);
        let a: f64 = 0.35;
        let n = [-a.sin(), a.cos()];
        // Any point on the ridge: the truth moved 9 px along it.
        let along = [a.cos() * 9.0, a.sin() * 9.0];
        let ridge = AnisotropicLink::across(1, 2, [t[0] + along[0], t[1] + along[1]], n, 0.05);
        let sol =
            solve_positions_anisotropic(&stage, &[], &[ridge], &SolveParams::default()).unwrap();
        let r = rel(&sol.positions_px, 1, 2);
        let across = (r[0] - t[0]) * n[0] + (r[1] - t[1]) * n[1];
        assert!(across.abs() < 1e-3, "across error {across}");
        // Along: where the stage put it.
        let s = rel(&stage, 1, 2);
        let along_err = (r[0] - s[0]) * n[1] - (r[1] - s[1]) * n[0];
        assert!(along_err.abs() < 1e-3, "along {along_err}");
        assert_eq!(sol.registered_directions, vec![0, 1, 1]);
    }

    #[test]
    fn two_ridges_a_degree_apart_leave_the_tile_to_the_stage_along_them() {
        // Tiles 0 and 1 are placed by a full link; tile 2 hangs from both by ridge links of one
        // scratch whose measured normals differ by 1 degree, with 0.05 px of misfit across
        // (estimation noise). Nothing fixes tile 2 along the scratch: it must sit there at its
        // stage position, not 2-3 px off where the two nearly parallel lines cross.
        let truth = vec![[0.0, 0.0], [100.0, 0.0], [50.0, 97.0]];
        let stage = vec![[0.0, 0.0], [100.0, 0.0], [50.0, 100.0]];
        // Tiles 0 and 1 firmly placed (in a scan, by many full links), so the misfit cannot
        // be shared with their link.
        let full = Link {
            a: 0,
            b: 1,
            offset_px: rel(&truth, 0, 1),
            sigma_px: 0.005,
        };
        // The scratch runs along y: normals near x.
        let deg = std::f64::consts::PI / 180.0;
        let (n0, n1) = ([1.0, 0.0], [deg.cos(), deg.sin()]);
        let ridges = [
            AnisotropicLink::across(0, 2, rel(&truth, 0, 2), n0, 0.05),
            AnisotropicLink::across(
                1,
                2,
                [rel(&truth, 1, 2)[0] - 0.05, rel(&truth, 1, 2)[1]],
                n1,
                0.05,
            ),
        ];
        let sol =
            solve_positions_anisotropic(&stage, &[full], &ridges, &SolveParams::default()).unwrap();
        assert_eq!(sol.registered_directions[2], 1);
        let p = rel(&sol.positions_px, 0, 2);
        // Along (y): the stage's 100, not where the two lines cross (95.9 before the links
        // were turned). Across (x): within 0.1 px (measured 0.051: the stage is 3 px off
        // along, and the link's normal is 1 degree off the fixed direction).
        assert!((p[0] - 50.0).abs() < 0.1, "{p:?}");
        assert!((p[1] - 100.0).abs() < 0.1, "{p:?}");
    }

    #[test]
    fn a_linked_pair_hanging_by_ridges_of_one_direction_is_free_along_them() {
        // Tiles 0-1 and 2-3 are two groups joined inside by full links; between the groups
        // only ridge links of one scratch along x (normals along y: they fix y). Tiles 2 and 3
        // have a full link each, yet nothing fixes the group along x: both are reported with
        // one direction, x left to the stage (sur-3 cut at 20 %, docs/registration.md).
        let truth = vec![[0.0, 0.0], [100.0, 0.0], [0.0, 97.0], [100.0, 97.0]];
        let stage = vec![[0.0, 0.0], [100.0, 0.0], [4.0, 100.0], [104.0, 100.0]];
        let full = |a, b| Link {
            a,
            b,
            offset_px: rel(&truth, a, b),
            sigma_px: 0.05,
        };
        let ridges = [
            AnisotropicLink::across(0, 2, rel(&truth, 0, 2), [0.0, 1.0], 0.05),
            AnisotropicLink::across(1, 3, rel(&truth, 1, 3), [0.0, 1.0], 0.05),
        ];
        let sol = solve_positions_anisotropic(
            &stage,
            &[full(0, 1), full(2, 3)],
            &ridges,
            &SolveParams::default(),
        )
        .unwrap();
        assert_eq!(sol.registered_directions, vec![2, 2, 1, 1]);
        assert_eq!(sol.linked, vec![true, true, false, false]);
        for t in [2, 3] {
            let d = sol.stage_direction[t].expect("the free direction");
            assert!(d[0].abs() > 0.99, "free along x: {d:?}");
        }
        // y is fixed by the ridges (97, not the stage's 100).
        let p = rel(&sol.positions_px, 0, 2);
        assert!((p[1] - 97.0).abs() < 0.1, "{p:?}");
    }

    #[test]
    fn a_ridge_link_picks_the_ambiguous_offset_that_agrees_across_it() {
        // Tiles 0 and 1 placed by a full link. Tile 2 has a ridge link to tile 0 (a scratch
        // along y, fixing x to 0.02 px) and an ambiguous pair to tile 1: the truth, or a
        // maximum 10 px along the scratch and 0.3 px across it, nearer the stage. Only the
        // truth agrees with the ridge across (the pills specimen's tile 8, docs/registration.md).
        let truth = vec![[0.0, 0.0], [100.0, 0.0], [50.3, 89.0]];
        let stage = vec![[0.0, 0.0], [100.0, 0.0], [50.0, 100.0]];
        let full = Link {
            a: 0,
            b: 1,
            offset_px: rel(&truth, 0, 1),
            sigma_px: 0.05,
        };
        let t02 = rel(&truth, 0, 2);
        let ridge = AnisotropicLink::across(0, 2, [t02[0] + 0.02, t02[1] + 4.0], [1.0, 0.0], 0.05);
        let t12 = rel(&truth, 1, 2);
        let ambiguous = AmbiguousLink {
            a: 1,
            b: 2,
            offsets_px: vec![[t12[0] - 0.3, t12[1] + 10.0], t12],
            sigma_px: 0.05,
        };
        let (sol, chosen) = solve_scan_positions(
            &stage,
            &[full],
            &[ridge],
            &[ambiguous],
            &SolveParams::default(),
        )
        .unwrap();
        assert_eq!(chosen, vec![Some(1)]);
        let p = rel(&sol.positions_px, 0, 2);
        assert!(
            (p[0] - t02[0]).abs() < 0.05 && (p[1] - t02[1]).abs() < 0.05,
            "{p:?}"
        );
        assert_eq!(sol.registered_directions[2], 2);
    }

    #[test]
    fn two_crossing_ridges_place_a_tile_fully() {
        // 2 x 2 grid; tile 3's only links are a ridge across x (to tile 2, left of it) and a
        // ridge across y (to tile 1, above it): together they fix it.
        let truth = vec![[0.0, 0.0], [101.2, -1.1], [0.8, 98.9], [102.4, 99.6]];
        let stage = grid(2, 2, 100.0);
        let full = |a: usize, b: usize| Link {
            a,
            b,
            offset_px: rel(&truth, a, b),
            sigma_px: 0.05,
        };
        let links = [full(0, 1), full(0, 2)];
        let t23 = rel(&truth, 2, 3);
        let t13 = rel(&truth, 1, 3);
        let ridges = [
            AnisotropicLink::across(2, 3, [t23[0], t23[1] + 4.0], [1.0, 0.0], 0.05),
            AnisotropicLink::across(1, 3, [t13[0] - 5.0, t13[1]], [0.0, 1.0], 0.05),
        ];
        let sol =
            solve_positions_anisotropic(&stage, &links, &ridges, &SolveParams::default()).unwrap();
        for i in 0..4 {
            let (p, t) = (rel(&sol.positions_px, 0, i), rel(&truth, 0, i));
            assert!(
                (p[0] - t[0]).abs() < 1e-3 && (p[1] - t[1]).abs() < 1e-3,
                "{i}: {p:?} {t:?}"
            );
        }
        assert_eq!(sol.registered_directions, vec![2, 2, 2, 2]);
        assert!(sol.linked.iter().all(|&l| l));
        assert!(sol.stage_direction.iter().all(|d| d.is_none()));
    }

    #[test]
    fn a_ridge_link_wrong_across_is_removed_and_one_wrong_along_is_not() {
        // A loop 0-1-3-2-0 of full links plus a ridge between 0 and 3 (diagonal, for the test).
        let truth = vec![[0.0, 0.0], [101.2, -1.1], [0.8, 98.9], [102.4, 99.6]];
        let stage = grid(2, 2, 100.0);
        let full = |a: usize, b: usize| Link {
            a,
            b,
            offset_px: rel(&truth, a, b),
            sigma_px: 0.05,
        };
        let links = [full(0, 1), full(0, 2), full(1, 3), full(2, 3)];
        let t = rel(&truth, 0, 3);
        for (shift, removed) in [([0.0, 3.0], true), ([12.0, 0.0], false)] {
            let ridge =
                AnisotropicLink::across(0, 3, [t[0] + shift[0], t[1] + shift[1]], [0.0, 1.0], 0.05);
            let sol =
                solve_positions_anisotropic(&stage, &links, &[ridge], &SolveParams::default())
                    .unwrap();
            assert_eq!(!sol.anisotropic_links[0].kept, removed, "{shift:?}");
            assert!(sol.links.iter().all(|l| l.kept));
            let p = rel(&sol.positions_px, 0, 3);
            assert!(
                (p[0] - t[0]).abs() < 1e-3 && (p[1] - t[1]).abs() < 1e-3,
                "{p:?}"
            );
        }
    }

    #[test]
    fn without_anisotropic_links_the_solve_is_the_isotropic_one() {
        let (truth, stage) = row_with_stage_error();
        let links = [Link {
            a: 0,
            b: 1,
            offset_px: rel(&truth, 0, 1),
            sigma_px: 0.05,
        }];
        let p = SolveParams::default();
        let a = solve_positions(&stage, &links, &p).unwrap();
        let b = solve_positions_anisotropic(&stage, &links, &[], &p).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.registered_directions, vec![2, 2, 0]);
        assert_eq!(a.linked, vec![true, true, false]);
    }

    #[test]
    fn malformed_anisotropic_links_are_refused() {
        let stage = grid(1, 2, 100.0);
        let p = SolveParams::default();
        let with = |m: [[f64; 2]; 2]| AnisotropicLink {
            a: 0,
            b: 1,
            offset_px: [100.0, 0.0],
            information_per_px2: m,
        };
        for m in [
            [[1.0, 0.0], [0.0, -1.0]],
            [[1.0, 2.0], [2.0, 1.0]],
            [[1.0, 0.5], [0.0, 1.0]],
            [[0.0, 0.0], [0.0, 0.0]],
            [[f64::NAN, 0.0], [0.0, 1.0]],
        ] {
            assert!(
                matches!(
                    solve_positions_anisotropic(&stage, &[], &[with(m)], &p),
                    Err(SolveError::BadLink { link: 0 })
                ),
                "{m:?}"
            );
        }
        let mut l = with([[1.0, 0.0], [0.0, 0.0]]);
        l.b = 7;
        assert!(matches!(
            solve_positions_anisotropic(&stage, &[], &[l], &p),
            Err(SolveError::TileOutOfRange { tile: 7, .. })
        ));
    }

    #[test]
    fn malformed_links_are_refused() {
        let stage = grid(1, 2, 100.0);
        let l = |a, b, off: f64, s: f64| Link {
            a,
            b,
            offset_px: [off, 0.0],
            sigma_px: s,
        };
        let p = SolveParams::default();
        assert!(matches!(
            solve_positions(&stage, &[l(0, 5, 1.0, 0.1)], &p),
            Err(SolveError::TileOutOfRange { tile: 5, .. })
        ));
        assert!(matches!(
            solve_positions(&stage, &[l(1, 1, 1.0, 0.1)], &p),
            Err(SolveError::SelfLink { .. })
        ));
        assert!(matches!(
            solve_positions(&stage, &[l(0, 1, f64::NAN, 0.1)], &p),
            Err(SolveError::BadLink { .. })
        ));
        assert!(matches!(
            solve_positions(&stage, &[l(0, 1, 1.0, 0.0)], &p),
            Err(SolveError::BadLink { .. })
        ));
        assert!(matches!(
            solve_positions(&[[f64::INFINITY, 0.0]], &[], &p),
            Err(SolveError::BadStage { tile: 0 })
        ));
    }
}
