//! Scan directories (DESIGN §5): `scan.toml` plus one height-map file per field, in
//! acquisition order — the format `bench/make_tiles.py` writes. Tiles may be any format
//! `surfstream_io::formats::read_surface` reads (`surfstream_io::formats::EXTENSIONS`).
//!
//! Pitch: `pitch_x_um` / `pitch_y_um` may be left out of `[scan]` when every tile file carries
//! its own lateral calibration; when both say something they must agree (within 1e-6
//! relative), and all tiles must agree with each other, else it is an error. `height_unit`
//! applies to files without a height unit (.npy, .xyz); instrument files carry theirs, and a
//! `height_unit` other than um beside them is an error.
//!
//! `mask_exclude = ["name", "#rrggbb"]` in `[scan]` drops regions of the tiles' X3P colour
//! masks (x3ptools / FiX3P labels; every point is measured otherwise): see
//! `surfstream_io::formats::x3p::ColourMask`.
//!
//! Everything is validated before the first tile is sent: every error names the manifest or
//! tile file, the field, and what was expected.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use serde::Deserialize;
use surfstream_core::frame::{to_frame_heights_at, valid_mean};
use surfstream_core::{ParamError, Pitch};
use surfstream_io::formats;

/// Pitches agree when within 1e-6 relative (files store f32 calibrations).
fn same_pitch(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-6 * a.abs().max(b.abs())
}

/// `[scan]` as written: pitch and unit optional.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScanSection {
    name: String,
    pitch_x_um: Option<f64>,
    pitch_y_um: Option<f64>,
    height_unit: Option<String>,
    rows: usize,
    cols: usize,
    /// Regions of the tiles' X3P colour masks to drop (annotation, "background" or #rrggbb).
    #[serde(default)]
    mask_exclude: Vec<String>,
    /// The folder of the tile files when it is not the manifest's own (absolute, or relative
    /// to the manifest): `stitch DIR --grid` writes its inferred manifest into OUT and names
    /// DIR here. Tile files must lie inside it.
    tile_dir: Option<String>,
}

/// `[scan]`, resolved: the pitch from the manifest or the tile files.
#[derive(Debug, Clone)]
pub struct ScanSection {
    pub name: String,
    /// The tiles' pitch (their shape is the tiles': [`ScanDirectory::tile_width_px`] x
    /// [`ScanDirectory::tile_height_px`]).
    pub pitch: Pitch,
    /// Height unit of files without one (.npy, .xyz); "um" when not given.
    pub height_unit: String,
    pub rows: usize,
    pub cols: usize,
    /// `mask_exclude = ["name", "#rrggbb"]`: regions of the tiles' X3P colour masks whose
    /// points are read as not measured (x3ptools / FiX3P labels; by default every point is
    /// measured). Each name must be a region of at least one tile's mask.
    pub mask_exclude: Vec<String>,
}

/// `[scan]` while the tiles are read: a pitch the manifest leaves out is NaN until a tile
/// file gives it.
struct ScanFields {
    name: String,
    pitch_x_um: f64,
    pitch_y_um: f64,
    height_unit: String,
    rows: usize,
    cols: usize,
    mask_exclude: Vec<String>,
}

impl ScanFields {
    /// The section with its pitch checked by [`Pitch::new`].
    fn resolved(self) -> Result<ScanSection, ParamError> {
        Ok(ScanSection {
            pitch: Pitch::new(self.pitch_x_um, self.pitch_y_um)?,
            name: self.name,
            height_unit: self.height_unit,
            rows: self.rows,
            cols: self.cols,
            mask_exclude: self.mask_exclude,
        })
    }
}

/// One `[[tile]]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TileEntry {
    pub file: String,
    pub row: usize,
    pub col: usize,
    /// Nominal stage position of the tile's pixel (0, 0), um.
    pub stage_x_um: f64,
    pub stage_y_um: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct ManifestFile {
    scan: RawScanSection,
    #[serde(default)]
    tile: Vec<TileEntry>,
}

/// A loaded scan: the manifest and every tile's heights (um), checked.
#[derive(Debug, Clone)]
pub struct ScanDirectory {
    pub manifest_path: PathBuf,
    pub scan: ScanSection,
    pub tiles: Vec<LoadedTile>,
    /// One height offset for the whole scan (um, f64): the mean of the first tile's valid
    /// heights. Tiles hold f32 heights relative to it (DESIGN §2), so a part sitting tens of
    /// micrometres (or millimetres) up the z axis keeps the reader's f64 precision, and every
    /// tile shares the offset, so overlaps compare without conversion.
    pub z_offset_um: f64,
    pub tile_width_px: usize,
    pub tile_height_px: usize,
}

/// One field of the scan.
#[derive(Debug, Clone)]
pub struct LoadedTile {
    pub entry: TileEntry,
    /// Heights in um relative to [`ScanDirectory::z_offset_um`]; NaN = not measured.
    pub heights_um: Vec<f32>,
}

/// The sampling an optical profiler can have: below 10 nm or above 100 um (per pixel) a value
/// is a unit mistake, not a measurement.
pub const MIN_PITCH_UM: f64 = 0.001;
pub const MAX_PITCH_UM: f64 = 1000.0;

/// The tile extensions the readers take, from `formats::EXTENSIONS` so the message cannot go
/// stale: ".npy, .datx, ... or .al3d".
fn supported_extensions() -> String {
    let dotted: Vec<String> = formats::EXTENSIONS
        .iter()
        .map(|e| format!(".{e}"))
        .collect();
    match dotted.split_last() {
        Some((last, [])) => last.clone(),
        Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
        None => String::new(),
    }
}

/// The height units `[scan] height_unit` (and `stitch --height-unit`) accept.
pub const HEIGHT_UNITS: &str = "um, nm, mm, m";

/// Heights in the manifest's unit -> um ([`HEIGHT_UNITS`]); `None` for another unit.
pub fn unit_scale(unit: &str) -> Option<f64> {
    Some(match unit {
        "um" | "µm" => 1.0,
        "nm" => 1e-3,
        "mm" => 1e3,
        "m" => 1e6,
        _ => return None,
    })
}

