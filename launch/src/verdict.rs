//! The verdict printed at the end of `launch`, `run` and `stitch`: what a metrologist asks
//! first. Key parameters of the measured surface, where the outputs are, the mesh size, Table
//! 6's pass/fail with the reason (which stage, parameter, region, by how much, against which
//! limit) and the tiles placed by stage fallback. Built from run.json alone, so it says
//! exactly what the file says; latency tables only with `--verbose` (and in report.html).
//!
//! Numbers: heights with 3 significant figures, in nm below 1 um ([`surfstream_core::units`]:
//! a smooth map's Sa reads "5.12 nm", not "0.005 um"); deviations in % with 2 decimals,
//! times in ms with 2.

use std::fmt::Write as _;
use std::path::Path;

use serde_json::Value;
use surfstream_core::record::{
    DeviationRecord, LatencySummary, MeshReport, OutputChoice, Percentiles, RunRecord,
    Table6Record, TileRecord,
};

/// Exit code of a run whose outputs were written but a check failed under `--strict`
/// (1 stays "error, no result"; 2 is clap's usage error).
pub const STRICT_FAILURE_EXIT: u8 = 3;

/// What the verdict found.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    /// The text to print (several lines, no trailing newline).
    pub text: String,
    /// Every failed check, one short line each (empty: all passed).
    pub failures: Vec<String>,
}

/// A height (or length) with 3 significant figures, nm below 1 um: "1.38 um", "5.12 nm".
pub fn um(v: f64) -> String {
    surfstream_core::units::height(v)
}

/// A count with thin grouping for readability: 27850 -> "27 850".
pub fn count(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (k, c) in digits.chars().enumerate() {
        if k > 0 && (digits.len() - k).is_multiple_of(3) {
            out.push(' ');
        }
        out.push(c);
    }
    out
}

/// The verdict's first line with the time the user waited (`wall_s`: the whole command,
/// Table 6, x3p and report included) and, beside it, the pipeline's own (run.json).
pub fn with_wall_time(text: &str, wall_s: f64) -> String {
    let (first, rest) = text.split_once('\n').unwrap_or((text, ""));
    let pipeline = first
        .strip_prefix("surfstream: done in ")
        .and_then(|t| t.strip_suffix(" s"))
        .map(str::to_string);
    let line = match pipeline {
        Some(p) => format!(
            "surfstream: done in {wall_s:.2} s (pipeline {p} s; then Table 6, x3p and report)"
        ),
        None => first.to_string(),
    };
    if rest.is_empty() {
        line
    } else {
        format!("{line}\n{rest}")
    }
}

/// Reads `<out>/run.json` and builds the verdict.
pub fn from_out_dir(out: &Path, verbose: bool) -> anyhow::Result<Verdict> {
    let path = out.join("run.json");
    let text = std::fs::read_to_string(&path)
        .map_err(|e| anyhow::anyhow!("{}: cannot read run.json: {e}", path.display()))?;
    let run: RunRecord = serde_json::from_str(&text)
        .map_err(|e| anyhow::anyhow!("{}: not a run record: {e}", path.display()))?;
    Ok(verdict(&run, out, verbose))
}

