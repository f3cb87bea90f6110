//! The surfaces the report draws, read from the out dir's `.npy` files with their pitch (from
//! run.json), all heights relative to one reference: the panorama's mean height, so panorama,
//! datum and pooled map share one scale (the roughness is relative by nature).
//!
//! Bounded memory (issue 17): a map whose longest side exceeds [`MAX_SIDE_PX`] (the largest
//! map the page inlines at full resolution) is held as `block` x `block` block means
//! ([`NpyRows::read_block_means_f64`]), read `block` rows at a time; maps, the 3-D view, the
//! PSD and the Abbott-Firestone curve are drawn from it (the page says so). What the page
//! states as numbers of the whole map (the reference height, the key parameters, the
//! histogram, the share not measured, the profile cut) is computed from the files at full
//! resolution, streamed by rows, exactly as from the whole map.

use std::path::Path;

use anyhow::Result;
use surfstream_core::metrology::{functional_params, FunctionalParams, Grid, Params, ParamsByRows};
use surfstream_core::record::{FusionReport, RunRecord};
use surfstream_io::npy::{read_npy_f64, NpyRows};

use super::surface_stats::Histogram;

/// Longest side of a map held at full resolution: maps larger are held as block means.
pub const MAX_SIDE_PX: usize = 2048;
/// Bins of the height histogram, and the fine bins per bin the Abbott-Firestone curve of a
/// decimated panorama is read from.
pub const HISTOGRAM_BINS: usize = 80;
const FINE_PER_BIN: usize = 64;
/// Rows per read when streaming a file.
const BAND_ROWS: usize = 64;

/// One height map: row-major heights in um (NaN = not measured), rows grow with y.
#[derive(Debug, Clone)]
pub struct Surface {
    pub name: &'static str,
    pub z: Vec<f64>,
    pub rows: usize,
    pub cols: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    /// Each value is the mean of `block` x `block` heights of the file (1: the file's map);
    /// the pitch is the block's.
    pub block: usize,
    /// The file's map size (rows, cols).
    pub file_shape: (usize, usize),
}

impl Surface {
    /// The file's map's extent (a decimated map's last block may be ragged).
    pub fn width_um(&self) -> f64 {
        self.file_shape.1 as f64 * self.pitch_x_um / self.block as f64
    }
    pub fn height_um(&self) -> f64 {
        self.file_shape.0 as f64 * self.pitch_y_um / self.block as f64
    }
    pub fn row(&self, r: usize) -> &[f64] {
        &self.z[r * self.cols..(r + 1) * self.cols]
    }
    pub fn to_f32(&self) -> Vec<f32> {
        self.z.iter().map(|&v| v as f32).collect()
    }
}

/// The surfaces found in the out dir (any may be missing) and the reference height removed.
#[derive(Debug, Clone, Default)]
pub struct Surfaces {
    pub panorama: Option<Surface>,
    pub datum: Option<Surface>,
    pub roughness: Option<Surface>,
    pub pooled: Option<Surface>,
    /// The panorama's mean height (um), subtracted from panorama, datum and pooled map.
    pub reference_um: f64,
    /// Files that exist but could not be read, with the reason (shown on the page).
    pub problems: Vec<String>,
    /// From the files at full resolution: the panorama's histogram ([`HISTOGRAM_BINS`] bins,
    /// heights relative to the reference) and its [`FINE_PER_BIN`] times finer counts.
    pub histogram: Option<(Histogram, Vec<usize>)>,
    /// Points of the panorama and how many are not measured.
    pub panorama_points: (usize, usize),
    /// ISO 25178 parameters of panorama, roughness and pooled map at full resolution.
    pub params: [Option<Params>; 3],
    /// The Sk family (and the other functional parameters) of the same three maps, at full
    /// resolution; None for a map over [`FUNCTIONAL_MAX_POINTS`] (the material ratio curve
    /// sorts every height).
    pub functional: [Option<FunctionalParams>; 3],
    /// The profile cut at full resolution: the file row and the panorama's, datum's and
    /// roughness's heights along it (panorama and datum relative to the reference).
    pub profile: Option<ProfileRows>,
}

/// One row of the panorama, datum and roughness files.
#[derive(Debug, Clone)]
pub struct ProfileRows {
    pub row: usize,
    pub panorama: Vec<f64>,
    pub datum: Option<Vec<f64>>,
    pub roughness: Option<Vec<f64>>,
}

