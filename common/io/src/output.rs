//! A node's result files: one surface becomes `<name>.npy` (the numbers), `<name>.png` (the
//! preview a person looks at) and, when asked, `<name>.x3p` (ISO 25178-72, for metrology
//! tools), each written atomically (through [`surfstream_core::fsutil::write_atomic`]) so a
//! crash never leaves a half-written file.
//!
//! Heights arrive as frames carry them: f32 relative to an f64 `z_offset_um` (DESIGN §2). A
//! surface with an absolute position (panorama, datum, pooled map) is written as absolute f64
//! so the file loses neither the offset nor the f32's precision near zero; a surface that is
//! relative by nature (roughness) stays f32 as computed.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use surfstream_core::frame::from_frame_heights;
use surfstream_core::raster::RasterView;

use crate::formats::{Metadata, Surface};
use crate::npy::{write_npy_abs_f64, write_npy_f32, write_npy_f64};
use crate::preview::{write_preview_png, PreviewOptions};

/// How a surface's numbers go into its `.npy`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NpyHeights {
    /// float64, the frame heights plus `z_offset_um`: absolute heights.
    AbsoluteF64,
    /// float32, the frame heights as they are (relative; the offset is not added).
    RelativeF32,
}

/// One surface to write: frame heights (um relative to `z_offset_um`, NaN = not measured).
#[derive(Debug, Clone, Copy)]
pub struct SurfaceOutput<'a> {
    /// File stem: `name.npy`, `name.png`, `name.x3p`.
    pub name: &'a str,
    pub heights: RasterView<'a, f32>,
    pub z_offset_um: f64,
    pub npy: NpyHeights,
    /// Title drawn on the preview.
    pub title: &'a str,
    /// Also write `name.x3p` (absolute f64 heights) at this pitch (x, y) in um.
    pub x3p_pitch_um: Option<(f64, f64)>,
}

/// Writes surfaces into one directory and remembers which files it wrote, in order.
#[derive(Debug, Clone)]
pub struct OutputWriter {
    dir: PathBuf,
    files: Vec<String>,
}

impl OutputWriter {
    /// A writer into `dir` (which must exist).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self {
            dir: dir.into(),
            files: Vec::new(),
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The file names written so far (relative to [`OutputWriter::dir`]), in order.
    pub fn files(&self) -> &[String] {
        &self.files
    }

    /// Writes `name.npy`, `name.png` and, when asked, `name.x3p`.
    pub fn write_surface(&mut self, s: &SurfaceOutput<'_>) -> Result<()> {
        check_name(s.name)?;
        let (rows, cols) = (s.heights.rows(), s.heights.cols());
        let values = s.heights.values();
        let npy = format!("{}.npy", s.name);
        match s.npy {
            NpyHeights::AbsoluteF64 => {
                write_npy_abs_f64(self.dir.join(&npy), values, rows, cols, s.z_offset_um)?
            }
            NpyHeights::RelativeF32 => write_npy_f32(self.dir.join(&npy), values, rows, cols)?,
        }
        self.files.push(npy);
        let png = format!("{}.png", s.name);
        let opts = PreviewOptions {
            title: Some(s.title.to_string()),
            ..Default::default()
        };
        write_preview_png(self.dir.join(&png), values, rows, cols, &opts)?;
        self.files.push(png);
        if let Some((pitch_x_um, pitch_y_um)) = s.x3p_pitch_um {
            let x3p = format!("{}.x3p", s.name);
            let surface = Surface {
                width: cols,
                height: rows,
                pitch_x_um,
                pitch_y_um,
                heights_um: from_frame_heights(s.z_offset_um, values),
                metadata: Metadata {
                    format: "x3p".into(),
                    pitch_known: true,
                    ..Metadata::default()
                },
            };
            crate::formats::x3p::write(&self.dir.join(&x3p), &surface)?;
            self.files.push(x3p);
        }
        Ok(())
    }

