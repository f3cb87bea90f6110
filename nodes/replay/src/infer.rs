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
use surfstream_core::Pitch;
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

/// The layout of fields, `RxC` (rows x cols of tiles), e.g. "3x4" (not a raster's sampling).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TileGrid {
    pub rows: usize,
    pub cols: usize,
}

impl FromStr for TileGrid {
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
        Ok(TileGrid { rows, cols })
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

/// What one tile file says about itself.
struct TileFile {
    path: PathBuf,
    rows: usize,
    cols: usize,
    /// The file's own lateral calibration; `None` when it carries none.
    pitch: Option<Pitch>,
    format: String,
    position_um: Option<[f64; 2]>,
}

/// Reads every tile of `dir` (in acquisition order) for its shape, pitch and stored position;
/// tiles of different shapes are an error naming both files.
fn read_tiles(dir: &Path) -> Result<Vec<TileFile>> {
    let files = tile_files(dir)?;
    if files.is_empty() {
        bail!("{}: no height-map files in the folder", dir.display());
    }
    let mut tiles: Vec<TileFile> = Vec::with_capacity(files.len());
    for path in files {
        let s = formats::read_surface(&path)?;
        let t = TileFile {
            rows: s.height,
            cols: s.width,
            pitch: s
                .metadata
                .pitch_known
                .then(|| Pitch::new(s.pitch_x_um, s.pitch_y_um))
                .transpose()
                .map_err(|e| anyhow!("{}: {e}", path.display()))?,
            format: s.metadata.format,
            position_um: s.metadata.stage_position_um,
            path,
        };
        if let Some(first) = tiles.first() {
            if (t.rows, t.cols) != (first.rows, first.cols) {
                bail!(
                    "{}: {} x {} px (rows x cols), but {} is {} x {} px: the tiles of one scan \
                     have one shape",
                    t.path.display(),
                    t.rows,
                    t.cols,
                    first.path.display(),
                    first.rows,
                    first.cols
                );
            }
        }
        tiles.push(t);
    }
    Ok(tiles)
}

/// The positions the files store, when every file stores one and they are not all the same
/// (writers that always put 0 say nothing about the stage).
fn stored_positions(tiles: &[TileFile]) -> Option<Vec<[f64; 2]>> {
    let positions: Option<Vec<[f64; 2]>> = tiles.iter().map(|t| t.position_um).collect();
    positions.filter(|p| p.len() > 1 && p.iter().any(|q| *q != p[0]))
}

/// Pitch from the first file, or from `--pitch-um` for files that carry none. A `--pitch-um`
/// that disagrees with a file's own calibration is refused, as every verb does (it used to
/// override the file silently, so a typo rescaled the whole panorama).
fn scan_pitch(first: &TileFile, pitch_um: Option<f64>) -> Result<Pitch> {
    let given = pitch_um
        .map(|p| {
            Pitch::square(p)
                .map_err(|_| anyhow!("--pitch-um {p}: expected a positive pitch in micrometres"))
        })
        .transpose()?;
    match (given, first.pitch) {
        (Some(given), Some(file)) => {
            let p = given.x_um();
            let same = |a: f64| (a - p).abs() <= 1e-6 * p;
            let [x, y] = file.um();
            if !(same(x) && same(y)) {
                bail!(
                    "{}: the file carries its pitch, {x} x {y} um; --pitch-um {p} disagrees: \
                     --pitch-um is only for tiles without a pitch (leave it out)",
                    first.path.display()
                );
            }
            Ok(file)
        }
        (Some(given), None) => Ok(given),
        (None, Some(file)) => Ok(file),
        (None, None) => bail!(
            "{}: a {} file carries no lateral calibration: give --pitch-um",
            first.path.display(),
            first.format
        ),
    }
}

/// A disagreement between a file's stored position and the grid larger than this fraction of
/// a field is an error: stage error and a rounded overlap stay well below it, a wrong grid,
/// overlap or serpentine does not.
pub const POSITION_TOLERANCE_FIELDS: f64 = 0.1;

/// One tile's place in the manifest.
struct Placed<'a> {
    file: &'a Path,
    row: usize,
    col: usize,
    stage_um: [f64; 2],
}

