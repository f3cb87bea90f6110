//! report.html end to end: a small graph run (threads, fast pacing, 256 px fields) writes one
//! self-contained page: no external resource, the panorama / datum / roughness / pooled
//! previews as PNG data: URIs, the tile layout as inline SVG, the parameter and Table-6
//! deviation tables, the latencies and the mesh statistics, all taken from the same run.json.

use surfstream_e2e::{read_json, run, stderr, surfstream};

#[test]
fn report_is_one_self_contained_page_with_every_section() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let mut cmd = surfstream();
    cmd.args(["run", "launch/graphs/demo.toml", "--out"])
        .arg(&out)
        .args([
            "--set",
            "stage.pacing=\"fast\"",
            "--set",
            "stage.tile_px=256",
        ]);
    let o = run(cmd);
    assert!(o.status.success(), "{}", stderr(&o));
    let html = std::fs::read_to_string(out.join("report.html")).expect("report.html written");
    let run_json = read_json(&out.join("run.json"));

    // Self-contained: every src / href is inline data or a fragment, nothing is linked.
    for attr in ["src=\"", "href=\""] {
        for (k, _) in html.match_indices(attr) {
            let value = &html[k + attr.len()..];
            assert!(
                value.starts_with("data:") || value.starts_with('#'),
                "external {attr}{}",
                &value[..value.len().min(60)]
            );
        }
    }
    for tag in ["<link", "<script", "@import", "url(http"] {
        assert!(!html.contains(tag), "report.html contains {tag}");
    }

    // The previews, inline PNGs (base64 of the PNG signature starts with iVBORw0KGgo).
    for name in ["panorama", "datum", "roughness", "pooled"] {
        let img = format!("<img alt=\"{name}\" src=\"data:image/png;base64,iVBORw0KGgo");
        assert!(html.contains(&img), "no inline {name} preview");
    }
    // The tile layout: registered (solid) and stage (dashed) outlines of all four fields.
    assert!(html.contains("<h2>Tile layout</h2>") && html.contains("<svg"));
    assert!(html.contains("stroke-dasharray"));
    let tiles = run_json["tiles"].as_array().unwrap();
    assert_eq!(tiles.len(), 4);

    // Parameters and Table 6: every stage and region of run.json's deviation, with the judged
    // parameters' values.
    assert!(html.contains("<h2>Parameters and deviation (Table 6)</h2>"));
    let dev = &run_json["deviation"]["stages"];
    for (stage, st) in dev.as_object().expect("deviation stages in run.json") {
        assert!(
            html.contains(&format!("<h3>{stage} (pass:")),
            "no table for {stage}"
        );
        for region in st["regions"].as_object().unwrap().keys() {
            assert!(
                html.contains(&format!("<td class=\"k\">{region}</td>")),
                "{region}"
            );
        }
    }
    assert!(html.contains("<td>Sa *</td>") && html.contains("<td>Sdr</td>"));

    // Latencies and mesh statistics, the numbers of this run.
    assert!(html.contains("<h2>Latencies (ms)</h2>"));
    assert!(
        html.contains("tile_to_mesh") || html.contains("mesh"),
        "no mesh latency"
    );
    assert!(html.contains("<h2>Mesh</h2>"));
    let mesh = &run_json["stages"]["mesher"];
    let triangles = mesh["triangles"]
        .as_u64()
        .expect("mesher triangles in run.json");
    assert!(
        html.contains(&format!("<td>{triangles}</td>")),
        "triangle count not shown"
    );
    assert!(html.contains("<td class=\"k\">watertight</td><td>true</td>"));
    assert!(html.contains("<th>height field</th><th>mesh resampled</th>"));
    assert!(html.contains("<td class=\"k\">Sdr %</td>"));
}
