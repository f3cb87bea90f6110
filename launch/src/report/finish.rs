//! The finishing simulation's section of report.html, for a graph with a `finish` node
//! (launch/graphs/finish.toml): the wear map, the worn against the original profile, the
//! Abbott-Firestone curves before/after, the parameters beside the paper's and the
//! calibration table. finish.json is read through its typed record, core's
//! ([`surfstream_core::record::finish::FinishSummary`]); the figures are the finish crate's own
//! (the same as its finish.html), from wear.npy, original.npy and worn.npy in the node's
//! folder.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, Result};
use serde::Deserialize;
use serde_json::Value;
use surfstream_core::record::finish::{FinishReport, FinishSummary};
use surfstream_core::record::RunRecord;

use super::html::{esc, um};

/// Whether a stage's report is a finish node's: run.json keys its stages by node id, not by
/// kind, and of the node reports (every one a record of `surfstream_core::record`) only the
/// finish node's has finish.json's `cycles_requested`.
fn is_finish_stage(report: &Value) -> bool {
    report.get("cycles_requested").is_some()
}

/// The folders of `out` where a finish node wrote: each finish node's folder as its report
/// says (run.json `stages.ID`, a [`FinishReport`]) and "finish" (the default, and the
/// `finish` verb's), holding finish.json and wear.npy; in name order. With them, each finish
/// stage whose report does not read as a [`FinishReport`], named with serde's message (its
/// folder is not known, so it is not shown, and the section says so).
fn finish_dirs(run: &RunRecord, out: &Path) -> (Vec<PathBuf>, Vec<String>) {
    let mut names: Vec<String> = vec!["finish".into()];
    let mut unread = Vec::new();
    for (id, report) in run.stages.iter().filter(|(_, v)| is_finish_stage(v)) {
        match FinishReport::deserialize(report) {
            Ok(r) => names.push(r.dir),
            Err(e) => unread.push(format!(
                "run.json stages.{id}: not a finish report this surfstream reads: {e}"
            )),
        }
    }
    names.sort();
    names.dedup();
    let dirs = names
        .into_iter()
        .map(|n| out.join(n))
        .filter(|d| d.join("finish.json").is_file() && d.join("wear.npy").is_file())
        .collect();
    (dirs, unread)
}

/// The section, or "" when the run has no finish output.
pub fn section(run: &RunRecord, out: &Path) -> String {
    section_of(run, out)
}

/// The section for a run whose nodes' parameters are `parameters`.
fn section_of(run: &RunRecord, out: &Path) -> String {
    let mut h = String::new();
    let not_shown = |h: &mut String, why: &str| {
        let _ = writeln!(
            h,
            "<section id=\"finish\"><h2>Finishing simulation</h2>\
             <p class=\"bad\">Not shown: {}</p></section>",
            esc(why)
        );
    };
    let (dirs, unread) = finish_dirs(run, out);
    for why in &unread {
        not_shown(&mut h, why);
    }
    for dir in dirs {
        let rel = dir.strip_prefix(out).unwrap_or(&dir).display().to_string();
        match render(&dir, &rel) {
            Ok(s) => h.push_str(&s),
            Err(e) => not_shown(&mut h, &format!("{e:#}")),
        }
    }
    h
}

fn read_map(path: &Path) -> Result<(Vec<f64>, usize, usize)> {
    let a =
        surfstream_io::npy::read_npy_f64(path).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    Ok((a.data, a.rows, a.cols))
}

