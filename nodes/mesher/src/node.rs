//! The mesher node: turns the final (pooled) surface into an error-bounded STL solid or sheet
//! (or, with `method = "grid"`, the full-grid solid). Live patches are counted and skipped: a
//! mesh is written once, from the exact final surface.

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_common::frame::{flags, monotonic_ns, HeightMap};
use surfstream_common::graph::NodeContext;
use surfstream_common::node::{Input, NodeLogic, Outbox};

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
    final_surface: Option<HeightMap>,
    live_frames: u64,
    done: bool,
    summary: serde_json::Value,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p: Params = ctx.params()?;
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
            })
        }
        other => bail!(
            "graph '{}', node '{}': method = {other:?}: expected \"adaptive\" or \"grid\"",
            ctx.graph_name,
            ctx.node_id
        ),
    };
    Ok(Box::new(MesherNode {
        params,
        adaptive,
        ascii,
        path: ctx.out_dir.join(&p.file),
        file: p.file,
        final_surface: None,
        live_frames: 0,
        done: false,
        summary: serde_json::Value::Null,
    }))
}

impl MesherNode {
    fn mesh(&mut self) -> Result<()> {
        let s = self
            .final_surface
            .take()
            .ok_or_else(|| anyhow!("mesher: end of scan without a final surface"))?;
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
        let (solid, adaptive) = match &self.adaptive {
            None => (grid_solid(field, &self.params)?, None),
            Some(p) => {
                let m = mesh_height_field(field, p)?;
                let summary = m.summary();
                (m.mesh, Some(summary))
            }
        };
        let check = check_closed(&solid);
        let label = stl::stl_header(&solid, "surfstream surface");
        let ascii = self.ascii;
        surfstream_common::fsutil::write_atomic(&self.path, |w| {
            if ascii {
                crate::write_stl_ascii(w, &solid, &label)?;
            } else {
                crate::write_stl_binary(w, &solid, &label)?;
            }
            Ok(())
        })?;
        self.summary = json!({
            "file": self.file,
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

impl NodeLogic for MesherNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("mesher: input '{port}' must carry frames")
        };
        if f.header.has(flags::END_OF_SCAN) {
            self.mesh()?;
            self.done = true;
        } else if f.header.has(flags::FINAL) {
            self.final_surface = Some(f.to_owned());
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
