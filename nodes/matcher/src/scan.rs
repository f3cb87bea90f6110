//! A whole scan's registration: each tile against its already-placed grid neighbours as the
//! stage delivers it ([`ScanRegistration::register`]), then every tile at once at end of scan
//! ([`ScanRegistration::finish`]). The matcher node only feeds it frames.
//!
//! While streaming, a tile's position is its placed neighbours' positions plus the measured
//! offsets (averaged over accepted links, weighted by NCC). With no trustworthy link it keeps
//! its stage position relative to its placed neighbours (the stage's own offset between them)
//! and is flagged `placed_by: "stage"`. The plane correction (piston, tilt) levels it onto its
//! neighbours.
//!
//! At end of scan, [`crate::global::solve_positions_with_alternatives`] places every tile from
//! all accepted links at once (inconsistent links removed, ambiguous pairs resolved by the rest
//! of the scan, stage positions as weak prior; a tile left without a kept link is placed by the
//! stage and flagged), and [`crate::global::solve_planes`] levels every tile over all overlaps
//! at those positions (the first tile is the gauge, as in streaming). The report ("tiles",
//! "pairs" in run.json) gives the FINAL positions; the streaming ones stay beside them under
//! "streaming".
//!
//! Memory: every tile's heights are needed again at end of scan (the z alignment needs the
//! overlaps at the final positions), but not in memory: only the newest tile stays resident;
//! the others go to an unnamed spill file ([`ScanParams::spill_dir`]) and are read back when
//! a later tile pairs with them (the tile above, in a serpentine) and, a pair at a time, by
//! the final z alignment. Resident heights are therefore a few tiles whatever the scan's size,
//! and the registrations are the same, bit for bit, as with every tile in memory.

use std::collections::BTreeMap;
use std::path::PathBuf;

use surfstream_core::frame::{flags, placed_by, TileRegistration};
use surfstream_core::raster::{Raster, RasterView, Shape};
use surfstream_core::record::{
    self, DirectionalPair, FeatureSummaryRecord, GlobalSolveRecord, LayoutMisfit, MatcherPair,
    MatcherReport, MatcherTile, StreamingPlacement, TilePlacement,
};
use surfstream_core::store::{AppendLog, StoreError};
use surfstream_core::Pitch;
use thiserror::Error;

use crate::global::{
    solve_planes_in, solve_scan_positions, AmbiguousLink, AnisotropicLink, GlobalSolution, Link,
    PlaneSolution, PlaneTiles, SolveError, SolveParams,
};
use crate::register::DirectionalOffset;
use crate::{
    estimate_plane, register_pair_features, FeatureParams, FeatureRegistration, PairRegistration,
    PhaseCorrelator, PhaseParams, PlaneCorrection,
};
use surfstream_io::truth::TruthError;

/// Standard deviation (px) of an accepted link with NCC 1; lower NCC trusts it less (the
/// global solve then puts a loop's misfit on the weaker links).
const LINK_SIGMA_PX: f64 = 0.05;

/// Sample every 2nd row and column of the overlaps in the final z alignment: a 20 % overlap of
/// 1024 px tiles still gives 50 000 samples per pair.
const Z_STRIDE: usize = 2;

/// How a scan is registered.
#[derive(Debug, Clone, Default)]
pub struct ScanParams {
    /// Phase correlation (used when `features` is `None`).
    pub phase: PhaseParams,
    /// Harris or SIFT instead of phase correlation ([`crate::feature_match`]).
    pub features: Option<FeatureParams>,
    /// The global solve at end of scan.
    pub solve: SolveParams,
    /// A `ground_truth.json`: with a feature method, r and MAP of every pair against it,
    /// read at end of scan ([`crate::efficiency`]).
    pub truth: Option<PathBuf>,
    /// Folder of the unnamed file placed tiles' heights are spilled to (the node uses its out
    /// dir); `None`: the system temp folder.
    pub spill_dir: Option<PathBuf>,
}

/// A tile as the stage delivers it.
#[derive(Debug, Clone)]
pub struct ScanTile {
    /// Acquisition index.
    pub index: u32,
    /// Grid row and column: the neighbours are the grid's 4-neighbours.
    pub row: u32,
    pub col: u32,
    /// Pixel pitch (checked when made; the tile's shape is `heights`').
    pub pitch: Pitch,
    /// Nominal stage position of pixel (0, 0) `[x, y]`, um.
    pub stage_um: [f64; 2],
    /// Passed through to the registrations (the trace of the tile).
    pub t_acquired_ns: u64,
    /// Heights, um, NaN = not measured.
    pub heights: Raster<f32>,
}

impl ScanTile {
    /// Refuses a stage position that no placement can use (the pitch was checked when
    /// made).
    pub fn validate(&self) -> Result<(), ScanError> {
        if !self.stage_um.iter().all(|v| v.is_finite()) {
            return Err(ScanError::BadStage {
                index: self.index,
                stage_um: self.stage_um,
            });
        }
        Ok(())
    }

    fn raster(&self) -> RasterView<'_, f32> {
        self.heights.view()
    }
}