/// `[scan] mask_exclude` over a scan's tiles: each tile drops the named regions its own mask
/// holds; a name that no tile's mask holds is an error naming the regions there are.
struct MaskExclusion<'a> {
    names: &'a [String],
    matched: Vec<bool>,
    /// The regions seen, "'label' #rrggbb", for the error.
    known: std::collections::BTreeSet<String>,
    dropped: usize,
}

impl<'a> MaskExclusion<'a> {
    fn new(names: &'a [String]) -> Self {
        MaskExclusion {
            names,
            matched: vec![false; names.len()],
            known: Default::default(),
            dropped: 0,
        }
    }

    fn apply(&mut self, surface: &mut formats::Surface) -> Result<()> {
        let Some(mask) = surface
            .metadata
            .mask
            .as_ref()
            .filter(|_| !self.names.is_empty())
        else {
            return Ok(());
        };
        let mut here = Vec::new();
        for (k, name) in self.names.iter().enumerate() {
            if !mask.find(name).is_empty() {
                self.matched[k] = true;
                here.push(name.clone());
            }
        }
        for r in &mask.regions {
            self.known.insert(format!("'{}' {}", r.label(), r.colour));
        }
        self.dropped += surface.exclude_mask_regions(&here)?;
        Ok(())
    }

    fn finish(self) -> Result<()> {
        let unknown: Vec<&str> = self
            .names
            .iter()
            .zip(&self.matched)
            .filter(|(_, m)| !**m)
            .map(|(n, _)| n.as_str())
            .collect();
        if unknown.is_empty() {
            if !self.names.is_empty() {
                eprintln!(
                    "scan: mask_exclude {}: {} points dropped (read as not measured)",
                    self.names.join(", "),
                    self.dropped
                );
            }
            return Ok(());
        }
        if self.known.is_empty() {
            bail!(
                "'{}': no tile carries a colour mask (X3P with Record3/Mask, x3ptools / FiX3P)",
                unknown.join("', '")
            );
        }
        bail!(
            "'{}' is not a region of any tile's colour mask; the regions are {} (name one by its \
             annotation, 'background', or its colour #rrggbb)",
            unknown.join("', '"),
            self.known.iter().cloned().collect::<Vec<_>>().join(", ")
        )
    }
}

/// The manifest, read and checked before any tile is: `[scan]` (a pitch it leaves out is NaN
/// until a tile file gives it), the height unit's scale, and the `[[tile]]` entries (grid
/// size, count, one file per field).
struct Manifest {
    path: PathBuf,
    scan: ScanFields,
    /// Heights in the manifest's `height_unit` times this are um.
    scale: f64,
    unit_given: bool,
    tile_dir: Option<String>,
    tiles: Vec<TileEntry>,
}

fn read_manifest(path: &Path) -> Result<Manifest> {
    let manifest_path = if path.is_dir() {
        path.join("scan.toml")
    } else {
        path.to_path_buf()
    };
    let m = manifest_path.display();
    surfstream_io::input::check_regular_file(&manifest_path, "a scan.toml or its directory")?;
    let text = std::fs::read_to_string(&manifest_path)
        .with_context(|| format!("{m}: cannot read scan manifest"))?;
    let file: ManifestFile =
        toml::from_str(&text).map_err(|e| anyhow!("{m}: not a valid scan manifest: {e}"))?;
    let raw = file.scan;
    for (field, v) in [
        ("pitch_x_um", raw.pitch_x_um),
        ("pitch_y_um", raw.pitch_y_um),
    ] {
        if let Some(v) = v {
            if !(v.is_finite() && v > 0.0) {
                bail!("{m}: [scan] {field} = {v}: expected a positive pitch in micrometres");
            }
            if !(MIN_PITCH_UM..=MAX_PITCH_UM).contains(&v) {
                bail!(
                    "{m}: [scan] {field} = {v}: expected a pitch between {MIN_PITCH_UM} and \
                     {MAX_PITCH_UM} um (an optical profiler's field is sampled at 0.01-100 um)"
                );
            }
        }
    }
    let unit_given = raw.height_unit.is_some();
    let tile_dir = raw.tile_dir;
    let scan = ScanFields {
        name: raw.name,
        pitch_x_um: raw.pitch_x_um.unwrap_or(f64::NAN),
        pitch_y_um: raw.pitch_y_um.unwrap_or(f64::NAN),
        height_unit: raw.height_unit.unwrap_or_else(|| "um".into()),
        rows: raw.rows,
        cols: raw.cols,
        mask_exclude: raw.mask_exclude,
    };
    let scale = unit_scale(&scan.height_unit).ok_or_else(|| {
        anyhow!(
            "{m}: [scan] height_unit = {:?}: expected one of {HEIGHT_UNITS}",
            scan.height_unit
        )
    })?;
    if scan.rows == 0 || scan.cols == 0 {
        bail!(
            "{m}: [scan] rows = {}, cols = {}: expected at least 1 each",
            scan.rows,
            scan.cols
        );
    }
    if file.tile.is_empty() {
        bail!("{m}: no [[tile]] entries: expected one per field, in acquisition order");
    }
    // Checked: rows = cols = 2^32 overflowed to "expected at most 0".
    let cells = scan
        .rows
        .checked_mul(scan.cols)
        .filter(|&n| n <= crate::stage::MAX_TILES)
        .ok_or_else(|| {
            anyhow!(
                "{m}: [scan] rows = {}, cols = {}: expected rows * cols <= {}",
                scan.rows,
                scan.cols,
                crate::stage::MAX_TILES
            )
        })?;
    if file.tile.len() > cells {
        bail!(
            "{m}: {} [[tile]] entries for a {} x {} (rows x cols) scan: expected at most {cells}",
            file.tile.len(),
            scan.rows,
            scan.cols,
        );
    }
    if file.tile.len() < cells {
        // Not silent: a field missing from a grid leaves a hole in the panorama.
        let listed: std::collections::BTreeSet<(usize, usize)> =
            file.tile.iter().map(|t| (t.row, t.col)).collect();
        let missing: Vec<String> = (0..scan.rows)
            .flat_map(|r| (0..scan.cols).map(move |c| (r, c)))
            .filter(|rc| !listed.contains(rc))
            .take(8)
            .map(|(r, c)| format!("row {r} col {c}"))
            .collect();
        eprintln!(
            "stitch: warning: {m}: {} [[tile]] entries for a {} x {} (rows x cols) grid: {} field(s) have no tile ({}{}); the panorama has holes there",
            file.tile.len(),
            scan.rows,
            scan.cols,
            cells - file.tile.len(),
            missing.join(", "),
            if cells - file.tile.len() > missing.len() { ", ..." } else { "" }
        );
    }
    // One field measured once: the same file at two grid positions would be placed twice.
    let mut files = std::collections::BTreeMap::new();
    for (k, t) in file.tile.iter().enumerate() {
        if let Some(first) = files.insert(t.file.as_str(), k) {
            bail!(
                "{m}: [[tile]] #{} and #{} both name file {:?}: each field is one file",
                first + 1,
                k + 1,
                t.file
            );
        }
    }
    Ok(Manifest {
        path: manifest_path,
        scan,
        scale,
        unit_given,
        tile_dir,
        tiles: file.tile,
    })
}

