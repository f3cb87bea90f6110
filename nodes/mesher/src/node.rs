//! The mesher node: turns the final surface into an error-bounded STL solid or sheet (or, with
//! `method = "grid"`, the full-grid solid), once every wired input has ended its scan.
//!
//! A shell: the settings, the choice of surface and the meshing are [`crate::job`]; this file
//! checks the wiring against the choice, maps frames to [`MeshJob::accept`], and writes the
//! STL, the resampled mesh and the summary for run.json.

use anyhow::{anyhow, bail, Result};
use surfstream_core::frame::monotonic_ns;
use surfstream_core::record::{self, MeshReport, PANORAMA_TILES};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::config::MesherConfig;
use crate::job::MeshJob;

pub use crate::config::SurfaceChoice;

/// The mesh re-sampled on the meshed grid, absolute heights (um, f64), beside the STL.
pub const MESH_RESAMPLED: &str = "mesh_resampled.npy";

pub struct MesherNode {
    job: MeshJob,
    path: std::path::PathBuf,
    file: String,
    /// Where each input comes from ("node/port"), for run.json.
    sources: Vec<(String, String)>,
    done: bool,
    /// The report once the mesh is written.
    summary: Option<MeshReport>,
}

/// The node's parameters and wiring checked as [`build`] checks them (nothing is read or
/// written either way).
pub fn check(ctx: &NodeContext) -> Result<()> {
    MesherNode::new(ctx).map(drop)
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    Ok(Box::new(MesherNode::new(ctx)?))
}

impl MesherNode {
    /// The node's logic from its graph context (parameters and wiring checked here).
    pub fn new(ctx: &NodeContext) -> Result<Self> {
        let in_graph =
            |e: String| anyhow!("graph '{}', node '{}': {e}", ctx.graph_name, ctx.node_id);
        let config: MesherConfig = ctx.params()?;
        let wired: Vec<&str> = ctx.inputs.iter().map(|i| i.port.as_str()).collect();
        config.surface.check_wiring(&wired).map_err(in_graph)?;
        let settings = config.settings().map_err(in_graph)?;
        let sources = ctx
            .inputs
            .iter()
            .map(|i| (i.port.clone(), format!("{}/{}", i.from_node, i.from_port)))
            .collect();
        // Table 6's tile regions, from the fusion's tile placements in the out dir.
        let mut job = MeshJob::new(settings).with_tile_footprints(ctx.out_dir.join(PANORAMA_TILES));
        if wired.contains(&"roughness") && config.surface == SurfaceChoice::Panorama {
            job = job.with_roughness_reference();
        }
        Ok(MesherNode {
            job,
            path: ctx.out_dir.join(&config.file),
            file: config.file,
            sources,
            done: false,
            summary: None,
        })
    }

    fn mesh(&mut self) -> Result<()> {
        // Beside the STL, as before (the STL name may carry a sub-directory).
        let dir = self.path.parent().unwrap_or(std::path::Path::new("."));
        let written = self
            .job
            .mesh_to_files(&self.path, &dir.join(MESH_RESAMPLED))?;
        self.summary = Some(MeshReport {
            file: self.file.clone(),
            resampled: MESH_RESAMPLED.into(),
            sources: self.sources.iter().cloned().collect(),
            t_written_ns: monotonic_ns(),
            live_frames_skipped: self.job.live_frames_skipped(),
            ..written.summary
        });
        Ok(())
    }
}

impl NodeLogic for MesherNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("mesher: input '{port}' must carry frames")
        };
        if self.job.accept(port, f) {
            self.mesh()?;
            self.done = true;
        }
        Ok(())
    }

    fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
        Ok(())
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> anyhow::Result<serde_json::Value> {
        // Null until the mesh is written; its times are lifted into run.json's latency_ms by
        // the launcher.
        Ok(record::to_value(&self.summary)?)
    }
}
