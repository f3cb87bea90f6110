//! Height-map files: every reader returns a [`Surface`] (f64 heights in micrometres, NaN =
//! not measured, row index grows with y, pitch in micrometres) and every writer takes one.
//!
//! [`read_surface`] picks the reader from the file's extension; [`parse_surface`] reads bytes
//! already in memory (what the fuzz targets call). Rows keep the order in which the file
//! stores them (first stored row = row 0 = smallest y) for every format, so a file read here
//! and written back as .x3p / .npy keeps its orientation, and parameters match surfalize.
//!
//! Readers never panic on input: every size, count and offset from a header is checked against
//! the file, and errors name the file, the field and what was expected.

mod bytes;
pub mod date;
pub mod datx;
pub mod metropro;
pub mod nms;
pub mod opd;
pub mod plu;
pub mod sur;
pub mod vk4;
pub mod x3p;
pub mod xyz;
pub mod zmg;

// Issue 12, group "open": Gwyddion, ISO 25178-71 SDF, TrueMap, Alicona.
pub mod al3d;
pub mod gsf;
pub mod gwy;
pub mod sdf;
pub mod tmd;

// Issue 35, "Formats": FRT MicroProf, MountainsMap documents, Bruker Nanoscope.
pub mod di;
pub mod frt;
pub mod mnt;

use std::collections::BTreeMap;
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
    /// Reader that produced the surface: "npy", "datx", "metropro", "x3p", "sur", "xyz",
    /// "plu", "vk4", "opd", "zmg", "frt", "mnt", ...
    pub format: String,
    /// False when the file carries no lateral calibration (e.g. .npy): pitch is then 1 um
    /// unless the caller supplies one.
    pub pitch_known: bool,
    pub instrument: Option<String>,
    pub serial: Option<String>,
    pub date: Option<String>,
    pub wavelength_um: Option<f64>,
    /// Further format-specific header fields, by name (e.g. MetroPro "phase_res").
    pub extra: BTreeMap<String, String>,
    /// Where the file puts pixel (0, 0), micrometres (x, y), in the instrument's coordinates:
    /// X3P `Axes/CX|CY/Offset`, Gwyddion `.gsf` `XOffset`/`YOffset`, `.gwy` `xoff`/`yoff`.
    /// None where the format or the file stores none. A stitch run's tiles carry their stage
    /// positions here (`stitch DIR` uses them).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stage_position_um: Option<[f64; 2]>,
    /// What the reader accepted but the user should know (a checksum that does not match).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// The labelled regions of an X3P colour mask (x3ptools / FiX3P). Labels, not validity:
    /// every point stays as measured unless [`Surface::exclude_mask_regions`] drops a region.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mask: Option<x3p::ColourMask>,
}

impl Surface {
    pub fn invalid_count(&self) -> usize {
        self.heights_um.iter().filter(|z| z.is_nan()).count()
    }

    /// Drops (sets to NaN, not measured) the points of every colour-mask region named in
    /// `regions` (an annotation, "background" or "#rrggbb"; see [`x3p::ColourMask::find`]) and
    /// returns how many measured points that removed. Nothing to drop is not an error; a name
    /// the mask does not hold, or a file without a colour mask, is.
    pub fn exclude_mask_regions(&mut self, regions: &[String]) -> Result<usize> {
        if regions.is_empty() {
            return Ok(0);
        }
        match &self.metadata.mask {
            Some(mask) => mask.exclude(&mut self.heights_um, regions),
            None => bail!(
                "no colour mask to exclude '{}' from: only X3P files with a mask image \
                 (x3ptools / FiX3P, Record3/Mask) carry labelled regions",
                regions.join("', '")
            ),
        }
    }

    /// The heights as a frame carries them: see [`surfstream_core::frame::to_frame_heights`].
    pub fn to_frame_heights(&self) -> (f64, Vec<f32>) {
        to_frame_heights(&self.heights_um)
    }
}

pub use surfstream_core::frame::{from_frame_heights, to_frame_heights, valid_mean};

