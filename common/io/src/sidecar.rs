//! The pitch of a `.npy` height map travels in a sidecar: `NAME.npy` + `NAME.npy.json`.
//!
//! A `.npy` holds numbers only; without the sidecar its pitch is unknown (1 um, with a
//! warning in every verb). Every surface surfstream writes as `.npy` (`convert`, `separate`,
//! a run's panorama / datum / roughness / pooled map) gets one, and every reader of a `.npy`
//! surface ([`crate::formats::read_surface`]) reads it back. The one convention:
//!
//! ```json
//! {
//!   "sidecar": "surfstream npy geometry 1",
//!   "array": "roughness.npy",
//!   "pitch_um": { "x": 0.5, "y": 0.5 },
//!   "height_unit": "um",
//!   "axes": "first axis = rows = y (row 0 = smallest y), second axis = cols = x",
//!   "origin_um": { "x": 0.0, "y": 0.0 }
//! }
//! ```
//!
//! `pitch_um` is required (x = spacing of the columns, y = of the rows, micrometres);
//! `height_unit` must be "um" when present; `origin_um` (where pixel (0, 0) sits, the file's
//! stage position) is optional. Other keys are ignored, so a person may add notes.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::Serialize;
use serde_json::Value;

/// The value of the `sidecar` key this module writes.
pub const SIDECAR_TAG: &str = "surfstream npy geometry 1";

/// What a sidecar says about its array.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NpyGeometry {
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    /// Where pixel (0, 0) sits, um (x, y); None when unknown.
    pub origin_um: Option<[f64; 2]>,
}

/// `x.npy` -> `x.npy.json` (the whole file name plus `.json`: it cannot collide with a run's
/// `run.json` or `separate.json`, and sorts next to its array).
pub fn sidecar_path(npy: &Path) -> PathBuf {
    let mut name = npy.as_os_str().to_owned();
    name.push(".json");
    PathBuf::from(name)
}

/// Writes `npy`'s sidecar (atomically).
pub fn write_sidecar(npy: &Path, g: &NpyGeometry) -> Result<()> {
    write_sidecar_to(None, npy, g)
}

/// Writes `npy`'s sidecar as one file of `set` (it appears on the set's commit).
pub fn write_sidecar_into(
    set: &mut surfstream_core::fsutil::OutputSet,
    npy: &Path,
    g: &NpyGeometry,
) -> Result<()> {
    write_sidecar_to(Some(set), npy, g)
}

/// The sidecar as written. Fields in key order: the file has always listed its keys sorted.
#[derive(Serialize)]
struct SidecarFile<'a> {
    array: String,
    axes: &'a str,
    height_unit: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    origin_um: Option<PointUm>,
    pitch_um: PointUm,
    sidecar: &'a str,
}

/// An (x, y) pair in um.
#[derive(Serialize)]
struct PointUm {
    x: f64,
    y: f64,
}

fn write_sidecar_to(
    set: Option<&mut surfstream_core::fsutil::OutputSet>,
    npy: &Path,
    g: &NpyGeometry,
) -> Result<()> {
    for (field, v) in [("pitch x", g.pitch_x_um), ("pitch y", g.pitch_y_um)] {
        if !(v.is_finite() && v > 0.0) {
            bail!(
                "{}: {field} {v} um: expected a finite positive pitch",
                npy.display()
            );
        }
    }
    let array = npy
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let doc = SidecarFile {
        array,
        axes: "first axis = rows = y (row 0 = smallest y), second axis = cols = x",
        height_unit: "um",
        origin_um: g.origin_um.map(|[x, y]| PointUm { x, y }),
        pitch_um: PointUm {
            x: g.pitch_x_um,
            y: g.pitch_y_um,
        },
        sidecar: SIDECAR_TAG,
    };
    let path = sidecar_path(npy);
    let text = serde_json::to_string_pretty(&doc)?;
    let fill = |w: &mut std::io::BufWriter<std::fs::File>| {
        use std::io::Write;
        w.write_all(text.as_bytes())
            .with_context(|| format!("{}: write failed", path.display()))?;
        w.write_all(b"\n")?;
        Ok(())
    };
    match set {
        Some(set) => set.write(&path, fill),
        None => surfstream_core::fsutil::write_atomic(&path, fill),
    }
}

/// Removes a sidecar left by an earlier file of the same name (a `.npy` written without a
/// pitch must not pick up an old one).
pub fn remove_stale_sidecar(npy: &Path) -> Result<()> {
    let path = sidecar_path(npy);
    match std::fs::remove_file(&path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => {
            Err(e).with_context(|| format!("{}: cannot remove the stale sidecar", path.display()))
        }
    }
}

