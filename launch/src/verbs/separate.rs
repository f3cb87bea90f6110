//! `surfstream separate`: datum / roughness separation of one height map.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;

#[derive(Args)]
pub struct SeparateArgs {
    /// Height-map file.
    pub file: PathBuf,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(_a: SeparateArgs) -> Result<()> {
    bail!("separate: not built yet")
}