/// Why a tile or the scan could not be registered.
#[derive(Debug, Error)]
pub enum ScanError {
    #[error("tile {index}: stage position ({}, {}) um is not finite", stage_um[0], stage_um[1])]
    BadStage { index: u32, stage_um: [f64; 2] },
    #[error(
        "tile {index} has pitch {:?} um, tile {first} has {:?} um: one scan needs one pitch",
        pitch.um(),
        first_pitch.um()
    )]
    PitchMismatch {
        index: u32,
        pitch: Pitch,
        first: u32,
        first_pitch: Pitch,
    },
    #[error("global position solve: {0}")]
    Positions(SolveError),
    #[error("global z alignment: {0}")]
    Planes(SolveError),
    #[error("truth: {0}")]
    Truth(#[from] TruthError),
    #[error("placed tiles: {0}")]
    Spill(#[from] StoreError),
}

/// A registered tile, kept to the end of the scan with its streaming placement.
struct PlacedTile {
    /// The tile; once spilled its `heights` are a 1 x 1 placeholder and `spilled` says where
    /// they are.
    tile: ScanTile,
    /// Offset of the heights in the spill file, once spilled.
    spilled: Option<u64>,
    /// The tile's size (also once spilled).
    shape: Shape,
    position_um: [f64; 2],
    plane: PlaneCorrection,
    placed_by: u32,
    links_tried: u32,
}

/// One registered pair (b = the later tile), positions into the tile list.
struct PairRecord {
    a: usize,
    b: usize,
    offset_px: Option<[f64; 2]>,
    ncc: f64,
    /// Standard deviation of `offset_px` along its worst-known direction, px, when the
    /// Lucas-Kanade refinement measured it.
    sd_px: Option<f64>,
    /// An ambiguous pair's distinct NCC maxima, for the global solve to choose from.
    alternatives: Vec<[f64; 2]>,
    /// A refused pair's one-direction answer (an NCC ridge), for the global solve.
    directional: Option<DirectionalOffset>,
    /// The feature matcher's outcome (methods "harris", "sift").
    features: Option<FeatureRegistration>,
    report: MatcherPair,
}

/// Candidate positions of a new tile, um, weighted: one per neighbour.
type Vote = (f64, [f64; 2]);

/// The global solve's placement: positions (px, in the streaming scan frame), the links it
/// saw with their pair numbers, and per ambiguous pair its number and chosen offset.
struct GlobalPlacement {
    sol: GlobalSolution,
    positions_px: Vec<[f64; 2]>,
    links: Vec<Link>,
    /// Pair number of each of `links`.
    link_pairs: Vec<usize>,
    ambiguous_pairs: Vec<usize>,
    chosen: Vec<Option<usize>>,
    /// Pair number of each anisotropic (one-direction) link, in the solve's order.
    directional_pairs: Vec<usize>,
}

/// The registration of one scan; see the module documentation.
pub struct ScanRegistration {
    params: ScanParams,
    correlator: PhaseCorrelator,
    tiles: Vec<PlacedTile>,
    spill: AppendLog<f32>,
    by_grid: BTreeMap<(u32, u32), usize>,
    pairs: Vec<PairRecord>,
    tiles_report: Vec<MatcherTile>,
    pairs_report: Vec<MatcherPair>,
    global_report: Option<GlobalSolveRecord>,
}

impl ScanRegistration {
    pub fn new(params: ScanParams) -> Self {
        ScanRegistration {
            spill: AppendLog::new(params.spill_dir.clone()),
            params,
            correlator: PhaseCorrelator::new(),
            tiles: Vec::new(),
            by_grid: BTreeMap::new(),
            pairs: Vec::new(),
            tiles_report: Vec::new(),
            pairs_report: Vec::new(),
            global_report: None,
        }
    }

    /// Tiles whose heights are in memory (the others are in the spill file): 1 once any
    /// tile is registered, whatever the scan's size.
    pub fn resident_tiles(&self) -> usize {
        self.tiles.iter().filter(|t| t.spilled.is_none()).count()
    }

    /// "phase", "harris" or "sift".
    pub fn method(&self) -> &'static str {
        self.params
            .features
            .as_ref()
            .map_or("phase", |f| f.method.name())
    }

    /// Streaming registration of one tile against its placed grid neighbours: its position,
    /// how it was placed, and its plane correction onto them.
    pub fn register(&mut self, tile: ScanTile) -> Result<TileRegistration, ScanError> {
        tile.validate()?;
        if let Some(first) = self.tiles.first() {
            if first.tile.pitch != tile.pitch {
                return Err(ScanError::PitchMismatch {
                    index: tile.index,
                    pitch: tile.pitch,
                    first: first.tile.index,
                    first_pitch: first.tile.pitch,
                });
            }
        }
        let neighbours = self.placed_neighbours(&tile);
        // Spilled neighbours are read back for this tile only.
        let loaded: Vec<Option<Raster<f32>>> = neighbours
            .iter()
            .map(|&i| self.read_spilled(i))
            .collect::<Result<_, _>>()?;
        let views: Vec<RasterView<'_, f32>> = neighbours
            .iter()
            .zip(&loaded)
            .map(|(&i, l)| {
                l.as_ref()
                    .map_or_else(|| self.tiles[i].tile.raster(), |r| r.view())
            })
            .collect();
        let mut votes = Vec::new();
        let mut stage_votes = Vec::new();
        let mut records = Vec::new();
        for (&ai, &a_heights) in neighbours.iter().zip(&views) {
            let (vote, stage_vote, record) = register_link(
                &mut self.correlator,
                &self.params,
                &self.tiles[ai],
                a_heights,
                &tile,
            );
            votes.extend(vote);
            stage_votes.push(stage_vote);
            records.push((ai, record));
        }
        let (position_um, how) = place(&tile, &votes, &stage_votes);
        let plane = self.level(&tile, &neighbours, &views, position_um);
        drop(views);
        drop(loaded);
        let b = self.tiles.len();
        for (ai, (offset_px, (ncc, sd_px), alternatives, directional, features, report)) in records
        {
            self.pairs.push(PairRecord {
                a: ai,
                b,
                offset_px,
                ncc,
                sd_px,
                alternatives,
                directional,
                features,
                report,
            });
        }
        let quality = votes.iter().map(|v| v.0).fold(0.0, f64::max);
        let reg = TileRegistration {
            tile_index: tile.index,
            placed_by: how,
            flags: if how == placed_by::STAGE {
                flags::PLACED_BY_STAGE
            } else {
                0
            },
            links_accepted: votes.len() as u32,
            links_tried: neighbours.len() as u32,
            x_um: position_um[0],
            y_um: position_um[1],
            piston_um: plane.piston_um,
            tilt_x_um_per_px: plane.tilt_x_um_per_px,
            tilt_y_um_per_px: plane.tilt_y_um_per_px,
            quality,
            t_acquired_ns: tile.t_acquired_ns,
            ..Default::default()
        };
        // Only the newest tile stays in memory: the next one pairs with it (left or right);
        // any other neighbour is read back from the spill file.
        if let Some(prev) = b.checked_sub(1) {
            self.spill_tile(prev)?;
        }
        self.by_grid.insert((tile.row, tile.col), b);
        let shape = tile.heights.shape();
        self.tiles.push(PlacedTile {
            tile,
            spilled: None,
            shape,
            position_um,
            plane,
            placed_by: how,
            links_tried: neighbours.len() as u32,
        });
        Ok(reg)
    }

    /// Moves tile `i`'s heights to the spill file (nothing if already there).
    fn spill_tile(&mut self, i: usize) -> Result<(), ScanError> {
        let Some(t) = self.tiles.get_mut(i) else {
            return Ok(());
        };
        if t.spilled.is_some() {
            return Ok(());
        }
        t.spilled = Some(self.spill.append(t.tile.heights.values())?);
        // A 1 x 1 placeholder: the heights are on disk now.
        t.tile.heights = Raster::filled(Shape::new(1, 1), f32::NAN);
        Ok(())
    }

    /// Tile `i`'s heights read back from the spill file; `None` while they are in memory.
    fn read_spilled(&self, i: usize) -> Result<Option<Raster<f32>>, ScanError> {
        let t = &self.tiles[i];
        let Some(offset) = t.spilled else {
            return Ok(None);
        };
        let values = self.spill.read(offset, t.shape.len())?;
        Raster::new(values, t.shape).map(Some).map_err(|e| {
            ScanError::Spill(StoreError {
                folder: self.spill.folder().to_path_buf(),
                action: format!("reading tile {i} back"),
                source: std::io::Error::other(e.to_string()),
            })
        })
    }

    /// The already-placed grid 4-neighbours of `t` (left, right, above, below).
    fn placed_neighbours(&self, t: &ScanTile) -> Vec<usize> {
        let keys = [
            (t.row, t.col.wrapping_sub(1)),
            (t.row, t.col + 1),
            (t.row.wrapping_sub(1), t.col),
            (t.row + 1, t.col),
        ];
        keys.iter()
            .filter_map(|k| self.by_grid.get(k).copied())
            .collect()
    }

    /// The plane correction that levels `t`, at `position_um`, onto its placed neighbours.
    fn level(
        &self,
        t: &ScanTile,
        neighbours: &[usize],
        heights: &[RasterView<'_, f32>],
        position_um: [f64; 2],
    ) -> PlaneCorrection {
        let pitch = t.pitch.um();
        let levels: Vec<_> = neighbours
            .iter()
            .zip(heights)
            .map(|(&ai, &a_heights)| {
                let a = &self.tiles[ai];
                (
                    a_heights,
                    [
                        (position_um[0] - a.position_um[0]) / pitch[0],
                        (position_um[1] - a.position_um[1]) / pitch[1],
                    ],
                    a.plane,
                )
            })
            .collect();
        if levels.is_empty() {
            PlaneCorrection::default()
        } else {
            estimate_plane(t.raster(), &levels).unwrap_or_default()
        }
    }

    /// The global solve over the whole scan: one FINAL registration per tile, in acquisition
    /// order (the report is filled too). An empty scan gives none.
    pub fn finish(&mut self) -> Result<Vec<TileRegistration>, ScanError> {
        if self.tiles.is_empty() {
            return Ok(Vec::new());
        }
        let placement = self.solve_positions()?;
        let overlaps: Vec<(usize, usize)> = self.pairs.iter().map(|p| (p.a, p.b)).collect();
        // The tiles a pair at a time, spilled ones read back (a few at once, not the scan).
        let mut tiles = PlacedTiles {
            scan: self,
            cache: Vec::new(),
        };
        let planes = solve_planes_in(&mut tiles, &placement.positions_px, &overlaps, 0, Z_STRIDE)
            .map_err(|e| match e {
            PlanesError::Solve(e) => ScanError::Planes(e),
            PlanesError::Spill(e) => e,
        })?;
        let regs = self.final_registrations(&placement, &planes);
        let feature_summary = self.report_pairs(&placement, &planes)?;
        let count = |n: usize| n as u64;
        self.global_report = Some(GlobalSolveRecord {
            links: count(placement.links.len()),
            links_removed: count(placement.sol.links.iter().filter(|l| !l.kept).count()),
            max_residual_px: placement.sol.max_residual_px,
            tiles_placed_by_stage: count(
                regs.iter()
                    .filter(|r| r.placed_by == placed_by::STAGE)
                    .count(),
            ),
            directional_links: count(placement.directional_pairs.len()),
            directional_links_removed: count(
                placement
                    .sol
                    .anisotropic_links
                    .iter()
                    .filter(|l| !l.kept)
                    .count(),
            ),
            tiles_one_direction_by_stage: count(
                placement
                    .sol
                    .registered_directions
                    .iter()
                    .filter(|&&d| d == 1)
                    .count(),
            ),
            stage_sigma_px: self.params.solve.stage_sigma_px,
            outlier_px: self.params.solve.outlier_px,
            z_rms_before_um: planes.rms_before_um,
            z_rms_residual_um: planes.rms_residual_um,
            features: feature_summary,
        });
        Ok(regs)
    }

    /// Positions of all tiles from all accepted and ambiguous pairs, shifted so that tile 0
    /// keeps its streaming position (the scan frame is the first tile's stage position).
    fn solve_positions(&self) -> Result<GlobalPlacement, ScanError> {
        let pitch = self.tiles[0].tile.pitch.um();
        let stage_px: Vec<[f64; 2]> = self
            .tiles
            .iter()
            .map(|t| [t.tile.stage_um[0] / pitch[0], t.tile.stage_um[1] / pitch[1]])
            .collect();
        let mut link_pairs: Vec<usize> = (0..self.pairs.len())
            .filter(|&k| self.pairs[k].offset_px.is_some())
            .collect();
        let mut links: Vec<Link> = link_pairs
            .iter()
            .filter_map(|&k| {
                let p = &self.pairs[k];
                p.offset_px.map(|o| Link {
                    a: p.a,
                    b: p.b,
                    offset_px: o,
                    sigma_px: p
                        .sd_px
                        .map_or_else(|| link_sigma_px(p.ncc), |s| s.max(LK_SIGMA_FLOOR_PX)),
                })
            })
            .collect();
        let ambiguous_pairs: Vec<usize> = (0..self.pairs.len())
            .filter(|&k| self.pairs[k].alternatives.len() >= 2)
            .collect();
        let ambiguous: Vec<AmbiguousLink> = ambiguous_pairs
            .iter()
            .map(|&k| {
                let p = &self.pairs[k];
                AmbiguousLink {
                    a: p.a,
                    b: p.b,
                    offsets_px: p.alternatives.clone(),
                    sigma_px: link_sigma_px(p.ncc),
                }
            })
            .collect();
        // Refused pairs whose NCC ridge fixes one direction: one-direction links, trusted
        // across as an accepted link of the same NCC is.
        let directional_pairs: Vec<usize> = (0..self.pairs.len())
            .filter(|&k| self.pairs[k].offset_px.is_none() && self.pairs[k].directional.is_some())
            .collect();
        let anisotropic: Vec<AnisotropicLink> = directional_pairs
            .iter()
            .filter_map(|&k| {
                let p = &self.pairs[k];
                let d = p.directional?;
                Some(AnisotropicLink::across(
                    p.a,
                    p.b,
                    d.offset_px,
                    d.normal,
                    link_sigma_px(d.ncc),
                ))
            })
            .collect();
        let (sol, chosen) = solve_scan_positions(
            &stage_px,
            &links,
            &anisotropic,
            &ambiguous,
            &self.params.solve,
        )
        .map_err(ScanError::Positions)?;
        // The solution's links: the accepted pairs, then the chosen ambiguous ones in input
        // order (as the solve appends them).
        for (i, c) in chosen.iter().enumerate() {
            if let Some(c) = *c {
                let l = &ambiguous[i];
                link_pairs.push(ambiguous_pairs[i]);
                links.push(Link {
                    a: l.a,
                    b: l.b,
                    offset_px: l.offsets_px[c],
                    sigma_px: l.sigma_px,
                });
            }
        }
        // The gauge shift: tile 0 keeps its streaming position when it is linked.
        let first = &self.tiles[0];
        let shift = [
            first.position_um[0] / pitch[0] - sol.positions_px[0][0],
            first.position_um[1] / pitch[1] - sol.positions_px[0][1],
        ];
        let positions_px: Vec<[f64; 2]> = sol
            .positions_px
            .iter()
            .map(|p| [p[0] + shift[0], p[1] + shift[1]])
            .collect();
        Ok(GlobalPlacement {
            sol,
            positions_px,
            links,
            link_pairs,
            ambiguous_pairs,
            chosen,
            directional_pairs,
        })
    }

    /// One FINAL registration per tile from the global placement and planes; fills the tile
    /// report.
    fn final_registrations(
        &mut self,
        g: &GlobalPlacement,
        planes: &PlaneSolution,
    ) -> Vec<TileRegistration> {
        let pitch = self.tiles[0].tile.pitch.um();
        let single = self.tiles.len() == 1;
        let mut regs = Vec::with_capacity(self.tiles.len());
        let mut accepted_per_tile = vec![0u32; self.tiles.len()];
        for (l, o) in g.links.iter().zip(&g.sol.links) {
            if o.kept {
                accepted_per_tile[l.a] += 1;
                accepted_per_tile[l.b] += 1;
            }
        }
        let mut tried_per_tile = vec![0u32; self.tiles.len()];
        for p in &self.pairs {
            tried_per_tile[p.a] += 1;
            tried_per_tile[p.b] += 1;
        }
        for (i, t) in self.tiles.iter().enumerate() {
            let directions = if single {
                2
            } else {
                g.sol.registered_directions[i]
            };
            // A tile with one direction from the stage is flagged as placed by the stage (never
            // silently half-registered); the record says which direction.
            let how = if g.sol.linked[i] || single {
                placed_by::REGISTRATION
            } else {
                placed_by::STAGE
            };
            let plane = planes.corrections[i];
            let pos_um = [
                g.positions_px[i][0] * pitch[0],
                g.positions_px[i][1] * pitch[1],
            ];
            // The best NCC among the tile's links the global solve kept.
            let quality = self
                .pairs
                .iter()
                .zip(0..)
                .filter(|(p, _)| p.a == i || p.b == i)
                .filter_map(|(p, k)| {
                    let li = g.link_pairs.iter().position(|&a| a == k)?;
                    g.sol.links[li].kept.then_some(p.ncc)
                })
                .fold(0.0, f64::max);
            regs.push(TileRegistration {
                tile_index: t.tile.index,
                placed_by: how,
                flags: flags::FINAL
                    | if how == placed_by::STAGE {
                        flags::PLACED_BY_STAGE
                    } else {
                        0
                    },
                links_accepted: accepted_per_tile[i],
                links_tried: tried_per_tile[i],
                x_um: pos_um[0],
                y_um: pos_um[1],
                piston_um: plane.piston_um,
                tilt_x_um_per_px: plane.tilt_x_um_per_px,
                tilt_y_um_per_px: plane.tilt_y_um_per_px,
                quality,
                t_acquired_ns: t.tile.t_acquired_ns,
                ..Default::default()
            });
            self.tiles_report.push(MatcherTile {
                index: t.tile.index,
                row: t.tile.row,
                col: t.tile.col,
                placement: TilePlacement {
                    x_um: pos_um[0],
                    y_um: pos_um[1],
                    placed_by: placed_name(how).into(),
                    links_accepted: accepted_per_tile[i],
                    links_tried: tried_per_tile[i],
                    quality,
                    piston_um: plane.piston_um,
                    tilt_x_um_per_px: plane.tilt_x_um_per_px,
                    tilt_y_um_per_px: plane.tilt_y_um_per_px,
                    streaming: StreamingPlacement {
                        x_um: t.position_um[0],
                        y_um: t.position_um[1],
                        placed_by: placed_name(t.placed_by).into(),
                        links_tried: t.links_tried,
                        piston_um: t.plane.piston_um,
                        tilt_x_um_per_px: t.plane.tilt_x_um_per_px,
                        tilt_y_um_per_px: t.plane.tilt_y_um_per_px,
                    },
                    registered_directions: Some(directions),
                    stage_direction: if single {
                        None
                    } else {
                        g.sol.stage_direction[i]
                    },
                },
            });
        }
        regs
    }

    /// Fills the pair report with the global outcome of every pair (and, with a feature method
    /// and a truth file, r and AP); returns the feature summary (`global.features`).
    fn report_pairs(
        &mut self,
        g: &GlobalPlacement,
        planes: &PlaneSolution,
    ) -> Result<Option<FeatureSummaryRecord>, ScanError> {
        let (feature_truth, feature_summary) = match (&self.params.truth, &self.params.features) {
            (Some(path), Some(_)) => {
                let scored: Vec<(u64, u64, &FeatureRegistration)> = self
                    .pairs
                    .iter()
                    .filter_map(|p| {
                        let f = p.features.as_ref()?;
                        Some((
                            self.tiles[p.a].tile.index as u64,
                            self.tiles[p.b].tile.index as u64,
                            f,
                        ))
                    })
                    .collect();
                let (per_pair, summary) = crate::efficiency::score_feature_pairs(path, &scored)?;
                (per_pair, Some(summary))
            }
            _ => (Vec::new(), None),
        };
        let mut feature_truth = feature_truth.into_iter();
        for (k, p) in self.pairs.iter().enumerate() {
            let mut r = p.report.clone();
            if let Some(f) = &p.features {
                r.features = Some(f.report(feature_truth.next().flatten().as_ref()));
            }
            r.final_offset_px = Some([
                g.positions_px[p.b][0] - g.positions_px[p.a][0],
                g.positions_px[p.b][1] - g.positions_px[p.a][1],
            ]);
            r.z_samples = Some(planes.samples[k] as u64);
            if let Some(i) = g.ambiguous_pairs.iter().position(|&a| a == k) {
                // An ambiguous pair: its candidate offsets, and the one the global solve took.
                r.alternatives_px = Some(p.alternatives.clone());
                r.chosen_alternative = Some(g.chosen[i].map(|c| c as u64));
            }
            if let Some(d) = &p.directional {
                let outcome = g
                    .directional_pairs
                    .iter()
                    .position(|&a| a == k)
                    .map(|li| g.sol.anisotropic_links[li]);
                r.directional = Some(DirectionalPair {
                    offset_px: d.offset_px,
                    normal: d.normal,
                    curvature_per_px2: d.curvature_per_px2,
                    ncc: d.ncc,
                    kept_by_global_solve: outcome.map(|o| o.kept),
                    residual_px: outcome.map(|o| o.residual_px),
                });
            }
            let outcome = g
                .link_pairs
                .iter()
                .position(|&a| a == k)
                .map(|li| g.sol.links[li]);
            r.kept_by_global_solve = Some(outcome.is_some_and(|o| o.kept));
            r.residual_px = outcome.map(|o| o.residual_px);
            self.pairs_report.push(r);
        }
        Ok(feature_summary)
    }

    /// Every pair decided so far, in decision order, as streaming recorded it (before the
    /// global solve): the records the report's `pairs` complete, and the pair log's lines
    /// ([`crate::pair_log`]).
    pub fn streaming_pairs(&self) -> impl ExactSizeIterator<Item = &MatcherPair> {
        self.pairs.iter().map(|p| &p.report)
    }

    /// The run report: the method, per tile and per pair outcomes, and the global solve's
    /// summary (empty until [`ScanRegistration::finish`]).
    pub fn report(&self) -> Result<serde_json::Value, record::RecordError> {
        record::to_value(&MatcherReport {
            method: self.method().into(),
            tiles: self.tiles_report.clone(),
            pairs: self.pairs_report.clone(),
            global: self.global_report.clone(),
        })
    }
}

/// A pair's outcome while streaming: offset, NCC and the offset's standard deviation (when
/// measured), alternatives, one-direction answer, feature outcome, report.
type LinkRecord = (
    Option<[f64; 2]>,
    (f64, Option<f64>),
    Vec<[f64; 2]>,
    Option<DirectionalOffset>,
    Option<FeatureRegistration>,
    MatcherPair,
);

/// Registers the new tile `t` against the placed tile `a` (its heights `a_heights`): the
/// position it gives `t` when accepted (weighted by NCC), the one the stage gives, and the
/// pair's record.
fn register_link(
    correlator: &mut PhaseCorrelator,
    params: &ScanParams,
    a: &PlacedTile,
    a_heights: RasterView<'_, f32>,
    t: &ScanTile,
) -> (Option<Vote>, Vote, LinkRecord) {
    let pitch = t.pitch.um();
    let nominal = [
        (t.stage_um[0] - a.tile.stage_um[0]) / pitch[0],
        (t.stage_um[1] - a.tile.stage_um[1]) / pitch[1],
    ];
    let (r, alternatives, features) = match &params.features {
        Some(fp) => {
            let f = register_pair_features(a_heights, t.raster(), nominal, fp);
            (f.registration.clone(), Vec::new(), Some(f))
        }
        None => {
            let (r, alt) = correlator.register_with_alternatives(
                a_heights,
                t.raster(),
                nominal,
                &params.phase,
            );
            (r, alt, None)
        }
    };
    let mut r = r;
    let mut report = pair_report(&a.tile, t, nominal, &r, features.as_ref());
    let weak = features.is_none() && r.offset_px.is_some() && r.ncc < params.phase.min_ncc;
    if weak {
        // Accepted as a distinct peak below min_ncc (PhaseParams::min_ncc_distinct): said so.
        report.accepted_below_min_ncc = true;
    }
    if let Some(off) = r.offset_px {
        let misfit = layout_misfit(off, nominal, weak, params.solve.stage_sigma_px);
        if let Some(m) = misfit.filter(|m| m.refused) {
            // A weak peak off the plan: more likely an overlap that does not exist (a wrong
            // layout) than a stage error; not used.
            r.offset_px = None;
            report.offset_px = None;
            report.accepted = false;
            report.accepted_below_min_ncc = false;
            report.reason = Some(format!(
                "a weak peak (NCC {:.3}, below min_ncc {:.2}) {:.1} px from the layout's planned \
                 offset, more than the stage error allows ({:.1} px = sqrt 2 x stage_sigma_px \
                 {}): the planned overlap may not exist (check the layout: --serpentine, \
                 --overlap, scan.toml's positions)",
                r.ncc, params.phase.min_ncc, m.shift_px, m.bound_px, params.solve.stage_sigma_px
            ));
        }
        report.layout_inconsistent = misfit;
    }
    let stage_vote = (
        1.0,
        [
            a.position_um[0] + nominal[0] * pitch[0],
            a.position_um[1] + nominal[1] * pitch[1],
        ],
    );
    let vote = r.offset_px.map(|off| {
        (
            r.ncc.max(1e-3),
            [
                a.position_um[0] + off[0] * pitch[0],
                a.position_um[1] + off[1] * pitch[1],
            ],
        )
    });
    // The Lucas-Kanade refinement's covariance, when it ran: the link's weight, and said in
    // the pair's record so that an imprecise link is visible.
    let sd_px = r.covariance_px2.map(|c| {
        let sd = crate::refine::worst_sd_px(c);
        report.offset_covariance_px2 = Some(c);
        report.offset_sd_px = Some(sd);
        sd
    });
    let record = (
        r.offset_px,
        (r.ncc, sd_px),
        alternatives.iter().map(|c| c.offset_px).collect(),
        r.directional,
        features,
        report,
    );
    (vote, stage_vote, record)
}

/// How many standard deviations of a pair's stage error (sqrt 2 x `stage_sigma_px`: the
/// difference of two tiles' errors) a strong link may lie from the layout's planned offset
/// before it is flagged inconsistent with the layout.
const LAYOUT_STRONG_SIGMAS: f64 = 3.0;

/// Does the link's measured `offset` (px) disagree with the layout's planned `nominal` offset
/// by more than the stated stage error (`stage_sigma_px`, one tile's, px) allows? A pair's
/// offset error is the difference of two tiles' stage errors, sigma sqrt 2. A weak link
/// (accepted below min_ncc as a distinct peak) gets one such sigma and is refused beyond it:
/// its only support is standing out, and a false peak on an overlap that does not exist
/// stands out as well anywhere within the search. A strong link gets three and is kept but
/// flagged beyond them. `None`: consistent.
pub fn layout_misfit(
    offset: [f64; 2],
    nominal: [f64; 2],
    weak: bool,
    stage_sigma_px: f64,
) -> Option<LayoutMisfit> {
    let shift_px = (offset[0] - nominal[0]).hypot(offset[1] - nominal[1]);
    let pair_sigma = std::f64::consts::SQRT_2 * stage_sigma_px;
    let bound_px = if weak {
        pair_sigma
    } else {
        LAYOUT_STRONG_SIGMAS * pair_sigma
    };
    (shift_px > bound_px).then_some(LayoutMisfit {
        shift_px,
        bound_px,
        refused: weak,
    })
}

/// Why the final z alignment failed: the solve, or reading a tile back.
enum PlanesError {
    Solve(SolveError),
    Spill(ScanError),
}

impl From<SolveError> for PlanesError {
    fn from(e: SolveError) -> Self {
        PlanesError::Solve(e)
    }
}

/// Spilled tiles read back this many at a time (least recently used out): a pair and the
/// next pair's new tile.
const PLANE_CACHE_TILES: usize = 3;

/// The scan's placed tiles for the final z alignment, spilled ones read back on demand.
struct PlacedTiles<'a> {
    scan: &'a ScanRegistration,
    /// Read-back tiles, least recently used first.
    cache: Vec<(usize, Raster<f32>)>,
}

