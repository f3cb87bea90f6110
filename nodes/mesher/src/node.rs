//! The mesher node: turns the final surface into an error-bounded STL solid or sheet (or, with
//! `method = "grid"`, the full-grid solid). Live patches are counted and skipped: a mesh is
//! written once, from the exact final surface, after every wired input has ended its scan.
//!
//! Which surface (`surface`, issue item 4): "pooled" (default) or "panorama" arrive on the input
//! `surface` (wired to wavelet/pooled or fusion/panorama); "datum" and "roughness" on the inputs
//! of those names; "datum+roughness" needs both and meshes their sum (the panorama as the
//! separation rebuilds it). The wiring must match the choice: a missing or an unused input is
//! an error when the graph is read.

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_core::frame::{flags, monotonic_ns, HeightMap};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::{
    check_closed, grid_solid, mesh_height_field, stl, Epsilon, HeightFieldRef, LengthUnit,
    MeshKind, MeshParams, MissingSamples, SolidParams,
};

/// The bound when the graph gives none: 5 % of the surface's Sq.
const DEFAULT_EPSILON_SQ_FRACTION: f64 = 0.05;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Params {
    /// STL coordinate unit: "mm" (default), "m" or "um".
    #[serde(default)]
    units: LengthUnit,
    /// "binary" (EDEM, Rocky, MercuryDPM) or "ascii" (LIGGGHTS).
    #[serde(default = "binary")]
    format: String,
    /// Base of the solid below the lowest sample, um (default: from the height range).
    base_depth_um: Option<f64>,
    #[serde(default = "stl_name")]
    file: String,
    /// "adaptive" (error-bounded, default) or "grid" (two triangles per grid cell).
    #[serde(default = "adaptive")]
    method: String,
    /// Largest vertical error, um (adaptive).
    epsilon_um: Option<f64>,
    /// Largest vertical error as a fraction of the surface's Sq (adaptive; default 0.05 when
    /// `epsilon_um` is not given).
    epsilon_sq_fraction: Option<f64>,
    /// Triangle budget of the surface (adaptive).
    max_triangles: Option<usize>,
    /// "solid" (default) or "sheet" (adaptive).
    #[serde(default)]
    kind: MeshKind,
    /// "fill" (default) or "holes" (sheet only): missing samples.
    #[serde(default)]
    missing: MissingSamples,
    /// Which surface to mesh (see the module docs).
    #[serde(default)]
    surface: SurfaceChoice,
}

/// Which surface the mesher meshes, and the input ports that carry it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
pub enum SurfaceChoice {
    #[default]
    #[serde(rename = "pooled")]
    Pooled,
    #[serde(rename = "panorama")]
    Panorama,
    #[serde(rename = "datum+roughness")]
    DatumPlusRoughness,
    #[serde(rename = "datum")]
    Datum,
    #[serde(rename = "roughness")]
    Roughness,
}

impl SurfaceChoice {
    /// The input ports this choice needs (and the only ones it accepts).
    pub fn ports(self) -> &'static [&'static str] {
        match self {
            Self::Pooled | Self::Panorama => &["surface"],
            Self::DatumPlusRoughness => &["datum", "roughness"],
            Self::Datum => &["datum"],
            Self::Roughness => &["roughness"],
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Pooled => "pooled",
            Self::Panorama => "panorama",
            Self::DatumPlusRoughness => "datum+roughness",
            Self::Datum => "datum",
            Self::Roughness => "roughness",
        }
    }
}

fn adaptive() -> String {
    "adaptive".into()
}

fn binary() -> String {
    "binary".into()
}
fn stl_name() -> String {
    "surface.stl".into()
}

pub struct MesherNode {
    params: SolidParams,
    /// `None`: the full-grid solid.
    adaptive: Option<MeshParams>,
    ascii: bool,
    path: std::path::PathBuf,
    file: String,
    surface: SurfaceChoice,
    /// Where each input comes from ("node/port"), for run.json.
    sources: Vec<(String, String)>,
    /// The final frame per input port, and the ports whose scan has ended.
    finals: std::collections::BTreeMap<String, HeightMap>,
    ended: std::collections::BTreeSet<String>,
    live_frames: u64,
    done: bool,
    summary: serde_json::Value,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    Ok(Box::new(MesherNode::new(ctx)?))
}