/// The manifest text: a header comment, the [scan] table and one [[tile]] per file.
fn manifest_text(
    comment: &str,
    dir: &Path,
    rows: usize,
    cols: usize,
    pitch: Option<Pitch>,
    height_unit: Option<&str>,
    tiles: &[Placed],
) -> Result<String> {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().replace('"', "'"))
        .unwrap_or_else(|| "scan".into());
    // The manifest goes to OUT, the tiles stay in `dir`: [scan] tile_dir names it, and the
    // tile files are named inside it (a manifest reads only its tile folder).
    let dir_real = dir
        .canonicalize()
        .with_context(|| format!("{}: cannot resolve", dir.display()))?;
    let dir_text = dir_real
        .to_str()
        .ok_or_else(|| anyhow!("{}: the path is not UTF-8", dir_real.display()))?;
    let mut toml = format!(
        "{comment}[scan]\nname = \"{name}\"\nrows = {rows}\ncols = {cols}\ntile_dir = {dir_text:?}\n"
    );
    if let Some(p) = pitch {
        toml += &format!("pitch_x_um = {}\npitch_y_um = {}\n", p.x_um(), p.y_um());
    }
    if let Some(unit) = height_unit {
        toml += &format!("height_unit = {unit:?}\n");
    }
    for t in tiles {
        let real = t
            .file
            .canonicalize()
            .with_context(|| format!("{}: cannot resolve", t.file.display()))?;
        let rel = real.strip_prefix(&dir_real).unwrap_or(&real);
        let path = rel
            .to_str()
            .ok_or_else(|| anyhow!("{}: the path is not UTF-8", rel.display()))?;
        toml += &format!(
            "\n[[tile]]\nfile = {path:?}\nrow = {}\ncol = {}\nstage_x_um = {}\nstage_y_um = {}\n",
            t.row, t.col, t.stage_um[0], t.stage_um[1]
        );
    }
    Ok(toml)
}

