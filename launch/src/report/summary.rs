//! The top of the page: what was measured (input, instrument, pitch, scan and panorama size),
//! the verdict (Table 6 pass / fail with the reason, tiles placed by the stage fallback), the
//! key ISO 25178 parameters and the output files.

use std::fmt::Write as _;

use surfstream_core::metrology::{FunctionalParams, Params};
use surfstream_core::record::{DeviationRecord, MeshReport, RunRecord, ScanRecord};
use surfstream_core::units::percent;

use super::html::{esc, fixed, length, pitch, sig, signed, table_raw, um};
use super::surfaces::Surfaces;

/// The verdict banner and the facts table.
pub fn section(run: &RunRecord, surfaces: &Surfaces) -> String {
    let mut h = String::new();
    // The registration's failures first: a misplaced tile voids Table 6's pass, so a green
    // PASS is never shown above (or beside) a FAIL (issue 36).
    let layout = layout_wrong(&mut h, run);
    let placed = stage_placed(&mut h, run);
    verdict(&mut h, run.deviation.as_ref(), layout || placed);
    let scan = run.scan.as_ref();
    let mut rows: Vec<(String, Vec<String>)> = Vec::new();
    let mut row = |k: &str, v: String| rows.push((String::new(), vec![esc(k), v]));
    row("input", input(run));
    row("instrument", instrument(scan));
    if let Some((px, py)) = scan.map(ScanRecord::pitch_um) {
        row(
            "pitch (x, y)",
            if px == py {
                pitch(px)
            } else {
                format!("{} x {}", pitch(px), pitch(py))
            },
        );
    }
    let tiles = run.tiles.len();
    let grid = match scan.and_then(ScanRecord::grid) {
        Some((r, c)) => format!("{r} x {c} tiles (rows x cols)"),
        None => format!("{tiles} tiles"),
    };
    let tile = match scan {
        Some(s) => {
            let ((w, h), (px, py)) = (s.tile_px(), s.pitch_um());
            format!(
                ", each {h} x {w} px = {} x {}",
                length(h as f64 * py),
                length(w as f64 * px)
            )
        }
        None => String::new(),
    };
    let overlap = match scan {
        Some(ScanRecord::Simulated { overlap, .. }) => Some((overlap[0], overlap[1])),
        _ => None,
    };
    let overlap = overlap
        .map(|(x, y)| {
            if x == y {
                format!(", {} % nominal overlap", fixed(x * 100.0, 0))
            } else {
                format!(
                    ", {} / {} % nominal overlap (x / y)",
                    fixed(x * 100.0, 0),
                    fixed(y * 100.0, 0)
                )
            }
        })
        .unwrap_or_default();
    row("scan", esc(&format!("{grid}{tile}{overlap}")));
    if let Some(p) = &surfaces.panorama {
        let (points, nan) = surfaces.panorama_points;
        row(
            "panorama",
            esc(&format!(
                "{} x {} px = {} x {} (rows x cols); {} % not measured",
                p.file_shape.0,
                p.file_shape.1,
                length(p.height_um()),
                length(p.width_um()),
                fixed(100.0 * nan as f64 / points.max(1) as f64, 2)
            )),
        );
    }
    let by_stage: Vec<String> = run
        .tiles
        .iter()
        .filter(|t| t.placement.as_ref().is_some_and(|p| p.placed_by == "stage"))
        .map(|t| format!("tile {}", t.source.index))
        .collect();
    row(
        "tile placement",
        if by_stage.is_empty() {
            format!("all {tiles} tiles placed by registration")
        } else {
            format!(
                "<span class=\"bad\">{} of {tiles} placed by the stage position (registration \
                 fallback): {}</span>",
                by_stage.len(),
                esc(&by_stage.join(", "))
            )
        },
    );
    if let Some(m) = mesh(run) {
        row("model (STL)", m);
    }
    row(
        "run",
        esc(&format!(
            "{} mode, {} s, surfstream {}, graph {} ({})",
            run.mode,
            fixed(run.elapsed_s, 2),
            run.surfstream_version,
            run.graph.name,
            run.graph.file,
        )),
    );
    h.push_str("<section id=\"summary\"><h2>Summary</h2>");
    h.push_str(
        &table_raw(&["", ""], &rows).replace("<thead><tr><th></th><th></th></tr></thead>", ""),
    );
    h.push_str("</section>\n");
    h
}

