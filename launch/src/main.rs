//! `surfstream`: start a node graph as processes (`launch`) or threads (`run`), or stitch a
//! scan directory or recording in one go (`stitch`); the single-file verbs ([`verbs`]); after a
//! run, run.json, Table 6 from the output files, report.html and the verdict.
//!
//! Not for: algorithms. Each computation lives in a library (surfstream-core, surfstream-io,
//! the node crates) that the verbs and the Python package call alike; this crate parses
//! arguments, starts and supervises nodes, and assembles and presents what they wrote
//! (docs/architecture.md §4, §7).

mod compare_fusion;
mod deviation;
mod launcher;
mod live;
mod nodes;
mod outdir;
mod outdir_space;
mod outputs;
mod progress;
mod report;
mod runjson;
mod verbs;
mod verdict;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use surfstream_core::record::{NodeRecord, OutputChoice};
use surfstream_runtime::graph::GraphFile;

#[derive(Parser)]
#[command(
    name = "surfstream",
    version,
    about = "Optical-profiler tiles in, a stitched surface model out: panorama, datum, roughness, pooled map, STL.",
    long_about = "surfstream streams overlapping height-map tiles from a (simulated or recorded) profiler \
stage through registration, fusion, wavelet separation and meshing.\n\n\
  surfstream launch launch/graphs/demo.toml     every node its own process, frames over shared memory\n\
  surfstream run launch/graphs/demo.toml        the same graph in one process (identical outputs)\n\
  surfstream stitch scan.toml -o out/scan       the default pipeline for a scan directory or recording\n\n\
Conventions of every verb: outputs go where -o/--out says (missing folders are created); \
heights and lengths in um; sizes as rows x cols; a warning on stderr whenever a pitch, unit or \
level is assumed or changed. launch, run and stitch print a line per registered tile while they \
work and a verdict at the end (key parameters, outputs, mesh size, Table 6 pass/fail); \
--strict makes a failed check exit with status 3."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Args, Clone)]
struct GraphArgs {
    /// Graph file (TOML): nodes, parameters, wiring. See launch/graphs/demo.toml.
    graph: PathBuf,
    /// Output directory (overrides [graph] out_dir).
    #[arg(short = 'o', long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Override one node parameter, e.g. --set stage.rows=3 (VALUE is read as TOML); or the
    /// Table-6 threshold: --set deviation.threshold_percent=2.
    #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
    set: Vec<String>,
    /// Replace an existing output directory even though it is not a surfstream run (its
    /// files are deleted). Never needed for a new folder or an earlier run's folder.
    #[arg(long)]
    force: bool,
    /// The model's tolerance per region, percent: sa, sq, sz (default 1, 1, 3), res (the
    /// pointwise residual, % of Sq, default 50) and rough (the roughness the mesh carries,
    /// default 5 when the graph wires the measured roughness); `=off` drops a bound. The mesher
    /// makes the fewest triangles that meet it (docs/model.md). Sets `tolerance` on every
    /// mesher node.
    #[arg(long, value_name = "sa=1,sq=1,sz=3")]
    tolerance: Option<String>,
    /// Which files the run keeps: model (the STL, run.json, report.html and the small
    /// records; no height-map arrays, previews or recording) or full (every file, the
    /// default). Overrides the graph's [outputs] set (docs/outputs.md).
    #[arg(long, value_name = "model|full")]
    outputs: Option<OutputChoice>,
    #[command(flatten)]
    verdict: VerdictArgs,
    #[command(flatten)]
    view: live::ViewArgs,
}

/// How the end of a graph run is judged and told.
#[derive(Args, Clone, Copy)]
struct VerdictArgs {
    /// Exit with status 3 when a check fails (Table 6 deviation beyond the threshold, tiles
    /// placed by stage fallback), after writing every output.
    #[arg(long)]
    strict: bool,
    /// Also print the latency tables (p50 / p95 / max per stage, ms); they are always in
    /// run.json and report.html.
    #[arg(short, long)]
    verbose: bool,
}