/// The height-map formats read here.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Npy,
    Datx,
    MetroPro,
    X3p,
    Sur,
    Xyz,
    // Instrument formats (issue 12): Sensofar, Keyence, Bruker/Wyko, KLA Zeta.
    Plu,
    Vk4,
    Opd,
    Zmg,
    Nms,
    // Issue 12, group "open".
    Gsf,
    Gwy,
    Sdf,
    Tmd,
    Al3d,
    // Issue 35.
    Frt,
    Mnt,
    /// Bruker / Veeco Nanoscope (`.di`, `.spm`).
    Di,
    /// TIFF: ours (float32 um, pitch in the description) or another height TIFF.
    Tif,
}

/// Every extension [`Format::from_path`] accepts (lower case, no dot), for messages that list
/// them: keep in step with its match.
pub const EXTENSIONS: &[&str] = &[
    "npy", "datx", "dat", "x3p", "sur", "xyz", "txt", "csv", "asc", "plu", "vk4", "opd", "zmg",
    "nms", "gsf", "gwy", "sdf", "tmd", "al3d", "frt", "mnt", "di", "spm", "tif", "tiff",
];

impl Format {
    /// The format for a file name's extension (case-insensitive).
    pub fn from_path(path: &Path) -> Result<Format> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .unwrap_or_default();
        Ok(match ext.as_str() {
            "npy" => Format::Npy,
            "datx" => Format::Datx,
            "dat" => Format::MetroPro,
            "x3p" => Format::X3p,
            "sur" => Format::Sur,
            "xyz" | "txt" | "csv" | "asc" => Format::Xyz,
            "plu" => Format::Plu,
            "vk4" => Format::Vk4,
            "opd" => Format::Opd,
            "zmg" => Format::Zmg,
            "nms" => Format::Nms,
            "gsf" => Format::Gsf,
            "gwy" => Format::Gwy,
            "sdf" => Format::Sdf,
            "tmd" => Format::Tmd,
            "al3d" => Format::Al3d,
            "frt" => Format::Frt,
            "mnt" => Format::Mnt,
            "di" | "spm" => Format::Di,
            "tif" | "tiff" => Format::Tif,
            other => bail!(
                "{}: unsupported height-map format '.{other}' (expected .npy, .datx, .dat, .x3p, .sur, .xyz/.txt/.csv/.asc, .plu, .vk4, .opd, .zmg, .nms, .gsf, .gwy, .sdf, .tmd, .al3d, .frt, .mnt, .di/.spm, .tif/.tiff)",
                path.display()
            ),
        })
    }
}

/// True when `path` has an extension [`read_surface`] reads.
pub fn is_surface_file(path: &Path) -> bool {
    Format::from_path(path).is_ok()
}

/// Reads any supported height-map file, chosen by extension (a folder is named as one:
/// [`crate::input::not_a_folder`]).
pub fn read_surface(path: &Path) -> Result<Surface> {
    crate::input::not_a_folder(path, "reading")?;
    let format = Format::from_path(path)?;
    crate::input::check_regular_file(path, "a height-map file")?;
    if format == Format::Npy {
        let s = read_npy_surface(path).map(invalid_if_not_finite)?;
        check_pitch(&s).with_context(|| format!("{}", path.display()))?;
        return Ok(s);
    }
    let data = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    parse_surface(&data, format).with_context(|| format!("{}", path.display()))
}

