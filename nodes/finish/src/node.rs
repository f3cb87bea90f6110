//! The finish node: once the wired surface (and datum, when wired) have ended their scan, runs
//! the finishing simulation on the final surface into `<out_dir>/<dir>` (default `finish/`).

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::AtomicBool;

use anyhow::{anyhow, bail, Result};
use surfstream_core::frame::{flags, HeightMap};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

pub use crate::config::FinishConfig;
use crate::process::finish_record;
use crate::run::{FinishOptions, Model};
use surfstream_core::record::finish::FinishReport;

pub struct FinishNode {
    config: FinishConfig,
    options: FinishOptions,
    out_dir: std::path::PathBuf,
    wired: BTreeSet<String>,
    ended: BTreeSet<String>,
    finals: BTreeMap<String, HeightMap>,
    done: bool,
    /// Null in run.json until the simulation has run.
    report: Option<FinishReport>,
}

/// The node's parameters checked as [`build`] checks them (building starts no engine).
pub fn check(ctx: &NodeContext) -> Result<()> {
    FinishNode::new(ctx).map(drop)
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    Ok(Box::new(FinishNode::new(ctx)?))
}

impl FinishNode {
    pub fn new(ctx: &NodeContext) -> Result<Self> {
        let config: FinishConfig = ctx.params()?;
        let options = config
            .options()
            .map_err(|e| anyhow!("graph '{}', node '{}': {e}", ctx.graph_name, ctx.node_id))?;
        Ok(FinishNode {
            out_dir: ctx.out_dir.join(&config.dir),
            config,
            options,
            wired: ctx.inputs.iter().map(|i| i.port.clone()).collect(),
            ended: BTreeSet::new(),
            finals: BTreeMap::new(),
            done: false,
            report: None,
        })
    }

    fn model(&mut self, port: &str) -> Result<Option<Model>> {
        let Some(f) = self.finals.remove(port) else {
            return Ok(None);
        };
        let h = &f.header;
        Ok(Some(Model {
            heights_um: f
                .heights
                .iter()
                .map(|&z| f64::from(z) + h.z_offset_um)
                .collect(),
            rows: h.height as usize,
            cols: h.width as usize,
            pitch_x_um: h.pitch_x_um,
            pitch_y_um: h.pitch_y_um,
            source: format!("graph input '{port}'"),
        }))
    }

    fn run(&mut self) -> Result<()> {
        let model = self
            .model("surface")?
            .ok_or_else(|| anyhow!("finish: end of scan without a final 'surface' frame"))?;
        let mut options = self.options.clone();
        options.ideal = self.model("datum")?;
        let stop = AtomicBool::new(false);
        let summary = finish_record(&model, &options, &self.out_dir, &stop, &mut |l| {
            eprintln!("{l}")
        })?;
        self.report = Some(FinishReport::of(summary, &self.config.dir));
        Ok(())
    }
}

impl NodeLogic for FinishNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("finish: input '{port}' must carry frames")
        };
        if f.header.has(flags::END_OF_SCAN) {
            self.ended.insert(port.to_owned());
            if !self.done && self.wired.iter().all(|p| self.ended.contains(p)) {
                self.run()?;
                self.done = true;
            }
        } else if f.header.has(flags::FINAL) {
            self.finals.insert(port.to_owned(), f.to_owned());
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
        Ok(surfstream_core::record::to_value(&self.report)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::Calibration;

    #[test]
    fn graph_parameters_become_options_and_typos_are_refused() {
        let t: toml::Table = toml::from_str(
            "time_budget_s = 60\ncycles = 2\npatch_um = [200]\ncalibrate_sa_um = [1.272, 0.565]",
        )
        .unwrap();
        let c: FinishConfig = surfstream_runtime::graph::params_from_table(&t).unwrap();
        let o = c.options().unwrap();
        assert_eq!(o.patch_um, Some((200.0, 200.0)));
        assert_eq!(o.cycles, 2);
        assert!(matches!(o.calibrate, Some(Calibration::Sa { .. })));
        let bad: toml::Table = toml::from_str("cycle = 2").unwrap();
        assert!(surfstream_runtime::graph::params_from_table::<FinishConfig>(&bad).is_err());
        let t: toml::Table = toml::from_str("patch_um = [1, 2, 3]").unwrap();
        let c: FinishConfig = surfstream_runtime::graph::params_from_table(&t).unwrap();
        assert!(c.options().is_err());
    }
}
