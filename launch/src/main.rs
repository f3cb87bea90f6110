//! `surfstream`: start a node graph as processes (`launch`) or threads (`run`), or stitch a
//! scan directory or recording in one go (`stitch`).

mod compare_fusion;
mod deviation;
mod launcher;
mod nodes;
mod outdir;
mod report;
mod runjson;
mod verbs;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, Parser, Subcommand};
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
  surfstream stitch scan.toml --out out/scan    the default pipeline for a scan directory or recording"
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
    #[arg(long)]
    out: Option<PathBuf>,
    /// Override one node parameter, e.g. --set stage.rows=3 (VALUE is read as TOML); or the
    /// Table-6 threshold: --set deviation.threshold_percent=2.
    #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
    set: Vec<String>,
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
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Override one node parameter (nodes: stage, matcher, fusion, wavelet, mesher), or
        /// the Table-6 threshold: --set deviation.threshold_percent=2.
        #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
        set: Vec<String>,
        /// Registration method of the matcher: auto | phase | harris | sift (auto = the best
        /// available, phase correlation; the same as `--set matcher.method=...`).
        #[arg(long, value_name = "METHOD")]
        method: Option<String>,
        /// Stitch once per fusion method (average, gradual, wavelet) into OUT/<method>/ and
        /// print the SSIM of the overlaps side by side (the paper's Table 2), plus the height
        /// error against the specimen when the scan has make_tiles.py's ground truth.
        #[arg(long)]
        compare_fusion: bool,
        /// SCAN is a folder of tiles without scan.toml: the grid as ROWSxCOLS (e.g. 3x4); the
        /// tiles in file-name order are the acquisition order. The inferred scan.toml is
        /// written to OUT.
        #[arg(long, value_name = "ROWSxCOLS", requires = "overlap")]
        grid: Option<surfstream_replay::infer::Grid>,
        /// With --grid: the overlap of neighbouring fields, "20%" or "0.2".
        #[arg(long, requires = "grid")]
        overlap: Option<surfstream_replay::infer::Overlap>,
        /// With --grid: odd rows run right to left (the stage's serpentine).
        #[arg(long, requires = "grid")]
        serpentine: bool,
        /// With --grid: the pitch, um, for tiles that carry none (.npy).
        #[arg(long, requires = "grid")]
        pitch_um: Option<f64>,
    },
    /// Show a height-map file's metadata, shape, pitch and invalid count.
    Inspect(verbs::metrology::InspectArgs),
    /// ISO 25178 height and hybrid parameters of a height-map file.
    Params(verbs::metrology::ParamsArgs),
    /// Convert a height-map file to another format (by extension).
    Convert(verbs::metrology::ConvertArgs),
    /// Compare two height maps or images: SIM, SSIM, RMS difference.
    Compare(verbs::metrology::CompareArgs),
    /// Separate one height map into datum and roughness (2-D wavelet decomposition).
    Separate(verbs::separate::SeparateArgs),
    /// Mesh one height map with a bounded vertical error and write STL.
    Mesh(verbs::mesh::MeshArgs),
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
    match dispatch(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("surfstream: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn dispatch(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Launch(a) => {
            let (graph, deviation) = load_graph(&a)?;
            launcher::launch(graph, &a.graph, deviation)
        }
        Command::Run(a) => {
            let (graph, deviation) = load_graph(&a)?;
            launcher::run_in_process(graph, &a.graph, deviation)
        }
        Command::Stitch {
            scan,
            out,
            set,
            method,
            compare_fusion,
            grid,
            overlap,
            serpentine,
            pitch_um,
        } => {
            let scan = match (grid, overlap) {
                (Some(g), Some(o)) => infer_scan(&scan, &out, g, o, serpentine, pitch_um)?,
                _ => scan,
            };
            if compare_fusion {
                return compare_fusion::run(&scan, &out, &set, method.as_deref());
            }
            let (graph, deviation) = stitch_graph(&scan, out, &set, method.as_deref())?;
            launcher::run_in_process(graph, &scan, deviation)
        }
        Command::Inspect(a) => verbs::metrology::inspect(a),
        Command::Params(a) => verbs::metrology::params(a),
        Command::Convert(a) => verbs::metrology::convert(a),
        Command::Compare(a) => verbs::metrology::compare(a),
        Command::Separate(a) => verbs::separate::run(a),
        Command::Mesh(a) => verbs::mesh::run(a),
    }
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
    graph.validate(&a.graph.display().to_string(), &registry)?;
    Ok((graph, settings))
}

/// Writes OUT/scan.toml for a folder of tiles laid out as the user says, and returns its path.
fn infer_scan(
    dir: &std::path::Path,
    out: &std::path::Path,
    grid: surfstream_replay::infer::Grid,
    overlap: surfstream_replay::infer::Overlap,
    serpentine: bool,
    pitch_um: Option<f64>,
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
    let text = surfstream_replay::infer::infer_manifest(dir, &layout, pitch_um)?;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let manifest = out.join("scan.toml");
    surfstream_core::fsutil::write_atomic(&manifest, |w| {
        use std::io::Write;
        w.write_all(text.as_bytes())
            .with_context(|| format!("{}: write failed", manifest.display()))
    })?;
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
    if !path.exists() {
        bail!(
            "{}: no such file (expected a scan.toml, its directory, or a .mcap recording)",
            path.display()
        );
    }
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
inputs = {{ surface = "wavelet/pooled" }}
"#,
        path = path_str
    );
    let registry = nodes::registry();
    let mut graph = GraphFile::parse(&text, "stitch pipeline", &registry)?;
    if let Some(m) = method {
        // A string, whatever it looks like: the matcher validates the name.
        graph.apply_override(&format!("matcher.method={}", toml::Value::String(m.into())))?;
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
    Ok((graph, settings))
}
