//! `report.html`: one self-contained page for people, written beside run.json, that a
//! metrologist can read top to bottom: the summary (input, instrument, scan size, verdict), the
//! key parameters and the outputs; the height maps with axes, scale bar and colour bar; a 3-D
//! view of the model; a profile cut; the height distribution with the Abbott-Firestone curve
//! and the PSD; Table 6 with its failures first; the tile layout and mesh; latencies and node
//! reports collapsed. Images are inlined as data: URIs at about the size they are drawn and
//! charts drawn as inline SVG, so the page reads offline on its own; one small inline script
//! opens a map at full size on click, from `report_maps/NAME.png` beside the page (the inline
//! map when that file is missing). Sections are computed in parallel (rayon).
//!
//! Sections, one file each: [`summary`] (summary, key parameters, outputs), [`maps`],
//! [`view3d`], [`profile`], [`charts`] (histogram + Abbott-Firestone, PSD; the statistics in
//! [`surface_stats`]), [`table6`], [`details`] (tiles, mesh, latencies, node reports).

mod charts;
mod cost_curve;
mod details;
mod finish;
mod html;
mod maps;
mod profile;
mod summary;
mod surface_stats;
mod surfaces;
mod table6;
mod view3d;

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;

use anyhow::{anyhow, Context, Result};
use rayon::prelude::*;
use surfstream_core::record::{MapSummary, RunRecord, WaveletReport};

use html::{esc, um};
use surfaces::Surfaces;

/// Writes `<out>/report.html` from `<out>/run.json` and the height maps (`.npy`) in `out`.
pub fn write(out: &Path) -> Result<()> {
    let run_path = out.join("run.json");
    let text = std::fs::read_to_string(&run_path)
        .with_context(|| format!("{}: reading run.json", run_path.display()))?;
    let run: RunRecord = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a run record", run_path.display()))?;
    let html = render(&run, out)?;
    let path = out.join("report.html");
    surfstream_core::fsutil::write_atomic(&path, |w| {
        w.write_all(html.as_bytes())
            .map_err(|e| anyhow!("{}: {e}", path.display()))
    })
}

const STYLE: &str = "\
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,'DejaVu Sans',sans-serif;margin:0;color:#1d1d1f;background:#f4f5f7;font-size:15px;line-height:1.45}\
main{max-width:1180px;margin:0 auto;padding:18px 28px 60px;background:#fff;box-shadow:0 0 12px rgba(0,0,0,.08)}\
h1{margin:6px 0 2px;font-size:26px}h2{border-bottom:2px solid #dde1e6;padding-bottom:3px;margin-top:34px;font-size:21px}\
h3{font-size:17px;margin:18px 0 6px}h4{margin:10px 0 4px;font-size:15px}\
.sub{color:#555;margin:0 0 8px}nav{font-size:14px;margin:8px 0 0;display:flex;flex-wrap:wrap;gap:4px 14px}nav a{color:#1f5fa8;text-decoration:none}\
table{border-collapse:collapse;font-size:14px;margin:6px 0;font-variant-numeric:tabular-nums}\
td,th{border:1px solid #d5d9de;padding:3px 9px;text-align:right;vertical-align:top}th{background:#eef1f4;font-weight:600}\
td.k{text-align:left}#summary td:nth-child(2){text-align:left}#summary td.k{font-weight:600;white-space:nowrap;background:#f7f8fa}\
#parameters td:nth-child(2){text-align:left;color:#555}#parameters td:nth-child(3){text-align:left}\
#mesh td:nth-child(2){text-align:left}\
tr.fail td{background:#fdecea}tr.pass td:first-child{box-shadow:inset 3px 0 #2e7d32}tr.fail td:first-child{box-shadow:inset 3px 0 #c62828}\
.bad{color:#b71c1c;font-weight:600}.ok{color:#1b5e20;font-weight:600}.unjudged{color:#777}\
.badge{display:inline-block;padding:0 7px;border-radius:9px;font-size:12px;font-weight:700;vertical-align:middle}\
.badge.pass{background:#e3f4e4;color:#1b5e20;border:1px solid #81c784}.badge.fail{background:#fdecea;color:#b71c1c;border:1px solid #e57373}\
.verdict{padding:10px 14px;border-radius:6px;margin:14px 0;font-size:16px}.verdict ul{margin:4px 0 0;padding-left:22px;font-size:15px}\
.verdict.pass{background:#e8f5e9;border:1px solid #81c784}.verdict.fail{background:#fdecea;border:1px solid #e57373}.verdict.warn{background:#fff8e1;border:1px solid #ffca28}\
.note{color:#555;font-size:13px}figure{margin:12px 0 22px}figcaption{font-size:13px;color:#333;margin-top:4px;max-width:1100px}\
svg{font-family:inherit;max-width:100%;height:auto}svg .tick{font-size:12px;fill:#222}svg .axis{font-size:13px;fill:#111;font-weight:600}svg .grid{stroke:#e3e6ea;stroke-width:1}\
.mapsvg,.chart{width:100%;display:block}.chart.half{max-width:680px}.chart.half .tick{font-size:14px}.chart.half .axis{font-size:15px}\
.zoomable{cursor:zoom-in}img.view3d{width:100%;max-width:1200px;display:block;border:1px solid #e0e0e0}\
.flex{display:flex;gap:22px;flex-wrap:wrap;align-items:flex-start}.pair{display:grid;grid-template-columns:repeat(auto-fit,minmax(520px,1fr));gap:10px 26px}\
details{margin:16px 0;border:1px solid #dde1e6;border-radius:6px;padding:6px 12px}summary{cursor:pointer;font-weight:600;font-size:16px}\
ul.files{columns:2;font-size:14px;padding-left:20px}ul.files li{break-inside:avoid}code{font-size:13px}\
#lightbox{position:fixed;inset:0;background:rgba(20,20,20,.92);overflow:auto;z-index:10;cursor:zoom-out}\
#lightbox p{color:#fff;margin:10px 18px;font-size:14px}#lightbox img{display:block;margin:0 auto 20px;max-width:none;image-rendering:pixelated;background:#fff}\
[hidden]{display:none!important}\
@media print{#lightbox,nav{display:none}body{background:#fff}main{box-shadow:none}}";

