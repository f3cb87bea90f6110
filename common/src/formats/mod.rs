//! Height-map files: every reader returns a [`Surface`] (f64 heights in micrometres, NaN =
//! not measured, row index grows with y, pitch in micrometres) and every writer takes one.
//!
//! [`read_surface`] picks the reader from the file's extension.

use std::path::Path;

use anyhow::{bail, Context, Result};

/// A height map as read from a file.
#[derive(Debug, Clone, PartialEq)]
pub struct Surface {
    /// Columns (x).
    pub width: usize,
    /// Rows (y).
    pub height: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    /// Row-major, `width * height`, micrometres, NaN = not measured; row index grows with y.
    pub heights_um: Vec<f64>,
    pub metadata: Metadata,
}

/// What the file says about where the data came from (kept where the format has it).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Metadata {
    /// Reader that produced the surface: "npy", "datx", "metropro", "x3p", "sur", "xyz".
    pub format: String,
    /// False when the file carries no lateral calibration (e.g. .npy): pitch is then 1 um
    /// unless the caller supplies one.
    pub pitch_known: bool,
    pub instrument: Option<String>,
    pub serial: Option<String>,
    pub date: Option<String>,
    pub wavelength_um: Option<f64>,
}

impl Surface {
    pub fn invalid_count(&self) -> usize {
        self.heights_um.iter().filter(|z| z.is_nan()).count()
    }
}

/// Reads any supported height-map file, chosen by extension.
pub fn read_surface(path: &Path) -> Result<Surface> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "npy" => read_npy_surface(path),
        other => bail!(
            "{}: unsupported height-map format '.{other}' (expected .npy)",
            path.display()
        ),
    }
}

/// A 2-D .npy (f32 or f64) as heights in um; pitch unknown (1 um).
fn read_npy_surface(path: &Path) -> Result<Surface> {
    let a = crate::npy::read_npy_f64(path).with_context(|| format!("{}", path.display()))?;
    Ok(Surface {
        width: a.cols,
        height: a.rows,
        pitch_x_um: 1.0,
        pitch_y_um: 1.0,
        heights_um: a.data,
        metadata: Metadata {
            format: "npy".into(),
            ..Metadata::default()
        },
    })
}