/// The verdict of one run.json (the out dir only names the files).
pub fn verdict(run: &RunRecord, out: &Path, verbose: bool) -> Verdict {
    let mut s = String::new();
    let mut failures = Vec::new();
    let tiles = &run.tiles;
    let fallback: Vec<&TileRecord> = tiles
        .iter()
        .filter(|t| t.placement.as_ref().is_some_and(|p| p.placed_by == "stage"))
        .collect();
    let grid = match run.scan.as_ref().and_then(|s| s.grid()) {
        Some((r, c)) => format!("{r} x {c} tiles (rows x cols)"),
        None => format!("{} tiles", tiles.len()),
    };
    let _ = writeln!(s, "surfstream: done in {:.2} s", run.elapsed_s);
    let _ = writeln!(
        s,
        "  scan        {grid}: {} by registration, {} by stage fallback (end-of-scan solve)",
        tiles.len() - fallback.len(),
        fallback.len()
    );
    // Links off the layout's plan by more than the stage error: the layout is the cause of
    // whatever else failed (issue 36), so said and failed first.
    let layout = layout_line(run);
    if let Some(line) = &layout {
        let _ = writeln!(s, "  layout      {line}");
        failures.push(format!("layout: {line}"));
    }
    if let Some(line) = surface_line(run) {
        let _ = writeln!(s, "  surface     {line}");
    }
    if let Some(line) = mesh_line(run) {
        let _ = writeln!(s, "  mesh        {line}");
    }
    if let Some((line, failed)) = model_line(run) {
        let _ = writeln!(s, "  model       {line}");
        if failed {
            failures.push(format!("model: {line}"));
        }
    }
    match run.deviation.as_ref().and_then(deviation_line) {
        Some((line, failed)) => {
            // Table 6 of a panorama whose registration failed is no pass.
            let line = match line.strip_prefix("PASS: ") {
                Some(rest) if layout.is_some() || !fallback.is_empty() => format!(
                    "within limits, but no PASS (the registration failed: see layout / \
                     fallback): {rest}"
                ),
                _ => line,
            };
            let _ = writeln!(s, "  deviation   {line}");
            if failed {
                failures.push(format!("deviation: {line}"));
            }
        }
        None => {
            let _ = writeln!(s, "  deviation   not evaluated (no Table 6 in run.json)");
        }
    }
    if !fallback.is_empty() {
        let list: Vec<String> = fallback.iter().map(|t| tile_name(t)).collect();
        let line = format!(
            "{} tile(s) placed by stage position, not registration: {}",
            fallback.len(),
            list.join(", ")
        );
        let _ = writeln!(s, "  fallback    {line}");
        if layout.is_none() {
            let _ = writeln!(s, "  hint        {}", fallback_hint(&fallback, tiles.len()));
        }
        failures.push(format!("fallback: {line}"));
    }
    // Pairs the matcher accepted below its NCC floor because the peak stood out: usually
    // right on sparse texture, but a weak link, so named (never a failure).
    let weak: Vec<String> = run
        .pairs
        .iter()
        .filter(|p| p.accepted_below_min_ncc)
        .map(|p| format!("tiles {}-{} (NCC {:.2})", p.a, p.b, p.ncc))
        .collect();
    if !weak.is_empty() {
        let _ = writeln!(
            s,
            "  weak links  {} pair(s) accepted below the matcher's min_ncc as a distinct peak \
             (check their overlap; --set matcher.min_ncc_distinct=1 refuses them): {}",
            weak.len(),
            weak.join(", ")
        );
    }
    if let Some(line) = imprecise_links_line(run) {
        let _ = writeln!(s, "  imprecise   {line}");
    }
    if let Some(line) = memory_line(run) {
        let _ = writeln!(s, "  memory      {line}");
    }
    let _ = writeln!(s, "  outputs     {}", outputs_line(run, out));
    if verbose {
        s.push_str(&latency_table(&run.latency_ms));
    }
    let _ = write!(
        s,
        "verdict: {}",
        if failures.is_empty() {
            "PASS".to_string()
        } else {
            format!("FAIL ({} check(s) failed)", failures.len())
        }
    );
    Verdict { text: s, failures }
}

/// A kept link whose offset the matcher measured to worse than this (one standard deviation,
/// px, the Lucas-Kanade covariance's worst direction) is named: three of them reach 0.5 px.
const IMPRECISE_LINK_SD_PX: f64 = 0.17;

/// The kept links measured to worse than [`IMPRECISE_LINK_SD_PX`] (`pairs[].offset_sd_px`):
/// a sparse or noisy overlap whose offset the data fix only to a few tenths of a pixel. Named
/// so that such an error is never silent; not a failure.
fn imprecise_links_line(run: &RunRecord) -> Option<String> {
    let list: Vec<String> = run
        .pairs
        .iter()
        .filter(|p| p.kept_by_global_solve != Some(false))
        .filter_map(|p| {
            let sd = p.offset_sd_px?;
            (sd > IMPRECISE_LINK_SD_PX).then(|| format!("tiles {}-{} ({sd:.2} px)", p.a, p.b))
        })
        .collect();
    (!list.is_empty()).then(|| {
        format!(
            "{} link(s) measured to worse than {IMPRECISE_LINK_SD_PX} px (one standard \
             deviation, pairs[].offset_sd_px in run.json): the tiles they hold may be a few \
             tenths of a pixel off; more overlap or less noise fixes them: {}",
            list.len(),
            list.join(", ")
        )
    })
}

/// What to check when the layout is wrong (the tiles are not where the grid, overlap and
/// path put them).
const LAYOUT_HINT: &str = "check the layout: a serpentine scan stitched without --serpentine \
     (or with it, when rows all run one way), a wrong --overlap, or the scan.toml's positions";

/// The links whose offset disagrees with the layout's planned offset by more than the stage
/// error (`pairs[].layout_inconsistent`), with the layout hint: a failure of the run.
pub fn layout_line(run: &RunRecord) -> Option<String> {
    let list: Vec<String> = run
        .pairs
        .iter()
        .filter_map(|p| {
            let m = p.layout_inconsistent?;
            Some(format!(
                "tiles {}-{} ({:.1} px off the plan, bound {:.1} px, {})",
                p.a,
                p.b,
                m.shift_px,
                m.bound_px,
                if m.refused {
                    "refused"
                } else {
                    "kept, flagged"
                }
            ))
        })
        .collect();
    (!list.is_empty()).then(|| {
        format!(
            "{} link(s) disagree with the layout's planned offsets by more than the stage error \
             (matcher stage_sigma_px): the tiles are likely not where the layout puts them: \
             {LAYOUT_HINT}: {}",
            list.len(),
            list.join(", ")
        )
    })
}

