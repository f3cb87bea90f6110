//! The CLI verbs that work on single files rather than graphs: each module owns one group of
//! verbs (its clap arguments and its `run`), so main.rs only dispatches. The checks every
//! file verb shares (one input file, the `-o/--out` convention) live here.

pub mod finish;
pub mod mesh;
pub mod metrology;
pub mod prep;
pub mod separate;

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use surfstream_io::formats::{read_surface, Surface};

/// `--mask-exclude`, shared by every verb that reads a height map: an X3P colour mask (x3ptools
/// / FiX3P) labels regions, and every point is read as measured unless its region is named here.
#[derive(Args, Debug, Clone, Default)]
pub struct MaskArgs {
    /// Drop one labelled region of the file's X3P colour mask (its points become not
    /// measured): its annotation, "background", or its colour #rrggbb. Repeat for several.
    /// `inspect` lists the regions.
    #[arg(long = "mask-exclude", value_name = "NAME|#COLOUR")]
    pub mask_exclude: Vec<String>,
}

impl MaskArgs {
    /// Drops the named regions from `s`, read from `path`; says on stderr what it dropped.
    pub fn apply(&self, path: &Path, s: &mut Surface) -> Result<()> {
        if self.mask_exclude.is_empty() {
            return Ok(());
        }
        let dropped = s
            .exclude_mask_regions(&self.mask_exclude)
            .with_context(|| format!("{}: --mask-exclude", path.display()))?;
        eprintln!(
            "{}: --mask-exclude {}: {dropped} points dropped (read as not measured)",
            path.display(),
            self.mask_exclude.join(", ")
        );
        Ok(())
    }
}

/// The formats `convert` writes (surfstream_io::formats::write_surface), by extension.
pub const WRITABLE: &[&str] = surfstream_io::formats::WRITABLE;

/// Output formats that store a pitch: writing one from a file without a pitch would turn the
/// assumed 1 um into a claim, so `convert` refuses unless `--pitch-um` is given.
pub const WRITABLE_WITH_PITCH: &[&str] = &["x3p", "gsf", "tif", "tiff"];

/// `v` with `digits` significant digits (fixed-point where it reads well): how every verb
/// prints a pitch or a bound ("2.280", "0.001000"); core's, so the verdict and the report
/// agree ([`surfstream_core::units`]).
pub use surfstream_core::units::sig;

/// A pitch as every verb prints it: "2.280 um", or "2.280 x 1.000 um" (x, y) when they
/// differ; 4 significant digits.
pub fn pitch_text(pitch_x_um: f64, pitch_y_um: f64) -> String {
    if pitch_x_um == pitch_y_um {
        format!("{} um", sig(pitch_x_um, 4))
    } else {
        format!("{} x {} um (x, y)", sig(pitch_x_um, 4), sig(pitch_y_um, 4))
    }
}

/// A height map read for a verb, with whether its pitch is the 1 um stand-in.
pub struct Loaded {
    pub surface: Surface,
    pub pitch_assumed: bool,
}

/// Reads `path` for `verb` with the one `--pitch-um` rule of every verb: a file that carries
/// its pitch (every instrument format, a `.npy` with its `NAME.npy.json` sidecar) keeps it,
/// and a `--pitch-um` that disagrees with it is refused; a file without one takes
/// `--pitch-um`, or 1 um with a warning (`warn_assumed`). The reader's warnings are printed
/// with the file name.
pub fn load_surface(
    path: &Path,
    pitch_um: Option<f64>,
    verb: &str,
    warn_assumed: bool,
) -> Result<Loaded> {
    if let Some(p) = pitch_um {
        if !(p.is_finite() && p > 0.0) {
            bail!("--pitch-um {p}: expected a finite positive pitch in um");
        }
    }
    let mut s = read_surface(path)?;
    for w in &s.metadata.warnings {
        eprintln!("{}: warning: {w}", path.display());
    }
    let mut pitch_assumed = false;
    match (pitch_um, s.metadata.pitch_known) {
        (Some(p), true) => {
            let same = |a: f64| (a - p).abs() <= 1e-6 * p;
            if !(same(s.pitch_x_um) && same(s.pitch_y_um)) {
                let from = s
                    .metadata
                    .extra
                    .get("pitch_from")
                    .map_or(String::new(), |f| format!(" (from {f})"));
                bail!(
                    "{}: the file carries its pitch, {}{from}; --pitch-um {} disagrees: {verb} \
                     takes --pitch-um only for files without a pitch (leave it out)",
                    path.display(),
                    pitch_text(s.pitch_x_um, s.pitch_y_um),
                    sig(p, 4)
                );
            }
        }
        (Some(p), false) => {
            s.pitch_x_um = p;
            s.pitch_y_um = p;
        }
        (None, true) => {}
        (None, false) => {
            pitch_assumed = true;
            if warn_assumed {
                eprintln!(
                    "{}: warning: the file carries no pitch; {verb} assumed {} (give --pitch-um, \
                     or keep a {} sidecar beside it)",
                    path.display(),
                    pitch_text(s.pitch_x_um, s.pitch_y_um),
                    surfstream_io::sidecar::sidecar_path(Path::new("NAME.npy")).display()
                );
            }
        }
    }
    Ok(Loaded {
        surface: s,
        pitch_assumed,
    })
}