/// The `scan.toml` text for the tiles of `dir` laid out as `layout`. `pitch_um` is needed only
/// for files that carry no lateral calibration (.npy); `height_unit` ("um", "nm", "mm", "m")
/// states the unit of such files' heights (`[scan] height_unit`; checked when it is loaded). When every file stores its position
/// (X3P axis offsets, Gwyddion offsets), each must agree with its place on the grid within
/// [`POSITION_TOLERANCE_FIELDS`] of a field (relative to the first tile), and the stored
/// positions, more exact than the nominal grid, go into the manifest. Errors name the folder or
/// the file and what disagrees: the number of files and the grid, tile shapes, a file without
/// pitch and no `pitch_um`, a stored position off the grid.
pub fn infer_manifest(
    dir: &Path,
    layout: &GridLayout,
    pitch_um: Option<f64>,
    height_unit: Option<&str>,
) -> Result<String> {
    let tiles = read_tiles(dir)?;
    let wanted = layout.rows * layout.cols;
    if tiles.len() != wanted {
        bail!(
            "{}: {} tile files, but --grid {}x{} (rows x cols) needs {wanted}",
            dir.display(),
            tiles.len(),
            layout.rows,
            layout.cols
        );
    }
    let pitch = scan_pitch(&tiles[0], pitch_um)?;
    let (tile_rows, tile_cols) = (tiles[0].rows, tiles[0].cols);
    let field_um = [
        tile_cols as f64 * pitch.x_um(),
        tile_rows as f64 * pitch.y_um(),
    ];
    let step_um = [
        field_um[0] * (1.0 - layout.overlap_x),
        field_um[1] * (1.0 - layout.overlap_y),
    ];
    let stored = stored_positions(&tiles);
    let mut placed = Vec::with_capacity(tiles.len());
    for (i, t) in tiles.iter().enumerate() {
        let row = i / layout.cols;
        let mut col = i % layout.cols;
        if layout.serpentine && row % 2 == 1 {
            col = layout.cols - 1 - col;
        }
        let nominal = [col as f64 * step_um[0], row as f64 * step_um[1]];
        let stage_um = match &stored {
            None => nominal,
            Some(p) => {
                // Tile 0 is at row 0, col 0: positions relative to it compare to the grid's.
                let rel = [p[i][0] - p[0][0], p[i][1] - p[0][1]];
                let want = nominal;
                for axis in 0..2 {
                    if (rel[axis] - want[axis]).abs() > POSITION_TOLERANCE_FIELDS * field_um[axis] {
                        bail!(
                            "{}: the file puts its pixel (0, 0) at ({:.3}, {:.3}) um from the first \
                             tile's, but --grid {}x{} --overlap {:.0}/{:.0} %{} puts tile {i} (row {row}, \
                             col {col}) at ({:.3}, {:.3}) um: {:.1} % of a field off in {}, more than \
                             {:.0} %; check --grid, --overlap and --serpentine, or leave them out to \
                             stitch by the files' positions",
                            t.path.display(),
                            rel[0],
                            rel[1],
                            layout.rows,
                            layout.cols,
                            layout.overlap_x * 100.0,
                            layout.overlap_y * 100.0,
                            if layout.serpentine { " --serpentine" } else { "" },
                            want[0],
                            want[1],
                            (rel[axis] - want[axis]).abs() / field_um[axis] * 100.0,
                            ["x", "y"][axis],
                            POSITION_TOLERANCE_FIELDS * 100.0
                        );
                    }
                }
                p[i]
            }
        };
        placed.push(Placed {
            file: &t.path,
            row,
            col,
            stage_um,
        });
    }
    let comment =
        format!(
        "# Inferred by surfstream stitch --grid {}x{} --overlap {:.4}/{:.4}{} from the tiles of\n\
         # {} ({} x {} px each, rows x cols), in file-name order.\n{}",
        layout.rows,
        layout.cols,
        layout.overlap_x,
        layout.overlap_y,
        if layout.serpentine { " --serpentine" } else { "" },
        dir.display(),
        tile_rows,
        tile_cols,
        if stored.is_some() {
            "# Stage positions: the files' own (they agree with the grid).\n"
        } else {
            "# Stage positions: nominal, from the grid and the overlap.\n"
        }
    );
    manifest_text(
        &comment,
        dir,
        layout.rows,
        layout.cols,
        pitch_um.map(|_| pitch),
        height_unit,
        &placed,
    )
}

/// Groups coordinates closer than `gap_um` into one line; the index of each value's group,
/// in increasing coordinate order, and the group count.
fn cluster(values: &[f64], gap_um: f64) -> (Vec<usize>, usize) {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| values[a].total_cmp(&values[b]));
    let mut group = vec![0; values.len()];
    let mut g = 0;
    for w in 0..order.len() {
        if w > 0 && values[order[w]] - values[order[w - 1]] > gap_um {
            g += 1;
        }
        group[order[w]] = g;
    }
    (group, if values.is_empty() { 0 } else { g + 1 })
}