/// The likely cause when registration placed few tiles: a layout that does not match the
/// scan (overlaps computed where the fields do not overlap).
fn fallback_hint(fallback: &[&TileRecord], tiles: usize) -> String {
    let anchor = fallback.iter().any(|t| t.source.index == 0);
    let share = match (fallback.len() * 2 >= tiles, anchor) {
        (true, true) => "most tiles (the anchor too) were",
        (true, false) => "half the tiles or more were",
        (false, true) => "some tiles (the anchor too) were",
        (false, false) => "some tiles were",
    };
    // Tiles whose links fix one direction: the layout is right, the texture is a lay or a
    // scratch that fixes nothing along itself.
    let one_direction = fallback.iter().all(|t| {
        t.placement
            .as_ref()
            .is_some_and(|p| p.registered_directions == Some(1))
    });
    if one_direction {
        return format!(
            "{share} registered across a ridge only (a lay or a scratch seen in every overlap \
             they share): the stage placed them along it (run.json's stage_direction); more \
             overlap or a feature off the ridge fixes them"
        );
    }
    format!(
        "{share} not registered: {LAYOUT_HINT}; few features in the overlaps is the other cause"
    )
}

fn tile_name(t: &TileRecord) -> String {
    let t = &t.source;
    format!("tile {} (row {} x col {})", t.index, t.row, t.col)
}

/// Table 6, when it was computed.
fn table6(run: &RunRecord) -> Option<&Table6Record> {
    match run.deviation.as_ref()? {
        DeviationRecord::Table(t) => Some(t),
        DeviationRecord::NotComputed { .. } => None,
    }
}

/// Sa, Sq, Sz of the measured panorama: Table 6's "measured" for the whole-panorama region,
/// from a stage compared with the panorama as measured when there is one (a levelled mesh is
/// compared with the levelled panorama, and the line then says so).
fn surface_line(run: &RunRecord) -> Option<String> {
    let dev = table6(run)?;
    let mut stages: Vec<_> = dev.stages.values().collect();
    stages.sort_by_key(|st| st.measured != dev.measured);
    let (measured, file) = stages.iter().find_map(|st| {
        (st.regions.get("panorama").and_then(|r| r.measured)).map(|m| (m, st.measured.as_str()))
    })?;
    let p = |k: &str| finite(measured.by_name(k)).map(|v| format!("{k} {}", um(v)));
    let params: Vec<String> = ["Sa", "Sq", "Sz"].iter().filter_map(|k| p(k)).collect();
    if params.is_empty() {
        return None;
    }
    let shape = (dev.regions.iter())
        .find(|r| r.name == "panorama")
        .map(|r| format!(", {} x {} px", r.rows, r.cols))
        .unwrap_or_default();
    Some(format!(
        "{} of {file}{shape} (rows x cols), mean removed",
        params.join(", "),
    ))
}

/// A value JSON can carry (run.json writes NaN as null).
fn finite(v: Option<f64>) -> Option<f64> {
    v.filter(|v| v.is_finite())
}

/// The STL: file, triangles, vertices, units and the vertical error against its bound.
fn mesh_line(run: &RunRecord) -> Option<String> {
    let m = run.stage::<MeshReport>()?;
    let mut line = format!(
        "{}: {} triangles, {} vertices, units {}",
        m.file,
        count(m.triangles),
        count(m.vertices),
        m.units,
    );
    if let Some(fid) = m.adaptive().map(|a| a.fidelity) {
        let (max, eps) = (fid.error.max_um, fid.epsilon_um);
        if !max.is_nan() && !eps.is_nan() {
            let _ = write!(
                line,
                "; max vertical error {} (bound {}{})",
                um(max),
                um(eps),
                if fid.bound_met { "" } else { ", NOT met" }
            );
        }
    }
    Some(line)
}

/// Table 6 in one line: PASS, or FAIL with the worst judged parameter of every failing stage
/// (None when it was not computed).
fn deviation_line(dev: &DeviationRecord) -> Option<(String, bool)> {
    let DeviationRecord::Table(dev) = dev else {
        return None;
    };
    let limit = dev.threshold_pct;
    let judged: Vec<&str> = dev.judged.iter().map(String::as_str).collect();
    let mut reasons = Vec::new();
    for (name, st) in &dev.stages {
        // A stage reported but not judged (the pooled map when the STL is not made from it).
        if st.pass || !st.judged {
            continue;
        }
        let regions = &st.regions;
        let failing = regions.values().filter(|r| !r.pass).count();
        // The worst judged parameter over the failing regions.
        let worst = regions
            .iter()
            .filter(|(_, r)| !r.pass)
            .flat_map(|(region, r)| {
                judged
                    .iter()
                    .filter_map(move |k| r.deviation(k).map(|d| (region, *k, d)))
            })
            .max_by(|a, b| a.2.abs().total_cmp(&b.2.abs()));
        match worst {
            Some((region, param, d)) => {
                let limit = st.limits_pct.get(param).unwrap_or(limit);
                reasons.push(format!(
                    "{name}: {param} {d:+.2} % in {region}, beyond the limit of +/-{limit:.2} % \
                     ({failing} of {} regions fail)",
                    regions.len()
                ))
            }
            None => reasons.push(format!("{name} fails")),
        }
    }
    let pass = dev.pass && reasons.is_empty();
    let judged_text = judged.join(", ");
    // The limits as run.json writes them (1.0, not 1).
    let json = |v: f64| Value::from(v).to_string();
    let limits_text = match (dev.stages.get("mesh"), dev.model_tolerance_pct) {
        (Some(m), Some(_)) => format!(
            "the mesh within its tolerance (Sa {} %, Sq {} %, Sz {} %), the other judged stages within +/-{limit:.2} %",
            json(m.limits_pct.sa), json(m.limits_pct.sq), json(m.limits_pct.sz)
        ),
        _ => format!("every judged model stage within +/-{limit:.2} %"),
    };
    Some(if pass {
        (
            format!(
                "PASS: {limits_text} of the measurement on {judged_text}, at the measured points (Table 6)"
            ),
            false,
        )
    } else {
        (format!("FAIL: {}", reasons.join("; ")), true)
    })
}