/// The tile's file, checked before it is read: it exists, is a regular file inside the scan
/// directory `dir` (`dir_real` resolved) and of a format the readers know. Returns the path as
/// the manifest names it and the resolved one.
fn checked_tile_file(
    at: &str,
    dir: &Path,
    dir_real: &Path,
    t: &TileEntry,
) -> Result<(PathBuf, PathBuf)> {
    let tile_path = dir.join(&t.file);
    if !tile_path.exists() {
        bail!("{at}: {}: no such tile file", tile_path.display());
    }
    // A manifest reads its own folder only: `../` or an absolute path elsewhere would
    // read (and copy into the outputs) any file the user can read.
    let real = tile_path
        .canonicalize()
        .with_context(|| format!("{at}: cannot resolve {}", tile_path.display()))?;
    // A FIFO or a device would block the reader forever (a hang, not an error).
    surfstream_io::input::check_regular_file(&real, "a height-map file")
        .with_context(|| format!("{at}: {}", tile_path.display()))?;
    if !real.starts_with(dir_real) {
        bail!(
            "{at}: file = {:?} resolves to {}, outside the scan directory {}: tile files must be inside it",
            t.file,
            real.display(),
            dir_real.display()
        );
    }
    if !formats::is_surface_file(&tile_path) {
        bail!(
            "{at}: unsupported tile format: expected {}",
            supported_extensions()
        );
    }
    Ok((tile_path, real))
}

/// A tile whose every height is NaN (not measured): nothing to register or place, and the
/// first tile's mean would be the scan's NaN height offset. Named, never placed (issue 36).
fn refuse_unmeasured_tile(heights_um: &[f64], at: &str, masked: bool) -> Result<()> {
    if heights_um.iter().all(|z| z.is_nan()) {
        bail!(
            "{at}: every one of its {} heights is NaN (not measured{}): expected a tile with measured points",
            heights_um.len(),
            if masked {
                ", after [scan] mask_exclude"
            } else {
                ""
            }
        );
    }
    Ok(())
}

/// A tile file that carries its own lateral calibration and height unit: its pitch must agree
/// with the manifest's and with the first such tile's (`file_pitch`, set here).
fn check_file_calibration(
    at: &str,
    manifest: &str,
    surface: &formats::Surface,
    scan: &ScanFields,
    (unit_given, scale): (bool, f64),
    file_pitch: &mut Option<(f64, f64, String)>,
    tile_file: &str,
) -> Result<()> {
    let carries_units = surface.metadata.pitch_known;
    if carries_units && unit_given && scale != 1.0 {
        bail!(
            "{at}: [scan] height_unit = {:?}, but a {} file carries its own height unit: leave height_unit out",
            scan.height_unit,
            surface.metadata.format
        );
    }
    if carries_units {
        let (px, py) = (surface.pitch_x_um, surface.pitch_y_um);
        for (field, manifest, file) in [
            ("pitch_x_um", scan.pitch_x_um, px),
            ("pitch_y_um", scan.pitch_y_um, py),
        ] {
            if manifest.is_finite() && !same_pitch(manifest, file) {
                bail!("{at}: [scan] {field} = {manifest} but the file says {file} um: manifest and file disagree");
            }
        }
        match file_pitch {
            None => *file_pitch = Some((px, py, tile_file.to_string())),
            Some((fx, fy, first)) if !same_pitch(*fx, px) || !same_pitch(*fy, py) => bail!(
                "{at}: pitch {px} x {py} um, but {first} says {fx} x {fy} um: all tiles of a scan have one pitch"
            ),
            Some(_) => {}
        }
    } else if !(scan.pitch_x_um.is_finite() && scan.pitch_y_um.is_finite()) {
        bail!(
            "{manifest}: [scan] pitch_x_um / pitch_y_um missing, and {tile_file} carries no pitch: give the pitch in micrometres"
        );
    }
    Ok(())
}

/// A scan manifest as [`load_scan`] reads and checks it, before any tile is read: what the
/// launcher needs to know of a scan before it starts (the tiles' bytes for the out dir's
/// space, whether heights will be taken as um).
#[derive(Debug, Clone)]
pub struct ManifestListing {
    /// The manifest file.
    pub path: PathBuf,
    /// Each tile's file, where the loader will open it (not yet checked).
    pub tile_files: Vec<PathBuf>,
    /// `[scan] height_unit` is given.
    pub height_unit_given: bool,
}