/// Opens a zoomable image at full size (natural pixel size, scrollable); click or Esc closes.
/// Marks the page ready, so a test can tell that the script ran to its end.
const SCRIPT: &str = "(function(){\
var box=document.getElementById('lightbox'),img=box.querySelector('img'),cap=box.querySelector('p');\
function close(){box.hidden=true;img.removeAttribute('src');}\
function open(el){var inl=el.getAttribute('href')||el.getAttribute('src'),full=el.getAttribute('data-full');\
img.onerror=function(){if(full&&img.getAttribute('src')===full){img.src=inl;}};img.src=full||inl;\
cap.textContent=(el.getAttribute('data-title')||'')+': full size, one screen pixel per map pixel (click or Esc to close)';box.hidden=false;}\
document.querySelectorAll('.zoomable').forEach(function(el){el.addEventListener('click',function(){open(el);});});\
box.addEventListener('click',close);\
document.addEventListener('keydown',function(e){if(e.key==='Escape'){close();}});\
document.documentElement.setAttribute('data-report-ready','1');\
})();";

/// The page for one run; `out` is where the height maps are read. A section whose data is
/// missing is left out.
pub fn render(run: &RunRecord, out: &Path) -> Result<String> {
    let surfaces = Surfaces::load(out, run);
    let name = &run.graph.name;
    let mut h = String::new();
    let _ = writeln!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>surfstream report: {0}</title><style>{STYLE}</style></head><body><main>\n\
         <h1>Surface report: {0}</h1><p class=\"sub\">surfstream: stitched panorama, \
         datum / roughness separation, pooled model and STL, judged against the measurement.</p>\
         <nav><a href=\"#summary\">summary</a><a href=\"#parameters\">parameters</a><a href=\"#outputs\">outputs</a>\
         <a href=\"#maps\">height maps</a><a href=\"#view3d\">3-D view</a>\
         <a href=\"#profile\">profile</a><a href=\"#distribution\">distribution and PSD</a>\
         <a href=\"#table6\">Table 6</a><a href=\"#cost\">fidelity-cost</a><a href=\"#tiles\">tiles</a><a href=\"#mesh\">mesh</a>\
         <a href=\"#latencies\">latencies</a></nav>",
        esc(name)
    );
    // The sections are independent: computed in parallel (maps, 3-D view, profile,
    // distribution and PSD are the costly ones), joined in page order.
    let maps = || {
        let mut m = String::new();
        maps_section(&mut m, &surfaces, out);
        m
    };
    let view = || {
        let model = surfaces.pooled.as_ref().or(surfaces.panorama.as_ref())?;
        let f = view3d::figure(
            model,
            if model.name == "pooled" {
                "pooled map (4 x 4 max pooling of the panorama, drawn for speed; the STL's surface \
                 is named in the Mesh section)"
            } else {
                "panorama"
            },
        )?;
        Some(format!(
            "<section id=\"view3d\"><h2>3-D view of the model</h2>{f}</section>\n"
        ))
    };
    let profile = || {
        profile::section(&surfaces)
            .map(|f| format!("<section id=\"profile\"><h2>Profile cut</h2>{f}</section>\n"))
    };
    let distribution = || {
        let p = surfaces.panorama.as_ref()?;
        // The wavelet's level and its equivalent cutoff, as run.json and the verb state it
        // (a filter separation has neither).
        let scale = run
            .stage::<WaveletReport>()
            .and_then(|w| match w.final_pass?.separation {
                MapSummary::Wavelet(w) => Some((w.choices.level as u64, w.equivalent_cutoff_um)),
                MapSummary::Filter(_) => None,
            })
            .filter(|(_, cutoff_um)| cutoff_um.is_finite());
        Some(format!(
            "<section id=\"distribution\"><h2>Height distribution and power spectral density \
             (panorama)</h2><div class=\"pair\">{}{}</div></section>\n",
            surfaces
                .histogram
                .as_ref()
                .and_then(|hist| charts::distribution(p, hist))
                .unwrap_or_default(),
            charts::psd(p, scale).unwrap_or_default()
        ))
    };
    let ((maps, view), (profile, distribution)) = rayon::join(
        || rayon::join(maps, view),
        || rayon::join(profile, distribution),
    );
    h.push_str(&summary::section(run, &surfaces));
    h.push_str(&summary::key_parameters(&surfaces));
    h.push_str(&summary::outputs(run));
    for p in &surfaces.problems {
        let _ = write!(h, "<p class=\"bad\">Not shown: {}</p>", esc(p));
    }
    h.push_str(&maps);
    for section in [view, profile, distribution].into_iter().flatten() {
        h.push_str(&section);
    }
    h.push_str(&table6::section(run.deviation.as_ref()));
    h.push_str(&cost_curve::section(run));
    h.push_str(&finish::section(run, out));
    h.push_str(&details::tile_layout(run));
    h.push_str(&details::mesh(run));
    h.push_str(&details::latencies(run));
    h.push_str(&details::node_reports(run));
    let _ = writeln!(
        h,
        "</main><div id=\"lightbox\" hidden><p></p><img alt=\"full size\"></div>\
         <script>{SCRIPT}</script></body></html>"
    );
    Ok(h)
}