/// Calls `f` with every row of `file`, in order, a band at a time.
fn for_rows(file: &mut NpyRows, mut f: impl FnMut(&[f64])) -> Result<()> {
    let (rows, cols) = (file.rows(), file.cols());
    let mut band = Vec::new();
    let mut r0 = 0;
    while r0 < rows {
        let n = BAND_ROWS.min(rows - r0);
        file.read_rows_f64(r0, n, &mut band)?;
        band.chunks_exact(cols.max(1)).for_each(&mut f);
        r0 += n;
    }
    Ok(())
}

/// The nine parameters of a file's map with `shift` subtracted from every height (as the
/// report's whole-map path did), streamed: equal to `params` on the shifted map.
fn streamed_params(path: &Path, pitch_um: (f64, f64), shift: f64) -> Result<Option<Params>> {
    let mut file = NpyRows::open(path)?;
    let Ok(mut p) = ParamsByRows::new(file.cols(), pitch_um.0, pitch_um.1) else {
        return Ok(None);
    };
    let mut row = Vec::new();
    let mut ok = true;
    for second in [false, true] {
        for_rows(&mut file, |r| {
            row.clear();
            row.extend(r.iter().map(|v| v - shift));
            let pushed = if second {
                p.push_second(&row)
            } else {
                p.push_first(&row)
            };
            ok &= pushed.is_ok();
        })?;
        if !second {
            p.end_first();
        }
    }
    Ok(if ok { p.finish().ok() } else { None })
}

/// The largest map whose functional parameters the report computes (sorting 16 M heights
/// takes about a second; bigger maps: `surfstream params FILE --all`).
pub const FUNCTIONAL_MAX_POINTS: usize = 1 << 24;

/// The functional parameters of a file's whole map (independent of a height shift).
fn file_functional(path: &Path, pitch_um: (f64, f64)) -> Option<FunctionalParams> {
    let f = NpyRows::open(path).ok()?;
    if f.rows() * f.cols() > FUNCTIONAL_MAX_POINTS {
        return None;
    }
    let a = read_npy_f64(path).ok()?;
    let g = Grid::new(&a.data, a.rows, a.cols, pitch_um.0, pitch_um.1).ok()?;
    functional_params(&g).ok()
}

/// The reference (mean of the finite heights, summed in row order as the whole-map path
/// does), the points, the finite ones and their bounds.
fn panorama_sums(path: &Path) -> Result<(f64, usize, usize, f64, f64)> {
    let mut file = NpyRows::open(path)?;
    let (mut sum, mut n) = (0.0, 0usize);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for_rows(&mut file, |r| {
        for &v in r.iter().filter(|v| v.is_finite()) {
            sum += v;
            n += 1;
            lo = lo.min(v);
            hi = hi.max(v);
        }
    })?;
    let mean = if n > 0 { sum / n as f64 } else { 0.0 };
    Ok((mean, file.rows() * file.cols(), n, lo, hi))
}

/// The histogram of the panorama's heights minus `reference` (as `height_histogram` bins
/// them) and the counts in bins [`FINE_PER_BIN`] times finer (bin k holds fine bins
/// k * FINE_PER_BIN ..: the fine index is the coarse one's scaled by a power of two).
fn panorama_histogram(
    path: &Path,
    reference: f64,
    (lo, hi): (f64, f64),
) -> Result<Option<(Histogram, Vec<usize>)>> {
    if !lo.is_finite() {
        return Ok(None);
    }
    let (lo, hi) = (lo - reference, hi - reference);
    let (lo, hi) = if hi > lo {
        (lo, hi)
    } else {
        (lo - 0.5, lo + 0.5)
    };
    let bins = HISTOGRAM_BINS;
    let fine_bins = bins * FINE_PER_BIN;
    let mut counts = vec![0usize; bins];
    let mut fine = vec![0usize; fine_bins];
    let mut total = 0;
    let mut file = NpyRows::open(path)?;
    for_rows(&mut file, |r| {
        for &v in r.iter().filter(|v| v.is_finite()) {
            let x = (v - reference - lo) / (hi - lo);
            counts[((x * bins as f64) as usize).min(bins - 1)] += 1;
            fine[((x * fine_bins as f64) as usize).min(fine_bins - 1)] += 1;
            total += 1;
        }
    })?;
    Ok(Some((
        Histogram {
            lo,
            hi,
            counts,
            total,
        },
        fine,
    )))
}