/// Reads `npy`'s sidecar: None when there is none; an error naming the file and the field
/// when there is one that does not say a pitch in um.
pub fn read_sidecar(npy: &Path) -> Result<Option<NpyGeometry>> {
    let path = sidecar_path(npy);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("{}: cannot read", path.display())),
    };
    let doc: Value = serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not JSON (the pitch sidecar of {})",
            path.display(),
            npy.display()
        )
    })?;
    let number = |v: Option<&Value>, field: &str| -> Result<f64> {
        match v.and_then(Value::as_f64) {
            Some(x) if x.is_finite() => Ok(x),
            _ => bail!(
                "{}: {field}: expected a finite number (micrometres), found {}",
                path.display(),
                v.map_or("nothing".to_string(), |v| v.to_string())
            ),
        }
    };
    let pitch = doc.get("pitch_um");
    let pitch_x_um = number(pitch.and_then(|p| p.get("x")), "pitch_um.x")?;
    let pitch_y_um = number(pitch.and_then(|p| p.get("y")), "pitch_um.y")?;
    for (field, v) in [("pitch_um.x", pitch_x_um), ("pitch_um.y", pitch_y_um)] {
        if v <= 0.0 {
            bail!(
                "{}: {field} = {v}: expected a positive pitch in um",
                path.display()
            );
        }
    }
    if let Some(u) = doc.get("height_unit") {
        if u.as_str() != Some("um") {
            bail!(
                "{}: height_unit = {u}: expected \"um\" (surfstream's .npy heights are micrometres)",
                path.display()
            );
        }
    }
    let origin_um = match doc.get("origin_um") {
        None | Some(Value::Null) => None,
        Some(o) => Some([
            number(o.get("x"), "origin_um.x")?,
            number(o.get("y"), "origin_um.y")?,
        ]),
    };
    Ok(Some(NpyGeometry {
        pitch_x_um,
        pitch_y_um,
        origin_um,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_typed_sidecar_is_byte_identical_to_the_json_value_it_replaces() {
        let d = tempfile::tempdir().unwrap();
        let npy = d.path().join("a.npy");
        for origin_um in [None, Some([10.0, -3.5])] {
            let g = NpyGeometry {
                pitch_x_um: 2.2797945189999997,
                pitch_y_um: 0.5,
                origin_um,
            };
            write_sidecar(&npy, &g).unwrap();
            let mut old = serde_json::json!({
                "sidecar": SIDECAR_TAG,
                "array": "a.npy",
                "pitch_um": { "x": g.pitch_x_um, "y": g.pitch_y_um },
                "height_unit": "um",
                "axes": "first axis = rows = y (row 0 = smallest y), second axis = cols = x",
            });
            if let Some([x, y]) = origin_um {
                old["origin_um"] = serde_json::json!({ "x": x, "y": y });
            }
            let old = serde_json::to_string_pretty(&old).unwrap() + "\n";
            assert_eq!(std::fs::read_to_string(sidecar_path(&npy)).unwrap(), old);
        }
    }

    #[test]
    fn round_trip_and_named_errors() {
        let d = tempfile::tempdir().unwrap();
        let npy = d.path().join("a.npy");
        assert_eq!(sidecar_path(&npy), d.path().join("a.npy.json"));
        assert_eq!(read_sidecar(&npy).unwrap(), None);
        let g = NpyGeometry {
            pitch_x_um: 2.2797945189999997,
            pitch_y_um: 0.5,
            origin_um: Some([10.0, -3.5]),
        };
        write_sidecar(&npy, &g).unwrap();
        assert_eq!(read_sidecar(&npy).unwrap(), Some(g));
        remove_stale_sidecar(&npy).unwrap();
        assert_eq!(read_sidecar(&npy).unwrap(), None);
        remove_stale_sidecar(&npy).unwrap();

        let bad = |text: &str| {
            std::fs::write(sidecar_path(&npy), text).unwrap();
            read_sidecar(&npy).unwrap_err().to_string()
        };
        assert!(bad("{").contains("not JSON"));
        assert!(bad(r#"{"pitch_um": {"x": 1}}"#).contains("pitch_um.y: expected a finite number"));
        assert!(bad(r#"{"pitch_um": {"x": 1, "y": -1}}"#).contains("pitch_um.y = -1"));
        assert!(
            bad(r#"{"pitch_um": {"x": 1, "y": 1}, "height_unit": "nm"}"#)
                .contains("height_unit = \"nm\"")
        );
        assert!(write_sidecar(
            &npy,
            &NpyGeometry {
                pitch_x_um: 0.0,
                pitch_y_um: 1.0,
                origin_um: None
            }
        )
        .is_err());
    }
}