fn render(dir: &Path, rel: &str) -> Result<String> {
    let path = dir.join("finish.json");
    // The typed record; the figures are the finish crate's (the same page code as finish.html).
    let s = FinishSummary::read(&path)?;
    let (wear, rows, cols) = read_map(&dir.join("wear.npy"))?;
    let (original, r2, c2) = read_map(&dir.join("original.npy"))?;
    let (worn, r3, c3) = read_map(&dir.join("worn.npy"))?;
    if (r2, c2) != (rows, cols) || (r3, c3) != (rows, cols) {
        return Err(anyhow!(
            "{}: wear.npy is {rows} x {cols}, original.npy {r2} x {c2}, worn.npy {r3} x {c3}: expected one shape",
            dir.display()
        ));
    }
    let f = surfstream_finish::html::figures(&s, &original, &worn, &wear, rows, cols)?;
    let mut h = String::new();
    let (b, a) = (&s.before, &s.after);
    // The folder as it goes into the link's attribute and the text.
    let rel = esc(rel);
    let _ = write!(
        h,
        "<section id=\"finish\"><h2>Finishing simulation{}</h2>\
         <p class=\"sub\">{} of {} cycle(s), wear model {}; Sa {} → {}. \
         The page of this run alone: <a href=\"{rel}/finish.html\">{rel}/finish.html</a>; \
         the numbers: <code>{rel}/finish.json</code> (docs/finish.md).</p>",
        if s.partial {
            " (partial: stopped early)"
        } else {
            ""
        },
        s.cycles_completed,
        s.cycles_requested,
        esc(s.wear_model.as_deref().unwrap_or("sampled-map")),
        um(b.sa),
        um(a.sa),
    );
    let _ = write!(
        h,
        "<div class=\"flex\"><figure>{}<figcaption>Wear depth along z, µm (the dashed line \
         marks the profile row).</figcaption></figure><figure>{}<figcaption>Before.</figcaption>\
         </figure><figure>{}<figcaption>After, same colour scale.</figcaption></figure></div>\
         <div class=\"flex\"><figure>{}<figcaption>Worn (thin red) on the original (thick grey).\
         </figcaption></figure><figure>{}<figcaption>Removed depth along the row (worn.npy is \
         re-levelled: {:+.4} µm shift).</figcaption></figure></div>\
         <div class=\"flex\"><figure>{}<figcaption>Abbott-Firestone curves before (grey) and \
         after (red).</figcaption></figure><figure>{}<figcaption>The peak region.</figcaption>\
         </figure><figure>{}<figcaption>Height lost at each material ratio.</figcaption></figure></div>",
        f.wear_map,
        f.original_map,
        f.worn_map,
        f.profile_svg,
        f.removed_svg,
        f.level_shift_um,
        f.abbott_svg,
        f.abbott_peak_svg,
        f.abbott_diff_svg,
    );
    // Parameters beside the paper's measured part.
    let paper = |side: &str, k: &str| -> String {
        s.paper
            .as_ref()
            .and_then(|p| {
                if side == "before" {
                    &p.before
                } else {
                    &p.after
                }
                .get(k)
                .copied()
            })
            .map_or("–".into(), |v| format!("{v:.3}"))
    };
    let _ = write!(
        h,
        "<h3>Parameters (µm)</h3><table><tr><th class=\"k\">param</th><th>model before</th>\
         <th>predicted after</th><th>paper before</th><th>paper after 5 min</th></tr>"
    );
    let sa_fitted = s.series.last().is_some_and(|p| !p.fitted.is_empty());
    for (k, bv, av) in [
        ("Sa", b.sa, a.sa),
        ("Sq", b.sq, a.sq),
        ("Sz", b.sz, a.sz),
        ("Spk", b.spk, a.spk),
        ("Svk", b.svk, a.svk),
        ("Sk", b.sk, a.sk),
    ] {
        let _ = write!(
            h,
            "<tr><td class=\"k\">{k}</td><td>{bv:.3}</td><td>{av:.3}{}</td><td>{}</td><td>{}</td></tr>",
            if k == "Sa" && sa_fitted { " (fitted)" } else { "" },
            paper("before", k),
            paper("after", k)
        );
    }
    h.push_str("</table>");
    // The predictions versus time beside the no-DEM baselines, what was fitted (the finish
    // crate's own section of finish.html).
    h.push_str(&surfstream_finish::html::predictions_section(&s));
    // The calibration table.
    if let Some(c) = &s.calibration {
        let opt = |v: Option<f64>, dp: usize| v.map_or("–".into(), |x| format!("{x:.dp$}"));
        let _ = write!(
            h,
            "<h3>Calibration</h3><table><tr><th class=\"k\">quantity</th><th>value</th></tr>\
             <tr><td class=\"k\">kind</td><td>{}</td></tr>\
             <tr><td class=\"k\">target Sa (µm)</td><td>{}</td></tr>\
             <tr><td class=\"k\">predicted Sa (µm)</td><td>{}</td></tr>\
             <tr><td class=\"k\">relative error (tolerance ±{} %)</td><td>{}</td></tr>\
             <tr><td class=\"k\">reached</td><td>{}</td></tr>\
             <tr><td class=\"k\">fitted k_finnie (1/Pa)</td><td>{}</td></tr>",
            esc(&c.kind),
            opt(c.target_sa_um, 4),
            opt(c.sa_after_um, 4),
            opt(c.tolerance_percent, 0),
            c.relative_error
                .map_or("–".into(), |e| format!("{:+.2} %", e * 100.0)),
            c.reached.map_or("–", |r| if r { "yes" } else { "no" }),
            c.k_finnie_fitted_per_pa
                .map_or("–".into(), |k| format!("{k:.3e}")),
        );
        if let Some(cf) = &s.contact_field {
            let _ = write!(
                h,
                "<tr><td class=\"k\">impacts over the process (patch)</td><td>{:.0}</td></tr>\
                 <tr><td class=\"k\">DEM impacts measured</td><td>{}</td></tr>\
                 <tr><td class=\"k\">AUC: the contact field ranks the DEM's worn cells</td><td>{}</td></tr>\
                 <tr><td class=\"k\">DEM wear volume within reach</td><td>{}</td></tr>\
                 <tr><td class=\"k\">cells worn after the process</td><td>{}</td></tr>",
                cf.impacts_over_process,
                cf.table.impacts,
                opt(cf.check_mean.auc_gap_predicts_worn, 3),
                opt(cf.check_mean.dem_volume_within_reach, 3),
                opt(cf.worn_cells_after, 3),
            );
        }
        h.push_str("</table>");
    }
    if let Some(cf) = &s.contact_field {
        h.push_str(
            "<h3>Wear per contact measured by the DEM</h3><table><tr><th>gap below the ball's \
             envelope (µm)</th><th>cells</th><th>expected contacts</th><th>DEM worn cells</th>\
             <th>wear per contact measured (µm, DEM k)</th><th>used (pooled: *)</th></tr>",
        );
        for bin in &cf.table.bins {
            let _ = write!(
                h,
                "<tr><td>{:.3}–{:.3}</td><td>{}</td><td>{:.1}</td><td>{}</td><td>{:.3e}</td><td>{:.3e}{}</td></tr>",
                bin.gap_from_um,
                bin.gap_to_um,
                bin.cells,
                bin.expected_contacts,
                bin.dem_worn_cells,
                bin.measured_wear_per_contact_um,
                bin.wear_per_contact_um,
                if bin.pooled { " *" } else { "" }
            );
        }
        let _ = write!(
            h,
            "</table><p class=\"note\">Ball radius {:.0} µm; engine {:.1} s of {:.1} s.</p>",
            cf.ball_radius_um, s.timings.engine_s, s.timings.total_s
        );
    }
    h.push_str("</section>\n");
    Ok(h)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_without_finish_output_has_no_section_and_a_broken_one_says_why() {
        let dir = tempfile::tempdir().unwrap();
        let report = FinishReport::of(example_summary(), "f2");
        let stage = surfstream_core::record::to_value(&report).unwrap();
        let run = crate::runjson::test_record(serde_json::json!({"stages": {"fin": stage}}));
        assert_eq!(section_of(&run, dir.path()), "");
        // A node's record (nodes/finish.json) is not a finish output.
        std::fs::create_dir_all(dir.path().join("nodes")).unwrap();
        std::fs::write(dir.path().join("nodes/finish.json"), "{}").unwrap();
        assert_eq!(section_of(&run, dir.path()), "");
        let f = dir.path().join("f2");
        std::fs::create_dir_all(&f).unwrap();
        std::fs::write(f.join("finish.json"), "{\"model\": 3}").unwrap();
        std::fs::write(f.join("wear.npy"), "").unwrap();
        let s = section_of(&run, dir.path());
        assert!(s.contains("Not shown") && s.contains("finish.json"), "{s}");
    }

    /// A finish stage whose report does not read is named with serde's message, not dropped;
    /// another node's stage is not a finish stage.
    #[test]
    fn a_finish_stage_whose_report_does_not_read_says_so() {
        let dir = tempfile::tempdir().unwrap();
        let run = crate::runjson::test_record(serde_json::json!({"stages": {
            "fin": {"dir": "f2", "cycles_requested": 1},
            "mesher": {"t_acquired_ns": 1, "t_written_ns": 2},
        }}));
        let (dirs, unread) = finish_dirs(&run, dir.path());
        assert!(dirs.is_empty());
        assert_eq!(unread.len(), 1, "{unread:?}");
        assert!(unread[0].contains("stages.fin"), "{unread:?}");
        assert!(unread[0].contains("missing field"), "{unread:?}");
        let s = section_of(&run, dir.path());
        assert!(s.contains("Not shown") && s.contains("stages.fin"), "{s}");
    }

    /// A finish.json with the fields every page needs.
    fn example_summary() -> FinishSummary {
        let params = serde_json::json!({"Sa": 1.0, "Sq": 1.0, "Spk": 1.0, "Sp": 1.0, "Sv": 1.0,
            "Sz": 1.0, "Ssk": 1.0, "Sku": 1.0, "Sdq": 1.0, "Sk": 1.0, "Svk": 1.0, "Smr1": 1.0,
            "Smr2": 1.0});
        let curve =
            serde_json::json!({"material_ratio_pct": [0.0, 100.0], "height_um": [1.0, -1.0]});
        serde_json::from_value(serde_json::json!({
            "model": "m.x3p", "cycles_completed": 0, "cycles_requested": 1,
            "before": params, "after": params, "abbott_before": curve, "abbott_after": curve,
            "timings": {"engine_s": 0.0, "total_s": 1.0},
        }))
        .unwrap()
    }

    /// Issue 39: report.html's maps and the finishing figures (finish.html's, shown in
    /// report.html's finishing section) give one normalised height one colour: the same
    /// palette (viridis, the not-measured grey) and the same colour-bar stops.
    #[test]
    fn both_reports_colour_a_normalised_height_alike() {
        let (rows, cols) = (6, 6);
        let z: Vec<f64> = (0..rows * cols).map(|i| i as f64 * 0.1).collect();
        let surface = crate::report::surfaces::Surface {
            name: "panorama",
            z: z.clone(),
            rows,
            cols,
            pitch_x_um: 1.0,
            pitch_y_um: 1.0,
            block: 1,
            file_shape: (rows, cols),
        };
        let report_map = super::super::maps::figure(&surface, "t", "mean", None, None);
        let summary = example_summary();
        let wear = vec![0.0; rows * cols];
        let f = surfstream_finish::html::figures(&summary, &z, &z, &wear, rows, cols).unwrap();
        let report = super::super::maps::tests::inline_pngs(&report_map);
        let finish = super::super::maps::tests::inline_pngs(&f.original_map);
        assert_eq!(report[0].0.len(), 256 * 3);
        assert_eq!(report[0].0, finish[0].0, "one palette");
        for i in [0usize, 100, 254] {
            let t = i as f64 / 254.0;
            assert_eq!(
                report[0].0[i * 3..i * 3 + 3],
                surfstream_io::figure::viridis(t)
            );
        }
        let stops = surfstream_io::figure::gradient_stops(surfstream_io::figure::viridis);
        assert!(report_map.contains(&stops) && f.original_map.contains(&stops));
    }

    /// A folder name with a quote cannot end the link's attribute in report.html.
    #[test]
    fn the_link_to_finish_html_is_escaped() {
        let d = tempfile::tempdir().unwrap();
        let dir = d.path().join("fin\"x");
        std::fs::create_dir_all(&dir).unwrap();
        let summary = example_summary();
        std::fs::write(
            dir.join("finish.json"),
            serde_json::to_string(&summary).unwrap(),
        )
        .unwrap();
        let z: Vec<f64> = (0..16).map(|i| i as f64 * 0.1).collect();
        for f in ["wear.npy", "original.npy", "worn.npy"] {
            surfstream_io::npy::write_npy_f64(dir.join(f), &z, 4, 4).unwrap();
        }
        let h = render(&dir, "fin\"x").unwrap();
        assert!(h.contains("<a href=\"fin&quot;x/finish.html\">"), "{h}");
        assert!(!h.contains("fin\"x"));
    }
}
