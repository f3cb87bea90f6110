//! A node's result files: one surface becomes `<name>.npy` (the numbers), `<name>.png` (the
//! preview a person looks at) and, when asked, `<name>.x3p` (ISO 25178-72, for metrology
//! tools), each written atomically (through [`surfstream_core::fsutil::write_atomic`]) so a
//! crash never leaves a half-written file.
//!
//! Heights arrive as frames carry them: f32 relative to an f64 `z_offset_um` (DESIGN §2). A
//! surface with an absolute position (panorama, datum, pooled map) is written as absolute
//! heights: float32 when the frame carries no offset (its f32 heights are then the absolute
//! heights exactly: half the bytes, nothing lost), float64 when it does, so the file loses
//! neither the offset nor the f32's precision near zero ([`crate::npy::absolute_fits_f32`]).
//! A surface that is relative by nature (roughness) stays f32 as computed.
//!
//! Every `.npy` surface gets its pitch sidecar `<name>.npy.json` ([`crate::sidecar`]) once the
//! writer knows the pitch ([`OutputWriter::set_geometry`]), so `params`, `separate` or `mesh`
//! on a run's output runs at the right pitch.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use surfstream_core::frame::from_frame_heights;
use surfstream_core::raster::RasterView;

use crate::formats::{Metadata, Surface};
use crate::npy::{write_npy_abs, write_npy_f32, write_npy_f64, NpyRowWriter};
use crate::preview::{write_preview_png, PreviewBuilder, PreviewOptions};
use crate::sidecar::{remove_stale_sidecar, write_sidecar, NpyGeometry};

/// How a surface's numbers go into its `.npy`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NpyHeights {
    /// Absolute heights, the frame heights plus `z_offset_um`: float32 when the offset is 0
    /// (exact), else float64 ([`crate::npy::write_npy_abs`]).
    Absolute,
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
    geometry: Option<NpyGeometry>,
}

