//! The CLI verbs that work on single files rather than graphs: each module owns one group of
//! verbs (its clap arguments and its `run`), so main.rs only dispatches. The checks every
//! file verb shares (one input file, the `-o/--out` convention) live here.

pub mod mesh;
pub mod metrology;
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

    /// [`read_surface`], then [`MaskArgs::apply`].
    pub fn read(&self, path: &Path) -> Result<Surface> {
        let mut s = read_surface(path)?;
        self.apply(path, &mut s)?;
        Ok(s)
    }
}

/// The formats `convert` writes (surfstream_io::formats::write_surface), by extension.
pub const WRITABLE: &[&str] = &["x3p", "npy"];

/// `path` must be one existing file: a folder or a missing path is named as such, not as an
/// "unsupported format '.'".
pub fn one_file(path: &Path, verb: &str) -> Result<()> {
    if path.is_dir() {
        let hint = if path.join("scan.toml").is_file() {
            format!(
                " (it holds a scan: stitch it with `surfstream stitch {} -o OUT`)",
                path.display()
            )
        } else {
            String::new()
        };
        bail!(
            "{}: is a folder; {verb} takes one height-map file ({}){hint}",
            path.display(),
            readable_list()
        );
    }
    if !path.exists() {
        bail!("{}: no such file", path.display());
    }
    Ok(())
}

fn readable_list() -> String {
    surfstream_io::formats::EXTENSIONS
        .iter()
        .map(|e| format!(".{e}"))
        .collect::<Vec<_>>()
        .join(", ")
}

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
        (None, None) => bail!("convert: no output: write `convert IN -o OUT.x3p` (or .npy)"),
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
            e.contains("cannot write .png files; the formats convert writes are .x3p, .npy"),
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
}