/// The readable height-map files of a folder (not its sub-folders), in natural file-name
/// order (`t_2` before `t_10`): what `params DIR` and `convert DIR` work through.
pub fn readable_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("{}: cannot list the folder", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && surfstream_io::formats::is_surface_file(p))
        .collect();
    files.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));
    if files.is_empty() {
        bail!(
            "{}: no height-map files in the folder (readable: {})",
            dir.display(),
            readable_list()
        );
    }
    Ok(files)
}

/// Compares names with runs of digits as numbers.
fn natural_cmp(a: &str, b: &str) -> std::cmp::Ordering {
    let (mut a, mut b) = (a.chars().peekable(), b.chars().peekable());
    loop {
        match (a.peek().copied(), b.peek().copied()) {
            (None, None) => return std::cmp::Ordering::Equal,
            (None, _) => return std::cmp::Ordering::Less,
            (_, None) => return std::cmp::Ordering::Greater,
            (Some(x), Some(y)) if x.is_ascii_digit() && y.is_ascii_digit() => {
                let take = |it: &mut std::iter::Peekable<std::str::Chars>| {
                    let mut n = String::new();
                    while let Some(c) = it.peek().copied().filter(char::is_ascii_digit) {
                        n.push(c);
                        it.next();
                    }
                    n
                };
                let (na, nb) = (take(&mut a), take(&mut b));
                let (ta, tb) = (na.trim_start_matches('0'), nb.trim_start_matches('0'));
                let o = ta.len().cmp(&tb.len()).then(ta.cmp(tb));
                if o != std::cmp::Ordering::Equal {
                    return o;
                }
            }
            (Some(x), Some(y)) => {
                if x != y {
                    return x.cmp(&y);
                }
                a.next();
                b.next();
            }
        }
    }
}

/// `path` must be one existing file: a folder or a missing path is named as such, not as an
/// "unsupported format '.'" (the folder's message is the readers' and Python's:
/// [`surfstream_io::input::not_a_folder`]).
pub fn one_file(path: &Path, verb: &str) -> Result<()> {
    surfstream_io::input::not_a_folder(path, verb)?;
    if !path.exists() {
        bail!("{}: no such file", path.display());
    }
    Ok(())
}

/// The help of a verb's height-map argument, naming every readable extension: the same list
/// as the errors (one source, `surfstream_io::formats::EXTENSIONS`).
pub fn file_help() -> &'static str {
    static HELP: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    HELP.get_or_init(|| format!("Height-map file: {}", readable_list()))
}

/// The readable extensions, as every message lists them.
pub use surfstream_io::input::readable_list;