    /// Writes `name.npy` only: absolute heights (um) already in f64, written as they are (the
    /// mesher's resampled mesh; no preview, it is for comparing numbers).
    pub fn write_npy_f64(&mut self, name: &str, heights: RasterView<'_, f64>) -> Result<()> {
        check_name(name)?;
        let npy = format!("{name}.npy");
        write_npy_f64(
            self.dir.join(&npy),
            heights.values(),
            heights.rows(),
            heights.cols(),
        )?;
        self.files.push(npy);
        Ok(())
    }
}

/// A file stem stays inside the writer's directory.
fn check_name(name: &str) -> Result<()> {
    if name.is_empty() || name.contains(['/', '\\']) {
        bail!("output name {name:?}: expected a plain file stem");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::raster::{Raster, Shape};

    #[test]
    fn writes_absolute_f64_relative_f32_preview_and_x3p() {
        let dir = tempfile::tempdir().unwrap();
        let r = Raster::new(
            vec![0.5f32, -0.25, f32::NAN, 1.0, 2.0, 3.0],
            Shape::new(2, 3),
        )
        .unwrap();
        let mut w = OutputWriter::new(dir.path());
        w.write_surface(&SurfaceOutput {
            name: "datum",
            heights: r.view(),
            z_offset_um: 100.0,
            npy: NpyHeights::AbsoluteF64,
            title: "datum (um)",
            x3p_pitch_um: Some((0.5, 0.5)),
        })
        .unwrap();
        w.write_surface(&SurfaceOutput {
            name: "roughness",
            heights: r.view(),
            z_offset_um: 100.0,
            npy: NpyHeights::RelativeF32,
            title: "roughness (um)",
            x3p_pitch_um: None,
        })
        .unwrap();
        assert_eq!(
            w.files(),
            [
                "datum.npy",
                "datum.png",
                "datum.x3p",
                "roughness.npy",
                "roughness.png"
            ]
        );
        let abs = crate::npy::read_npy_f64(dir.path().join("datum.npy")).unwrap();
        assert_eq!((abs.rows, abs.cols), (2, 3));
        assert_eq!(abs.data[0], 100.5);
        assert!(abs.data[2].is_nan());
        let rel = crate::npy::read_npy(dir.path().join("roughness.npy")).unwrap();
        assert_eq!(rel.data[..2], [0.5f32, -0.25]);
        assert!(rel.data[2].is_nan());
        let x3p = crate::formats::read_surface(&dir.path().join("datum.x3p")).unwrap();
        assert_eq!((x3p.height, x3p.width), (2, 3));
        assert_eq!(x3p.heights_um[5], 103.0);
        assert!(dir.path().join("datum.png").exists());
        assert!(w
            .write_surface(&SurfaceOutput {
                name: "../x",
                ..SurfaceOutput {
                    name: "x",
                    heights: r.view(),
                    z_offset_um: 0.0,
                    npy: NpyHeights::RelativeF32,
                    title: "",
                    x3p_pitch_um: None,
                }
            })
            .is_err());
    }

    #[test]
    fn writes_f64_npy_as_given() {
        let dir = tempfile::tempdir().unwrap();
        let r = Raster::new(vec![50.125f64, f64::NAN, -1e-9, 3.0], Shape::new(2, 2)).unwrap();
        let mut w = OutputWriter::new(dir.path());
        w.write_npy_f64("mesh_resampled", r.view()).unwrap();
        assert_eq!(w.files(), ["mesh_resampled.npy"]);
        let back = crate::npy::read_npy_f64(dir.path().join("mesh_resampled.npy")).unwrap();
        assert_eq!((back.rows, back.cols), (2, 2));
        assert_eq!(back.data[0].to_bits(), 50.125f64.to_bits());
        assert!(back.data[1].is_nan());
        assert_eq!(back.data[2], -1e-9);
        assert!(w.write_npy_f64("a/b", r.view()).is_err());
    }
}
