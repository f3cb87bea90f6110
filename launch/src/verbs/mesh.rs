//! `surfstream mesh`: error-bounded triangle mesh of one height map, written as STL.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;

#[derive(Args)]
pub struct MeshArgs {
    /// Height-map file.
    pub file: PathBuf,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(_a: MeshArgs) -> Result<()> {
    bail!("mesh: not built yet")
}
