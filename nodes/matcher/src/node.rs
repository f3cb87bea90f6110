//! The matcher node: registers each arriving tile against its already-placed grid neighbours
//! and publishes one [`TileRegistration`] per tile, in acquisition order; at end of scan it
//! runs the global solve once and publishes one more registration per tile, flagged
//! [`flags::FINAL`], before the end-of-scan marker.
//!
//! While streaming, a tile's position is its placed neighbours' positions plus the measured
//! offsets (averaged over accepted links, weighted by NCC). With no trustworthy link it keeps
//! its stage position relative to its placed neighbours (the stage's own offset between them)
//! and is flagged `placed_by: "stage"`. The plane correction (piston, tilt) levels it onto its
//! neighbours.
//!
//! At end of scan, [`crate::global::solve_positions`] places every tile from all accepted
//! links at once (inconsistent links removed, stage positions as weak prior; a tile left
//! without a kept link is placed by the stage and flagged), and
//! [`crate::global::solve_planes`] levels every tile over all overlaps at those positions
//! (the first tile is the gauge, as in streaming). The node report ("tiles", "pairs" in
//! run.json) gives the FINAL positions; the streaming ones stay beside them under "streaming".
//!
//! Memory: every tile's heights are kept until end of scan (the z alignment needs the
//! overlaps at the final positions): 4 MiB per 1024 x 1024 tile.

use std::collections::BTreeMap;

use anyhow::{bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_core::frame::{flags, placed_by, FrameKind, TileRegistration};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::global::{
    solve_planes, solve_positions_with_alternatives, AmbiguousLink, Link, SolveParams,
};
use crate::{
    estimate_plane, register_pair_features, FeatureMethod, FeatureParams, FeatureRegistration,
    PhaseCorrelator, PhaseParams, PlaneCorrection, RasterRef,
};

const OUT: &str = "registrations";

/// Standard deviation (px) of an accepted link with NCC 1; lower NCC trusts it less (the
/// global solve then puts a loop's misfit on the weaker links).
const LINK_SIGMA_PX: f64 = 0.05;

/// Sample every 2nd row and column of the overlaps in the final z alignment: a 20 % overlap of
/// 1024 px tiles still gives 50 000 samples per pair.
const Z_STRIDE: usize = 2;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Params {
    /// Registration method: "phase" (phase correlation with NCC-verified candidates) or
    /// "auto" (= the best available, today "phase").
    #[serde(default = "auto")]
    method: String,
    /// Lowest NCC of the overlap at the chosen shift for a link to be trusted.
    min_ncc: Option<f64>,
    /// Largest accepted deviation from the stage's nominal offset, px.
    max_shift_px: Option<f64>,
    /// Standard deviation of the stage positions, px: the weight of the prior in the global
    /// solve (5).
    stage_sigma_px: Option<f64>,
    /// A link disagreeing with the global solve by more than this (px) is removed (1).
    outlier_px: Option<f64>,
    /// A ground_truth.json (make_tiles.py's, or the simulated stage's truth.json; relative to
    /// the output directory): with a feature method, r and MAP against it (crate::efficiency).
    truth: Option<String>,
}

fn auto() -> String {
    "auto".into()
}

/// A tile as received, kept to the end of the scan.
struct StoredTile {
    index: u32,
    row: u32,
    col: u32,
    width: usize,
    height: usize,
    pitch_um: [f64; 2],
    stage_um: [f64; 2],
    t_acquired_ns: u64,
    heights: Vec<f32>,
    /// Streaming placement.
    position_um: [f64; 2],
    plane: PlaneCorrection,
    placed_by: u32,
    links_tried: u32,
}

/// One registered pair (b = the later tile), positions into `tiles`.
struct PairRecord {
    a: usize,
    b: usize,
    offset_px: Option<[f64; 2]>,
    ncc: f64,
    /// An ambiguous pair's distinct NCC maxima, for the global solve to choose from.
    alternatives: Vec<[f64; 2]>,
    /// The feature matcher's outcome (methods "harris", "sift").
    features: Option<FeatureRegistration>,
    report: serde_json::Value,
}

pub struct MatcherNode {
    params: PhaseParams,
    solve: SolveParams,
    method: String,
    /// Harris or SIFT instead of phase correlation (crate::feature_match).
    features: Option<FeatureParams>,
    truth: Option<std::path::PathBuf>,
    correlator: PhaseCorrelator,
    pending: Vec<StoredTile>,
    tiles: Vec<StoredTile>,
    by_grid: BTreeMap<(u32, u32), usize>,
    pairs: Vec<PairRecord>,
    ended: bool,
    done: bool,
    last: (u32, u64),
    tiles_report: Vec<serde_json::Value>,
    pairs_report: Vec<serde_json::Value>,
    global_report: serde_json::Value,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p: Params = ctx.params()?;
    let where_ = || format!("graph '{}', node '{}'", ctx.graph_name, ctx.node_id);
    let features = match p.method.as_str() {
        "auto" | "phase" => None,
        "harris" => Some(FeatureParams::for_method(FeatureMethod::Harris)),
        "sift" => Some(FeatureParams::for_method(FeatureMethod::Sift)),
        m => bail!(
            "{}: method = {m:?}: expected \"auto\", \"phase\", \"harris\" or \"sift\"",
            where_()
        ),
    };
    let mut params = PhaseParams::default();
    if let Some(v) = p.min_ncc {
        params.min_ncc = v;
    }
    if let Some(v) = p.max_shift_px {
        params.max_shift_px = v;
    }
    params
        .validate()
        .map_err(|e| anyhow::anyhow!("{}: {e}", where_()))?;
    let mut solve = SolveParams::default();
    if let Some(v) = p.stage_sigma_px {
        if !(v.is_finite() && v > 0.0) {
            bail!("{}: stage_sigma_px = {v}: expected a number > 0", where_());
        }
        solve.stage_sigma_px = v;
    }
    if let Some(v) = p.outlier_px {
        if !(v.is_finite() && v > 0.0) {
            bail!("{}: outlier_px = {v}: expected a number > 0", where_());
        }
        solve.outlier_px = v;
    }
    Ok(Box::new(MatcherNode {
        params,
        solve,
        method: features
            .as_ref()
            .map_or("phase", |f| f.method.name())
            .into(),
        features,
        truth: p.truth.map(|t| ctx.out_dir.join(t)),
        correlator: PhaseCorrelator::new(),
        pending: Vec::new(),
        tiles: Vec::new(),
        by_grid: BTreeMap::new(),
        pairs: Vec::new(),
        ended: false,
        done: false,
        last: (0, 0),
        tiles_report: Vec::new(),
        pairs_report: Vec::new(),
        global_report: serde_json::Value::Null,
    }))
}

fn raster(t: &StoredTile) -> RasterRef<'_> {
    RasterRef {
        heights: &t.heights,
        width: t.width,
        height: t.height,
    }
}

