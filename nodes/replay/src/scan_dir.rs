//! Scan directories (DESIGN §5): `scan.toml` plus one height-map file per field, in
//! acquisition order — the format `bench/make_tiles.py` writes.
//!
//! Everything is validated before the first tile is sent: every error names the manifest or
//! tile file, the field, and what was expected.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use serde::Deserialize;

/// `[scan]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanSection {
    pub name: String,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    #[serde(default = "default_unit")]
    pub height_unit: String,
    pub rows: usize,
    pub cols: usize,
}

fn default_unit() -> String {
    "um".into()
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
    scan: ScanSection,
    #[serde(default)]
    tile: Vec<TileEntry>,
}

/// A loaded scan: the manifest and every tile's heights (um), checked.
#[derive(Debug, Clone)]
pub struct ScanDirectory {
    pub manifest_path: PathBuf,
    pub scan: ScanSection,
    pub tiles: Vec<LoadedTile>,
    pub tile_width_px: usize,
    pub tile_height_px: usize,
}

/// One field of the scan.
#[derive(Debug, Clone)]
pub struct LoadedTile {
    pub entry: TileEntry,
    pub heights_um: Vec<f32>,
}

/// Heights in the manifest's unit -> um.
fn unit_scale(unit: &str) -> Option<f64> {
    Some(match unit {
        "um" | "µm" => 1.0,
        "nm" => 1e-3,
        "mm" => 1e3,
        "m" => 1e6,
        _ => return None,
    })
}

/// Reads `scan.toml` (or a directory holding one) and every tile it lists.
pub fn load_scan(path: &Path) -> Result<ScanDirectory> {
    let manifest_path = if path.is_dir() {
        path.join("scan.toml")
    } else {
        path.to_path_buf()
    };
    let m = manifest_path.display();
    let text = std::fs::read_to_string(&manifest_path)
        .with_context(|| format!("{m}: cannot read scan manifest"))?;
    let file: ManifestFile =
        toml::from_str(&text).map_err(|e| anyhow!("{m}: not a valid scan manifest: {e}"))?;
    let scan = file.scan;
    for (field, v) in [
        ("pitch_x_um", scan.pitch_x_um),
        ("pitch_y_um", scan.pitch_y_um),
    ] {
        if !(v.is_finite() && v > 0.0) {
            bail!("{m}: [scan] {field} = {v}: expected a positive pitch in micrometres");
        }
    }
    let scale = unit_scale(&scan.height_unit).ok_or_else(|| {
        anyhow!(
            "{m}: [scan] height_unit = {:?}: expected one of um, nm, mm, m",
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
    let dir = manifest_path.parent().unwrap_or(Path::new("."));
    let mut seen = std::collections::BTreeSet::new();
    let mut tiles = Vec::with_capacity(file.tile.len());
    let mut shape: Option<(usize, usize, String)> = None;
    for (k, t) in file.tile.into_iter().enumerate() {
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
        let tile_path = dir.join(&t.file);
        if !tile_path.exists() {
            bail!("{at}: {}: no such tile file", tile_path.display());
        }
        let ext = tile_path.extension().and_then(|e| e.to_str()).unwrap_or("");
        if ext != "npy" {
            bail!("{at}: unsupported tile format {ext:?}: expected .npy");
        }
        let arr = surfstream_common::npy::read_npy(&tile_path)?;
        match &shape {
            None => shape = Some((arr.rows, arr.cols, t.file.clone())),
            Some((r, c, first)) if (*r, *c) != (arr.rows, arr.cols) => bail!(
                "{}: shape {} x {} (rows x cols), expected {r} x {c} like {first}: all tiles of a scan have one shape",
                tile_path.display(),
                arr.rows,
                arr.cols
            ),
            Some(_) => {}
        }
        let mut heights_um = arr.data;
        if scale != 1.0 {
            heights_um
                .iter_mut()
                .for_each(|z| *z = (*z as f64 * scale) as f32);
        }
        tiles.push(LoadedTile {
            entry: t,
            heights_um,
        });
    }
    let (rows, cols, _) = shape.ok_or_else(|| anyhow!("{m}: no tiles"))?;
    Ok(ScanDirectory {
        manifest_path,
        scan,
        tiles,
        tile_width_px: cols,
        tile_height_px: rows,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_scan(dir: &Path, manifest: &str, tiles: &[(&str, usize, usize)]) {
        std::fs::write(dir.join("scan.toml"), manifest).unwrap();
        for (name, r, c) in tiles {
            let data: Vec<f32> = (0..r * c).map(|i| i as f32).collect();
            surfstream_common::npy::write_npy_f32(dir.join(name), &data, *r, *c).unwrap();
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
        assert_eq!(s.tiles[1].heights_um[5], 0.005);
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
}