impl MesherNode {
    /// The node's logic from its graph context (parameters and wiring checked here).
    pub fn new(ctx: &NodeContext) -> Result<Self> {
        let p: Params = ctx.params()?;
        let wired: Vec<&str> = ctx.inputs.iter().map(|i| i.port.as_str()).collect();
        let needed = p.surface.ports();
        for port in needed {
            if !wired.contains(port) {
                bail!(
                    "graph '{}', node '{}': surface = \"{}\" needs the input '{port}' \
                     (wired: {wired:?})",
                    ctx.graph_name,
                    ctx.node_id,
                    p.surface.name()
                );
            }
        }
        if let Some(extra) = wired.iter().find(|w| !needed.contains(w)) {
            bail!(
                "graph '{}', node '{}': input '{extra}' is wired but surface = \"{}\" does \
                 not use it (it uses {needed:?})",
                ctx.graph_name,
                ctx.node_id,
                p.surface.name()
            );
        }
        let sources = ctx
            .inputs
            .iter()
            .map(|i| (i.port.clone(), format!("{}/{}", i.from_node, i.from_port)))
            .collect();
        let ascii = match p.format.as_str() {
            "binary" => false,
            "ascii" => true,
            other => bail!(
                "graph '{}', node '{}': format = {other:?}: expected \"binary\" or \"ascii\"",
                ctx.graph_name,
                ctx.node_id
            ),
        };
        let params = SolidParams {
            units: p.units,
            base_depth_um: p.base_depth_um,
            recentre: true,
        };
        params
            .validate()
            .map_err(|e| anyhow!("graph '{}', node '{}': {e}", ctx.graph_name, ctx.node_id))?;
        let adaptive = match p.method.as_str() {
            "grid" => None,
            "adaptive" => {
                let epsilon = match (p.epsilon_um, p.epsilon_sq_fraction) {
                    (Some(_), Some(_)) => bail!(
                        "graph '{}', node '{}': give epsilon_um or epsilon_sq_fraction, not both",
                        ctx.graph_name,
                        ctx.node_id
                    ),
                    (Some(e), None) => Epsilon::Um(e),
                    (None, f) => Epsilon::SqFraction(f.unwrap_or(DEFAULT_EPSILON_SQ_FRACTION)),
                };
                Some(MeshParams {
                    epsilon,
                    max_triangles: p.max_triangles,
                    kind: p.kind,
                    missing: p.missing,
                    solid: params.clone(),
                    block_samples: None,
                })
            }
            other => bail!(
                "graph '{}', node '{}': method = {other:?}: expected \"adaptive\" or \"grid\"",
                ctx.graph_name,
                ctx.node_id
            ),
        };
        Ok(MesherNode {
            params,
            adaptive,
            ascii,
            path: ctx.out_dir.join(&p.file),
            file: p.file,
            surface: p.surface,
            sources,
            finals: Default::default(),
            ended: Default::default(),
            live_frames: 0,
            done: false,
            summary: serde_json::Value::Null,
        })
    }

    /// The surface to mesh from the final frames: one input as is, or datum + roughness summed
    /// (the roughness is relative to the same z offset as the datum's frame, so the sum keeps
    /// the datum's offset).
    fn surface_to_mesh(&mut self) -> Result<HeightMap> {
        let mut take = |port: &str| {
            self.finals
                .remove(port)
                .ok_or_else(|| anyhow!("mesher: end of scan without a final '{port}' frame"))
        };
        match self.surface {
            SurfaceChoice::Pooled | SurfaceChoice::Panorama => take("surface"),
            SurfaceChoice::Datum => take("datum"),
            SurfaceChoice::Roughness => take("roughness"),
            SurfaceChoice::DatumPlusRoughness => {
                let mut d = take("datum")?;
                let r = take("roughness")?;
                let (a, b) = (&d.header, &r.header);
                if (a.width, a.height) != (b.width, b.height)
                    || a.pitch_x_um != b.pitch_x_um
                    || a.pitch_y_um != b.pitch_y_um
                    || a.origin_x_um != b.origin_x_um
                    || a.origin_y_um != b.origin_y_um
                    || d.heights.len() != r.heights.len()
                {
                    bail!(
                        "mesher: datum ({} x {} px, pitch {} x {} um, origin {}, {} um) and \
                         roughness ({} x {} px, pitch {} x {} um, origin {}, {} um) are not on \
                         the same grid",
                        a.width,
                        a.height,
                        a.pitch_x_um,
                        a.pitch_y_um,
                        a.origin_x_um,
                        a.origin_y_um,
                        b.width,
                        b.height,
                        b.pitch_x_um,
                        b.pitch_y_um,
                        b.origin_x_um,
                        b.origin_y_um
                    );
                }
                for (z, &r) in d.heights.iter_mut().zip(&r.heights) {
                    *z += r;
                }
                Ok(d)
            }
        }
    }