impl PlacedTiles<'_> {
    fn ensure(&mut self, i: usize) -> Result<(), PlanesError> {
        if let Some(k) = self.cache.iter().position(|c| c.0 == i) {
            let hit = self.cache.remove(k);
            self.cache.push(hit);
            return Ok(());
        }
        if let Some(r) = self.scan.read_spilled(i).map_err(PlanesError::Spill)? {
            if self.cache.len() >= PLANE_CACHE_TILES {
                self.cache.remove(0);
            }
            self.cache.push((i, r));
        }
        Ok(())
    }

    fn view(&self, i: usize) -> Option<RasterView<'_, f32>> {
        let t = self.scan.tiles.get(i)?;
        if t.spilled.is_none() {
            return Some(t.tile.raster());
        }
        self.cache.iter().find(|c| c.0 == i).map(|c| c.1.view())
    }
}

impl PlaneTiles for PlacedTiles<'_> {
    type Error = PlanesError;
    fn len(&self) -> usize {
        self.scan.tiles.len()
    }
    fn shape(&self, i: usize) -> Shape {
        self.scan.tiles[i].shape
    }
    fn with_pair(
        &mut self,
        a: usize,
        b: usize,
        f: &mut dyn FnMut(RasterView<'_, f32>, RasterView<'_, f32>),
    ) -> Result<(), PlanesError> {
        self.ensure(a)?;
        self.ensure(b)?;
        match (self.view(a), self.view(b)) {
            (Some(va), Some(vb)) => {
                f(va, vb);
                Ok(())
            }
            _ => Err(PlanesError::Spill(ScanError::Spill(StoreError {
                folder: self.scan.spill.folder().to_path_buf(),
                action: format!("reading tiles {a} and {b} back"),
                source: std::io::Error::other("not both readable"),
            }))),
        }
    }
}