/// The output of `convert`: `-o OUT`, or the older second positional argument (with a
/// deprecation warning); its extension must be one `convert` writes.
pub fn convert_output(out: Option<PathBuf>, positional: Option<PathBuf>) -> Result<PathBuf> {
    let out = match (out, positional) {
        (Some(o), None) => o,
        (None, Some(p)) => {
            eprintln!(
                "convert: warning: the output as a second argument is deprecated; write `convert IN -o {}`",
                p.display()
            );
            p
        }
        (Some(o), Some(p)) => bail!(
            "convert: two outputs ({} and -o {}): give the output once, with -o",
            p.display(),
            o.display()
        ),
        (None, None) => bail!(
            "convert: no output: write `convert IN -o OUT.x3p` (or {})",
            WRITABLE[1..]
                .iter()
                .map(|e| format!(".{e}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext {
        Some(e) if WRITABLE.contains(&e.as_str()) => Ok(out),
        other => bail!(
            "{}: cannot write {}; the formats convert writes are {}",
            out.display(),
            other.map_or("a file without extension".into(), |e| format!(".{e} files")),
            WRITABLE
                .iter()
                .map(|e| format!(".{e}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn convert_takes_dash_o_or_the_old_positional_and_names_writable_formats() {
        let o = |s: &str| Some(PathBuf::from(s));
        assert_eq!(
            convert_output(o("a/b.x3p"), None).unwrap(),
            PathBuf::from("a/b.x3p")
        );
        assert_eq!(
            convert_output(None, o("b.NPY")).unwrap(),
            PathBuf::from("b.NPY")
        );
        let e = convert_output(o("x.png"), None).unwrap_err().to_string();
        assert!(
            e.contains(
                "cannot write .png files; the formats convert writes are .x3p, .npy, .gsf, .tif"
            ),
            "{e}"
        );
        let e = convert_output(o("x"), None).unwrap_err().to_string();
        assert!(e.contains("a file without extension"), "{e}");
        assert!(convert_output(o("a.npy"), o("b.npy")).is_err());
        assert!(convert_output(None, None).is_err());
    }

    #[test]
    fn a_folder_is_not_a_height_map() {
        let d = tempfile::tempdir().unwrap();
        let e = one_file(d.path(), "inspect").unwrap_err().to_string();
        assert!(
            e.contains("is a folder; inspect takes one height-map file (.npy"),
            "{e}"
        );
        assert!(!e.contains("unsupported format"), "{e}");
        let e = one_file(&d.path().join("nope.dat"), "inspect")
            .unwrap_err()
            .to_string();
        assert!(e.ends_with("nope.dat: no such file"), "{e}");
    }

    fn npy(dir: &Path, name: &str, rows: usize, cols: usize) -> PathBuf {
        let p = dir.join(name);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| ((i % cols) as f64 * 0.7).sin() + ((i / cols) as f64 * 0.3).cos())
            .collect();
        surfstream_io::npy::write_npy_f64(&p, &z, rows, cols).unwrap();
        p
    }

    #[test]
    fn one_pitch_rule_on_every_verb() {
        let d = tempfile::tempdir().unwrap();
        let bare = npy(d.path(), "bare.npy", 8, 9);
        // No pitch anywhere: the stand-in, flagged.
        let l = load_surface(&bare, None, "params", false).unwrap();
        assert!(l.pitch_assumed && l.surface.pitch_x_um == 1.0);
        // --pitch-um gives one.
        let l = load_surface(&bare, Some(0.5), "params", false).unwrap();
        assert!(!l.pitch_assumed && l.surface.pitch_y_um == 0.5);
        assert!(load_surface(&bare, Some(-1.0), "mesh", false).is_err());
        // A file with its pitch (the sidecar): kept; a disagreeing --pitch-um is refused by
        // every verb in the same words; an agreeing one is fine.
        surfstream_io::sidecar::write_sidecar(
            &bare,
            &surfstream_io::sidecar::NpyGeometry {
                pitch_x_um: 2.2797945189999997,
                pitch_y_um: 2.2797945189999997,
                origin_um: None,
            },
        )
        .unwrap();
        let l = load_surface(&bare, None, "separate", false).unwrap();
        assert!(!l.pitch_assumed && l.surface.pitch_x_um == 2.2797945189999997);
        for verb in ["params", "convert", "separate", "mesh"] {
            let e = load_surface(&bare, Some(1.0), verb, false)
                .err()
                .unwrap()
                .to_string();
            assert!(
                e.contains("the file carries its pitch, 2.280 um (from bare.npy.json); --pitch-um 1.000 disagrees")
                    && e.contains(&format!("{verb} takes --pitch-um only")),
                "{e}"
            );
        }
        assert!(load_surface(&bare, Some(2.2797945189999997), "mesh", false).is_ok());
    }

    #[test]
    fn pitches_and_bounds_print_with_four_significant_digits() {
        assert_eq!(
            pitch_text(2.2797945189999997, 2.2797945189999997),
            "2.280 um"
        );
        assert_eq!(pitch_text(0.5, 0.25), "0.5000 x 0.2500 um (x, y)");
        assert_eq!(sig(0.001, 4), "0.001000");
        assert_eq!(sig(1234.5678, 4), "1235");
        assert_eq!(sig(0.0, 4), "0");
    }

    #[test]
    fn folder_batches_list_readable_files_in_natural_order() {
        let d = tempfile::tempdir().unwrap();
        for n in ["t_10.npy", "t_2.npy", "notes.md", "t_1.npy"] {
            std::fs::write(d.path().join(n), b"x").unwrap();
        }
        std::fs::create_dir(d.path().join("sub.npy")).unwrap();
        let names: Vec<String> = readable_files(d.path())
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["t_1.npy", "t_2.npy", "t_10.npy"]);
        let e = readable_files(&d.path().join("sub.npy"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("no height-map files in the folder"), "{e}");
    }

    #[test]
    fn help_names_every_readable_extension_like_the_errors() {
        let help = file_help();
        for e in surfstream_io::formats::EXTENSIONS {
            assert!(help.contains(&format!(".{e}")), "{help} lacks .{e}");
        }
        let e = one_file(&PathBuf::from("."), "params")
            .unwrap_err()
            .to_string();
        assert!(e.contains(&readable_list()), "{e}");
    }

    #[test]
    fn mesh_writes_stl_under_an_stl_name_only() {
        assert!(mesh::check_stl_name(Path::new("a/k.stl")).is_ok());
        assert!(mesh::check_stl_name(Path::new("K.STL")).is_ok());
        let e = mesh::check_stl_name(Path::new("k.obj"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("k.obj: mesh writes STL"), "{e}");
        assert!(mesh::check_stl_name(Path::new("k")).is_err());
    }
}

/// `--force` of the single-file verbs (issue 36: `convert a.x3p -o a.x3p` rewrote its input,
/// `mesh ... -o notes.stl` replaced a file, `separate p.npy -o sf` wrote into a user's folder).
#[derive(clap::Args, Clone, Copy, Debug, Default)]
pub struct Overwrite {
    /// Replace output files that exist already (an input is never replaced).
    #[arg(long)]
    pub force: bool,
}

/// The files `path` stands for: itself, and a `.npy`'s pitch sidecar.
fn with_sidecar(path: &Path) -> Vec<PathBuf> {
    let mut all = vec![path.to_path_buf()];
    let is_npy = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    if is_npy {
        all.push(surfstream_io::sidecar::sidecar_path(path));
    }
    all
}

/// The same file (both exist and are one inode), or the same path.
fn same_file(a: &Path, b: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (std::fs::metadata(a), std::fs::metadata(b)) {
        (Ok(x), Ok(y)) => x.dev() == y.dev() && x.ino() == y.ino(),
        _ => a == b,
    }
}

/// Checks, before any work, that the single-file verb `verb` may write `outputs` (each with
/// its sidecar): none is an input (or an input's sidecar), whatever `--force` says; none
/// exists unless `--force`; none is a folder, FIFO or device.
pub fn claim_output_files(
    verb: &str,
    inputs: &[&Path],
    outputs: &[&Path],
    overwrite: Overwrite,
) -> Result<()> {
    let inputs: Vec<PathBuf> = inputs.iter().flat_map(|p| with_sidecar(p)).collect();
    for out in outputs.iter().flat_map(|p| with_sidecar(p)) {
        if let Some(input) = inputs.iter().find(|i| same_file(i, &out)) {
            bail!(
                "{verb}: {} is {}: an input is never overwritten; choose another -o",
                out.display(),
                if *input == out {
                    "the input".to_string()
                } else {
                    format!("the input {}", input.display())
                }
            );
        }
        let Ok(meta) = std::fs::symlink_metadata(&out) else {
            continue;
        };
        if !meta.file_type().is_file() {
            bail!(
                "{verb}: {} exists and is not a regular file (a folder, link, FIFO or device): choose another -o",
                out.display()
            );
        }
        if !overwrite.force {
            bail!(
                "{verb}: {} exists: pass --force to replace it, or choose another -o",
                out.display()
            );
        }
    }
    Ok(())
}

/// Checks, before any work, that the verb may write into the folder `dir`: a new or empty
/// folder, or with `--force` an existing one; never a folder that is or holds an input.
pub fn claim_output_folder(
    verb: &str,
    inputs: &[&Path],
    dir: &Path,
    overwrite: Overwrite,
) -> Result<()> {
    let Ok(meta) = std::fs::symlink_metadata(dir) else {
        return Ok(()); // the verb makes it
    };
    if !meta.is_dir() {
        bail!(
            "{verb}: {} exists and is not a folder: choose another -o",
            dir.display()
        );
    }
    let canon = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
    for input in inputs {
        if input.canonicalize().is_ok_and(|i| i.starts_with(&canon)) {
            bail!(
                "{verb}: the output folder {} holds the input {}: choose another -o",
                dir.display(),
                input.display()
            );
        }
    }
    let empty = std::fs::read_dir(dir)
        .with_context(|| format!("{}: cannot read", dir.display()))?
        .next()
        .is_none();
    if !empty && !overwrite.force {
        bail!(
            "{verb}: {} is a folder that exists and is not empty (surfstream did not make it for this run): pass --force to write into it, or choose a new folder with -o",
            dir.display()
        );
    }
    Ok(())
}