fn input(run: &RunRecord) -> String {
    let graph = esc(&run.graph.file);
    match &run.scan {
        Some(ScanRecord::Simulated { specimen, .. }) => format!(
            "simulated profiler stage (graph {graph}), specimen {}",
            esc(specimen)
        ),
        Some(ScanRecord::Scan { manifest, .. }) => format!("scan directory {}", esc(manifest)),
        Some(ScanRecord::Mcap { recording, .. }) => format!("recording {}", esc(recording)),
        None => format!("graph {graph}"),
    }
}

fn instrument(scan: Option<&ScanRecord>) -> String {
    match scan {
        Some(ScanRecord::Simulated { .. }) => {
            "simulated optical profiler (noise, dropouts, stage error)".into()
        }
        _ => "not recorded in the scan files".into(),
    }
}

fn mesh(run: &RunRecord) -> Option<String> {
    let m = run.stage::<MeshReport>()?;
    let f = m.adaptive().map(|a| a.fidelity);
    let units = format!("STL in {}", m.units);
    let shown = |v: Option<f64>| v.filter(|v| !v.is_nan()).map(um).unwrap_or("-".into());
    Some(esc(&format!(
        "{}: {} triangles, {} vertices, {}, {} {}, max vertical error {} (bound {}, {})",
        m.file,
        m.triangles,
        m.vertices,
        if m.watertight {
            "watertight"
        } else {
            "not watertight"
        },
        m.format,
        units,
        shown(f.map(|f| f.error.max_um)),
        shown(f.map(|f| f.epsilon_um)),
        if f.is_some_and(|f| f.bound_met) {
            "met"
        } else {
            "NOT met"
        },
    )))
}

/// Links off the layout's plan beyond the stage error: the run fails with the layout as the
/// cause (the verdict's `layout` line). True when shown.
fn layout_wrong(h: &mut String, run: &RunRecord) -> bool {
    let Some(line) = crate::verdict::layout_line(run) else {
        return false;
    };
    let _ = write!(
        h,
        "<div class=\"verdict fail\"><b>FAIL: wrong layout?</b> {} (Tile layout and pairs \
         below).</div>",
        esc(&line)
    );
    true
}

/// Tiles the stage placed (no registration, or one direction only): a banner of their own,
/// since the run's verdict fails on them whatever Table 6 says. True when shown.
fn stage_placed(h: &mut String, run: &RunRecord) -> bool {
    let tiles: Vec<String> = run
        .tiles
        .iter()
        .filter(|t| t.placement.as_ref().is_some_and(|p| p.placed_by == "stage"))
        .map(|t| {
            format!(
                "tile {} (row {} x col {})",
                t.source.index, t.source.row, t.source.col
            )
        })
        .collect();
    if tiles.is_empty() {
        return false;
    }
    let _ = write!(
        h,
        "<div class=\"verdict fail\"><b>FAIL</b>: {} tile(s) placed by the stage position, not \
         (or in one direction only) by registration: {}. Their place in the panorama is as good \
         as the stage (Tile layout below).</div>",
        tiles.len(),
        esc(&tiles.join(", "))
    );
    true
}

