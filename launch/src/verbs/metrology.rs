//! `surfstream inspect | params | convert | compare`: reading instrument files and judging
//! surfaces (ISO 25178 parameters, SIM, SSIM).

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;

#[derive(Args)]
pub struct InspectArgs {
    /// Height-map file.
    pub file: PathBuf,
}

#[derive(Args)]
pub struct ParamsArgs {
    /// Height-map file.
    pub file: PathBuf,
}

#[derive(Args)]
pub struct ConvertArgs {
    pub input: PathBuf,
    pub output: PathBuf,
}

#[derive(Args)]
pub struct CompareArgs {
    pub a: PathBuf,
    pub b: PathBuf,
}

pub fn inspect(_a: InspectArgs) -> Result<()> {
    bail!("inspect: not built yet")
}
pub fn params(_a: ParamsArgs) -> Result<()> {
    bail!("params: not built yet")
}
pub fn convert(_a: ConvertArgs) -> Result<()> {
    bail!("convert: not built yet")
}
pub fn compare(_a: CompareArgs) -> Result<()> {
    bail!("compare: not built yet")
}