impl ManifestListing {
    /// `path`: a scan.toml or the folder holding one. The error is the loader's.
    pub fn read(path: &Path) -> Result<Self> {
        let manifest = read_manifest(path)?;
        let manifest_dir = manifest.path.parent().unwrap_or(Path::new("."));
        let dir = match &manifest.tile_dir {
            Some(t) => manifest_dir.join(t),
            None => manifest_dir.to_path_buf(),
        };
        Ok(Self {
            tile_files: manifest.tiles.iter().map(|t| dir.join(&t.file)).collect(),
            height_unit_given: manifest.unit_given,
            path: manifest.path,
        })
    }

    /// No `height_unit` in the manifest, and a tile's format carries none (.npy, .xyz): the
    /// loader takes those heights as um (said, never assumed silently).
    pub fn heights_assumed_um(&self) -> bool {
        !self.height_unit_given
            && self.tile_files.iter().any(|f| {
                f.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| e.eq_ignore_ascii_case("npy") || e.eq_ignore_ascii_case("xyz"))
            })
    }
}

/// Reads `scan.toml` (or a directory holding one) and every tile it lists.
pub fn load_scan(path: &Path) -> Result<ScanDirectory> {
    let Manifest {
        path: manifest_path,
        mut scan,
        scale,
        unit_given,
        tile_dir,
        tiles: entries,
    } = read_manifest(path)?;
    // The manifest's name, formatted once for every message below.
    let m = manifest_path.display().to_string();
    let manifest_dir = manifest_path.parent().unwrap_or(Path::new("."));
    let dir_buf = match &tile_dir {
        Some(t) => manifest_dir.join(t),
        None => manifest_dir.to_path_buf(),
    };
    let dir = dir_buf.as_path();
    let dir_real = dir
        .canonicalize()
        .with_context(|| format!("{}: cannot resolve the scan directory", dir.display()))?;
    let mut seen = std::collections::BTreeSet::new();
    // Resolved tile files: one file listed twice through different names or links would be
    // placed at two grid positions (the manifest's own names are checked in read_manifest).
    let mut resolved: std::collections::BTreeMap<PathBuf, (usize, String)> = Default::default();
    let mut tiles = Vec::with_capacity(entries.len());
    let mut z_offset_um: Option<f64> = None;
    let mut shape: Option<(usize, usize, String)> = None;
    // (pitch x, pitch y, file) of the first tile that carries a lateral calibration.
    let mut file_pitch: Option<(f64, f64, String)> = None;
    let mut masks = MaskExclusion::new(&scan.mask_exclude);
    // The position each tile file stores for its pixel (0, 0), when it stores one.
    let mut stored_positions: Vec<Option<[f64; 2]>> = Vec::with_capacity(entries.len());
    for (k, t) in entries.into_iter().enumerate() {
        let at = format!("{m}: [[tile]] #{} (file {:?})", k + 1, t.file);
        if t.row >= scan.rows || t.col >= scan.cols {
            bail!(
                "{at}: row = {}, col = {}: expected row < {} and col < {} ([scan] rows / cols)",
                t.row,
                t.col,
                scan.rows,
                scan.cols
            );
        }
        if !seen.insert((t.row, t.col)) {
            bail!("{at}: row {} col {} is listed twice", t.row, t.col);
        }
        for (field, v) in [("stage_x_um", t.stage_x_um), ("stage_y_um", t.stage_y_um)] {
            if !v.is_finite() {
                bail!("{at}: {field} = {v}: expected a finite position in micrometres");
            }
        }
        let (tile_path, real) = checked_tile_file(&at, dir, &dir_real, &t)?;
        if let Some((first, name)) = resolved.insert(real.clone(), (k, t.file.clone())) {
            bail!(
                "{at}: resolves to {}, the file of [[tile]] #{} (file {name:?}): the same file listed twice (through a link or another path); each field is one file",
                real.display(),
                first + 1
            );
        }
        let mut surface = formats::read_surface(&tile_path).with_context(|| at.clone())?;
        masks.apply(&mut surface).with_context(|| at.clone())?;
        refuse_unmeasured_tile(&surface.heights_um, &at, !scan.mask_exclude.is_empty())?;
        let (rows, cols) = (surface.height, surface.width);
        match &shape {
            None => shape = Some((rows, cols, t.file.clone())),
            Some((r, c, first)) if (*r, *c) != (rows, cols) => bail!(
                "{}: shape {} x {} (rows x cols), expected {r} x {c} like {first}: all tiles of a scan have one shape",
                tile_path.display(),
                rows,
                cols
            ),
            Some(_) => {}
        }
        check_file_calibration(
            &at,
            &m,
            &surface,
            &scan,
            (unit_given, scale),
            &mut file_pitch,
            &t.file,
        )?;
        stored_positions.push(surface.metadata.stage_position_um);
        let carries_units = surface.metadata.pitch_known;
        let file_scale = if carries_units { 1.0 } else { scale };
        let mut heights = surface.heights_um;
        heights.iter_mut().for_each(|z| *z *= file_scale);
        refuse_absurd_heights(&heights, &at, cols)?;
        // Every tile is relative to the FIRST tile's mean, so overlaps compare without
        // conversion. The readers already turned every non-finite height into NaN
        // (formats::parse_surface), so valid_mean's !is_nan is the former is_finite filter.
        let offset = *z_offset_um.get_or_insert_with(|| valid_mean(&heights));
        let heights_um = to_frame_heights_at(&heights, offset);
        tiles.push(LoadedTile {
            entry: t,
            heights_um,
        });
    }
    masks
        .finish()
        .with_context(|| format!("{m}: [scan] mask_exclude"))?;
    let (rows, cols, _) = shape.ok_or_else(|| anyhow!("{m}: no tiles"))?;
    if let Some((px, py, first)) = file_pitch {
        // The manifest's range holds whichever source the pitch comes from (issue 36).
        for (field, v) in [("pitch_x_um", px), ("pitch_y_um", py)] {
            if !(MIN_PITCH_UM..=MAX_PITCH_UM).contains(&v) {
                bail!(
                    "{m}: {first}: the tile file's {field} = {v:e}, and [scan] gives none: expected a pitch between {MIN_PITCH_UM} and {MAX_PITCH_UM} um (an optical profiler's field is sampled at 0.01-100 um)"
                );
            }
        }
        scan.pitch_x_um = px;
        scan.pitch_y_um = py;
    }
    let scan = scan.resolved().map_err(|e| anyhow!("{m}: [scan] {e}"))?;
    check_pitch_against_truth(&manifest_path, &scan)?;
    check_grid_against_positions(&m, &tiles)?;
    check_positions_against_files(&m, &scan, &tiles, &stored_positions, cols, rows)?;
    check_stage_steps(&m, &scan, &tiles, cols, rows)?;
    Ok(ScanDirectory {
        manifest_path,
        scan,
        tiles,
        z_offset_um: z_offset_um.unwrap_or(0.0),
        tile_width_px: cols,
        tile_height_px: rows,
    })
}

