//! A scan manifest inferred from a folder of tiles and what the user knows of the scan: the
//! grid (rows x cols), the overlap and the stage's path (row by row, or serpentine).
//!
//! The tiles are taken in file-name order (numbers compared as numbers, so `tile_2` comes before
//! `tile_10`) as the acquisition order; the i-th tile sits at row `i / cols` and column `i % cols`
//! (reversed on odd rows for a serpentine). Its nominal stage position is its grid position times
//! the field size less the overlap. The result is an ordinary `scan.toml`, which the caller
//! writes beside its outputs so the run can be repeated and checked.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use anyhow::{anyhow, bail, Context, Result};
use surfstream_io::formats;

/// The scan as the user describes it on the command line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridLayout {
    pub rows: usize,
    pub cols: usize,
    /// Overlap of neighbouring fields along x and y, as a fraction of the field (0.2 = 20 %).
    pub overlap_x: f64,
    pub overlap_y: f64,
    /// Odd rows run right to left (the instrument's serpentine), else every row left to right.
    pub serpentine: bool,
}

/// `RxC` (rows x cols), e.g. "3x4".
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grid {
    pub rows: usize,
    pub cols: usize,
}

impl FromStr for Grid {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let bad = || format!("grid {s:?}: expected ROWSxCOLS, e.g. 3x4 (3 rows of 4 fields)");
        let (r, c) = s.split_once(['x', 'X', '×']).ok_or_else(bad)?;
        let (rows, cols) = (
            r.trim().parse::<usize>().map_err(|_| bad())?,
            c.trim().parse::<usize>().map_err(|_| bad())?,
        );
        if rows == 0 || cols == 0 {
            return Err(bad());
        }
        Ok(Grid { rows, cols })
    }
}

/// An overlap as a fraction: "20%" or "0.2".
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Overlap(pub f64);

impl FromStr for Overlap {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let t = s.trim();
        let value = match t.strip_suffix('%') {
            Some(p) => p.trim().parse::<f64>().map(|v| v / 100.0),
            None => t.parse::<f64>(),
        }
        .map_err(|_| format!("overlap {s:?}: expected a percentage (20%) or a fraction (0.2)"))?;
        if !(0.0..0.9).contains(&value) {
            return Err(format!(
                "overlap {s:?}: expected at least 0 and below 90 % of the field"
            ));
        }
        Ok(Overlap(value))
    }
}

/// File-name order with digit runs compared as numbers.
fn natural_key(name: &str) -> Vec<(u8, u128, String)> {
    let mut key = Vec::new();
    let mut chars = name.chars().peekable();
    while let Some(&c) = chars.peek() {
        let digits = c.is_ascii_digit();
        let mut run = String::new();
        while let Some(&d) = chars.peek() {
            if d.is_ascii_digit() != digits {
                break;
            }
            run.push(d);
            chars.next();
        }
        key.push(if digits {
            (0, run.parse::<u128>().unwrap_or(u128::MAX), run)
        } else {
            (1, 0, run)
        });
    }
    key
}

/// The height-map files of `dir` (every format the readers know), in acquisition order.
pub fn tile_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir)
        .with_context(|| format!("{}: cannot list the tile folder", dir.display()))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && formats::is_surface_file(p))
        .collect();
    files.sort_by_key(|p| {
        natural_key(
            &p.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
        )
    });
    Ok(files)
}

/// The `scan.toml` text for the tiles of `dir` laid out as `layout`. `pitch_um` is needed only
/// for files that carry no lateral calibration (.npy). Errors name the folder and what
/// disagrees: the number of files and the grid, a file without pitch and no `pitch_um`.
pub fn infer_manifest(dir: &Path, layout: &GridLayout, pitch_um: Option<f64>) -> Result<String> {
    let files = tile_files(dir)?;
    let wanted = layout.rows * layout.cols;
    if files.len() != wanted {
        bail!(
            "{}: {} tile files, but --grid {}x{} (rows x cols) needs {wanted}",
            dir.display(),
            files.len(),
            layout.rows,
            layout.cols
        );
    }
    let first = formats::read_surface(&files[0])?;
    let (pitch_x_um, pitch_y_um) = match (pitch_um, first.metadata.pitch_known) {
        (Some(p), _) if p.is_finite() && p > 0.0 => (p, p),
        (Some(p), _) => bail!("--pitch-um {p}: expected a positive pitch in micrometres"),
        (None, true) => (first.pitch_x_um, first.pitch_y_um),
        (None, false) => bail!(
            "{}: a {} file carries no lateral calibration: give --pitch-um",
            files[0].display(),
            first.metadata.format
        ),
    };
    let (tile_rows, tile_cols) = (first.height, first.width);
    let step_x_um = tile_cols as f64 * (1.0 - layout.overlap_x) * pitch_x_um;
    let step_y_um = tile_rows as f64 * (1.0 - layout.overlap_y) * pitch_y_um;
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().replace('"', "'"))
        .unwrap_or_else(|| "scan".into());
    let mut toml =
        format!(
        "# Inferred by surfstream stitch --grid {}x{} --overlap {:.4}/{:.4}{} from the tiles of\n\
         # {} ({} x {} px each, rows x cols), in file-name order.\n\
         [scan]\nname = \"{name}\"\nrows = {}\ncols = {}\n",
        layout.rows,
        layout.cols,
        layout.overlap_x,
        layout.overlap_y,
        if layout.serpentine { " --serpentine" } else { "" },
        dir.display(),
        tile_rows,
        tile_cols,
        layout.rows,
        layout.cols,
    );
    if pitch_um.is_some() {
        toml += &format!("pitch_x_um = {pitch_x_um}\npitch_y_um = {pitch_y_um}\n");
    }
    for (i, file) in files.iter().enumerate() {
        let row = i / layout.cols;
        let mut col = i % layout.cols;
        if layout.serpentine && row % 2 == 1 {
            col = layout.cols - 1 - col;
        }
        let path = file
            .canonicalize()
            .with_context(|| format!("{}: cannot resolve", file.display()))?;
        let path = path
            .to_str()
            .ok_or_else(|| anyhow!("{}: the path is not UTF-8", path.display()))?;
        toml += &format!(
            "\n[[tile]]\nfile = {path:?}\nrow = {row}\ncol = {col}\nstage_x_um = {}\nstage_y_um = {}\n",
            col as f64 * step_x_um,
            row as f64 * step_y_um
        );
    }
    Ok(toml)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grids_overlaps_and_file_order_parse() {
        assert_eq!("3x4".parse::<Grid>(), Ok(Grid { rows: 3, cols: 4 }));
        assert!("3by4".parse::<Grid>().unwrap_err().contains("ROWSxCOLS"));
        assert!("0x4".parse::<Grid>().is_err());
        assert_eq!("20%".parse::<Overlap>(), Ok(Overlap(0.2)));
        assert_eq!("0.15".parse::<Overlap>(), Ok(Overlap(0.15)));
        assert!("95%".parse::<Overlap>().is_err());
        let mut names = ["t_10.npy", "t_2.npy", "t_1.npy"];
        names.sort_by_key(|n| natural_key(n));
        assert_eq!(names, ["t_1.npy", "t_2.npy", "t_10.npy"]);
    }
}