/// The Table-6 verdict as a banner: pass, or which stage failed where and by how much. When
/// the registration failed (`registration_failed`), a Table 6 within its limits is no PASS:
/// it judged a panorama with misplaced tiles, and says so in a warning box.
fn verdict(h: &mut String, dev: Option<&DeviationRecord>, registration_failed: bool) {
    let dev = match dev {
        None => return,
        Some(DeviationRecord::Table(t)) => t,
        Some(DeviationRecord::NotComputed { error: e }) => {
            let _ = write!(
            h,
            "<div class=\"verdict warn\"><b>No verdict:</b> the model-vs-measurement deviation \
             could not be computed: {}</div>",
            esc(e)
            );
            return;
        }
    };
    let e = dev.threshold_pct;
    let judged: Vec<&str> = dev.judged.iter().map(String::as_str).collect();
    // A stage's limits: the threshold, or the model's tolerance (the mesh made from one).
    let limits = |st: &surfstream_core::record::StageDeviation| {
        let l: Vec<f64> = judged.iter().filter_map(|p| st.limits_pct.get(p)).collect();
        if l.iter().all(|&v| v == e) {
            format!("±{} %", fixed(e, 1))
        } else {
            let parts: Vec<String> = judged
                .iter()
                .filter_map(|p| st.limits_pct.get(p).map(|v| format!("{p} {v} %")))
                .collect();
            format!("its tolerance ({})", parts.join(", "))
        }
    };
    if dev.pass && registration_failed {
        let _ = write!(
            h,
            "<div class=\"verdict warn\"><b>No PASS:</b> Table 6 is within its limits (±{} % \
             for {}), but it judged a panorama whose registration failed (above): the run \
             fails.</div>",
            fixed(e, 1),
            judged.join(", ")
        );
        return;
    }
    if dev.pass {
        let mesh = dev
            .stages
            .get("mesh")
            .filter(|m| m.judged)
            .map(&limits)
            .filter(|l| !l.starts_with('±'));
        let _ = match mesh {
            Some(l) => write!(
                h,
                "<div class=\"verdict pass\"><b>PASS</b>: the mesh is within {l} and every other \
                 judged model stage within ±{} % of the measurement for {} in every region \
                 (Table 6 below).</div>",
                fixed(e, 1),
                judged.join(", ")
            ),
            None => write!(
                h,
                "<div class=\"verdict pass\"><b>PASS</b>: every model stage is within ±{} % of \
                 the measurement for {} in every region (Table 6 below).</div>",
                fixed(e, 1),
                judged.join(", ")
            ),
        };
        return;
    }
    let mut reasons = Vec::new();
    for (stage, st) in &dev.stages {
        // A stage reported but not judged (the pooled map when the STL is not made from it)
        // is not a reason.
        if st.pass || !st.judged {
            continue;
        }
        let mut worst: Option<(String, String, f64)> = None;
        let mut failed = 0;
        for (region, r) in &st.regions {
            if !r.pass {
                failed += 1;
            }
            for p in &judged {
                if let Some(d) = r.deviation(p) {
                    if worst.as_ref().is_none_or(|w| d.abs() > w.2.abs()) {
                        worst = Some((region.clone(), p.to_string(), d));
                    }
                }
            }
        }
        let grid = &st.grid.name;
        reasons.push(match worst {
            Some((region, p, d)) => format!(
                "<b>{}</b> ({}): {failed} region(s) outside {}, worst {p} {} % in {}",
                esc(stage),
                esc(grid),
                limits(st),
                signed(d, 1),
                esc(&region)
            ),
            None => format!("<b>{}</b>: no parameters could be compared", esc(stage)),
        });
    }
    let _ = write!(
        h,
        "<div class=\"verdict fail\"><b>FAIL</b>: the model deviates from the measurement \
         beyond its limits in {} (Table 6 below):<ul>",
        judged.join(" / ")
    );
    for r in reasons {
        let _ = write!(h, "<li>{r}</li>");
    }
    h.push_str("</ul></div>");
}

