//! X3P colour masks (x3ptools / FiX3P) as region labels, through the release binary: every
//! point is measured by default, `inspect` lists the regions, and `--mask-exclude` drops
//! exactly a region's points in every verb that reads a height map.

use std::path::Path;

use serde_json::Value;
use surfstream_e2e::{run, stderr, surfstream};
use surfstream_io::formats::x3p::{ColourMask, MaskRegion};
use surfstream_io::formats::{Metadata, Surface};

const W: usize = 48;
const H: usize = 40;

/// Region of point (row, col): 1 "break-off" (a 10 x 12 corner), 2 "groove" (columns 30..34),
/// 3 an unannotated colour (one point), 0 the background.
fn label(r: usize, c: usize) -> u16 {
    if r < 10 && c < 12 {
        1
    } else if (30..34).contains(&c) {
        2
    } else if (r, c) == (35, 5) {
        3
    } else {
        0
    }
}

/// A 48 x 40 rough surface with a four-region colour mask, written by our X3P writer (the
/// reader's unit tests check the same layout against hand-built archives). Two points are
/// not measured (NaN), one inside "groove".
fn labelled_x3p(path: &Path) -> Vec<u16> {
    let labels: Vec<u16> = (0..W * H).map(|i| label(i / W, i % W)).collect();
    let count = |l: u16| labels.iter().filter(|&&x| x == l).count();
    let region = |colour: &str, name: Option<&str>, l: u16| MaskRegion {
        colour: colour.into(),
        annotation: name.map(str::to_string),
        background: l == 0,
        points: count(l),
    };
    let heights_um = (0..W * H)
        .map(|i| {
            if i == 3 * W + 31 || i == 20 * W + 20 {
                f64::NAN
            } else {
                ((i * 7919 % 1009) as f64 / 1009.0 - 0.5) * 2.0 + (i / W) as f64 * 0.01
            }
        })
        .collect();
    let s = Surface {
        width: W,
        height: H,
        pitch_x_um: 2.58,
        pitch_y_um: 2.58,
        heights_um,
        metadata: Metadata {
            format: "x3p".into(),
            pitch_known: true,
            mask: Some(ColourMask {
                image: "bindata/mask.png".into(),
                regions: vec![
                    region("#cd7f32", None, 0),
                    region("#1f376c", Some("break-off"), 1),
                    region("#629d4b", Some("groove"), 2),
                    region("#00ffff", None, 3),
                ],
                labels: labels.clone(),
            }),
            ..Metadata::default()
        },
    };
    surfstream_io::formats::x3p::write(path, &s).unwrap();
    labels
}

fn output(args: &[&str]) -> std::process::Output {
    run({
        let mut c = surfstream();
        c.args(args);
        c
    })
}

fn ok(args: &[&str]) -> String {
    let out = output(args);
    assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn valid_points(file: &str, extra: &[&str]) -> u64 {
    let mut args = vec!["params", file, "--json"];
    args.extend_from_slice(extra);
    let v: Value = serde_json::from_str(&ok(&args)).unwrap();
    v["valid_points"]
        .as_u64()
        .unwrap_or_else(|| panic!("valid_points in {v}"))
}

#[test]
fn mask_regions_are_labels_and_mask_exclude_drops_exactly_them() {
    let dir = tempfile::tempdir().unwrap();
    let x3p = dir.path().join("labelled.x3p");
    let labels = labelled_x3p(&x3p);
    let f = x3p.to_str().unwrap();
    let measured_in = |l: u16| {
        (0..W * H)
            .filter(|&i| labels[i] == l && i != 3 * W + 31 && i != 20 * W + 20)
            .count() as u64
    };
    let all = (W * H - 2) as u64;

    // inspect: every point measured but the two NaN, the regions listed.
    let text = ok(&["inspect", f]);
    assert!(text.contains("invalid     2 of 1920 points"), "{text}");
    for line in [
        "background  #cd7f32       1639 points  (background)",
        "break-off   #1f376c        120 points",
        "groove      #629d4b        160 points",
        "#00ffff     #00ffff          1 points",
    ] {
        assert!(text.contains(line), "{line:?} in\n{text}");
    }
    let json: Value = serde_json::from_str(&ok(&["inspect", f, "--json"])).unwrap();
    assert_eq!(json["invalid_points"], 2);
    assert_eq!(
        json["metadata"]["mask"]["regions"][2]["annotation"],
        "groove"
    );
    assert_eq!(json["metadata"]["mask"]["regions"][2]["points"], 160);

    // params: all measured points by default; each exclusion drops exactly its region.
    assert_eq!(valid_points(f, &[]), all);
    assert_eq!(
        valid_points(f, &["--mask-exclude", "break-off"]),
        all - measured_in(1)
    );
    assert_eq!(
        valid_points(
            f,
            &["--mask-exclude", "GROOVE", "--mask-exclude", "#00FFFF"]
        ),
        all - measured_in(2) - measured_in(3)
    );
    assert_eq!(
        valid_points(f, &["--mask-exclude", "background"]),
        all - measured_in(0)
    );
    let json: Value =
        serde_json::from_str(&ok(&["inspect", f, "--json", "--mask-exclude", "groove"])).unwrap();
    assert_eq!(json["invalid_points"], 2 + measured_in(2));

    // An unknown name: a clear error naming the regions there are.
    let out = output(&["params", f, "--mask-exclude", "grooves"]);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("mask region 'grooves' is not in the mask")
            && err.contains("'break-off' #1f376c (120 points)")
            && err.contains("'groove' #629d4b (160 points)")
            && !err.contains("panicked"),
        "{err}"
    );

    // convert: the excluded points are not measured in the output, the labels kept.
    let conv = dir.path().join("conv.x3p");
    ok(&[
        "convert",
        f,
        "-o",
        conv.to_str().unwrap(),
        "--mask-exclude",
        "break-off",
    ]);
    let back = surfstream_io::formats::read_surface(&conv).unwrap();
    assert_eq!(back.invalid_count() as u64, 2 + measured_in(1));
    assert_eq!(back.metadata.mask.as_ref().unwrap().labels, labels);

    // separate: the roughness is NaN exactly where the input is not measured.
    let sep = dir.path().join("sep");
    ok(&[
        "separate",
        f,
        "-o",
        sep.to_str().unwrap(),
        "--mask-exclude",
        "groove",
        "--level",
        "2",
    ]);
    let r = surfstream_io::npy::read_npy(sep.join("roughness.npy")).unwrap();
    let nan = r.data.iter().filter(|z| z.is_nan()).count() as u64;
    assert_eq!(nan, 2 + measured_in(2));

    // mesh: reads through the same path (the mesher's own tests cover missing samples).
    let stl = dir.path().join("m.stl");
    let out = output(&[
        "mesh",
        f,
        "-o",
        stl.to_str().unwrap(),
        "--mask-exclude",
        "break-off",
    ]);
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("--mask-exclude break-off: 120 points dropped"),
        "{err}"
    );
    assert_eq!(measured_in(1), 120);
}