    fn mesh(&mut self) -> Result<()> {
        let s = self.surface_to_mesh()?;
        let h = s.header;
        let field = HeightFieldRef {
            heights_um: &s.heights,
            width: h.width as usize,
            height: h.height as usize,
            pitch_x_um: h.pitch_x_um,
            pitch_y_um: h.pitch_y_um,
            origin_x_um: h.origin_x_um,
            origin_y_um: h.origin_y_um,
            z_offset_um: h.z_offset_um,
        };
        // The mesh re-sampled on the meshed grid (um relative to the frame's offset): for the
        // grid mesh the samples themselves, for the adaptive one its interpolation. It becomes
        // the "mesh" stage of the model-vs-measurement table (Table 6) in run.json.
        let (solid, adaptive, resampled_um) = match &self.adaptive {
            None => (grid_solid(field, &self.params)?, None, s.heights.clone()),
            Some(p) => {
                let m = mesh_height_field(field, p)?;
                let summary = m.summary();
                (m.mesh, Some(summary), m.resampled_um)
            }
        };
        let resampled_path = self.path.with_file_name(MESH_RESAMPLED);
        let absolute: Vec<f64> = resampled_um
            .iter()
            .map(|&z| f64::from(z) + h.z_offset_um)
            .collect();
        surfstream_io::npy::write_npy_f64(
            &resampled_path,
            &absolute,
            h.height as usize,
            h.width as usize,
        )?;
        let check = check_closed(&solid);
        let label = stl::stl_header(&solid, "surfstream surface");
        let ascii = self.ascii;
        surfstream_core::fsutil::write_atomic(&self.path, |w| {
            if ascii {
                crate::write_stl_ascii(w, &solid, &label)?;
            } else {
                crate::write_stl_binary(w, &solid, &label)?;
            }
            Ok(())
        })?;
        self.summary = json!({
            "file": self.file,
            "resampled": MESH_RESAMPLED,
            "format": if self.ascii { "ascii" } else { "binary" },
            "units": self.params.units.symbol(),
            "offset_um": solid.offset_um,
            "triangles": solid.triangles.len(),
            "top_triangles": solid.top_triangles,
            "vertices": solid.vertices.len(),
            "filled_samples": solid.filled_samples,
            "base_depth_um": solid.base_depth_um,
            "watertight": check.watertight,
            "consistently_oriented": check.consistently_oriented,
            "grid_px": [h.width, h.height],
            "pitch_um": [h.pitch_x_um, h.pitch_y_um],
            "t_acquired_ns": h.t_acquired_ns,
            "t_written_ns": monotonic_ns(),
            "live_frames_skipped": self.live_frames,
            "surface": self.surface.name(),
            "sources": self.sources.iter().map(|(p, f)| (p.clone(), json!(f))).collect::<serde_json::Map<_, _>>(),
        });
        if let (Some(o), Some(serde_json::Value::Object(a))) =
            (self.summary.as_object_mut(), adaptive)
        {
            o.insert("method".into(), json!("adaptive"));
            o.extend(a);
        } else if let Some(o) = self.summary.as_object_mut() {
            o.insert("method".into(), json!("grid"));
        }
        Ok(())
    }
}

/// The mesh re-sampled on the meshed grid, absolute heights (um, f64), beside the STL.
pub const MESH_RESAMPLED: &str = "mesh_resampled.npy";

impl NodeLogic for MesherNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("mesher: input '{port}' must carry frames")
        };
        if f.header.has(flags::END_OF_SCAN) {
            self.ended.insert(port.to_owned());
            if self.surface.ports().iter().all(|p| self.ended.contains(*p)) {
                self.mesh()?;
                self.done = true;
            }
        } else if f.header.has(flags::FINAL) {
            self.finals.insert(port.to_owned(), f.to_owned());
        } else {
            self.live_frames += 1;
        }
        Ok(())
    }

    fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
        Ok(())
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> serde_json::Value {
        let mut r = self.summary.clone();
        if let Some(o) = r.as_object_mut() {
            // Latency trace: lifted into run.json's latency_ms by the launcher.
            o.entry("live_frames_skipped")
                .or_insert(json!(self.live_frames));
        }
        r
    }
}