/// Row `row` of a file, or `None` when it has no such row.
fn file_row(path: &Path, row: usize, shift: f64) -> Option<Vec<f64>> {
    let mut file = NpyRows::open(path).ok()?;
    let mut out = Vec::new();
    (row < file.rows())
        .then_some(())
        .and_then(|_| file.read_rows_f64(row, 1, &mut out).ok())?;
    out.iter_mut().for_each(|v| *v -= shift);
    Some(out)
}

/// The panorama's pitch from the node report that carries its geometry.
pub fn panorama_pitch_um(run: &RunRecord) -> Option<(f64, f64)> {
    let g = run.stage::<FusionReport>()?.panorama?;
    Some((g.pitch_x_um, g.pitch_y_um))
}

impl Surfaces {
    pub fn load(out: &Path, run: &RunRecord) -> Self {
        let mut s = Surfaces::default();
        let Some((px, py)) =
            panorama_pitch_um(run).or_else(|| run.scan.as_ref().map(|s| s.pitch_um()))
        else {
            return s;
        };
        // One block size for the panorama and the maps on its grid; the pooled map its own.
        let side = |name: &str| {
            NpyRows::open(out.join(format!("{name}.npy")))
                .ok()
                .map(|f| f.rows().max(f.cols()))
        };
        let pano_block = side("panorama").map_or(1, |n| n.div_ceil(MAX_SIDE_PX).max(1));
        let mut read = |name: &'static str, block: usize| -> Option<Surface> {
            let path = out.join(format!("{name}.npy"));
            if !path.exists() {
                return None;
            }
            let read = if block <= 1 {
                read_npy_f64(&path).map(|a| (a.data, a.rows, a.cols, (a.rows, a.cols)))
            } else {
                NpyRows::open(&path).and_then(|mut f| {
                    let (z, r, c) = f.read_block_means_f64(block)?;
                    Ok((z, r, c, (f.rows(), f.cols())))
                })
            };
            match read {
                Ok((z, rows, cols, file_shape)) => Some(Surface {
                    name,
                    z,
                    rows,
                    cols,
                    pitch_x_um: px * block as f64,
                    pitch_y_um: py * block as f64,
                    block,
                    file_shape,
                }),
                Err(e) => {
                    s.problems.push(format!("{}: {e:#}", path.display()));
                    None
                }
            }
        };
        let panorama = read("panorama", pano_block);
        let datum = read("datum", pano_block);
        let roughness = read("roughness", pano_block);
        let pooled_block = side("pooled").map_or(1, |n| n.div_ceil(MAX_SIDE_PX).max(1));
        let mut pooled = read("pooled", pooled_block);
        if let (Some(p), Some(q)) = (&panorama, &mut pooled) {
            // One pooled cell covers `factor` x `factor` panorama pixels.
            let factor = p.file_shape.1.div_ceil(q.file_shape.1.max(1)).max(1) as f64;
            q.pitch_x_um = px * factor * q.block as f64;
            q.pitch_y_um = py * factor * q.block as f64;
        }
        let pano_path = out.join("panorama.npy");
        let sums = panorama
            .as_ref()
            .and_then(|_| panorama_sums(&pano_path).ok());
        let reference = sums.map_or(0.0, |s| s.0);
        if let Some((_, points, finite, lo, hi)) = sums {
            s.panorama_points = (points, points - finite);
            s.histogram = panorama_histogram(&pano_path, reference, (lo, hi))
                .ok()
                .flatten();
        }
        let full_params = |name: &str, surface: &Option<Surface>, shift: f64| {
            let m = surface.as_ref()?;
            let pitch = (m.pitch_x_um / m.block as f64, m.pitch_y_um / m.block as f64);
            streamed_params(&out.join(format!("{name}.npy")), pitch, shift)
                .ok()
                .flatten()
        };
        let functional = |name: &str, surface: &Option<Surface>| {
            let m = surface.as_ref()?;
            let pitch = (m.pitch_x_um / m.block as f64, m.pitch_y_um / m.block as f64);
            file_functional(&out.join(format!("{name}.npy")), pitch)
        };
        // Six independent passes over the files: in parallel.
        let (params, functional) = rayon::join(
            || {
                let ((a, b), c) = rayon::join(
                    || {
                        rayon::join(
                            || full_params("panorama", &panorama, reference),
                            || full_params("roughness", &roughness, 0.0),
                        )
                    },
                    || full_params("pooled", &pooled, reference),
                );
                [a, b, c]
            },
            || {
                let ((a, b), c) = rayon::join(
                    || {
                        rayon::join(
                            || functional("panorama", &panorama),
                            || functional("roughness", &roughness),
                        )
                    },
                    || functional("pooled", &pooled),
                );
                [a, b, c]
            },
        );
        s.params = params;
        s.functional = functional;
        if let Some(p) = &panorama {
            let row = p.file_shape.0 / 2;
            let same_grid =
                |m: &Option<Surface>| m.as_ref().is_some_and(|m| m.file_shape == p.file_shape);
            s.profile = file_row(&pano_path, row, reference).map(|panorama| ProfileRows {
                row,
                panorama,
                datum: same_grid(&datum)
                    .then(|| file_row(&out.join("datum.npy"), row, reference))
                    .flatten(),
                roughness: same_grid(&roughness)
                    .then(|| file_row(&out.join("roughness.npy"), row, 0.0))
                    .flatten(),
            });
        }
        let shift = |m: Option<Surface>| {
            m.map(|mut m| {
                m.z.iter_mut().for_each(|v| *v -= reference);
                m
            })
        };
        s.panorama = shift(panorama);
        s.datum = shift(datum);
        s.pooled = shift(pooled);
        s.roughness = roughness;
        s.reference_um = reference;
        s
    }
}