#[derive(Subcommand)]
enum Command {
    /// Start every node of GRAPH as its own process, supervise, and write run.json.
    Launch(GraphArgs),
    /// Run GRAPH in this process, nodes as threads (bit-identical outputs to `launch`).
    Run(GraphArgs),
    /// Stitch a scan directory (scan.toml) or an MCAP recording with the default pipeline.
    Stitch {
        /// scan.toml (or its directory), or a .mcap recording made by the recorder.
        scan: PathBuf,
        /// Output directory (created with its missing parents).
        #[arg(short = 'o', long, value_name = "DIR")]
        out: PathBuf,
        /// Override one node parameter (nodes: stage, matcher, fusion, wavelet, mesher), or
        /// the Table-6 threshold: --set deviation.threshold_percent=2.
        #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
        set: Vec<String>,
        /// The model's tolerance per region, percent: sa, sq, sz (default 1, 1, 3), res
        /// (default 50, % of Sq), rough (default 5); `=off` drops a bound (docs/model.md).
        #[arg(long, value_name = "sa=1,sq=1,sz=3")]
        tolerance: Option<String>,
        /// Which files the run keeps: model (the STL, run.json, report.html and the small
        /// records) or full (every file, the default) (docs/outputs.md).
        #[arg(long, value_name = "model|full")]
        outputs: Option<OutputChoice>,
        /// Registration method of the matcher: auto | phase | harris | sift (auto = the best
        /// available, phase correlation; the same as `--set matcher.method=...`).
        #[arg(long, value_name = "METHOD")]
        method: Option<String>,
        /// Stitch once per fusion method (average, gradual, wavelet) into OUT/<method>/ and
        /// print the SSIM of the overlaps side by side (the paper's Table 2), plus the height
        /// error against the specimen when the scan directory holds specimen.npy and
        /// ground_truth.json.
        #[arg(long)]
        compare_fusion: bool,
        /// SCAN is a folder of tiles without scan.toml: the grid as ROWSxCOLS (e.g. 3x4); the
        /// tiles in file-name order are the acquisition order. The inferred scan.toml is
        /// written to OUT.
        #[arg(long, value_name = "ROWSxCOLS", requires = "overlap")]
        grid: Option<surfstream_replay::infer::TileGrid>,
        /// With --grid: the overlap of neighbouring fields, "20%" or "0.2".
        #[arg(long, requires = "grid")]
        overlap: Option<surfstream_replay::infer::Overlap>,
        /// With --grid: odd rows run right to left (the stage's serpentine).
        #[arg(long, requires = "grid")]
        serpentine: bool,
        /// With --grid: the pitch, um, for tiles that carry none (.npy without a NAME.npy.json
        /// sidecar); refused when it disagrees with the tiles' own (the rule of every verb).
        #[arg(long, requires = "grid")]
        pitch_um: Option<f64>,
        /// For a folder of tiles without scan.toml: the unit of heights in tiles that carry
        /// none (.npy, .xyz): um, nm, mm or m (written to the inferred scan.toml's [scan]
        /// height_unit; without it such heights are taken as um, with a warning).
        #[arg(long, value_name = "UNIT")]
        height_unit: Option<String>,
        /// Replace an existing output directory even though it is not a surfstream run (its
        /// files are deleted). The scan's own folder is never accepted as OUT.
        #[arg(long)]
        force: bool,
        #[command(flatten)]
        verdict: VerdictArgs,
        #[command(flatten)]
        view: live::ViewArgs,
    },
    /// Show a height-map file's metadata, shape, pitch and invalid count.
    Inspect(verbs::metrology::InspectArgs),
    /// ISO 25178 parameters of height-map files (--all: the full set; --json/--csv/--jsonl).
    Params(verbs::metrology::ParamsArgs),
    /// Convert a height-map file to another format (by extension): convert IN -o OUT.
    Convert(ConvertCmd),
    /// Compare two height maps or images: SIM, SSIM, RMS difference.
    Compare(verbs::metrology::CompareArgs),
    /// Pre-process a height map: level, filter, crop, rotate, fill, threshold, outliers, in
    /// the order given: prep IN OUT --level plane --filter l=80um.
    Prep(verbs::prep::PrepArgs),
    /// Separate one height map into datum and roughness (2-D wavelet decomposition).
    Separate(SeparateCmd),
    /// Mesh one height map with a bounded vertical error and write STL.
    Mesh(MeshCmd),
    /// Finishing simulation on LIGGGHTS: a patch of FILE (or of a run's out dir) worn by
    /// media over cycles; wear maps, worn surface, finish.json, finish.html.
    Finish(Box<verbs::finish::FinishArgs>),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if !matches!(
        cli.command,
        Command::Launch(_) | Command::Run(_) | Command::Stitch { .. }
    ) {
        // The single-file verbs print tables that users pipe into `head` or `grep`: a closed
        // pipe ends them quietly, like any Unix filter, instead of a "Broken pipe" panic.
        // (Graph verbs keep Rust's default, so a supervisor never dies of a closed terminal.)
        // SAFETY: restoring a signal's default disposition before any thread is started.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    // A full or closed stderr (`2> /dev/full`) must not turn a message into a panic.
    surfstream_runtime::stdio::discard_unwritable_stderr();
    surfstream_runtime::stdio::exit_cleanly_on_stream_panics();
    if matches!(
        cli.command,
        Command::Launch(_) | Command::Run(_) | Command::Stitch { .. }
    ) {
        // One signal story: Ctrl-C, SIGTERM, SIGHUP at any phase stop the run through its
        // failure path (FAILED names the signal); a second one forces.
        if let Err(e) = surfstream_runtime::stop::install() {
            eprintln!("surfstream: error: {e:#}");
            return ExitCode::FAILURE;
        }
    }
    let outcome = dispatch(cli);
    // The live view (if any) shows the verdict, and stays as long as --view-linger-s says.
    live::end(outcome.as_ref().map(|_| ()));
    match outcome {
        Ok(code) => code,
        Err(e) => {
            eprintln!("surfstream: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn dispatch(cli: Cli) -> Result<ExitCode> {
    let done = |r: Result<()>| r.map(|()| ExitCode::SUCCESS);
    match cli.command {
        Command::Launch(a) => {
            let started = std::time::Instant::now();
            let (graph, deviation) = load_graph(&a)?;
            let out = graph.graph.out_dir.clone();
            note_replaced_run(&a, &out);
            let claim = graph_claim(&graph, &a.graph, a.force);
            live::start(&a.view, &out)?;
            launcher::launch(graph, &a.graph, deviation, &claim)?;
            // The nodes' stderr went to logs/: their warnings reach the user here too.
            relay_node_warnings(&out);
            tell_verdict(&out, a.verdict, started)
        }
        Command::Run(a) => {
            let started = std::time::Instant::now();
            let (graph, deviation) = load_graph(&a)?;
            let out = graph.graph.out_dir.clone();
            note_replaced_run(&a, &out);
            let claim = graph_claim(&graph, &a.graph, a.force);
            live::start(&a.view, &out)?;
            launcher::run_in_process(graph, &a.graph, deviation, &claim)?;
            tell_verdict(&out, a.verdict, started)
        }
        Command::Stitch {
            scan,
            out,
            set,
            tolerance,
            outputs,
            method,
            compare_fusion,
            grid,
            overlap,
            serpentine,
            pitch_um,
            height_unit,
            force,
            verdict,
            view,
        } => {
            let started = std::time::Instant::now();
            refuse_single_file_scan(&scan)?;
            let inferred = grid.is_some() || (scan.is_dir() && !scan.join("scan.toml").exists());
            if let Some(unit) = &height_unit {
                if surfstream_replay::scan_dir::unit_scale(unit).is_none() {
                    bail!(
                        "--height-unit {unit:?}: expected one of {}",
                        surfstream_replay::scan_dir::HEIGHT_UNITS
                    );
                }
                if !inferred {
                    bail!(
                        "--height-unit is for a folder of tiles without scan.toml; {} has its \
                         own manifest: state the unit there ([scan] height_unit)",
                        scan.display()
                    );
                }
            }
            let height_unit = height_unit.as_deref();
            // The scan's folder (or the recording) is never the out dir nor inside it.
            let scan_input = if scan.is_dir() {
                scan.clone()
            } else {
                scan.parent()
                    .filter(|p| !p.as_os_str().is_empty())
                    .map_or_else(|| PathBuf::from("."), std::path::Path::to_path_buf)
            };
            let mut claim = outdir::Claim {
                inputs: vec![scan_input, scan.clone()],
                force,
            };
            if grid.is_some()
                || compare_fusion
                || (scan.is_dir() && !scan.join("scan.toml").exists())
            {
                // Written into OUT before the run is staged: OUT must be ours first.
                outdir::check_ours(&out, &claim)?;
                outdir::create_marked(&out)?;
                claim.force = false;
            }
            let scan = match (grid, overlap) {
                (Some(g), Some(o)) => {
                    let layout = (g, o, serpentine);
                    infer_scan(&scan, &out, layout, pitch_um, height_unit)?
                }
                // A folder of tiles without a manifest: the layout from the files' stage positions.
                (None, None) if scan.is_dir() && !scan.join("scan.toml").exists() => {
                    infer_scan_from_positions(&scan, &out, pitch_um, height_unit)?
                }
                _ => scan,
            };
            if compare_fusion {
                // Each method's graph gets the same --tolerance and --outputs as a plain stitch.
                let prepare = |graph: &mut GraphFile| -> Result<()> {
                    if let Some(t) = &tolerance {
                        apply_tolerance(graph, t, "stitch pipeline")?;
                    }
                    if let Some(o) = outputs {
                        graph.set_output_choice(o);
                    }
                    Ok(())
                };
                let methods = compare_fusion::Methods {
                    set: &set,
                    method: method.as_deref(),
                    outputs,
                    prepare: &prepare,
                };
                return done(compare_fusion::run(&scan, &out, &methods));
            }
            let (mut graph, deviation) = stitch_graph(&scan, out.clone(), &set, method.as_deref())?;
            if let Some(t) = &tolerance {
                apply_tolerance(&mut graph, t, "stitch pipeline")?;
            }
            if let Some(o) = outputs {
                graph.set_output_choice(o);
            }
            claim.inputs.extend(outdir::inputs_of(&graph, &out));
            live::start(&view, &out)?;
            launcher::run_in_process(graph, &scan, deviation, &claim)?;
            tell_verdict(&out, verdict, started)
        }
        Command::Inspect(a) => {
            verbs::one_file(&a.file, "inspect")?;
            done(verbs::metrology::inspect(a))
        }
        Command::Params(a) => done(verbs::metrology::params(a)),
        Command::Convert(ConvertCmd { a, .. }) if a.input.is_dir() => {
            done(verbs::metrology::convert_folder(a))
        }
        Command::Convert(ConvertCmd { mut a, overwrite }) => {
            verbs::one_file(&a.input, "convert")?;
            let out = verbs::convert_output(a.out.take(), a.output.take())?;
            verbs::claim_output_files("convert", &[&a.input], &[&out], overwrite)?;
            a.out = Some(out);
            done(verbs::metrology::convert(a))
        }
        Command::Prep(a) => {
            verbs::one_file(&a.input, "prep")?;
            done(verbs::prep::run(a))
        }
        Command::Compare(a) => {
            verbs::one_file(&a.a, "compare")?;
            verbs::one_file(&a.b, "compare")?;
            done(verbs::metrology::compare(a))
        }
        Command::Separate(SeparateCmd { a, overwrite }) => {
            verbs::one_file(&a.file, "separate")?;
            verbs::claim_output_folder("separate", &[&a.file], &a.out, overwrite)?;
            done(verbs::separate::run(a))
        }
        Command::Mesh(MeshCmd { a, overwrite }) => {
            verbs::one_file(&a.file, "mesh")?;
            let json = a.out.with_extension("json");
            verbs::claim_output_files("mesh", &[&a.file], &[&a.out, &json], overwrite)?;
            done(verbs::mesh::run(a))
        }
        Command::Finish(a) => done(verbs::finish::run(*a)),
    }
}

/// `convert` with `--force` (issue 36: an existing output or an input is never replaced
/// silently).
#[derive(Args)]
struct ConvertCmd {
    #[command(flatten)]
    a: verbs::metrology::ConvertArgs,
    #[command(flatten)]
    overwrite: verbs::Overwrite,
}

/// `separate` with `--force` (it writes into a new or empty folder unless told).
#[derive(Args)]
struct SeparateCmd {
    #[command(flatten)]
    a: verbs::separate::SeparateArgs,
    #[command(flatten)]
    overwrite: verbs::Overwrite,
}

/// `mesh` with `--force` (the STL and its OUT.json).
#[derive(Args)]
struct MeshCmd {
    #[command(flatten)]
    a: verbs::mesh::MeshArgs,
    #[command(flatten)]
    overwrite: verbs::Overwrite,
}

/// What a graph run reads (so its out dir may not replace it) and `--force`.
fn graph_claim(graph: &GraphFile, graph_file: &std::path::Path, force: bool) -> outdir::Claim {
    let mut inputs = outdir::inputs_of(graph, &graph.graph.out_dir);
    inputs.push(graph_file.to_path_buf());
    outdir::Claim { inputs, force }
}

/// `launch`/`run` without `-o` write into the graph's out_dir: say so when a run is there
/// already (it is replaced).
fn note_replaced_run(a: &GraphArgs, out: &std::path::Path) {
    if a.out.is_none() && out.join("run.json").is_file() {
        eprintln!(
            "surfstream: note: no -o given: writing to {} (the graph's out_dir), replacing the run \
             there; give -o DIR to keep it",
            out.display()
        );
    }
}

/// Lines of the nodes' logs (`out/logs/NODE.stderr`, where `launch` sends each process's
/// stderr) that carry a warning, printed to the user's stderr with the node's name.
fn relay_node_warnings(out: &std::path::Path) {
    let Ok(entries) = std::fs::read_dir(out.join("logs")) else {
        return;
    };
    let mut logs: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "stderr"))
        .collect();
    logs.sort();
    for log in logs {
        let Ok(text) = std::fs::read_to_string(&log) else {
            continue;
        };
        let node = log
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        for line in text.lines().filter(|l| l.contains("warning")) {
            let line = line.trim();
            if line.starts_with(&format!("{node}:")) {
                eprintln!("{line}");
            } else {
                eprintln!("{node}: {line}");
            }
        }
    }
}

/// `stitch FILE` where FILE is neither a manifest nor a recording (a tile, say): named as
/// such, not as a TOML parse error.
fn refuse_single_file_scan(scan: &std::path::Path) -> Result<()> {
    let ext = scan
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    if scan.is_file() && ext != "toml" && ext != "mcap" {
        let what = if surfstream_io::formats::is_surface_file(scan) {
            "one height-map file"
        } else {
            "neither a scan.toml nor a .mcap recording"
        };
        bail!(
            "{}: {what}; stitch takes a scan.toml (or its folder), a folder of tiles \
             (--grid ROWSxCOLS --overlap P) or a .mcap recording. For one file: surfstream \
             params | separate | mesh FILE",
            scan.display()
        );
    }
    Ok(())
}

/// Prints the verdict of the run in `out` (stdout: it is the result; progress and warnings
/// go to stderr). Under `--strict` a failed check is exit status 3.
fn tell_verdict(
    out: &std::path::Path,
    how: VerdictArgs,
    started: std::time::Instant,
) -> Result<ExitCode> {
    let mut v = verdict::from_out_dir(out, how.verbose)?;
    // run.json's elapsed_s ends with the pipeline; the user waited for Table 6, the x3p and
    // the report as well: the first line says the whole time.
    v.text = verdict::with_wall_time(&v.text, started.elapsed().as_secs_f64());
    {
        use std::io::Write;
        let mut stdout = std::io::stdout().lock();
        writeln!(stdout, "{}", v.text)
            .and_then(|()| stdout.flush())
            .map_err(|e| {
                anyhow!(
                    "cannot write the verdict to stdout ({e}); the run itself is complete in {}",
                    out.display()
                )
            })?;
    }
    // The run is complete; a stop signal that came after it still ends with an error.
    surfstream_runtime::stop::check()
        .map_err(|e| e.context(format!("the run completed in {}", out.display())))?;
    if how.strict && !v.failures.is_empty() {
        eprintln!(
            "surfstream: --strict: {} check(s) failed (outputs are written):",
            v.failures.len()
        );
        for f in &v.failures {
            eprintln!("  {f}");
        }
        return Ok(ExitCode::from(verdict::STRICT_FAILURE_EXIT));
    }
    Ok(ExitCode::SUCCESS)
}

/// Reads a graph file and applies `--out` and `--set`; returns the graph and the Table-6
/// settings of its `[deviation]` table.
fn load_graph(a: &GraphArgs) -> Result<(GraphFile, deviation::Settings)> {
    let origin = a.graph.display().to_string();
    let text = std::fs::read_to_string(&a.graph)
        .with_context(|| format!("{origin}: cannot read graph file"))?;
    let registry = nodes::registry();
    let mut graph = GraphFile::parse(&text, &origin, &registry)?;
    // The [deviation] table and `--set deviation.*` are the launcher's, not a node's.
    let mut settings = deviation::Settings::from_graph(&graph, &origin)?;
    for s in settings.apply_sets(&a.set)? {
        graph.apply_override(&s)?;
    }
    if let Some(out) = &a.out {
        graph.graph.out_dir = out.clone();
    }
    if let Some(t) = &a.tolerance {
        apply_tolerance(&mut graph, t, &origin)?;
    }
    if let Some(o) = a.outputs {
        graph.set_output_choice(o);
    }
    graph.validate(&a.graph.display().to_string(), &registry)?;
    check_node_params(&graph, &origin)?;
    Ok((graph, settings))
}

/// `--tolerance`: checked, then set on every mesher node of the graph.
fn apply_tolerance(graph: &mut GraphFile, tolerance: &str, origin: &str) -> Result<()> {
    use surfstream_core::record::MeshReport;
    tolerance
        .parse::<surfstream_mesher::Tolerance>()
        .map_err(|e| anyhow!("--tolerance: {e}"))?;
    let mut meshers = 0;
    for n in graph
        .nodes
        .iter_mut()
        .filter(|n| n.node == <MeshReport as NodeRecord>::NODE_KIND)
    {
        // Written as given (run.json's parameters show the user's text), under the key the
        // mesher's config reads.
        n.params.insert(
            surfstream_mesher::MesherConfig::TOLERANCE_KEY.into(),
            toml::Value::String(tolerance.into()),
        );
        meshers += 1;
    }
    if meshers == 0 {
        bail!("--tolerance: {origin} has no mesher node");
    }
    check_node_params(graph, origin)
}

/// Every node's parameters checked the way the node will check them (each kind's `check`),
/// before anything is started or written (the out dir is not touched): a typo fails here,
/// not after "launched graph" with a half-prepared out dir.
fn check_node_params(graph: &GraphFile, origin: &str) -> Result<()> {
    let contexts = graph.resolve(0, &nodes::registry())?;
    for c in &contexts {
        // The nodes' own errors name the graph, the node and the field: the graph file's
        // name goes before them.
        nodes::check(c).with_context(|| origin.to_string())?;
    }
    Ok(())
}

/// Writes OUT/scan.toml for a folder of tiles laid out as the user says, and returns its path.
fn infer_scan(
    dir: &std::path::Path,
    out: &std::path::Path,
    (grid, overlap, serpentine): (
        surfstream_replay::infer::TileGrid,
        surfstream_replay::infer::Overlap,
        bool,
    ),
    pitch_um: Option<f64>,
    height_unit: Option<&str>,
) -> Result<PathBuf> {
    if !dir.is_dir() {
        anyhow::bail!("{}: --grid needs a folder of tiles", dir.display());
    }
    if dir.join("scan.toml").exists() {
        anyhow::bail!(
            "{}: the folder has a scan.toml; stitch it without --grid, or move it away",
            dir.display()
        );
    }
    let layout = surfstream_replay::infer::GridLayout {
        rows: grid.rows,
        cols: grid.cols,
        overlap_x: overlap.0,
        overlap_y: overlap.0,
        serpentine,
    };
    let text = surfstream_replay::infer::infer_manifest(dir, &layout, pitch_um, height_unit)?;
    let manifest = write_inferred_manifest(out, &text)?;
    eprintln!(
        "stitch: {} tiles as {} x {} (rows x cols){}, inferred manifest {}",
        grid.rows * grid.cols,
        grid.rows,
        grid.cols,
        if serpentine { ", serpentine" } else { "" },
        manifest.display()
    );
    Ok(manifest)
}

/// Writes OUT/scan.toml for a folder of tiles whose files store their stage positions (no
/// --grid), and returns its path.
fn infer_scan_from_positions(
    dir: &std::path::Path,
    out: &std::path::Path,
    pitch_um: Option<f64>,
    height_unit: Option<&str>,
) -> Result<PathBuf> {
    let (text, rows, cols) =
        surfstream_replay::infer::infer_manifest_from_positions(dir, pitch_um, height_unit)?;
    let manifest = write_inferred_manifest(out, &text)?;
    eprintln!(
        "stitch: {} tiles as {rows} x {cols} (rows x cols) from the stage positions in the files, \
         inferred manifest {}",
        rows * cols,
        manifest.display()
    );
    Ok(manifest)
}

fn write_inferred_manifest(out: &std::path::Path, text: &str) -> Result<PathBuf> {
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let manifest = out.join("scan.toml");
    surfstream_core::fsutil::write_atomic(&manifest, |w| {
        use std::io::Write;
        w.write_all(text.as_bytes())
            .with_context(|| format!("{}: write failed", manifest.display()))
    })?;
    Ok(manifest)
}

/// The default pipeline for a scan directory or a recording.
fn stitch_graph(
    scan: &std::path::Path,
    out: PathBuf,
    set: &[String],
    method: Option<&str>,
) -> Result<(GraphFile, deviation::Settings)> {
    let source = if scan.extension().is_some_and(|e| e == "mcap") {
        toml::Value::String("mcap".into())
    } else {
        toml::Value::String("scan".into())
    };
    let path = if scan.is_dir() {
        scan.join("scan.toml")
    } else {
        scan.to_path_buf()
    };
    surfstream_io::input::check_regular_file(
        &path,
        "a scan.toml, its directory, or a .mcap recording",
    )?;
    let path = path
        .canonicalize()
        .with_context(|| format!("{}: cannot resolve path", path.display()))?;
    let path_str = path
        .to_str()
        .ok_or_else(|| anyhow!("{}: path is not UTF-8", path.display()))?;
    let text = format!(
        r#"
[graph]
name = "stitch"

[[node]]
id = "stage"
node = "replay"
params = {{ source = {source}, path = {path:?}, pacing = "fast" }}

[[node]]
id = "matcher"
node = "matcher"
inputs = {{ tiles = "stage/tiles" }}

[[node]]
id = "fusion"
node = "fusion"
inputs = {{ tiles = "stage/tiles", registrations = "matcher/registrations" }}

[[node]]
id = "wavelet"
node = "wavelet"
inputs = {{ panorama = "fusion/panorama" }}

[[node]]
id = "mesher"
node = "mesher"
inputs = {{ surface = "fusion/panorama", roughness = "wavelet/roughness" }}
"#,
        path = path_str
    );
    let registry = nodes::registry();
    let mut graph = GraphFile::parse(&text, "stitch pipeline", &registry)?;
    if let Some(m) = method {
        use surfstream_matcher::{MatcherConfig, RegistrationMethod};
        m.parse::<RegistrationMethod>()
            .map_err(|e| anyhow!("--method {e}"))?;
        // Written as given (run.json's parameters show the user's text), under the key the
        // matcher's config reads.
        let matcher = graph
            .nodes
            .iter_mut()
            .find(|n| n.node == <surfstream_core::record::MatcherReport as NodeRecord>::NODE_KIND)
            .ok_or_else(|| anyhow!("--method: the stitch pipeline has no matcher"))?;
        matcher.params.insert(
            MatcherConfig::METHOD_KEY.into(),
            toml::Value::String(m.into()),
        );
    }
    // make_tiles.py's ground truth beside scan.toml: the matcher scores feature matches
    // against it (r and MAP in run.json); `--set matcher.truth=...` still overrides.
    let truth = path.with_file_name("ground_truth.json");
    if path.extension().is_some_and(|e| e == "toml") && truth.is_file() {
        if let Some(t) = truth.to_str() {
            graph.apply_override(&format!("matcher.truth={}", toml::Value::String(t.into())))?;
        }
    }
    let mut settings = deviation::Settings::default();
    for s in settings.apply_sets(set)? {
        graph.apply_override(&s)?;
    }
    graph.graph.out_dir = out;
    graph.validate("stitch pipeline", &registry)?;
    check_node_params(&graph, "stitch pipeline")?;
    Ok((graph, settings))
}
