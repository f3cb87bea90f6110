//! Times the nine ISO 25178 parameters on a .npy height map and reading height-map files, for
//! side-by-side runs with ../shared/bench/params_anchor.py (same input via --save-inputs).
//!
//!     cargo run --release -p surfstream-io --example metrology_bench -- params FILE.npy [REPS]
//!     cargo run --release -p surfstream-io --example metrology_bench -- read FILE... [REPS via SURFSTREAM_REPS]
//!     cargo run --release -p surfstream-io --example metrology_bench -- make-sur IN.npy OUT.sur plain|compressed
//!
//! Prints one JSON line per measurement: median / min / max seconds over the repeats (the
//! first, warm-up run is not counted), and the rayon thread count.

use std::path::Path;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::Serialize;
use surfstream_core::metrology::{height_params, hybrid_params, level_plane, params, Grid};
use surfstream_io::formats::read_surface;

/// The times of one measurement, s.
#[derive(Serialize)]
struct Stats {
    median_s: f64,
    min_s: f64,
    max_s: f64,
    n: usize,
}

fn stats(mut t: Vec<f64>) -> Stats {
    t.sort_by(f64::total_cmp);
    Stats {
        median_s: t[t.len() / 2],
        min_s: t[0],
        max_s: t[t.len() - 1],
        n: t.len(),
    }
}

/// One JSON line: `what` was measured on `file`, and the measurement's own fields.
#[derive(Serialize)]
struct Line<'a, M: Serialize> {
    what: &'static str,
    file: &'a str,
    rayon_threads: usize,
    #[serde(flatten)]
    measured: M,
}

impl<M: Serialize> Line<'_, M> {
    /// Printed through a JSON value: keys sorted, as the lines have always had them.
    fn print(&self) -> Result<()> {
        println!("{}", serde_json::to_value(self)?);
        Ok(())
    }
}

#[derive(Serialize)]
struct ParamsTimes<P: Serialize> {
    rows: usize,
    cols: usize,
    all_9_params: Stats,
    height_7: Stats,
    sdq_sdr: Stats,
    level_and_all_9: Stats,
    params: P,
}

#[derive(Serialize)]
struct FamilyTimes {
    basic_9: Stats,
    functional: Stats,
    acf_sal_str: Stats,
    spatial: Stats,
    feature: Stats,
    all: Stats,
}

#[derive(Serialize)]
struct ReadTimes {
    rows: usize,
    cols: usize,
    read: Stats,
}

fn time<T>(reps: usize, mut f: impl FnMut() -> Result<T>) -> Result<(Stats, T)> {
    let mut last = f()?;
    let mut ts = Vec::with_capacity(reps);
    for _ in 0..reps {
        let t0 = Instant::now();
        last = f()?;
        ts.push(t0.elapsed().as_secs_f64());
    }
    Ok((stats(ts), last))
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let threads = rayon::current_num_threads();
    match args.first().map(String::as_str) {
        Some("params") => {
            let file = args.get(1).context("params FILE.npy [REPS]")?;
            let reps: usize = args.get(2).map(|r| r.parse()).transpose()?.unwrap_or(7);
            let s = read_surface(Path::new(file))?;
            let g = Grid::new(&s.heights_um, s.height, s.width, s.pitch_x_um, s.pitch_y_um)?;
            let (all9, p) = time(reps, || Ok(params(&g)?))?;
            // Where the time goes: the height parameters alone, the two hybrid ones alone.
            let (heights7, _) = time(reps, || Ok(height_params(&g)?))?;
            let (hybrid2, _) = time(reps, || Ok(hybrid_params(&g)))?;
            let (lev, _) = time(reps, || {
                let l = level_plane(&g)?;
                Ok(params(&Grid::of(&l, g.sampling())?)?)
            })?;
            Line {
                what: "params",
                file,
                rayon_threads: threads,
                measured: ParamsTimes {
                    rows: s.height,
                    cols: s.width,
                    all_9_params: all9,
                    height_7: heights7,
                    sdq_sdr: hybrid2,
                    level_and_all_9: lev,
                    params: p,
                },
            }
            .print()?;
        }
        Some("families") => {
            // Where the time of `params --all` goes: each family alone, then all together.
            let file = args.get(1).context("families FILE.npy [REPS]")?;
            let reps: usize = args.get(2).map(|r| r.parse()).transpose()?.unwrap_or(3);
            let s = read_surface(Path::new(file))?;
            let g = Grid::new(&s.heights_um, s.height, s.width, s.pitch_x_um, s.pitch_y_um)?;
            use surfstream_core::metrology as m;
            let (basic, _) = time(reps, || Ok(params(&g)?))?;
            let (functional, _) = time(reps, || Ok(m::functional_params(&g)?))?;
            let (acf, _) = time(reps, || Ok(m::Acf::of(&g)?.sal_str(0.2)))?;
            let (spatial, _) = time(reps, || Ok(m::spatial_params(&g)?))?;
            let (feature, _) = time(reps, || Ok(m::feature_params(&g, 5.0)?))?;
            let (all, _) = time(reps, || Ok(m::all_params(&g)?))?;
            Line {
                what: "families",
                file,
                rayon_threads: threads,
                measured: FamilyTimes {
                    basic_9: basic,
                    functional,
                    acf_sal_str: acf,
                    spatial,
                    feature,
                    all,
                },
            }
            .print()?;
        }
        Some("read") => {
            let reps: usize = std::env::var("SURFSTREAM_REPS")
                .ok()
                .map(|r| r.parse())
                .transpose()?
                .unwrap_or(9);
            for file in &args[1..] {
                let (t, s) = time(reps, || read_surface(Path::new(file)))?;
                Line {
                    what: "read",
                    file,
                    rayon_threads: threads,
                    measured: ReadTimes {
                        rows: s.height,
                        cols: s.width,
                        read: t,
                    },
                }
                .print()?;
            }
        }
        Some("make-sur") => {
            // Benchmark inputs only: a .sur (1 nm steps) of the same heights, plain or compressed.
            let (input, out, kind) = match &args[1..] {
                [i, o, k] => (i, o, k.as_str()),
                _ => bail!("make-sur IN.npy OUT.sur plain|compressed"),
            };
            let compressed = match kind {
                "plain" => false,
                "compressed" => true,
                other => bail!("make-sur: '{other}', expected plain or compressed"),
            };
            let s = read_surface(Path::new(input))?;
            let bytes = surfstream_io::formats::sur::encode_for_tests(&s, compressed, false);
            surfstream_core::fsutil::write_atomic(Path::new(out), |w| {
                use std::io::Write;
                Ok(w.write_all(&bytes)?)
            })?;
        }
        _ => bail!(
            "usage: metrology_bench params FILE.npy [REPS] | read FILE... | make-sur IN.npy OUT.sur plain|compressed"
        ),
    }
    Ok(())
}
