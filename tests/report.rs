//! report.html end to end: a small graph run (threads, fast pacing, 256 px fields) writes one
//! self-contained page with every section, built from that run's run.json and height maps;
//! headless Chromium (the Debian package `chromium`, installed by scripts/test.sh) loads it
//! offline, runs its script to the end without a console message, and draws it: the
//! screenshot is not blank and shows the viridis maps.

use std::path::Path;
use std::process::Command;

use surfstream_e2e::{read_json, small_demo};

const CHROMIUM: &str = "/usr/bin/chromium";

/// Headless Chromium with a fresh profile and nothing that reaches the network.
fn chromium(profile: &Path) -> Command {
    assert!(
        Path::new(CHROMIUM).exists(),
        "{CHROMIUM} not found: install the Debian package `chromium` (scripts/test.sh does)"
    );
    let mut c = Command::new("timeout");
    c.args(["180", CHROMIUM])
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.display()));
    c
}

#[test]
fn report_is_one_self_contained_page_with_every_section() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    small_demo(&out, &[]);
    let html = std::fs::read_to_string(out.join("report.html")).expect("report.html written");
    let run_json = read_json(&out.join("run.json"));
    let files: Vec<&str> = run_json["files"]
        .as_array()
        .expect("files in run.json")
        .iter()
        .filter_map(|f| f.as_str())
        .collect();

    // Self-contained: every src is inline data; every href is inline data, a fragment, or
    // one of the run's output files beside the page (the outputs list).
    for attr in ["src=\"", "href=\""] {
        for (k, _) in html.match_indices(attr) {
            let value = &html[k + attr.len()..];
            let value = &value[..value.find('"').unwrap_or(value.len())];
            let ok = value.starts_with("data:")
                || value.starts_with('#')
                || (attr == "href=\"" && files.contains(&value));
            assert!(ok, "external {attr}{}", &value[..value.len().min(60)]);
        }
    }
    for tag in [
        "<link",
        "<script src",
        "@import",
        "url(http",
        "http://",
        "https://",
    ] {
        assert!(!html.contains(tag), "report.html contains {tag}");
    }

    // Every section, in reading order.
    let mut at = 0;
    for id in [
        "summary",
        "parameters",
        "outputs",
        "maps",
        "view3d",
        "profile",
        "distribution",
        "table6",
        "tiles",
        "mesh",
        "latencies",
        "nodes",
    ] {
        let k = html[at..]
            .find(&format!("id=\"{id}\""))
            .unwrap_or_else(|| panic!("section {id} missing or out of order"));
        at += k;
    }
    // The summary: scan size, pitch, the verdict as run.json has it.
    assert!(html.contains("2 x 2 tiles (rows x cols), each 256 x 256 px"));
    assert!(html.contains("0.8148 µm"));
    let pass = run_json["deviation"]["pass"]
        .as_bool()
        .expect("deviation.pass");
    assert!(html.contains(if pass {
        "<div class=\"verdict pass\"><b>PASS</b>"
    } else {
        "<div class=\"verdict fail\"><b>FAIL</b>"
    }));
    // Key parameters of the panorama with 3 significant figures and their unit (nm below
    // 1 µm).
    let sa_row = "<td class=\"k\"><b>Sa</b></td><td>arithmetic mean height</td><td>";
    let sa = html
        .split_once(sa_row)
        .and_then(|(_, rest)| rest.split_once("</td>"))
        .map(|(cell, _)| cell)
        .expect("the key parameters' Sa row");
    let (number, unit) = sa.split_once(' ').expect("a value and its unit");
    assert!(unit == "µm" || unit == "nm", "{sa}");
    let figures = number.trim_start_matches(['-', '0', '.']).replace('.', "");
    assert_eq!(figures.len(), 3, "3 significant figures: {sa}");
    // Four maps as inline PNGs inside SVG figures with axes, colour bar and "not measured".
    for name in ["panorama", "datum", "roughness", "pooled"] {
        assert!(
            html.contains(&format!("<figure class=\"map\" id=\"map-{name}\">")),
            "{name}"
        );
    }
    assert_eq!(
        html.matches("href=\"data:image/png;base64,iVBORw0KGgo")
            .count(),
        4
    );
    assert!(html.matches(">not</text>").count() == 4 && html.contains(">x (µm)</text>"));
    assert!(html.contains("Colour scale clipped to the 0.5 / 99.5 percentiles"));
    // Charts: profile cut, histogram + Abbott-Firestone, PSD, and the 3-D render.
    assert!(html.contains("aria-label=\"profile cut\""));
    assert!(html.contains("material ratio Mr (%)"));
    assert!(html.contains("aria-label=\"power spectral density\""));
    assert!(html.contains("<img class=\"zoomable view3d\""));

    // Table 6: each stage says which grid it was judged on; the pooled map on its own.
    let dev = run_json["deviation"]["stages"]
        .as_object()
        .expect("deviation stages in run.json");
    let pooled_px = &run_json["stages"]["wavelet"]["final"]["pooled_px"];
    assert_eq!(
        dev["pooled"]["grid"]["cols"], pooled_px[0],
        "pooled judged on its own grid"
    );
    assert_eq!(dev["pooled"]["grid"]["cell_px"], 4);
    let mut failures = 0;
    for (stage, st) in dev {
        let grid = st["grid"]["name"].as_str().expect("grid name");
        assert!(
            html.contains(&format!("<b>{stage}</b></td><td>{grid}</td>")),
            "{stage} on {grid}"
        );
        // A stage that is not what the STL is made from is reported, not judged; the mesh is
        // judged against its tolerance (limits_pct), the others against 5 %.
        if st["judged"] == false {
            assert!(
                html.contains("reported</span>"),
                "{stage}: not shown as reported"
            );
            continue;
        }
        for r in st["regions"].as_object().unwrap().values() {
            for p in ["Sa", "Sq", "Sz"] {
                let limit = st["limits_pct"][p].as_f64().unwrap_or(5.0);
                if r["deviation_pct"][p]
                    .as_f64()
                    .is_none_or(|d| d.abs() > limit)
                {
                    failures += 1;
                }
            }
        }
    }
    if failures > 0 {
        assert!(
            html.contains(&format!(
                "<h3>Out of bounds ({failures} judged values)</h3>"
            )),
            "{failures} failures"
        );
    }
    assert!(html.contains("<details><summary>Full table:"));
    // Internal bookkeeping is not shown; latencies are, collapsed, with words for names.
    for internal in [
        "t_acquired_ns",
        "t_written_ns",
        "live_frames_skipped",
        "live_patches",
    ] {
        assert!(!html.contains(internal), "{internal} shown");
    }
    assert!(html.contains("<details id=\"latencies\">") && html.contains("tile → panorama"));
    // The mesh: this run's triangle count.
    let triangles = run_json["stages"]["mesher"]["triangles"]
        .as_u64()
        .expect("mesher triangles in run.json");
    assert!(html.contains(&format!("<td>{triangles}</td>")));

    // Chromium: the script runs to its end (it marks the page) ...
    let profile = tempfile::tempdir().unwrap();
    let url = format!("file://{}", out.join("report.html").display());
    let dom = chromium(profile.path())
        .arg("--dump-dom")
        .arg(&url)
        .output()
        .expect("start chromium");
    assert!(
        dom.status.success(),
        "{}",
        String::from_utf8_lossy(&dom.stderr)
    );
    let dom_text = String::from_utf8_lossy(&dom.stdout);
    assert!(
        dom_text.contains("data-report-ready=\"1\""),
        "the page's script did not finish"
    );
    // ... without a console message (errors and warnings are logged as CONSOLE lines) ...
    let profile = tempfile::tempdir().unwrap();
    let shot = dir.path().join("report.png");
    let o = chromium(profile.path())
        .args([
            "--enable-logging=stderr",
            "--v=0",
            "--window-size=1366,6000",
        ])
        .arg(format!("--screenshot={}", shot.display()))
        .arg(&url)
        .output()
        .expect("start chromium");
    let log = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{log}");
    let console: Vec<&str> = log.lines().filter(|l| l.contains(":CONSOLE")).collect();
    assert!(
        console.is_empty(),
        "console messages:\n{}",
        console.join("\n")
    );
    // ... and draws: the screenshot is not blank and shows viridis map pixels.
    let file = std::fs::File::open(&shot).expect("screenshot written");
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .expect("screenshot is a PNG");
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).expect("screenshot frame");
    assert_eq!(info.width, 1366);
    let channels = info.color_type.samples();
    let pixels: Vec<[u8; 3]> = buf[..info.buffer_size()]
        .chunks_exact(channels)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    let white = pixels
        .iter()
        .filter(|p| p.iter().all(|&c| c >= 245))
        .count();
    assert!(
        white < pixels.len() * 9 / 10,
        "screenshot nearly blank: {white} of {} px white",
        pixels.len()
    );
    let viridis: Vec<[u8; 3]> = (0..256)
        .map(|i| surfstream_io::preview::viridis(i as f64 / 255.0))
        .collect();
    let near_viridis = pixels
        .iter()
        .step_by(7)
        .filter(|p| {
            viridis.iter().any(|v| {
                v.iter()
                    .zip(p.iter())
                    .all(|(a, b)| (*a as i32 - *b as i32).abs() <= 4)
            })
        })
        .count()
        * 7;
    assert!(
        near_viridis > pixels.len() / 10,
        "the maps are not drawn: {near_viridis} of {} px in viridis colours",
        pixels.len()
    );
}