/// Parses a file image already in memory. `.npy` goes through [`crate::npy`], which reads
/// from a path: use [`read_surface`] for it.
pub fn parse_surface(data: &[u8], format: Format) -> Result<Surface> {
    let s = match format {
        Format::Datx => datx::parse(data)?,
        Format::MetroPro => metropro::parse(data)?,
        Format::X3p => x3p::parse(data)?,
        Format::Sur => sur::parse(data)?,
        Format::Xyz => xyz::parse(data)?,
        Format::Plu => plu::parse(data)?,
        Format::Vk4 => vk4::parse(data)?,
        Format::Opd => opd::parse(data)?,
        Format::Zmg => zmg::parse(data)?,
        Format::Nms => nms::parse(data)?,
        Format::Gsf => gsf::parse(data)?,
        Format::Gwy => gwy::parse(data)?,
        Format::Sdf => sdf::parse(data)?,
        Format::Tmd => tmd::parse(data)?,
        Format::Al3d => al3d::parse(data)?,
        Format::Frt => frt::parse(data)?,
        Format::Mnt => mnt::parse(data)?,
        Format::Di => di::parse(data)?,
        Format::Tif => crate::tiff::parse(data)?,
        Format::Npy => bail!(".npy is read from a path (read_surface)"),
    };
    debug_assert_eq!(s.heights_um.len(), s.width * s.height);
    check_pitch(&s)?;
    Ok(invalid_if_not_finite(s))
}

/// The lateral pitch every reader may return, um: 1 pm .. 1 m (issue 36: an X3P `Increment`
/// of 1e300, a MetroPro `lateral_res` or SUR spacing of 1e30 were read and failed far from
/// the cause).
pub const PITCH_RANGE_UM: (f64, f64) = (1e-6, 1e6);

/// Refuses a pitch outside [`PITCH_RANGE_UM`], naming the axis and the value (the caller adds
/// the file).
fn check_pitch(s: &Surface) -> Result<()> {
    let (lo, hi) = PITCH_RANGE_UM;
    for (field, v) in [("pitch_x_um", s.pitch_x_um), ("pitch_y_um", s.pitch_y_um)] {
        if !(v >= lo && v <= hi) {
            bail!(
                "the file's lateral calibration gives {field} = {v:e}: expected a pitch between {lo:e} um (1 pm) and {hi:e} um (1 m); the file's spacing field is corrupt or in another unit"
            );
        }
    }
    Ok(())
}

/// Every reader's one convention for invalid points: NaN. Some writers store them as +-inf
/// (Alicona's float x3p); left as inf they would poison every parameter.
fn invalid_if_not_finite(mut s: Surface) -> Surface {
    for z in s.heights_um.iter_mut() {
        if !z.is_finite() {
            *z = f64::NAN;
        }
    }
    flag_absurd_heights(&mut s);
    s
}

/// No profiler measures a height beyond +-1 m (1e6 um): such a value is a corrupt point or a
/// wrong unit, and would make an STL kilometres tall. Readers flag it (a warning every verb
/// prints); a scan directory refuses it.
pub const MAX_PLAUSIBLE_HEIGHT_UM: f64 = 1e6;

/// Adds a warning naming how many heights are physically absurd and the largest.
fn flag_absurd_heights(s: &mut Surface) {
    let (mut n, mut worst) = (0usize, 0.0f64);
    for z in s
        .heights_um
        .iter()
        .filter(|z| z.abs() > MAX_PLAUSIBLE_HEIGHT_UM)
    {
        n += 1;
        if z.abs() > worst.abs() {
            worst = *z;
        }
    }
    if n > 0 {
        s.metadata.warnings.push(format!(
            "{n} height(s) beyond +-{MAX_PLAUSIBLE_HEIGHT_UM:e} um (1 m), the largest {worst:.3e} um: \
             physically absurd for a profiler (a corrupt point or a wrong height unit)"
        ));
    }
}