fn placed_name(how: u32) -> &'static str {
    if how == placed_by::STAGE {
        "stage"
    } else {
        "registration"
    }
}

impl MatcherNode {
    /// Streaming registration of one tile against its placed grid neighbours.
    fn register(&mut self, mut t: StoredTile) -> Result<TileRegistration> {
        let pitch = t.pitch_um;
        if let Some(first) = self.tiles.first() {
            if first.pitch_um != pitch {
                bail!(
                    "matcher: tile {} has pitch {:?} um, tile {} has {:?} um: one scan needs one pitch",
                    t.index,
                    pitch,
                    first.index,
                    first.pitch_um
                );
            }
        }
        let me = self.tiles.len();
        let keys = [
            (t.row, t.col.wrapping_sub(1)),
            (t.row, t.col + 1),
            (t.row.wrapping_sub(1), t.col),
            (t.row + 1, t.col),
        ];
        let neighbours: Vec<usize> = keys
            .iter()
            .filter_map(|k| self.by_grid.get(k).copied())
            .collect();
        let mut votes = Vec::new();
        let mut stage_votes = Vec::new();
        let b = RasterRef {
            heights: &t.heights,
            width: t.width,
            height: t.height,
        };
        for &ai in &neighbours {
            let a = &self.tiles[ai];
            let nominal = [
                (t.stage_um[0] - a.stage_um[0]) / pitch[0],
                (t.stage_um[1] - a.stage_um[1]) / pitch[1],
            ];
            let (r, alternatives, features) = match &self.features {
                Some(fp) => {
                    let f = register_pair_features(raster(a), b, nominal, fp);
                    (f.registration.clone(), Vec::new(), Some(f))
                }
                None => {
                    let (r, alt) = self.correlator.register_with_alternatives(
                        raster(a),
                        b,
                        nominal,
                        &self.params,
                    );
                    (r, alt, None)
                }
            };
            let direction = if a.row == t.row {
                "horizontal"
            } else {
                "vertical"
            };
            let report = json!({
                "a": a.index, "b": t.index, "direction": direction,
                "nominal_offset_px": nominal,
                "offset_px": r.offset_px,
                "ncc": r.ncc, "peak_ratio": r.peak_ratio,
                "accepted": r.offset_px.is_some(),
                "reason": r.rejection.as_ref().map(|e| e.to_string()),
            });
            let report = match &features {
                Some(f) => {
                    let mut report = report;
                    report["reason"] = json!(f.reason());
                    report["features"] = f.report(None);
                    report
                }
                None => report,
            };
            self.pairs.push(PairRecord {
                a: ai,
                b: me,
                offset_px: r.offset_px,
                ncc: r.ncc,
                alternatives: alternatives.iter().map(|c| c.offset_px).collect(),
                features,
                report,
            });
            stage_votes.push((
                1.0,
                [
                    a.position_um[0] + nominal[0] * pitch[0],
                    a.position_um[1] + nominal[1] * pitch[1],
                ],
            ));
            if let Some(off) = r.offset_px {
                votes.push((
                    r.ncc.max(1e-3),
                    [
                        a.position_um[0] + off[0] * pitch[0],
                        a.position_um[1] + off[1] * pitch[1],
                    ],
                ));
            }
        }
        let (position_um, how) = if let Some(p) = weighted_mean(&votes) {
            (p, placed_by::REGISTRATION)
        } else if let Some(p) = weighted_mean(&stage_votes) {
            (p, placed_by::STAGE)
        } else {
            // The first tile defines the scan frame: its stage position.
            (t.stage_um, placed_by::REGISTRATION)
        };
        // Level onto the placed neighbours, at the streaming relative positions.
        let levels: Vec<_> = neighbours
            .iter()
            .map(|&ai| {
                let a = &self.tiles[ai];
                (
                    raster(a),
                    [
                        (position_um[0] - a.position_um[0]) / pitch[0],
                        (position_um[1] - a.position_um[1]) / pitch[1],
                    ],
                    a.plane,
                )
            })
            .collect();
        let plane = if levels.is_empty() {
            PlaneCorrection::default()
        } else {
            estimate_plane(b, &levels).unwrap_or_default()
        };
        let quality = votes.iter().map(|v| v.0).fold(0.0, f64::max);
        let reg = TileRegistration {
            tile_index: t.index,
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
            t_acquired_ns: t.t_acquired_ns,
            ..Default::default()
        };
        t.position_um = position_um;
        t.plane = plane;
        t.placed_by = how;
        t.links_tried = neighbours.len() as u32;
        self.by_grid.insert((t.row, t.col), me);
        self.tiles.push(t);
        Ok(reg)
    }