/// The model made from a tolerance: triangles, the worst region at the measured points and,
/// when the tolerance is not met, which region and why.
fn model_line(run: &RunRecord) -> Option<(String, bool)> {
    let m = run.stage::<MeshReport>()?;
    let t = m.tolerance.as_ref()?;
    let tol = &t.tolerance;
    // The optional bounds, named with their limits so the worst region's figures below read
    // against them.
    let mut extra = String::new();
    if let Some(r) = tol.residual_pct.filter(|r| !r.is_nan()) {
        let _ = write!(extra, ", residual {r} % of Sq");
    }
    if let Some(r) = tol.max_error_pct.filter(|r| !r.is_nan()) {
        let _ = write!(extra, ", max error {r} % of Sq");
    }
    let judges_roughness =
        (t.region_fits.first()).is_some_and(|w| w.roughness_deviation_pct.is_some());
    if let Some(r) = tol
        .roughness_pct
        .filter(|r| !r.is_nan() && judges_roughness)
    {
        let _ = write!(extra, ", roughness (mesh - datum) {r} %");
    }
    let mut line = format!(
        "tolerance Sa {} %, Sq {} %, Sz {} %{extra} per region: {} at {} surface triangles ({:.3} per measured px)",
        tol.sa_pct,
        tol.sq_pct,
        tol.sz_pct,
        if t.met { "met" } else { "NOT met" },
        count(t.surface_triangles),
        t.triangles_per_measured_px,
    );
    if let Some(w) = t.region_fits.first() {
        let d = w.deviation_pct;
        // The tile regions (S1...) are Table 6's, judged by the search beside its windows.
        let tiles = match t.footprints {
            0 => String::new(),
            n => format!(" (Table 6's {n} tile regions among them)"),
        };
        // Judged less the field's plane (form before roughness), as Table 6's mesh stage.
        let form = if t.judged_plane.is_some() {
            " less the least-squares plane"
        } else {
            ""
        };
        let _ = write!(
            line,
            "; worst of {} regions{tiles}{form} {}: Sa {:+.2} %, Sq {:+.2} %, Sz {:+.2} %, residual {:.1} % of Sq",
            t.regions, w.region, d[0], d[1], d[2], w.residual_pct_of_sq,
        );
        if let Some(d) = w.roughness_deviation_pct {
            let _ = write!(
                line,
                ", roughness Sa {:+.2} %, Sq {:+.2} %, Sz {:+.2} %",
                d[0], d[1], d[2]
            );
        }
    }
    // The largest pointwise error of any region (relative to its Sq), in um too: the
    // paper's "within 1 um".
    let pointwise = (t.region_fits.iter())
        .filter_map(|w| Some((w, w.max_error_um?, w.max_error_pct_of_sq?)))
        .max_by(|a, b| a.2.total_cmp(&b.2));
    if let Some((w, error_um, pct)) = pointwise {
        let _ = write!(
            line,
            "; max pointwise error {} ({pct:.1} % of Sq) in {}",
            um(error_um),
            w.region
        );
    }
    // With an engine's angle bound (LIGGGHTS): the smallest angle of the mesh written.
    if let Some(a) = &t.angles {
        let _ = write!(
            line,
            "; smallest angle {:.2} deg (bound {} deg)",
            a.min_angle_deg, a.bound_deg,
        );
    }
    let failed = !t.met;
    if let Some(r) = &t.reason {
        let _ = write!(line, " ({r})");
    }
    if let Some(o) = &m.outliers {
        let _ = write!(
            line,
            "; {} spike(s) (they add {:+.2} % to Sz), {}",
            count(o.count),
            // Not computed (no Sz without spikes): nothing added.
            if o.sz_effect_pct.is_nan() {
                0.0
            } else {
                o.sz_effect_pct
            },
            if o.policy == "remove" {
                "removed on request (outliers = \"remove\")"
            } else {
                "kept as measured"
            }
        );
    }
    Some((line, failed))
}

/// Megabytes (10^6 bytes) with no decimals: "612 MB".
fn mb(bytes: u64) -> String {
    format!("{} MB", count(bytes.div_ceil(1_000_000)))
}