impl OutputWriter {
    /// A writer into `dir` (which must exist).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self {
            dir: dir.into(),
            files: Vec::new(),
            geometry: None,
        }
    }

    /// The pitch (and origin) of the surfaces written from now on: each `.npy` surface gets
    /// its sidecar `<name>.npy.json`. None: no sidecar (an old one of that name is removed).
    pub fn set_geometry(&mut self, geometry: Option<NpyGeometry>) {
        self.geometry = geometry;
    }

    /// [`OutputWriter::set_geometry`] with a pitch and no origin.
    pub fn set_pitch_um(&mut self, pitch_x_um: f64, pitch_y_um: f64) {
        self.geometry = Some(NpyGeometry {
            pitch_x_um,
            pitch_y_um,
            origin_um: None,
        });
    }

    /// The sidecar of `npy` (a file name in the directory) for the current geometry.
    fn write_geometry(&self, npy: &str) -> Result<()> {
        let path = self.dir.join(npy);
        match &self.geometry {
            Some(g) => write_sidecar(&path, g),
            None => remove_stale_sidecar(&path),
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
            NpyHeights::Absolute => {
                write_npy_abs(self.dir.join(&npy), values, rows, cols, s.z_offset_um)?
            }
            NpyHeights::RelativeF32 => write_npy_f32(self.dir.join(&npy), values, rows, cols)?,
        }
        self.write_geometry(&npy)?;
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

/// A surface written row by row ([`OutputWriter::begin_surface`]): its `.npy` and `.png`
/// come out byte-identical to [`OutputWriter::write_surface`]'s for the same heights, without
/// the map ever being whole in memory. Both files appear only at
/// [`OutputWriter::finish_surface`]; dropped before that, nothing is left behind.
#[derive(Debug)]
pub struct SurfaceStream {
    name: String,
    npy: NpyRowWriter,
    npy_heights: NpyHeights,
    z_offset_um: f64,
    preview: PreviewBuilder,
}

impl SurfaceStream {
    /// The next whole rows of frame heights (um relative to the offset, NaN = not measured).
    pub fn push_rows(&mut self, heights: &[f32]) -> Result<()> {
        match self.npy_heights {
            NpyHeights::Absolute => self.npy.push_abs(heights, self.z_offset_um)?,
            NpyHeights::RelativeF32 => self.npy.push_f32(heights)?,
        }
        self.preview.push_rows(heights)
    }
}

impl OutputWriter {
    /// Starts `name.npy` and `name.png` of a `rows x cols` surface whose rows arrive in order
    /// ([`SurfaceStream::push_rows`]); [`OutputWriter::finish_surface`] completes them.
    pub fn begin_surface(
        &self,
        name: &str,
        rows: usize,
        cols: usize,
        z_offset_um: f64,
        npy: NpyHeights,
        title: &str,
    ) -> Result<SurfaceStream> {
        check_name(name)?;
        let path = self.dir.join(format!("{name}.npy"));
        let writer = match npy {
            NpyHeights::Absolute => NpyRowWriter::create_abs(path, rows, cols, z_offset_um)?,
            NpyHeights::RelativeF32 => NpyRowWriter::create_f32(path, rows, cols)?,
        };
        let opts = PreviewOptions {
            title: Some(title.to_string()),
            ..Default::default()
        };
        Ok(SurfaceStream {
            name: name.to_string(),
            npy: writer,
            npy_heights: npy,
            z_offset_um,
            preview: PreviewBuilder::new(rows, cols, &opts)?,
        })
    }

    /// Completes a streamed surface (every row must have arrived): `name.npy`, then
    /// `name.png`, recorded in [`OutputWriter::files`] as [`OutputWriter::write_surface`] does.
    pub fn finish_surface(&mut self, s: SurfaceStream) -> Result<()> {
        let SurfaceStream {
            name, npy, preview, ..
        } = s;
        npy.finish()?;
        let npy = format!("{name}.npy");
        self.write_geometry(&npy)?;
        self.files.push(npy);
        let png = format!("{name}.png");
        preview.write_png(self.dir.join(&png))?;
        self.files.push(png);
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
        w.set_pitch_um(0.5, 0.25);
        w.write_surface(&SurfaceOutput {
            name: "datum",
            heights: r.view(),
            z_offset_um: 100.0,
            npy: NpyHeights::Absolute,
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
        // The pitch travels with the .npy: read back through the sidecar.
        let npy = crate::formats::read_surface(&dir.path().join("roughness.npy")).unwrap();
        assert!(npy.metadata.pitch_known);
        assert_eq!((npy.pitch_x_um, npy.pitch_y_um), (0.5, 0.25));
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

    /// The dtype a `.npy` file's header names.
    fn descr(path: &Path) -> String {
        let bytes = std::fs::read(path).unwrap();
        let text = String::from_utf8_lossy(&bytes[..128.min(bytes.len())]).into_owned();
        let at = text.find("'descr': '").unwrap() + "'descr': '".len();
        text[at..at + 3].to_string()
    }

    #[test]
    fn absolute_heights_are_float32_without_an_offset_and_float64_with_one() {
        let dir = tempfile::tempdir().unwrap();
        let h = vec![0.1f32, -7.25e-3, f32::NAN, 1234.567];
        let r = Raster::new(h.clone(), Shape::new(2, 2)).unwrap();
        let mut w = OutputWriter::new(dir.path());
        for (name, z) in [("none", 0.0), ("up", 25_000.125)] {
            w.write_surface(&SurfaceOutput {
                name,
                heights: r.view(),
                z_offset_um: z,
                npy: NpyHeights::Absolute,
                title: "t (um)",
                x3p_pitch_um: None,
            })
            .unwrap();
        }
        assert_eq!(descr(&dir.path().join("none.npy")), "<f4");
        assert_eq!(descr(&dir.path().join("up.npy")), "<f8");
        // Both read back as the absolute heights f64::from(z) + offset, bit for bit.
        for (name, z) in [("none", 0.0), ("up", 25_000.125)] {
            let back = crate::npy::read_npy_f64(dir.path().join(format!("{name}.npy"))).unwrap();
            for (b, &v) in back.data.iter().zip(&h) {
                let want = f64::from(v) + z;
                assert!(b.to_bits() == want.to_bits() || (b.is_nan() && want.is_nan()));
            }
        }
    }

    #[test]
    fn streamed_surfaces_equal_whole_ones() {
        let dir = tempfile::tempdir().unwrap();
        let (whole_dir, rows_dir) = (dir.path().join("whole"), dir.path().join("rows"));
        std::fs::create_dir_all(&whole_dir).unwrap();
        std::fs::create_dir_all(&rows_dir).unwrap();
        let (rows, cols) = (301, 1290);
        let h: Vec<f32> = (0..rows * cols)
            .map(|i| {
                if i % 89 == 0 {
                    f32::NAN
                } else {
                    (i % 1000) as f32 * 0.01 - 3.0
                }
            })
            .collect();
        let r = Raster::new(h.clone(), Shape::new(rows, cols)).unwrap();
        let mut whole = OutputWriter::new(&whole_dir);
        let mut streamed = OutputWriter::new(&rows_dir);
        for (name, npy, z) in [
            ("datum", NpyHeights::Absolute, 250.5),
            ("datum0", NpyHeights::Absolute, 0.0),
            ("roughness", NpyHeights::RelativeF32, 250.5),
        ] {
            whole
                .write_surface(&SurfaceOutput {
                    name,
                    heights: r.view(),
                    z_offset_um: z,
                    npy,
                    title: "t (um)",
                    x3p_pitch_um: None,
                })
                .unwrap();
            let mut s = streamed
                .begin_surface(name, rows, cols, z, npy, "t (um)")
                .unwrap();
            for band in h.chunks(17 * cols) {
                s.push_rows(band).unwrap();
            }
            assert!(!rows_dir.join(format!("{name}.npy")).exists());
            streamed.finish_surface(s).unwrap();
        }
        assert_eq!(whole.files(), streamed.files());
        assert_eq!(descr(&rows_dir.join("datum0.npy")), "<f4");
        assert_eq!(descr(&rows_dir.join("datum.npy")), "<f8");
        for f in whole.files() {
            let a = std::fs::read(whole_dir.join(f)).unwrap();
            let b = std::fs::read(rows_dir.join(f)).unwrap();
            assert!(a == b, "{f} differs");
        }
        // Unfinished or short: nothing is written.
        let mut s = streamed
            .begin_surface("cut", rows, cols, 0.0, NpyHeights::RelativeF32, "")
            .unwrap();
        s.push_rows(&h[..cols]).unwrap();
        assert!(streamed.finish_surface(s).is_err());
        let s = streamed
            .begin_surface("dropped", rows, cols, 0.0, NpyHeights::RelativeF32, "")
            .unwrap();
        drop(s);
        let left: Vec<_> = std::fs::read_dir(&rows_dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("cut") || n.starts_with("dropped"))
            .collect();
        assert!(left.is_empty(), "{left:?}");
        assert!(streamed
            .begin_surface("a/b", 2, 2, 0.0, NpyHeights::RelativeF32, "")
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