/// `ground_truth.json` beside the manifest (the simulated stage's, `make_tiles.py`'s) knows the
/// pitch the tiles were made with: a manifest that says otherwise places every tile wrongly
/// (a 461 x 368 panorama instead of 461 x 461), so it is refused.
fn check_pitch_against_truth(manifest: &Path, scan: &ScanSection) -> Result<()> {
    let truth = manifest.with_file_name("ground_truth.json");
    let Ok(text) = std::fs::read_to_string(&truth) else {
        return Ok(());
    };
    let Ok(truth_record) = serde_json::from_str::<surfstream_core::record::TruthRecord>(&text)
    else {
        return Ok(()); // not ours to judge; the matcher's scorer names a bad file
    };
    let Some(pitch) = truth_record.pixel_pitch_um else {
        return Ok(());
    };
    for (axis, manifest_pitch, truth_pitch) in [
        ("x", scan.pitch.x_um(), pitch.x),
        ("y", scan.pitch.y_um(), pitch.y),
    ] {
        if truth_pitch > 0.0 && !same_pitch(manifest_pitch, truth_pitch) {
            bail!(
                "{}: [scan] pitch_{axis}_um = {manifest_pitch} but {} says the tiles were made at {truth_pitch} um: manifest and tiles disagree (fix the manifest's pitch)",
                manifest.display(),
                truth.display()
            );
        }
    }
    Ok(())
}

/// The stage positions at the manifest's pitch should make neighbouring tiles overlap: a step
/// larger than the tile is a wrong pitch (or wrong positions), flagged (once) before
/// registration falls back to the stage for every tile.
fn check_stage_steps(
    m: &str,
    scan: &ScanSection,
    tiles: &[LoadedTile],
    width_px: usize,
    height_px: usize,
) -> Result<()> {
    let at: std::collections::BTreeMap<(usize, usize), &TileEntry> = tiles
        .iter()
        .map(|t| ((t.entry.row, t.entry.col), &t.entry))
        .collect();
    for (&(r, c), a) in &at {
        for (b, axis, side_px, pitch) in [
            (at.get(&(r, c + 1)), "x", width_px, scan.pitch.x_um()),
            (at.get(&(r + 1, c)), "y", height_px, scan.pitch.y_um()),
        ] {
            let Some(b) = b else { continue };
            let step_um = match axis {
                "x" => (b.stage_x_um - a.stage_x_um).abs(),
                _ => (b.stage_y_um - a.stage_y_um).abs(),
            };
            let step_px = step_um / pitch;
            if step_px >= side_px as f64 {
                // Flagged, not refused: a sparse survey may leave gaps on purpose.
                eprintln!(
                    "stitch: warning: {m}: tiles {:?} and {:?} are {step_um} um apart in {axis} = {step_px:.0} px at pitch_{axis}_um = {pitch}, but a tile is {side_px} px: they cannot overlap (check the pitch or the stage positions)",
                    a.file,
                    b.file
                );
                return Ok(());
            }
        }
    }
    Ok(())
}

/// A wrong layout is not a registration (issue 36): x grows with the column and y with the
/// row (DESIGN §2), so a grid neighbour to the right (below) whose stage position is not
/// further along x (y) means the manifest's grid and its positions disagree, as when a
/// serpentine scan is listed as row-by-row. Refused, naming both tiles.
fn check_grid_against_positions(m: &str, tiles: &[LoadedTile]) -> Result<()> {
    let at: std::collections::BTreeMap<(usize, usize), &TileEntry> = tiles
        .iter()
        .map(|t| ((t.entry.row, t.entry.col), &t.entry))
        .collect();
    for (&(r, c), a) in &at {
        let right = at
            .get(&(r, c + 1))
            .map(|b| (b, "x", a.stage_x_um, b.stage_x_um));
        let below = at
            .get(&(r + 1, c))
            .map(|b| (b, "y", a.stage_y_um, b.stage_y_um));
        for (b, axis, pa, pb) in right.into_iter().chain(below) {
            if pb <= pa {
                let (next, field) = if axis == "x" {
                    (format!("col {}", c + 1), "column")
                } else {
                    (format!("row {}", r + 1), "row")
                };
                bail!(
                    "{m}: [[tile]] {:?} (row {r} col {c}) is at stage_{axis}_um = {pa}, and the next {field}'s {:?} ({next}) at {pb}: \
                     {axis} must grow with the {field}, so the grid and the stage positions disagree (a serpentine scan listed \
                     row by row, or the other way round?): fix row / col or the positions",
                    a.file,
                    b.file
                );
            }
        }
    }
    Ok(())
}