/// With a memory budget: the peak against the plan (run.json's `peak_rss`), naming every part
/// that went beyond its share (a node under `launch`, the one process under `run`). Not a
/// failed check: the outputs do not depend on the budget; the line says the plan was not kept.
fn memory_line(run: &RunRecord) -> Option<String> {
    let peak = run.peak_rss.as_ref()?;
    let gb = peak.memory_budget_gb?;
    let budget = format!("the {gb} GB budget");
    if run.mode == "launch" {
        if peak.over_plan.is_empty() {
            let sum = peak.run_bytes_at_most.map_or(String::new(), |b| {
                format!(" (all processes together at most {})", mb(b))
            });
            return Some(format!("every node within its share of {budget}{sum}"));
        }
        let list: Vec<String> = peak
            .over_plan
            .iter()
            .map(|o| {
                format!(
                    "{} {} (share {})",
                    o.part,
                    mb(o.peak_bytes),
                    mb(o.share_bytes)
                )
            })
            .collect();
        return Some(format!(
            "BEYOND THE PLAN: {} node(s) over their share of {budget}: {}",
            list.len(),
            list.join(", ")
        ));
    }
    let process = peak.process_bytes?;
    Some(match peak.over_plan.first() {
        Some(o) => format!(
            "BEYOND THE PLAN: peak {} of one process (every node of `run`), over {budget} \
             ({} over; `launch` gives each node's peak against its share)",
            mb(o.peak_bytes),
            mb(o.peak_bytes - o.share_bytes)
        ),
        None => format!(
            "peak {} of one process (every node of `run`), within {budget}",
            mb(process)
        ),
    })
}

fn outputs_line(run: &RunRecord, out: &Path) -> String {
    let files: Vec<&str> = run.files.iter().map(String::as_str).collect();
    let key: Vec<&str> = [
        "surface.stl",
        "report.html",
        "run.json",
        "panorama.npy",
        "panorama.x3p",
        "recording.mcap",
    ]
    .into_iter()
    // report.html is written after run.json lists the files: look on disk.
    .filter(|k| files.contains(k) || out.join(k).is_file())
    .collect();
    let stl = (run.stage::<MeshReport>())
        .map(|m| m.file)
        .filter(|f| f.ends_with(".stl"))
        .map(|f| format!("; STL {}", out.join(f).display()))
        .unwrap_or_default();
    let set = match &run.outputs {
        Some(o) if o.set == OutputChoice::Model => format!(
            "; output set model: {} files of arrays, previews and recordings removed ({:.1} MB; --outputs full keeps them)",
            o.removed.len(),
            o.removed_bytes as f64 / 1e6
        ),
        _ => String::new(),
    };
    format!(
        "{} ({} files: {}){stl}{set}",
        out.display(),
        files.len(),
        key.join(", ")
    )
}