/// The smallest standard deviation given a Lucas-Kanade link, px: its covariance counts the
/// noise only, not the interpolation's error (0.01-0.02 px on noise-free cuts of the real
/// specimens).
const LK_SIGMA_FLOOR_PX: f64 = 0.02;

/// Standard deviation of a link measured with this NCC, px.
fn link_sigma_px(ncc: f64) -> f64 {
    LINK_SIGMA_PX / ncc.clamp(0.05, 1.0)
}

/// A new tile's streaming position: the NCC-weighted mean of its accepted links, else the
/// stage's offsets from its placed neighbours (flagged), else (the first tile, which defines
/// the scan frame) its stage position.
fn place(t: &ScanTile, votes: &[Vote], stage_votes: &[Vote]) -> ([f64; 2], u32) {
    if let Some(p) = weighted_mean(votes) {
        (p, placed_by::REGISTRATION)
    } else if let Some(p) = weighted_mean(stage_votes) {
        (p, placed_by::STAGE)
    } else {
        (t.stage_um, placed_by::REGISTRATION)
    }
}

/// The pair's entry in the report while streaming.
fn pair_report(
    a: &ScanTile,
    b: &ScanTile,
    nominal: [f64; 2],
    r: &PairRegistration,
    features: Option<&FeatureRegistration>,
) -> MatcherPair {
    let direction = if a.row == b.row {
        "horizontal"
    } else {
        "vertical"
    };
    let (reason, features) = match features {
        Some(f) => (f.reason(), Some(f.report(None))),
        None => (r.rejection.as_ref().map(|e| e.to_string()), None),
    };
    MatcherPair {
        a: a.index,
        b: b.index,
        direction: direction.into(),
        nominal_offset_px: nominal,
        offset_px: r.offset_px,
        ncc: r.ncc,
        peak_ratio: r.peak_ratio,
        accepted: r.offset_px.is_some(),
        reason,
        accepted_below_min_ncc: false,
        layout_inconsistent: None,
        features,
        final_offset_px: None,
        z_samples: None,
        alternatives_px: None,
        chosen_alternative: None,
        directional: None,
        kept_by_global_solve: None,
        residual_px: None,
        offset_covariance_px2: None,
        offset_sd_px: None,
    }
}