/// Writes `s` by the extension of `path`: `.x3p` (float64, valid.bin for NaN), `.npy`
/// (float64, NaN kept, the pitch in the sidecar `NAME.npy.json`: [`crate::sidecar`]), `.gsf`
/// (Gwyddion simple field, float32) or `.tif`/`.tiff` (float32 TIFF, pitch as resolution).
pub fn write_surface(path: &Path, s: &Surface) -> Result<()> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "x3p" => x3p::write(path, s),
        "npy" => {
            crate::npy::write_npy_f64(path, &s.heights_um, s.height, s.width)?;
            write_npy_geometry(path, s)
        }
        "gsf" => gsf::write(path, s),
        "tif" | "tiff" => crate::tiff::write(path, s),
        other => bail!(
            "{}: cannot write {}; the formats written are {}",
            path.display(),
            if other.is_empty() {
                "a file without extension".to_string()
            } else {
                format!(".{other} files")
            },
            WRITABLE
                .iter()
                .map(|e| format!(".{e}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// The extensions [`write_surface`] writes.
pub const WRITABLE: &[&str] = &["x3p", "npy", "gsf", "tif", "tiff"];

/// The sidecar of a `.npy` surface: the pitch (and stage position) when the surface knows
/// them; an old sidecar removed when it does not.
fn write_npy_geometry(path: &Path, s: &Surface) -> Result<()> {
    if s.metadata.pitch_known {
        crate::sidecar::write_sidecar(
            path,
            &crate::sidecar::NpyGeometry {
                pitch_x_um: s.pitch_x_um,
                pitch_y_um: s.pitch_y_um,
                origin_um: s.metadata.stage_position_um,
            },
        )
    } else {
        crate::sidecar::remove_stale_sidecar(path)
    }
}

/// A 2-D .npy (f32 or f64) as heights in um; the pitch from its sidecar `NAME.npy.json`
/// ([`crate::sidecar`]), else unknown (1 um, `pitch_known` false).
fn read_npy_surface(path: &Path) -> Result<Surface> {
    // npy's errors already name the path.
    let a = crate::npy::read_npy_f64(path)?;
    let geometry = crate::sidecar::read_sidecar(path)?;
    let mut metadata = Metadata {
        format: "npy".into(),
        pitch_known: geometry.is_some(),
        ..Metadata::default()
    };
    if let Some(g) = &geometry {
        metadata.stage_position_um = g.origin_um;
        metadata.extra.insert(
            "pitch_from".into(),
            crate::sidecar::sidecar_path(path)
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
        );
    }
    Ok(Surface {
        width: a.cols,
        height: a.rows,
        pitch_x_um: geometry.map_or(1.0, |g| g.pitch_x_um),
        pitch_y_um: geometry.map_or(1.0, |g| g.pitch_y_um),
        heights_um: a.data,
        metadata,
    })
}

#[cfg(test)]
mod pitch_tests {
    use super::*;

    fn surface(pitch_x_um: f64, pitch_y_um: f64) -> Surface {
        Surface {
            width: 3,
            height: 2,
            pitch_x_um,
            pitch_y_um,
            heights_um: vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
            metadata: Metadata {
                pitch_known: true,
                ..Metadata::default()
            },
        }
    }

    /// A file whose lateral calibration lies (issue 36: an X3P Increment of 1e300 or 1e-300,
    /// a spacing of 1e30) is refused when read, naming the file, the axis and the value; 1 pm
    /// and 1 m themselves are read.
    #[test]
    fn a_pitch_outside_1_pm_to_1_m_is_refused_naming_the_file_and_the_field() {
        let dir = tempfile::tempdir().unwrap();
        for (px, py, field) in [
            (1e300, 1.0, "pitch_x_um = "),
            (1.0, 1e-300, "pitch_y_um = "),
            (1e30, 1e30, "pitch_x_um = "),
        ] {
            for ext in ["x3p", "gsf", "npy"] {
                let path = dir.path().join(format!("lies.{ext}"));
                write_surface(&path, &surface(px, py)).unwrap();
                let e = format!(
                    "{:#}",
                    read_surface(&path).expect_err("a lying pitch was read")
                );
                assert!(
                    e.contains(&format!("lies.{ext}")) && e.contains(field) && e.contains("1 pm"),
                    "{ext} {px} {py}: {e}"
                );
            }
        }
        for pitch in [PITCH_RANGE_UM.0, PITCH_RANGE_UM.1, 0.8148] {
            let path = dir.path().join("fine.x3p");
            write_surface(&path, &surface(pitch, pitch)).unwrap();
            let s = read_surface(&path).unwrap();
            assert!(
                (s.pitch_x_um / pitch - 1.0).abs() < 1e-9,
                "{pitch}: {}",
                s.pitch_x_um
            );
        }
    }
}