/// The `scan.toml` text for a folder whose files store their stage positions, without a grid
/// from the user: positions less than half a field apart along x are one column, along y one
/// row; every (row, col) must hold exactly one tile. Returns the text and (rows, cols).
pub fn infer_manifest_from_positions(
    dir: &Path,
    pitch_um: Option<f64>,
    height_unit: Option<&str>,
) -> Result<(String, usize, usize)> {
    let tiles = read_tiles(dir)?;
    let Some(stored) = stored_positions(&tiles) else {
        let formats: std::collections::BTreeSet<&str> =
            tiles.iter().map(|t| t.format.as_str()).collect();
        bail!(
            "{}: the {} tile files ({}) do not all store a stage position (or all store the same \
             one), so the layout cannot be read from them: give --grid ROWSxCOLS and --overlap",
            dir.display(),
            tiles.len(),
            formats.into_iter().collect::<Vec<_>>().join(", ")
        );
    };
    let pitch = scan_pitch(&tiles[0], pitch_um)?;
    let field_um = [
        tiles[0].cols as f64 * pitch.x_um(),
        tiles[0].rows as f64 * pitch.y_um(),
    ];
    let xs: Vec<f64> = stored.iter().map(|p| p[0]).collect();
    let ys: Vec<f64> = stored.iter().map(|p| p[1]).collect();
    let (col_of, cols) = cluster(&xs, field_um[0] / 2.0);
    let (row_of, rows) = cluster(&ys, field_um[1] / 2.0);
    if rows * cols != tiles.len() {
        bail!(
            "{}: the files' stage positions fall on {rows} rows x {cols} columns, which does not \
             hold {} tiles one per place; give --grid ROWSxCOLS and --overlap",
            dir.display(),
            tiles.len()
        );
    }
    let mut taken: Vec<Option<usize>> = vec![None; rows * cols];
    for i in 0..tiles.len() {
        let cell = row_of[i] * cols + col_of[i];
        if let Some(j) = taken[cell] {
            bail!(
                "{} and {}: both stored at row {}, col {} ({:.3}, {:.3} um and {:.3}, {:.3} um): \
                 two tiles at one place; give --grid ROWSxCOLS and --overlap",
                tiles[j].path.display(),
                tiles[i].path.display(),
                row_of[i],
                col_of[i],
                stored[j][0],
                stored[j][1],
                stored[i][0],
                stored[i][1]
            );
        }
        taken[cell] = Some(i);
    }
    let placed: Vec<Placed> = tiles
        .iter()
        .enumerate()
        .map(|(i, t)| Placed {
            file: &t.path,
            row: row_of[i],
            col: col_of[i],
            stage_um: stored[i],
        })
        .collect();
    let comment = format!(
        "# Inferred by surfstream stitch from the stage positions stored in the tiles of\n\
         # {} ({} x {} px each, rows x cols), acquisition order = file-name order.\n",
        dir.display(),
        tiles[0].rows,
        tiles[0].cols
    );
    let text = manifest_text(
        &comment,
        dir,
        rows,
        cols,
        pitch_um.map(|_| pitch),
        height_unit,
        &placed,
    )?;
    Ok((text, rows, cols))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grids_overlaps_and_file_order_parse() {
        assert_eq!("3x4".parse::<TileGrid>(), Ok(TileGrid { rows: 3, cols: 4 }));
        assert!("3by4"
            .parse::<TileGrid>()
            .unwrap_err()
            .contains("ROWSxCOLS"));
        assert!("0x4".parse::<TileGrid>().is_err());
        assert_eq!("20%".parse::<Overlap>(), Ok(Overlap(0.2)));
        assert_eq!("0.15".parse::<Overlap>(), Ok(Overlap(0.15)));
        assert!("95%".parse::<Overlap>().is_err());
        let mut names = ["t_10.npy", "t_2.npy", "t_1.npy"];
        names.sort_by_key(|n| natural_key(n));
        assert_eq!(names, ["t_1.npy", "t_2.npy", "t_10.npy"]);
    }

    /// A 4 x 3 px (cols x rows) Gwyddion simple field at 1 um pitch, with `XOffset`/`YOffset`
    /// when `at_um` is given.
    fn gsf(path: &Path, at_um: Option<[f64; 2]>) {
        let mut header = String::from(
            "Gwyddion Simple Field 1.0\nXRes = 4\nYRes = 3\nXReal = 4e-06\nYReal = 3e-06\n\
             XYUnits = m\nZUnits = m\n",
        );
        if let Some([x, y]) = at_um {
            header += &format!("XOffset = {:e}\nYOffset = {:e}\n", x * 1e-6, y * 1e-6);
        }
        let mut b = header.into_bytes();
        let pad = 4 - b.len() % 4;
        b.extend(std::iter::repeat_n(0u8, pad));
        for i in 0..12 {
            b.extend_from_slice(&(i as f32 * 1e-7).to_le_bytes());
        }
        std::fs::write(path, b).unwrap();
    }

    /// (row, col, stage x, stage y) of every [[tile]] in file order.
    fn tiles_of(toml_text: &str) -> Vec<(usize, usize, f64, f64)> {
        let v: toml::Value = toml_text.parse().unwrap();
        v["tile"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| {
                // `0` is written as an integer; scan.toml reads either.
                let num = |v: &toml::Value| v.as_float().or(v.as_integer().map(|i| i as f64));
                (
                    t["row"].as_integer().unwrap() as usize,
                    t["col"].as_integer().unwrap() as usize,
                    num(&t["stage_x_um"]).unwrap(),
                    num(&t["stage_y_um"]).unwrap(),
                )
            })
            .collect()
    }

    /// A 2 x 3 serpentine scan at 25 % overlap (steps 3 um and 2.25 um) whose files store their
    /// stage positions, with a little stage error: the layout comes from the files alone, and
    /// a grid that disagrees is an error naming the first file off it.
    #[test]
    fn stored_stage_positions_give_the_layout_and_check_the_grid() {
        let dir = tempfile::tempdir().unwrap();
        // Acquisition order (file names): row 0 left to right, row 1 right to left.
        let places = [(0, 0), (0, 1), (0, 2), (1, 2), (1, 1), (1, 0)];
        let mut want = Vec::new();
        for (i, (row, col)) in places.iter().enumerate() {
            let at = [
                1000.0 + *col as f64 * 3.0 + 0.05 * i as f64,
                -500.0 + *row as f64 * 2.25 - 0.03 * i as f64,
            ];
            gsf(&dir.path().join(format!("t_{}.gsf", i + 1)), Some(at));
            want.push((*row, *col, at[0], at[1]));
        }
        let (text, rows, cols) = infer_manifest_from_positions(dir.path(), None, None).unwrap();
        assert_eq!((rows, cols), (2, 3));
        let got = tiles_of(&text);
        for (g, w) in got.iter().zip(&want) {
            assert_eq!((g.0, g.1), (w.0, w.1));
            assert!(
                (g.2 - w.2).abs() < 1e-9 && (g.3 - w.3).abs() < 1e-9,
                "{g:?} {w:?}"
            );
        }
        // The right grid agrees, and the files' positions go into the manifest.
        let layout = GridLayout {
            rows: 2,
            cols: 3,
            overlap_x: 0.25,
            overlap_y: 0.25,
            serpentine: true,
        };
        let text = infer_manifest(dir.path(), &layout, None, None).unwrap();
        assert!(text.contains("the files' own"), "{text}");
        assert_eq!(tiles_of(&text), got);
        // Without --serpentine the fourth tile is 6 um (1.5 fields) off: an error naming it.
        let e = format!(
            "{:#}",
            infer_manifest(
                dir.path(),
                &GridLayout {
                    serpentine: false,
                    ..layout
                },
                None,
                None
            )
            .unwrap_err()
        );
        assert!(
            e.contains("t_4.gsf") && e.contains("off in x") && e.contains("--serpentine"),
            "{e}"
        );
        // 3 x 2 instead of 2 x 3: the second tile is a row down in the grid, not in the files.
        let e = format!(
            "{:#}",
            infer_manifest(
                dir.path(),
                &GridLayout {
                    rows: 3,
                    cols: 2,
                    ..layout
                },
                None,
                None
            )
            .unwrap_err()
        );
        assert!(e.contains("t_3.gsf") && e.contains("--grid 3x2"), "{e}");
        // A wrong overlap (50 % instead of 25 %) is 1 um = 25 % of a field off at the 2nd tile.
        let e = format!(
            "{:#}",
            infer_manifest(
                dir.path(),
                &GridLayout {
                    overlap_x: 0.5,
                    ..layout
                },
                None,
                None
            )
            .unwrap_err()
        );
        assert!(e.contains("t_2.gsf"), "{e}");
    }

    /// The gsf tiles carry 1 um: `--pitch-um 1` agrees and is accepted, `--pitch-um 0.8` is
    /// refused naming the file and both pitches (it used to rescale the scan silently).
    #[test]
    fn a_pitch_that_disagrees_with_the_files_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        for i in 0..4 {
            gsf(&dir.path().join(format!("t_{i}.gsf")), None);
        }
        let layout = GridLayout {
            rows: 2,
            cols: 2,
            overlap_x: 0.25,
            overlap_y: 0.25,
            serpentine: false,
        };
        let text = infer_manifest(dir.path(), &layout, Some(1.0), None).unwrap();
        assert!(text.contains("pitch_x_um = 1\n"), "{text}");
        assert!(!text.contains("height_unit"), "{text}");
        // A stated height unit goes into [scan] (the loader applies and checks it).
        let text = infer_manifest(dir.path(), &layout, Some(1.0), Some("nm")).unwrap();
        let scan = text.split("[[tile]]").next().unwrap_or_default();
        assert!(scan.contains("height_unit = \"nm\"\n"), "{text}");
        let e = format!(
            "{:#}",
            infer_manifest(dir.path(), &layout, Some(0.8), None).unwrap_err()
        );
        assert!(
            e.contains("t_0.gsf") && e.contains("1 x 1 um") && e.contains("--pitch-um 0.8"),
            "{e}"
        );
    }

    #[test]
    fn files_without_positions_need_a_grid() {
        let dir = tempfile::tempdir().unwrap();
        for i in 0..4 {
            gsf(&dir.path().join(format!("t_{i}.gsf")), None);
        }
        let e = format!(
            "{:#}",
            infer_manifest_from_positions(dir.path(), None, None).unwrap_err()
        );
        assert!(
            e.contains("do not all store a stage position") && e.contains("--grid"),
            "{e}"
        );
        // The same position in every file says nothing either.
        for i in 0..4 {
            gsf(&dir.path().join(format!("t_{i}.gsf")), Some([0.0, 0.0]));
        }
        assert!(infer_manifest_from_positions(dir.path(), None, None).is_err());
        // Two tiles at one place.
        for (i, at) in [[0.0, 0.0], [3.0, 0.0], [0.0, 2.25], [0.1, 0.1]]
            .into_iter()
            .enumerate()
        {
            gsf(&dir.path().join(format!("t_{i}.gsf")), Some(at));
        }
        let e = format!(
            "{:#}",
            infer_manifest_from_positions(dir.path(), None, None).unwrap_err()
        );
        assert!(
            e.contains("two tiles at one place") || e.contains("does not"),
            "{e}"
        );
        // With a grid, files without positions get the nominal grid.
        for i in 0..4 {
            gsf(&dir.path().join(format!("t_{i}.gsf")), None);
        }
        let layout = GridLayout {
            rows: 2,
            cols: 2,
            overlap_x: 0.25,
            overlap_y: 0.25,
            serpentine: false,
        };
        let text = infer_manifest(dir.path(), &layout, None, None).unwrap();
        assert!(text.contains("nominal"), "{text}");
        assert_eq!(
            tiles_of(&text),
            [
                (0, 0, 0.0, 0.0),
                (0, 1, 3.0, 0.0),
                (1, 0, 0.0, 2.25),
                (1, 1, 3.0, 2.25)
            ]
        );
    }
}