/// A manifest that contradicts its files (issue 36): when every tile file stores where its
/// pixel (0, 0) is (X3P axis offsets, Gwyddion offsets), each manifest position relative to
/// the first tile's must agree with the file's within
/// [`crate::infer::POSITION_TOLERANCE_FIELDS`] of a field. Refused, naming the tile and both.
/// Files that all store one and the same position carry none (skipped).
fn check_positions_against_files(
    m: &str,
    scan: &ScanSection,
    tiles: &[LoadedTile],
    stored: &[Option<[f64; 2]>],
    width_px: usize,
    height_px: usize,
) -> Result<()> {
    let Some(stored) = stored.iter().copied().collect::<Option<Vec<[f64; 2]>>>() else {
        return Ok(());
    };
    // Files that all say the same place store no position (an X3P writer without one writes
    // offset 0): nothing to compare.
    if stored.windows(2).all(|w| w[0] == w[1]) {
        return Ok(());
    }
    let (Some(first), Some(s0)) = (tiles.first(), stored.first()) else {
        return Ok(());
    };
    let field_um = [
        width_px as f64 * scan.pitch.x_um(),
        height_px as f64 * scan.pitch.y_um(),
    ];
    let limit = crate::infer::POSITION_TOLERANCE_FIELDS;
    for (t, p) in tiles.iter().zip(&stored).skip(1) {
        let manifest = [
            t.entry.stage_x_um - first.entry.stage_x_um,
            t.entry.stage_y_um - first.entry.stage_y_um,
        ];
        let file = [p[0] - s0[0], p[1] - s0[1]];
        for axis in 0..2 {
            let off = (manifest[axis] - file[axis]).abs() / field_um[axis];
            if off > limit {
                bail!(
                    "{m}: [[tile]] {:?} (row {} col {}): the manifest puts it at ({:.3}, {:.3}) um from {:?}, \
                     but the files' own positions put it at ({:.3}, {:.3}) um: {:.0} % of a field off in {}, \
                     more than {:.0} %: the manifest and the files disagree (check the stage positions, or \
                     stitch the folder without a manifest to use the files' positions)",
                    t.entry.file,
                    t.entry.row,
                    t.entry.col,
                    manifest[0],
                    manifest[1],
                    first.entry.file,
                    file[0],
                    file[1],
                    off * 100.0,
                    ["x", "y"][axis],
                    limit * 100.0
                );
            }
        }
    }
    Ok(())
}