/// Sa .. Sdr and the Sk family of the panorama, the roughness and the pooled map, each at its
/// own pitch: the page's one set of parameters of these surfaces, labelled (mean removed, not
/// levelled).
pub fn key_parameters(s: &Surfaces) -> String {
    // At full resolution, streamed from the files (Surfaces::load).
    let cols: Vec<(&str, Option<Params>, Option<FunctionalParams>)> = [
        (
            "panorama (measured)",
            s.panorama.as_ref(),
            s.params[0],
            s.functional[0],
        ),
        (
            "roughness",
            s.roughness.as_ref(),
            s.params[1],
            s.functional[1],
        ),
        (
            "pooled map",
            s.pooled.as_ref(),
            s.params[2],
            s.functional[2],
        ),
    ]
    .into_iter()
    .filter_map(|(n, m, p, f)| m.map(|_| (n, p, f)))
    .collect();
    if cols.is_empty() {
        return String::new();
    }
    // The first nine from Params::named (in its order), then the Sk family. Each cell carries
    // its unit: heights have 3 significant figures and read in nm below 1 µm.
    type Get = Option<fn(&FunctionalParams) -> f64>;
    type Show = fn(f64) -> String;
    let (height, ratio, pct): (Show, Show, Show) = (um, |v| sig(v, 3), percent);
    let what: [(&str, &str, Show, Get); 14] = [
        ("Sa", "arithmetic mean height", height, None),
        ("Sq", "root mean square height", height, None),
        ("Sp", "maximum peak height", height, None),
        ("Sv", "maximum pit depth", height, None),
        ("Sz", "maximum height", height, None),
        ("Ssk", "skewness", ratio, None),
        ("Sku", "kurtosis", ratio, None),
        ("Sdq", "root mean square gradient", ratio, None),
        ("Sdr", "developed interfacial area ratio", pct, None),
        (
            "Sk",
            "core height (Sk family, ISO 25178-2)",
            height,
            Some(|f| f.sk),
        ),
        ("Spk", "reduced peak height", height, Some(|f| f.spk)),
        ("Svk", "reduced valley depth", height, Some(|f| f.svk)),
        ("Smr1", "peak material ratio", pct, Some(|f| f.smr1)),
        ("Smr2", "valley material ratio", pct, Some(|f| f.smr2)),
    ];
    let mut head = vec!["parameter", ""];
    head.extend(cols.iter().map(|c| c.0));
    let rows: Vec<(String, Vec<String>)> = what
        .iter()
        .enumerate()
        .map(|(i, (name, long, show, get))| {
            let mut r = vec![format!("<b>{name}</b>"), esc(long)];
            for (_, p, f) in &cols {
                let v = match get {
                    None => p.map(|p| p.named()[i].1),
                    Some(get) => f.as_ref().map(get),
                };
                r.push(
                    v.filter(|v| v.is_finite())
                        .map(show)
                        .map_or_else(|| "-".into(), |t| esc(&t)),
                );
            }
            (String::new(), r)
        })
        .collect();
    format!(
        "<section id=\"parameters\"><h2>Key parameters (ISO 25178-2): mean removed, not \
         levelled</h2>{}<p class=\"note\">The page's parameters of these three surfaces. Over all \
         valid points of each map at its own pitch, mean removed, <b>no levelling</b> and no \
         filter (S-F or S-L) applied; the roughness is the panorama minus the wavelet datum. \
         Sdq and Sdr depend on the pitch: the pooled map's are taken over its coarser grid. The \
         mesh's fidelity table (below) is levelled and differs by the plane. Every parameter of \
         a map: <code>surfstream params FILE --all</code>.</p></section>\n",
        table_raw(&head, &rows)
    )
}

/// The output files, linked (relative links: the page sits beside them).
pub fn outputs(run: &RunRecord) -> String {
    let files = &run.files;
    if files.is_empty() {
        return String::new();
    }
    let describe = |f: &str| -> &str {
        match f {
            "panorama.npy" => {
                "stitched height map, absolute heights in µm (float32, float64 when the tiles carry a z offset; NaN = not measured)"
            }
            "panorama.x3p" => {
                "the panorama as ISO 25178-72 X3P (MountainsMap, Gwyddion, surfalize)"
            }
            "datum.npy" => "datum (wavelet approximation), absolute µm",
            "roughness.npy" => "roughness = panorama - datum, µm (float32)",
            "pooled.npy" => "pooled height map (the meshed model), absolute µm",
            "surface.stl" => "the model as STL for DEM simulators",
            "mesh_resampled.npy" => "the STL surface re-sampled on the grid it meshed",
            "recording.mcap" => "tiles and registrations as recorded",
            "truth.json" => "simulated truth (true tile origins)",
            "run.json" => "everything on this page as numbers",
            f if f.ends_with(".png") => "preview image",
            f if f.ends_with(".npy.json") => "the pitch of the .npy beside it (sidecar)",
            f if f.starts_with("logs/") => "a process's stderr",
            f if f.starts_with("nodes/") => "a node's report",
            _ => "",
        }
    };
    let mut main = String::new();
    let mut other = String::new();
    for f in files.iter().map(String::as_str) {
        let link = format!(
            "<li><a href=\"{0}\">{0}</a> <span class=\"note\">{1}</span></li>",
            esc(f),
            esc(describe(f))
        );
        if f.contains('/')
            || f.ends_with(".png")
            || f.ends_with(".npy.json")
            || f == "graph.resolved.json"
        {
            other.push_str(&link);
        } else {
            main.push_str(&link);
        }
    }
    format!(
        "<section id=\"outputs\"><h2>Outputs</h2><p class=\"note\">Beside this page in the \
         output folder.</p><ul class=\"files\">{main}</ul><details><summary>previews, node reports \
         and logs</summary><ul class=\"files\">{other}</ul></details></section>\n"
    )
}