fn weighted_mean(votes: &[Vote]) -> Option<[f64; 2]> {
    let w: f64 = votes.iter().map(|v| v.0).sum();
    (w > 0.0).then(|| {
        let x = votes.iter().map(|v| v.0 * v.1[0]).sum::<f64>() / w;
        let y = votes.iter().map(|v| v.0 * v.1[1]).sum::<f64>() / w;
        [x, y]
    })
}

fn placed_name(how: u32) -> &'static str {
    if how == placed_by::STAGE {
        "stage"
    } else {
        "registration"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 36: a link off the layout's plan by more than the stated stage error. With
    /// `stage_sigma_px` 5 a pair's sigma is 7.07 px: a weak link beyond it is refused, a strong
    /// one is kept up to three of them (21.2 px) and flagged beyond.
    #[test]
    fn links_off_the_layouts_plan_beyond_the_stage_error_are_refused_or_flagged() {
        let nominal = [204.8, 0.0];
        // The weak false link of a serpentine stitched row by row: (5.25, 6.38) px off.
        let m = layout_misfit([210.05, 6.38], nominal, true, 5.0).expect("refused");
        assert!(
            m.refused && (m.bound_px - 50f64.sqrt()).abs() < 1e-12,
            "{m:?}"
        );
        assert!((m.shift_px - 5.25f64.hypot(6.38)).abs() < 1e-9);
        // The same offset, strong: within three pair sigmas, consistent.
        assert_eq!(layout_misfit([210.05, 6.38], nominal, false, 5.0), None);
        // A weak link within one pair sigma (a true lone pit with a 3 px stage error).
        assert_eq!(layout_misfit([207.8, -3.0], nominal, true, 5.0), None);
        // A strong link 22.6 px off: flagged, kept.
        let m = layout_misfit([204.8, 22.6], nominal, false, 5.0).expect("flagged");
        assert!(!m.refused && (m.bound_px - 3.0 * 50f64.sqrt()).abs() < 1e-12);
        // A larger stated stage error widens both bounds.
        assert_eq!(layout_misfit([204.8, 22.6], nominal, false, 10.0), None);
        assert_eq!(layout_misfit([210.05, 6.38], nominal, true, 10.0), None);
    }
}