/// A height beyond +-1 m is a corrupt point or a wrong unit: stitched and meshed it would
/// make a model kilometres tall, so a scan refuses it, naming the tile, the pixel and the value.
fn refuse_absurd_heights(heights_um: &[f64], at: &str, cols: usize) -> Result<()> {
    let limit = formats::MAX_PLAUSIBLE_HEIGHT_UM;
    let bad: Vec<usize> = (0..heights_um.len())
        .filter(|&i| heights_um[i].abs() > limit)
        .collect();
    if let Some(&first) = bad.first() {
        bail!(
            "{at}: {} height(s) beyond +-{limit:e} um, the first {:.3e} um at row {}, col {}: \
             physically absurd for a profiler (a corrupt point, or check [scan] height_unit)",
            bad.len(),
            heights_um[first],
            first / cols.max(1),
            first % cols.max(1)
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_scan(dir: &Path, manifest: &str, tiles: &[(&str, usize, usize)]) {
        std::fs::write(dir.join("scan.toml"), manifest).unwrap();
        for (name, r, c) in tiles {
            let data: Vec<f32> = (0..r * c).map(|i| i as f32).collect();
            surfstream_io::npy::write_npy_f32(dir.join(name), &data, *r, *c).unwrap();
        }
    }

    const OK: &str = r#"
[scan]
name = "t"
pitch_x_um = 0.5
pitch_y_um = 0.5
height_unit = "nm"
rows = 1
cols = 2

[[tile]]
file = "a.npy"
row = 0
col = 0
stage_x_um = 0.0
stage_y_um = 0.0

[[tile]]
file = "b.npy"
row = 0
col = 1
stage_x_um = 4.0
stage_y_um = 0.0
"#;

    #[test]
    fn loads_and_scales_units() {
        let d = tempfile::tempdir().unwrap();
        write_scan(d.path(), OK, &[("a.npy", 3, 4), ("b.npy", 3, 4)]);
        let s = load_scan(d.path()).unwrap();
        assert_eq!((s.tile_height_px, s.tile_width_px), (3, 4));
        // Tile a holds 0..11 nm: the scan's offset is its mean, 5.5 nm.
        assert!((s.z_offset_um - 0.0055).abs() < 1e-15, "{}", s.z_offset_um);
        let absolute = f64::from(s.tiles[1].heights_um[5]) + s.z_offset_um;
        assert!((absolute - 0.005).abs() < 1e-10, "{absolute}");
    }

    /// A part tens of millimetres up the z axis: f32 alone would keep only ~2 nm of 25 mm;
    /// relative to the scan's f64 offset the tiles keep the reader's sub-picometre steps.
    #[test]
    fn tiles_keep_f64_precision_relative_to_the_scan_offset() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("scan.toml"), OK.replace("\"nm\"", "\"um\"")).unwrap();
        let truth: Vec<Vec<f64>> = (0..2)
            .map(|t| {
                (0..12)
                    .map(|i| 25_000.0 + (i * 7 + t) as f64 * 1e-4)
                    .collect()
            })
            .collect();
        for (name, z) in ["a.npy", "b.npy"].iter().zip(&truth) {
            surfstream_io::npy::write_npy_f64(d.path().join(name), z, 3, 4).unwrap();
        }
        let s = load_scan(d.path()).unwrap();
        assert!((s.z_offset_um - 25_000.0).abs() < 0.01);
        for (tile, z) in s.tiles.iter().zip(&truth) {
            for (&h, &want) in tile.heights_um.iter().zip(z) {
                let got = f64::from(h) + s.z_offset_um;
                assert!((got - want).abs() < 1e-9, "{got} vs {want}");
            }
        }
    }

    #[test]
    fn errors_name_file_and_field() {
        let d = tempfile::tempdir().unwrap();
        write_scan(d.path(), OK, &[("a.npy", 3, 4), ("b.npy", 3, 5)]);
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(e.contains("b.npy") && e.contains("expected 3 x 4"), "{e}");

        write_scan(
            d.path(),
            &OK.replace("stage_y_um = 0.0\n\n[[tile]]", "\n[[tile]]"),
            &[],
        );
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(e.contains("scan.toml") && e.contains("stage_y_um"), "{e}");

        write_scan(d.path(), &OK.replace("b.npy", "missing.npy"), &[]);
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(
            e.contains("missing.npy") && e.contains("no such tile file"),
            "{e}"
        );

        write_scan(d.path(), &OK.replace("pitch_x_um = 0.5\n", ""), &[]);
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(e.contains("scan.toml") && e.contains("pitch_x_um"), "{e}");
    }

    #[test]
    fn unsupported_tile_message_lists_every_reader_extension() {
        let list = supported_extensions();
        assert!(
            list.starts_with(".npy, ") && list.ends_with(" or .tiff"),
            "{list}"
        );
        for ext in formats::EXTENSIONS {
            assert!(
                formats::is_surface_file(Path::new(&format!("t.{ext}"))),
                "{ext}"
            );
            assert!(
                list.contains(&format!(".{ext}")),
                "{ext} missing from {list}"
            );
        }
        // The reader's own message names the extensions it matches: none missing here.
        let e = formats::Format::from_path(Path::new("t.bmp"))
            .unwrap_err()
            .to_string();
        let named = e.split("(expected ").nth(1).unwrap_or_default();
        for ext in named
            .split(|c: char| !c.is_ascii_alphanumeric())
            .filter(|w| !w.is_empty())
        {
            assert!(
                formats::EXTENSIONS.contains(&ext),
                "{ext} not in EXTENSIONS"
            );
        }

        let d = tempfile::tempdir().unwrap();
        write_scan(d.path(), &OK.replace("b.npy", "b.bmp"), &[("a.npy", 3, 4)]);
        std::fs::write(d.path().join("b.bmp"), b"not a height map").unwrap();
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(e.contains("b.bmp") && e.contains(&list), "{e}");
    }

    fn x3p_tile(dir: &Path, name: &str, pitch_um: f64) {
        let s = formats::Surface {
            width: 4,
            height: 3,
            pitch_x_um: pitch_um,
            pitch_y_um: pitch_um,
            heights_um: (0..12).map(|i| i as f64 * 0.25).collect(),
            metadata: formats::Metadata::default(),
        };
        formats::write_surface(&dir.join(name), &s).unwrap();
    }

    /// Issue 36: a wrong layout is refused, not registered. A 2 x 2 serpentine scan listed as
    /// row by row (row 1's columns swapped against its stage positions), and a manifest whose
    /// positions contradict the ones its X3P tiles store.
    #[test]
    fn a_grid_or_positions_that_contradict_the_scan_are_refused() {
        let d = tempfile::tempdir().unwrap();
        let tile = |name: &str, x_um: f64, y_um: f64| {
            let s = formats::Surface {
                width: 4,
                height: 3,
                pitch_x_um: 1.0,
                pitch_y_um: 1.0,
                heights_um: (0..12).map(|i| i as f64 * 0.25).collect(),
                metadata: formats::Metadata {
                    stage_position_um: Some([x_um, y_um]),
                    ..Default::default()
                },
            };
            formats::write_surface(&d.path().join(name), &s).unwrap();
        };
        let entry = |file: &str, row: usize, col: usize, x: f64, y: f64| {
            format!(
                "[[tile]]\nfile = \"{file}\"\nrow = {row}\ncol = {col}\nstage_x_um = {x:?}\nstage_y_um = {y:?}\n"
            )
        };
        let head = "[scan]\nname = \"t\"\nrows = 2\ncols = 2\n";
        // Serpentine acquisition: t0 (0,0), t1 (3,0), t2 (3,2), t3 (0,2) at steps 3 / 2 um.
        for (name, x, y) in [
            ("t0.x3p", 0.0, 0.0),
            ("t1.x3p", 3.0, 0.0),
            ("t2.x3p", 3.0, 2.0),
            ("t3.x3p", 0.0, 2.0),
        ] {
            tile(name, x, y);
        }
        let manifest = |entries: &[String]| {
            let path = d.path().join("scan.toml");
            std::fs::write(&path, format!("{head}{}", entries.concat())).unwrap();
            path
        };
        // Right: row 1 runs right to left, the grid says so.
        let right = [
            entry("t0.x3p", 0, 0, 0.0, 0.0),
            entry("t1.x3p", 0, 1, 3.0, 0.0),
            entry("t2.x3p", 1, 1, 3.0, 2.0),
            entry("t3.x3p", 1, 0, 0.0, 2.0),
        ];
        load_scan(&manifest(&right)).expect("a consistent serpentine");
        // Listed row by row: the third tile at col 0 with the fourth's x to its left.
        let raster = [
            entry("t0.x3p", 0, 0, 0.0, 0.0),
            entry("t1.x3p", 0, 1, 3.0, 0.0),
            entry("t2.x3p", 1, 0, 3.0, 2.0),
            entry("t3.x3p", 1, 1, 0.0, 2.0),
        ];
        let e = load_scan(&manifest(&raster)).unwrap_err().to_string();
        assert!(
            e.contains("\"t2.x3p\" (row 1 col 0)")
                && e.contains("the grid and the stage positions disagree")
                && e.contains("serpentine"),
            "{e}"
        );
        // Grid and positions agree with each other, but not with the files' stored positions
        // (t2 and t3 swapped in the manifest): refused naming the tile and both positions.
        let swapped = [
            entry("t0.x3p", 0, 0, 0.0, 0.0),
            entry("t1.x3p", 0, 1, 3.0, 0.0),
            entry("t3.x3p", 1, 1, 3.0, 2.0),
            entry("t2.x3p", 1, 0, 0.0, 2.0),
        ];
        let e = load_scan(&manifest(&swapped)).unwrap_err().to_string();
        assert!(
            e.contains("[[tile]] \"t3.x3p\" (row 1 col 1)")
                && e.contains("the manifest and the files disagree")
                && e.contains("75 % of a field off in x"),
            "{e}"
        );
    }

    #[test]
    fn instrument_tiles_carry_their_pitch() {
        let d = tempfile::tempdir().unwrap();
        let manifest = OK
            .replace("a.npy", "a.x3p")
            .replace("b.npy", "b.x3p")
            .replace("height_unit = \"nm\"\n", "");
        // Pitch omitted from the manifest: taken from the files.
        std::fs::write(
            d.path().join("scan.toml"),
            manifest.replace("pitch_x_um = 0.5\npitch_y_um = 0.5\n", ""),
        )
        .unwrap();
        x3p_tile(d.path(), "a.x3p", 0.8148);
        x3p_tile(d.path(), "b.x3p", 0.8148);
        let s = load_scan(d.path()).unwrap();
        assert!((s.scan.pitch.x_um() - 0.8148).abs() < 1e-12);
        let absolute = f64::from(s.tiles[1].heights_um[5]) + s.z_offset_um;
        assert!((absolute - 1.25).abs() < 1e-9, "{absolute}");
        // Manifest says 0.5, files say 0.8148: an error naming both.
        std::fs::write(d.path().join("scan.toml"), &manifest).unwrap();
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(e.contains("a.x3p") && e.contains("disagree"), "{e}");
        // Files disagree with each other.
        std::fs::write(
            d.path().join("scan.toml"),
            manifest.replace("pitch_x_um = 0.5\npitch_y_um = 0.5\n", ""),
        )
        .unwrap();
        x3p_tile(d.path(), "b.x3p", 0.9);
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(e.contains("b.x3p") && e.contains("one pitch"), "{e}");
        // A height unit beside instrument files.
        x3p_tile(d.path(), "b.x3p", 0.8148);
        std::fs::write(
            d.path().join("scan.toml"),
            manifest.replace(
                "pitch_x_um = 0.5\npitch_y_um = 0.5\n",
                "height_unit = \"nm\"\n",
            ),
        )
        .unwrap();
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(e.contains("height_unit"), "{e}");
    }

    /// `[scan] mask_exclude`: each X3P tile drops exactly the points of the named colour-mask
    /// regions it holds (a tile without that region keeps every point), all other points stay
    /// measured; a name no tile holds is an error listing the regions.
    #[test]
    fn mask_exclude_drops_the_labelled_points_of_every_tile() {
        use surfstream_io::formats::x3p::{ColourMask, MaskRegion};
        use surfstream_io::formats::{Metadata, Surface};
        let d = tempfile::tempdir().unwrap();
        let (w, h) = (20, 16);
        let region = |colour: &str, name: Option<&str>, background: bool| MaskRegion {
            colour: colour.into(),
            annotation: name.map(str::to_string),
            background,
            points: 0,
        };
        // Tile a: "dust" is a 3 x 2 patch; tile b: "scratch" is column 5, no dust.
        let tile = |name: &str, second: MaskRegion, label: &dyn Fn(usize, usize) -> bool| {
            let labels: Vec<u16> = (0..w * h).map(|i| label(i / w, i % w) as u16).collect();
            let mut regions = vec![region("#cd7f32", None, true), second];
            regions[1].points = labels.iter().filter(|&&l| l == 1).count();
            regions[0].points = w * h - regions[1].points;
            let s = Surface {
                width: w,
                height: h,
                pitch_x_um: 0.5,
                pitch_y_um: 0.5,
                heights_um: (0..w * h).map(|i| (i % 7) as f64 * 0.1).collect(),
                metadata: Metadata {
                    format: "x3p".into(),
                    pitch_known: true,
                    mask: Some(ColourMask {
                        image: "bindata/mask.png".into(),
                        regions,
                        labels,
                    }),
                    ..Metadata::default()
                },
            };
            surfstream_io::formats::x3p::write(&d.path().join(name), &s).unwrap();
        };
        tile("a.x3p", region("#ff0000", Some("dust"), false), &|r, c| {
            (4..6).contains(&r) && (10..13).contains(&c)
        });
        tile(
            "b.x3p",
            region("#00ff00", Some("scratch"), false),
            &|_, c| c == 5,
        );
        let manifest = |exclude: &str| {
            format!(
                "[scan]\nname = \"m\"\nrows = 1\ncols = 2\n{exclude}\n\
                 [[tile]]\nfile = \"a.x3p\"\nrow = 0\ncol = 0\nstage_x_um = 0.0\nstage_y_um = 0.0\n\
                 [[tile]]\nfile = \"b.x3p\"\nrow = 0\ncol = 1\nstage_x_um = 8.0\nstage_y_um = 0.0\n"
            )
        };
        let nans = |s: &ScanDirectory| -> Vec<usize> {
            s.tiles
                .iter()
                .map(|t| t.heights_um.iter().filter(|z| z.is_nan()).count())
                .collect()
        };
        std::fs::write(d.path().join("scan.toml"), manifest("")).unwrap();
        let s = load_scan(d.path()).unwrap();
        assert_eq!(nans(&s), [0, 0], "labels alone drop nothing");
        std::fs::write(
            d.path().join("scan.toml"),
            manifest("mask_exclude = [\"Dust\", \"#00FF00\"]"),
        )
        .unwrap();
        let s = load_scan(d.path()).unwrap();
        assert_eq!(s.scan.mask_exclude, ["Dust", "#00FF00"]);
        assert_eq!(nans(&s), [6, 16]);
        assert!(s.tiles[0].heights_um[4 * w + 10].is_nan());
        assert!(!s.tiles[0].heights_um[4 * w + 9].is_nan());
        assert!(s.tiles[1].heights_um[7 * w + 5].is_nan());
        std::fs::write(
            d.path().join("scan.toml"),
            manifest("mask_exclude = [\"dust\", \"pores\"]"),
        )
        .unwrap();
        let e = format!("{:#}", load_scan(d.path()).unwrap_err());
        assert!(
            e.contains("[scan] mask_exclude")
                && e.contains("'pores' is not a region of any tile's colour mask")
                && e.contains("'dust' #ff0000")
                && e.contains("'scratch' #00ff00")
                && e.contains("'background' #cd7f32"),
            "{e}"
        );
    }
}