#[cfg(test)]
mod tests {
    use super::super::surface_stats::{height_histogram, material_ratio_curve};
    use super::*;

    #[test]
    fn streamed_statistics_equal_the_whole_map_ones() {
        let dir = std::env::temp_dir().join(format!("report-surfaces-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (rows, cols) = (150, 70);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| {
                if i % 53 == 0 {
                    f64::NAN
                } else {
                    1000.0 + ((i * 7919 % 1013) as f64 * 0.01).sin() * 3.0
                }
            })
            .collect();
        let path = dir.join("panorama.npy");
        surfstream_io::npy::write_npy_f64(&path, &z, rows, cols).unwrap();
        let (reference, points, finite, lo, hi) = panorama_sums(&path).unwrap();
        let valid: Vec<f64> = z.iter().copied().filter(|v| v.is_finite()).collect();
        let mean = valid.iter().fold(0.0, |s, v| s + v) / valid.len() as f64;
        assert_eq!(reference.to_bits(), mean.to_bits());
        assert_eq!((points, finite), (rows * cols, valid.len()));
        let shifted: Vec<f64> = z.iter().map(|v| v - reference).collect();
        let (h, fine) = panorama_histogram(&path, reference, (lo, hi))
            .unwrap()
            .unwrap();
        assert_eq!(Some(h.clone()), height_histogram(&shifted, HISTOGRAM_BINS));
        // Each bin's fine counts add up to it.
        for (k, &c) in h.counts.iter().enumerate() {
            assert_eq!(
                fine[k * FINE_PER_BIN..(k + 1) * FINE_PER_BIN]
                    .iter()
                    .sum::<usize>(),
                c
            );
        }
        // The binned Abbott-Firestone curve lies within a fine bin of the two order
        // statistics the sorted one interpolates between.
        let width = (h.hi - h.lo) / fine.len() as f64;
        let exact = material_ratio_curve(&shifted, 40);
        let binned = super::super::charts::binned_material_ratio_curve(&h, &fine, 40);
        let mut sorted: Vec<f64> = shifted.iter().copied().filter(|v| v.is_finite()).collect();
        sorted.sort_by(f64::total_cmp);
        assert_eq!(exact.len(), binned.len());
        for (a, b) in exact.iter().zip(&binned) {
            assert_eq!(a.0, b.0);
            let pos = (1.0 - a.0 / 100.0) * (sorted.len() - 1) as f64;
            let (below, above) = (sorted[pos.floor() as usize], sorted[pos.ceil() as usize]);
            assert!(
                below - width <= b.1 && b.1 <= above + width,
                "{a:?} {b:?} (bin {width})"
            );
        }
        // Parameters streamed with the shift are those of the shifted map.
        let p = streamed_params(&path, (0.5, 0.6), reference)
            .unwrap()
            .unwrap();
        let whole = surfstream_core::metrology::params(
            &surfstream_core::metrology::Grid::new(&shifted, rows, cols, 0.5, 0.6).unwrap(),
        )
        .unwrap();
        assert_eq!(
            p.named().map(|(_, v)| v.to_bits()),
            whole.named().map(|(_, v)| v.to_bits())
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