/// The height maps: panorama (with the profile cut marked), datum, roughness, pooled map.
fn maps_section(h: &mut String, s: &Surfaces, out: &Path) {
    let reference = format!(
        "relative to the panorama's mean height ({})",
        um(s.reference_um)
    );
    let cut = profile::row(s).map(|row| maps::Cut {
        row,
        label: "profile cut".into(),
    });
    let figures: Vec<String> = [
        (
            s.panorama.as_ref(),
            "Panorama (measured, stitched)",
            reference.as_str(),
            cut.as_ref(),
        ),
        (
            s.datum.as_ref(),
            "Datum (wavelet approximation)",
            reference.as_str(),
            None,
        ),
        (
            s.roughness.as_ref(),
            "Roughness (panorama - datum)",
            "as separated (panorama - datum, not shifted)",
            None,
        ),
        (
            s.pooled.as_ref(),
            "Pooled map (the model the STL meshes)",
            reference.as_str(),
            None,
        ),
    ]
    .into_par_iter()
    .filter_map(|(m, title, r, cut)| Some(maps::figure(m?, title, r, cut, Some(out))))
    .collect();
    if !figures.is_empty() {
        let _ = writeln!(
            h,
            "<section id=\"maps\"><h2>Height maps</h2>{}</section>",
            figures.concat()
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_summary_table6_and_escapes_without_files() {
        let run = serde_json::json!({
            "graph": {"name": "t<x>", "file": "g.toml"}, "mode": "run", "elapsed_s": 1.0,
            "scan": {"source": "simulated", "rows": 1, "cols": 1, "pitch_x_um": 1.0, "pitch_y_um": 1.0,
                     "tile_width_px": 100, "tile_height_px": 100},
            "tiles": [{"index": 0, "stage_x_um": 0.0, "stage_y_um": 0.0, "x_um": 1.0, "y_um": 2.0, "placed_by": "stage"}],
            "stages": {"mesher": {"triangles": 10, "t_acquired_ns": 5, "fidelity": {"field": {"sq_um": 1.0}, "mesh": {"sq_um": 0.99}}}},
            "latency_ms": {"hops": {"a_to_b": {"p50": 1.0, "p95": 2.0, "max": 3.0, "n": 4}}},
            "deviation": {"measured": "panorama.npy", "pass": false, "judged": ["Sa"], "threshold_pct": 5.0,
                "stages": {"pooled": {"pass": false, "grid": {"name": "own grid, 4 x 4 px cells", "rows": 5, "cols": 5, "pitch_x_um": 4.0},
                    "regions": {"S1": {"pass": false,
                    "measured": {"Sa": 2.0, "Sdr": 10.0}, "model": {"Sa": 2.5, "Sdr": 9.0},
                    "deviation_pct": {"Sa": 25.0, "Sdr": -10.0}}}}}},
        });
        let h = render(&crate::runjson::test_record(run), Path::new("/nonexistent")).unwrap();
        assert!(h.contains("t&lt;x&gt;") && !h.contains("t<x>"));
        assert!(h.contains("<div class=\"verdict fail\"><b>FAIL</b>"));
        assert!(
            h.contains("worst Sa +25.0 % in S1"),
            "verdict names the worst value"
        );
        assert!(h.contains("<b>pooled</b> (own grid, 4 x 4 px cells)"));
        assert!(h.contains("1 of 1 placed by the stage position"));
        // The failure row: stage, region, parameter, measured, model, deviation.
        assert!(h.contains(
            "<tr class=\"fail\"><td class=\"k\">pooled</td><td>S1</td><td>Sa</td><td>2.00 µm</td><td>2.50 µm</td><td>+25.00 %</td></tr>"
        ));
        assert!(h.contains("<summary>Full table: 9 rows"));
        assert!(h.contains("a → b"));
        assert!(!h.contains("t_acquired_ns"), "internal fields are hidden");
        // Below 1 µm in nm, 3 significant figures.
        assert!(h.contains("<td>990 nm</td>"));
    }

    /// Issue 26: one labelled set of parameters (which surface, not levelled) with the Sk
    /// family, the mesh's levelled fidelity labelled as such, maps with row 0 at the top (issue
    /// 39: the instrument's and Python's orientation), the 3-D view with
    /// axes and a z scale, the tile caption as y x x, and big maps inline at display size
    /// with the full-size file beside the page.
    #[test]
    fn labels_say_which_surface_levelling_and_axes() {
        let d = tempfile::tempdir().unwrap();
        let (rows, cols) = (900, 1000);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| {
                ((i % cols) as f64 * 0.05).sin() * 2.0 + ((i / cols) as f64 * 0.03).cos() + 50.0
            })
            .collect();
        surfstream_io::npy::write_npy_f64(d.path().join("panorama.npy"), &z, rows, cols).unwrap();
        let rough: Vec<f32> = z.iter().map(|v| ((v * 7.0).sin() * 0.1) as f32).collect();
        surfstream_io::npy::write_npy_f32(d.path().join("roughness.npy"), &rough, rows, cols)
            .unwrap();
        let pooled: Vec<f64> = z
            .iter()
            .step_by(4)
            .take((rows / 4) * (cols / 4))
            .copied()
            .collect();
        surfstream_io::npy::write_npy_f64(d.path().join("pooled.npy"), &pooled, rows / 4, cols / 4)
            .unwrap();
        let run = serde_json::json!({
            "graph": {"name": "t", "file": "g.toml"}, "mode": "run", "elapsed_s": 1.0,
            "scan": {"source": "simulated", "rows": 1, "cols": 2, "pitch_x_um": 0.5, "pitch_y_um": 0.5,
                     "tile_width_px": 700, "tile_height_px": 1100},
            "tiles": [{"index": 0, "stage_x_um": 0.0, "stage_y_um": 0.0, "x_um": 0.0, "y_um": 0.0, "placed_by": "registration"},
                      {"index": 1, "stage_x_um": 300.0, "stage_y_um": 0.0, "x_um": 300.0, "y_um": 0.0, "placed_by": "registration"}],
            "stages": {"mesher": {"triangles": 10, "grid_px": [325, 275],
                "fidelity": {"field": {"sq_um": 1.0}, "mesh": {"sq_um": 0.99}}}},
        });
        let h = render(&crate::runjson::test_record(run), d.path()).unwrap();
        assert!(h.contains("Key parameters (ISO 25178-2): mean removed, not levelled"));
        assert!(h.contains("<b>no levelling</b>"));
        for p in ["Sk", "Spk", "Svk", "Smr1", "Smr2"] {
            assert!(
                h.contains(&format!("<td class=\"k\"><b>{p}</b></td>")),
                "{p}"
            );
        }
        assert!(h.contains("Fidelity of the mesh ("));
        assert!(h.contains("<td>275 x 325</td>"), "mesh grid as rows x cols");
        assert!(h.contains("row 0 at the top (y down from the top edge)"));
        assert!(!h.contains("y up"), "one orientation");
        assert!(h.contains("µm (y x x), y down as the stage moves"));
        // The 3-D view: axes and a z scale over the render.
        assert!(h.contains(">x (µm)</text>") && h.contains(">y (µm)</text>") && h.contains(">z "));
        // Maps over 800 px: inline near display size, full size in report_maps/.
        assert!(h.contains("data-full=\"report_maps/panorama.png\""));
        assert!(d.path().join("report_maps/panorama.png").is_file());
        assert!(h.contains("the file report_maps/panorama.png beside this page"));
        assert!(
            !h.contains("data-full=\"report_maps/pooled.png\""),
            "small maps stay inline"
        );
    }

    /// Measures writing report.html for an existing run folder (no assertion on time):
    /// `SURFSTREAM_REPORT_DIR=out/demo cargo test --release -p surfstream report_write_time
    /// -- --ignored --nocapture` (docs/outputs.md has the numbers).
    #[test]
    #[ignore]
    fn report_write_time() {
        let Some(dir) = std::env::var_os("SURFSTREAM_REPORT_DIR") else {
            panic!("set SURFSTREAM_REPORT_DIR to a run's output folder");
        };
        let dir = std::path::PathBuf::from(dir);
        // CPU time (all threads) beside the wall clock: on a shared, loaded machine the wall
        // clock says more about the neighbours than about the report.
        let cpu_s = || {
            let mut u: libc::rusage = unsafe { std::mem::zeroed() };
            // SAFETY: getrusage fills the struct it is given.
            unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
            let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
            t(u.ru_utime) + t(u.ru_stime)
        };
        let mut times = Vec::new();
        let mut cpu = Vec::new();
        for _ in 0..5 {
            let (t0, c0) = (std::time::Instant::now(), cpu_s());
            write(&dir).unwrap();
            times.push(t0.elapsed().as_secs_f64());
            cpu.push(cpu_s() - c0);
        }
        times.sort_by(f64::total_cmp);
        cpu.sort_by(f64::total_cmp);
        println!(
            "CPU time (user + sys, all threads): {:.3} s best, {:.3} s median",
            cpu[0], cpu[2]
        );
        let size = std::fs::metadata(dir.join("report.html")).unwrap().len();
        println!(
            "report.html of {}: {:.3} s best, {:.3} s median of 5; {:.2} MB; {} threads",
            dir.display(),
            times[0],
            times[2],
            size as f64 / 1e6,
            rayon::current_num_threads()
        );
    }
}