    /// The global solve over the whole scan: one FINAL registration per tile, and the report.
    fn finalize(&mut self) -> Result<Vec<TileRegistration>> {
        if self.tiles.is_empty() {
            return Ok(Vec::new());
        }
        let pitch = self.tiles[0].pitch_um;
        let stage_px: Vec<[f64; 2]> = self
            .tiles
            .iter()
            .map(|t| [t.stage_um[0] / pitch[0], t.stage_um[1] / pitch[1]])
            .collect();
        let accepted: Vec<usize> = (0..self.pairs.len())
            .filter(|&k| self.pairs[k].offset_px.is_some())
            .collect();
        let links: Vec<Link> = accepted
            .iter()
            .filter_map(|&k| {
                let p = &self.pairs[k];
                p.offset_px.map(|o| Link {
                    a: p.a,
                    b: p.b,
                    offset_px: o,
                    sigma_px: LINK_SIGMA_PX / p.ncc.clamp(0.05, 1.0),
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
                    sigma_px: LINK_SIGMA_PX / p.ncc.clamp(0.05, 1.0),
                }
            })
            .collect();
        let (sol, chosen) =
            solve_positions_with_alternatives(&stage_px, &links, &ambiguous, &self.solve)
                .map_err(|e| anyhow::anyhow!("matcher: global position solve: {e}"))?;
        // The solution's links: the accepted pairs, then the chosen ambiguous ones in input
        // order (as the solve appends them).
        let mut accepted = accepted;
        let mut links = links;
        for (i, c) in chosen.iter().enumerate() {
            if let Some(c) = *c {
                let l = &ambiguous[i];
                accepted.push(ambiguous_pairs[i]);
                links.push(Link {
                    a: l.a,
                    b: l.b,
                    offset_px: l.offsets_px[c],
                    sigma_px: l.sigma_px,
                });
            }
        }
        // The scan frame is the first tile's stage position, as while streaming: shift the
        // solution so tile 0 keeps its streaming position when it is linked.
        let shift = [
            self.tiles[0].position_um[0] / pitch[0] - sol.positions_px[0][0],
            self.tiles[0].position_um[1] / pitch[1] - sol.positions_px[0][1],
        ];
        let positions_px: Vec<[f64; 2]> = sol
            .positions_px
            .iter()
            .map(|p| [p[0] + shift[0], p[1] + shift[1]])
            .collect();
        let overlaps: Vec<(usize, usize)> = self.pairs.iter().map(|p| (p.a, p.b)).collect();
        let rasters: Vec<RasterRef<'_>> = self.tiles.iter().map(raster).collect();
        let planes = solve_planes(&rasters, &positions_px, &overlaps, 0, Z_STRIDE)
            .map_err(|e| anyhow::anyhow!("matcher: global z alignment: {e}"))?;
        let single = self.tiles.len() == 1;
        let mut regs = Vec::with_capacity(self.tiles.len());
        let mut accepted_per_tile = vec![0u32; self.tiles.len()];
        for (l, o) in links.iter().zip(&sol.links) {
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
            let how = if sol.linked[i] || single {
                placed_by::REGISTRATION
            } else {
                placed_by::STAGE
            };
            let plane = planes.corrections[i];
            let pos_um = [positions_px[i][0] * pitch[0], positions_px[i][1] * pitch[1]];
            let quality = self
                .pairs
                .iter()
                .zip(0..)
                .filter(|(p, _)| p.a == i || p.b == i)
                .filter_map(|(p, k)| {
                    let li = accepted.iter().position(|&a| a == k)?;
                    sol.links[li].kept.then_some(p.ncc)
                })
                .fold(0.0, f64::max);
            regs.push(TileRegistration {
                tile_index: t.index,
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
                t_acquired_ns: t.t_acquired_ns,
                ..Default::default()
            });
            self.tiles_report.push(json!({
                "index": t.index, "row": t.row, "col": t.col,
                "x_um": pos_um[0], "y_um": pos_um[1],
                "placed_by": placed_name(how),
                "links_accepted": accepted_per_tile[i], "links_tried": tried_per_tile[i],
                "quality": quality,
                "piston_um": plane.piston_um, "tilt_x_um_per_px": plane.tilt_x_um_per_px,
                "tilt_y_um_per_px": plane.tilt_y_um_per_px,
                "streaming": {
                    "x_um": t.position_um[0], "y_um": t.position_um[1],
                    "placed_by": placed_name(t.placed_by), "links_tried": t.links_tried,
                    "piston_um": t.plane.piston_um,
                    "tilt_x_um_per_px": t.plane.tilt_x_um_per_px,
                    "tilt_y_um_per_px": t.plane.tilt_y_um_per_px,
                },
            }));
        }
        // Feature methods with a truth file: r and MAP of every pair's matches.
        let (feature_truth, feature_summary) = match (&self.truth, &self.features) {
            (Some(path), Some(_)) => {
                let scored: Vec<(u64, u64, &FeatureRegistration)> = self
                    .pairs
                    .iter()
                    .filter_map(|p| {
                        let f = p.features.as_ref()?;
                        Some((
                            self.tiles[p.a].index as u64,
                            self.tiles[p.b].index as u64,
                            f,
                        ))
                    })
                    .collect();
                let (q, summary) = crate::efficiency::score_feature_pairs(path, &scored)
                    .map_err(|e| anyhow::anyhow!("matcher: truth: {e}"))?;
                (q, summary)
            }
            _ => (Vec::new(), serde_json::Value::Null),
        };
        let mut feature_truth = feature_truth.into_iter();
        for (k, p) in self.pairs.iter().enumerate() {
            let mut r = p.report.clone();
            if let Some(f) = &p.features {
                r["features"] = f.report(feature_truth.next().flatten().as_ref());
            }
            let final_offset = [
                positions_px[p.b][0] - positions_px[p.a][0],
                positions_px[p.b][1] - positions_px[p.a][1],
            ];
            r["final_offset_px"] = json!(final_offset);
            r["z_samples"] = json!(planes.samples[k]);
            if let Some(i) = ambiguous_pairs.iter().position(|&a| a == k) {
                // An ambiguous pair: its candidate offsets, and the one the global solve took.
                r["alternatives_px"] = json!(p.alternatives);
                r["chosen_alternative"] = json!(chosen[i]);
            }
            if let Some(li) = accepted.iter().position(|&a| a == k) {
                let o = sol.links[li];
                r["kept_by_global_solve"] = json!(o.kept);
                r["residual_px"] = json!(o.residual_px);
            } else {
                r["kept_by_global_solve"] = json!(false);
            }
            self.pairs_report.push(r);
        }
        self.global_report = json!({
            "links": links.len(),
            "links_removed": sol.links.iter().filter(|l| !l.kept).count(),
            "max_residual_px": sol.max_residual_px,
            "tiles_placed_by_stage": regs.iter().filter(|r| r.placed_by == placed_by::STAGE).count(),
            "stage_sigma_px": self.solve.stage_sigma_px,
            "outlier_px": self.solve.outlier_px,
            "z_rms_before_um": planes.rms_before_um,
            "z_rms_residual_um": planes.rms_residual_um,
            "features": feature_summary,
        });
        Ok(regs)
    }
}

fn weighted_mean(votes: &[(f64, [f64; 2])]) -> Option<[f64; 2]> {
    let w: f64 = votes.iter().map(|v| v.0).sum();
    (w > 0.0).then(|| {
        let x = votes.iter().map(|v| v.0 * v.1[0]).sum::<f64>() / w;
        let y = votes.iter().map(|v| v.0 * v.1[1]).sum::<f64>() / w;
        [x, y]
    })
}

impl NodeLogic for MatcherNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("matcher: input '{port}' carries registrations, expected tiles")
        };
        if f.header.has(flags::END_OF_SCAN) {
            self.ended = true;
            self.last = (f.header.tile_index, f.header.t_acquired_ns);
            return Ok(());
        }
        if f.header.kind() != Some(FrameKind::Tile) {
            bail!(
                "matcher: input '{port}' carries {:?} frames, expected tiles",
                f.header.kind()
            );
        }
        let h = f.header;
        let pitch = [h.pitch_x_um, h.pitch_y_um];
        if !pitch.iter().all(|p| p.is_finite() && *p > 0.0) {
            bail!(
                "matcher: tile {}: pitch {:?} um, expected finite and > 0",
                h.tile_index,
                pitch
            );
        }
        if !(h.origin_x_um.is_finite() && h.origin_y_um.is_finite()) {
            bail!(
                "matcher: tile {}: stage position ({}, {}) um is not finite",
                h.tile_index,
                h.origin_x_um,
                h.origin_y_um
            );
        }
        self.pending.push(StoredTile {
            index: h.tile_index,
            row: h.tile_row,
            col: h.tile_col,
            width: h.width as usize,
            height: h.height as usize,
            pitch_um: pitch,
            stage_um: [h.origin_x_um, h.origin_y_um],
            t_acquired_ns: h.t_acquired_ns,
            heights: f.heights.to_vec(),
            position_um: [0.0; 2],
            plane: PlaneCorrection::ZERO,
            placed_by: placed_by::REGISTRATION,
            links_tried: 0,
        });
        Ok(())
    }

    fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
        for t in std::mem::take(&mut self.pending) {
            let reg = self.register(t)?;
            out.send_registration(OUT, reg);
        }
        if self.ended && !self.done {
            for reg in self.finalize()? {
                out.send_registration(OUT, reg);
            }
            out.end_registrations(OUT, self.last.0, self.last.1);
            self.done = true;
        }
        Ok(())
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> serde_json::Value {
        json!({
            "method": self.method,
            "tiles": self.tiles_report,
            "pairs": self.pairs_report,
            "global": self.global_report,
        })
    }
}