/// The latency tables of run.json (`--verbose`), in ms.
fn latency_table(lat: &LatencySummary) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "  latency (ms)                          p50       p95       max     n"
    );
    let rows = (lat.end_to_end.iter())
        .chain(&lat.hops)
        .chain(&lat.final_frames);
    for (name, p) in rows {
        let Percentiles { p50, p95, max, n } = p;
        let _ = writeln!(
            s,
            "    {name:<34} {p50:>8.2}  {p95:>8.2}  {max:>8.2}  {n:>4}"
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn run_json(pass: bool, fallback: bool) -> Value {
        json!({
            "elapsed_s": 1.5,
            "scan": { "rows": 1, "cols": 2 },
            "tiles": [
                { "index": 0, "row": 0, "col": 0, "placed_by": "registration" },
                { "index": 1, "row": 0, "col": 1, "placed_by": if fallback { "stage" } else { "registration" } },
            ],
            "files": ["run.json", "surface.stl", "report.html"],
            "stages": { "mesher": { "file": "surface.stl", "triangles": 27850, "vertices": 13927,
                "units": "mm", "fidelity": { "epsilon_um": 0.08, "bound_met": true,
                "error": { "max_um": 0.0799 } } } },
            "deviation": {
                "pass": pass, "threshold_pct": 5.0, "judged": ["Sa", "Sq", "Sz"],
                "measured": "panorama.npy",
                "regions": [{ "name": "panorama", "rows": 487, "cols": 486 }],
                "stages": { "pooled": { "pass": pass, "regions": {
                    "panorama": { "pass": pass,
                        "measured": { "Sa": 1.3630563293, "Sq": 1.7, "Sz": 14.19 },
                        "deviation_pct": { "Sa": -2.97, "Sq": -3.2, "Sz": if pass { -1.0 } else { -8.14 } } },
                    "S1": { "pass": true, "deviation_pct": { "Sa": 0.1, "Sq": 0.1, "Sz": 0.1 } } } } }
            },
            "latency_ms": { "tile_to_panorama": { "p50": 1.0, "p95": 2.0, "max": 3.0, "n": 4 } }
        })
    }

    fn record(v: Value) -> RunRecord {
        crate::runjson::test_record(v)
    }

    #[test]
    fn a_passing_run_names_parameters_mesh_and_outputs_in_significant_figures() {
        let v = verdict(&record(run_json(true, false)), Path::new("/o"), false);
        assert!(v.failures.is_empty(), "{:?}", v.failures);
        let t = &v.text;
        assert!(t.contains("Sa 1.36 um, Sq 1.70 um, Sz 14.2 um"), "{t}");
        // The mesh's max error and bound below 1 um: in nm.
        assert!(
            t.contains("max vertical error 79.9 nm (bound 80.0 nm)"),
            "{t}"
        );
        assert!(
            t.contains("of panorama.npy, 487 x 486 px (rows x cols), mean removed"),
            "{t}"
        );
        assert!(t.contains("1 x 2 tiles (rows x cols)"), "{t}");
        assert!(
            t.contains("surface.stl: 27 850 triangles, 13 927 vertices, units mm"),
            "{t}"
        );
        assert!(t.contains("STL /o/surface.stl"), "{t}");
        assert!(t.contains("deviation   PASS"), "{t}");
        assert!(t.ends_with("verdict: PASS"), "{t}");
        assert!(!t.contains("latency"), "{t}");
        assert!(!t.contains("e0"), "no scientific notation: {t}");
    }

    #[test]
    fn a_failing_run_says_which_parameter_by_how_much_against_which_limit() {
        let v = verdict(&record(run_json(false, true)), Path::new("/o"), true);
        assert_eq!(v.failures.len(), 2, "{:?}", v.failures);
        let t = &v.text;
        assert!(
            t.contains("FAIL: pooled: Sz -8.14 % in panorama, beyond the limit of +/-5.00 % (1 of 2 regions fail)"),
            "{t}"
        );
        assert!(t.contains("tile 1 (row 0 x col 1)"), "{t}");
        // Half the tiles by fallback: the likely causes are named.
        assert!(
            t.contains("hint        half the tiles or more were not registered")
                && t.contains("without --serpentine")
                && t.contains("a wrong --overlap"),
            "{t}"
        );
        assert!(t.contains("tile_to_panorama"), "verbose shows latency: {t}");
        assert!(t.ends_with("verdict: FAIL (2 check(s) failed)"), "{t}");
    }

    #[test]
    fn a_model_that_misses_its_tolerance_names_the_region_and_fails() {
        let mut run = run_json(true, false);
        run["stages"]["mesher"]["tolerance"] = json!({
            "tolerance": { "sa_pct": 1.0, "sq_pct": 1.0, "sz_pct": 3.0 },
            "met": false, "surface_triangles": 1200, "triangles_per_measured_px": 0.012,
            "angles": { "min_angle_deg": 1.047, "bound_deg": 1.0, "min_angle_before_deg": 0.168,
                "below_bound_before": 37, "below_bound": 0, "triangles_before": 1150,
                "triangles": 1200 },
            "regions": 5,
            "region_fits": [{ "region": "W1.2", "deviation_pct": [-1.5, -1.2, 0.0],
                "residual_pct_of_sq": 31.0 }],
            "reason": "region W1.2: Sa -1.50 % beyond the tolerance of 1 %: the next finer mesh needs 5000 surface triangles, beyond max_triangles = 2000",
        });
        run["stages"]["mesher"]["outliers"] =
            json!({ "count": 3, "sz_effect_pct": 12.5, "policy": "keep" });
        let v = verdict(&record(run), Path::new("/o"), false);
        let t = &v.text;
        assert_eq!(v.failures.len(), 1, "{t}");
        assert!(t.contains("model       tolerance Sa 1 %, Sq 1 %, Sz 3 % per region: NOT met at 1 200 surface triangles"), "{t}");
        assert!(t.contains("worst of 5 regions W1.2: Sa -1.50 %"), "{t}");
        // LIGGGHTS' angle bound: the smallest angle of the mesh written.
        assert!(t.contains("; smallest angle 1.05 deg (bound 1 deg)"), "{t}");
        assert!(t.contains("beyond max_triangles = 2000"), "{t}");
        assert!(
            t.contains("3 spike(s) (they add +12.50 % to Sz), kept as measured"),
            "{t}"
        );
    }

    /// A tile region (Table 6's S3) as the search's worst region is named so, and the line
    /// says the tile regions were judged.
    #[test]
    fn the_model_line_names_a_tile_region_as_the_worst() {
        let mut run = run_json(true, false);
        run["stages"]["mesher"]["tolerance"] = json!({
            "tolerance": { "sa_pct": 1.0, "sq_pct": 1.0, "sz_pct": 3.0 },
            "met": false, "surface_triangles": 1200, "triangles_per_measured_px": 0.012,
            "regions": 21, "footprints": 4,
            "region_fits": [{ "region": "S3", "deviation_pct": [-1.29, -0.8, 0.0],
                "residual_pct_of_sq": 18.0 }],
            "reason": "region S3: Sa -1.29 % beyond the tolerance of 1 %: the next finer mesh needs 5000 surface triangles, beyond max_triangles = 2000",
        });
        let v = verdict(&record(run), Path::new("/o"), false);
        let t = &v.text;
        assert_eq!(v.failures.len(), 1, "{t}");
        assert!(
            t.contains("worst of 21 regions (Table 6's 4 tile regions among them) S3: Sa -1.29 %"),
            "{t}"
        );
        assert!(
            t.contains("(region S3: Sa -1.29 % beyond the tolerance of 1 %"),
            "{t}"
        );
    }

    /// The limits of the residual and of the roughness the mesh carries are printed beside the
    /// worst region's figures, and a miss on the roughness names it.
    #[test]
    fn the_model_line_names_the_residual_and_roughness_limits() {
        let mut run = run_json(true, false);
        run["stages"]["mesher"]["tolerance"] = json!({
            "tolerance": { "sa_pct": 1.0, "sq_pct": 1.0, "sz_pct": 3.0, "residual_pct": 50.0,
                "roughness_pct": 5.0 },
            "met": false, "surface_triangles": 1200, "triangles_per_measured_px": 0.012,
            "regions": 5,
            "region_fits": [{ "region": "W1.2", "deviation_pct": [0.5, 0.4, 0.0],
                "residual_pct_of_sq": 31.0, "roughness_deviation_pct": [20.17, 16.2, 0.0] }],
            "reason": "region W1.2: roughness Sa +20.17 % beyond the tolerance of 5 %: the next finer mesh needs 5000 surface triangles, beyond max_triangles = 2000",
        });
        let v = verdict(&record(run), Path::new("/o"), false);
        let t = &v.text;
        assert_eq!(v.failures.len(), 1, "{t}");
        assert!(
            t.contains("tolerance Sa 1 %, Sq 1 %, Sz 3 %, residual 50 % of Sq, roughness (mesh - datum) 5 % per region: NOT met"),
            "{t}"
        );
        assert!(
            t.contains("residual 31.0 % of Sq, roughness Sa +20.17 %, Sq +16.20 %, Sz +0.00 %"),
            "{t}"
        );
        assert!(
            t.contains("roughness Sa +20.17 % beyond the tolerance of 5 %"),
            "{t}"
        );
    }

    /// The pointwise bound is stated with the others, and the largest pointwise error of any
    /// region (relative to its Sq) is printed in um: the paper's "within 1 um".
    #[test]
    fn the_model_line_states_the_pointwise_bound_and_the_largest_error() {
        let mut run = run_json(true, false);
        run["stages"]["mesher"]["tolerance"] = json!({
            "tolerance": { "sa_pct": 1.0, "sq_pct": 1.0, "sz_pct": 3.0, "residual_pct": 20.0,
                "max_error_pct": 50.0 },
            "met": true, "surface_triangles": 1200, "triangles_per_measured_px": 0.012,
            "regions": 5,
            "region_fits": [
                { "region": "W1.2", "deviation_pct": [0.5, 0.4, 0.0], "residual_pct_of_sq": 14.0,
                  "max_error_um": 0.9, "max_error_pct_of_sq": 40.0 },
                { "region": "W2.1", "deviation_pct": [0.1, 0.1, 0.0], "residual_pct_of_sq": 12.0,
                  "max_error_um": 0.767, "max_error_pct_of_sq": 44.2 }],
        });
        let v = verdict(&record(run), Path::new("/o"), false);
        let t = &v.text;
        assert!(v.failures.is_empty(), "{t}");
        assert!(
            t.contains("Sz 3 %, residual 20 % of Sq, max error 50 % of Sq per region: met"),
            "{t}"
        );
        assert!(
            t.contains("; max pointwise error 767 nm (44.2 % of Sq) in W2.1"),
            "{t}"
        );
    }

    /// A tile the stage placed along a ridge (its links fix one direction) gets the ridge
    /// hint, not the layout one: the layout is right.
    #[test]
    fn a_tile_placed_along_a_ridge_gets_the_ridge_hint() {
        let mut run = run_json(true, true);
        run["tiles"][1]["registered_directions"] = json!(1);
        run["tiles"][1]["stage_direction"] = json!([1.0, 0.0]);
        let v = verdict(&record(run), Path::new("/o"), false);
        let t = &v.text;
        assert!(t.contains("registered across a ridge only"), "{t}");
        assert!(!t.contains("--serpentine"), "{t}");
        // Without the direction count the layout hint stays.
        let v = verdict(&record(run_json(true, true)), Path::new("/o"), false);
        assert!(v.text.contains("--serpentine"), "{}", v.text);
    }

    /// A pair accepted below min_ncc as a distinct peak is named, and is not a failure.
    #[test]
    fn a_weak_link_is_named_but_does_not_fail() {
        let mut run = run_json(true, false);
        let pair = |a: u32, ncc: f64| {
            json!({ "a": a, "b": a + 1, "direction": "horizontal",
                "nominal_offset_px": [900.0, 0.0], "offset_px": [901.0, 0.5], "ncc": ncc,
                "peak_ratio": 2.0, "accepted": true, "reason": null })
        };
        let mut weak = pair(0, 0.31);
        weak["accepted_below_min_ncc"] = json!(true);
        run["pairs"] = json!([weak, pair(1, 0.93)]);
        let v = verdict(&record(run), Path::new("/o"), false);
        assert!(v.failures.is_empty(), "{:?}", v.failures);
        assert!(
            v.text
                .contains("weak links  1 pair(s) accepted below the matcher's min_ncc")
                && v.text.contains("tiles 0-1 (NCC 0.31)")
                && !v.text.contains("tiles 1-2"),
            "{}",
            v.text
        );
        let v = verdict(&record(run_json(true, false)), Path::new("/o"), false);
        assert!(!v.text.contains("weak links"), "{}", v.text);
    }

    /// A kept link with a large standard deviation is named, and is not a failure; a dropped
    /// one is not named.
    #[test]
    fn an_imprecise_link_is_named_but_does_not_fail() {
        let mut run = run_json(true, false);
        // Complete pairs, as the matcher writes them (a MatcherPair has no optional core).
        let pair = |a: u32, b: u32, ncc: f64, sd: f64| {
            json!({ "a": a, "b": b, "direction": "horizontal",
                "nominal_offset_px": [900.0, 0.0], "offset_px": [901.0, 0.5], "ncc": ncc,
                "peak_ratio": 2.0, "accepted": true, "reason": null, "offset_sd_px": sd })
        };
        let mut dropped = pair(2, 5, 0.7, 0.4);
        dropped["kept_by_global_solve"] = json!(false);
        run["pairs"] = json!([pair(3, 4, 0.61, 0.23), pair(1, 2, 0.99, 0.05), dropped]);
        let v = verdict(&record(run), Path::new("/o"), false);
        assert!(v.failures.is_empty(), "{:?}", v.failures);
        assert!(
            v.text
                .contains("imprecise   1 link(s) measured to worse than 0.17 px")
                && v.text.contains("tiles 3-4 (0.23 px)")
                && !v.text.contains("tiles 1-2")
                && !v.text.contains("tiles 2-5"),
            "{}",
            v.text
        );
        let v = verdict(&record(run_json(true, false)), Path::new("/o"), false);
        assert!(!v.text.contains("imprecise"), "{}", v.text);
    }

    #[test]
    fn a_node_beyond_its_share_of_the_budget_is_named_but_does_not_fail() {
        let mut v = run_json(true, false);
        v["mode"] = json!("launch");
        v["peak_rss"] = json!({ "process_bytes": 30_000_000,
            "nodes_bytes": { "mesher": 612_400_000, "fusion": 90_000_000 },
            "run_bytes_at_most": 732_400_000, "memory_budget_gb": 0.5,
            "shares_bytes": { "mesher": 125_000_000, "fusion": 125_000_000 },
            "over_plan": [{ "part": "mesher", "peak_bytes": 612_400_000,
                "share_bytes": 125_000_000 }],
            "source": "" });
        let out = verdict(&record(v.clone()), Path::new("/o"), false);
        assert!(out.failures.is_empty(), "{:?}", out.failures);
        assert!(
            out.text.contains(
                "memory      BEYOND THE PLAN: 1 node(s) over their share of the 0.5 GB budget: \
                 mesher 613 MB (share 125 MB)"
            ),
            "{}",
            out.text
        );
        v["peak_rss"]["over_plan"] = json!([]);
        let out = verdict(&record(v.clone()), Path::new("/o"), false);
        assert!(out.text.contains("memory      every node within its share of the 0.5 GB budget (all processes together at most 733 MB)"), "{}", out.text);
        v["mode"] = json!("run");
        v["peak_rss"]["process_bytes"] = json!(700_000_000);
        v["peak_rss"]["over_plan"] = json!([{ "part": "run", "peak_bytes": 700_000_000,
            "share_bytes": 500_000_000 }]);
        let out = verdict(&record(v.clone()), Path::new("/o"), false);
        assert!(
            out.text
                .contains("BEYOND THE PLAN: peak 700 MB of one process"),
            "{}",
            out.text
        );
        assert!(out.text.contains("(200 MB over;"), "{}", out.text);
        // Without a budget: no line.
        v["peak_rss"]["memory_budget_gb"] = Value::Null;
        let out = verdict(&record(v), Path::new("/o"), false);
        assert!(!out.text.contains("memory "), "{}", out.text);
    }

    #[test]
    fn counts_are_grouped_by_thousands() {
        assert_eq!(count(0), "0");
        assert_eq!(count(999), "999");
        assert_eq!(count(1000), "1 000");
        assert_eq!(count(1234567), "1 234 567");
        assert_eq!(um(1.3630563293), "1.36 um");
        // A MetroPro 3 x 3's Sa read "0.005 um" at three decimals.
        assert_eq!(um(0.0051234), "5.12 nm");
    }

    #[test]
    fn the_first_line_says_the_whole_wait() {
        let t = "surfstream: done in 4.33 s\n  scan        x\nverdict: PASS";
        let w = with_wall_time(t, 6.1);
        assert!(
            w.starts_with("surfstream: done in 6.10 s (pipeline 4.33 s; then Table 6, x3p and report)\n  scan"),
            "{w}"
        );
        assert!(w.ends_with("verdict: PASS"));
    }
}
