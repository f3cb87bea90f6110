//! The surfaces the report draws, read from the out dir's `.npy` files with their pitch (from
//! run.json), all heights relative to one reference: the panorama's mean height, so panorama,
//! datum and pooled map share one scale (the roughness is relative by nature).

use std::path::Path;

use serde_json::Value;
use surfstream_io::npy::read_npy_f64;

/// One height map: row-major heights in um (NaN = not measured), rows grow with y.
#[derive(Debug, Clone)]
pub struct Surface {
    pub name: &'static str,
    pub z: Vec<f64>,
    pub rows: usize,
    pub cols: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
}

impl Surface {
    pub fn width_um(&self) -> f64 {
        self.cols as f64 * self.pitch_x_um
    }
    pub fn height_um(&self) -> f64 {
        self.rows as f64 * self.pitch_y_um
    }
    pub fn row(&self, r: usize) -> &[f64] {
        &self.z[r * self.cols..(r + 1) * self.cols]
    }
    pub fn valid(&self) -> impl Iterator<Item = f64> + '_ {
        self.z.iter().copied().filter(|v| v.is_finite())
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
}

/// The panorama's pitch from the node report that carries its geometry.
pub fn panorama_pitch_um(run: &Value) -> Option<(f64, f64)> {
    let g = run["stages"]
        .as_object()?
        .values()
        .find_map(|r| r.get("panorama").filter(|p| p.get("pitch_x_um").is_some()))?;
    Some((g["pitch_x_um"].as_f64()?, g["pitch_y_um"].as_f64()?))
}

impl Surfaces {
    pub fn load(out: &Path, run: &Value) -> Self {
        let mut s = Surfaces::default();
        let Some((px, py)) = panorama_pitch_um(run).or_else(|| {
            Some((
                run["scan"]["pitch_x_um"].as_f64()?,
                run["scan"]["pitch_y_um"].as_f64()?,
            ))
        }) else {
            return s;
        };
        let mut read = |name: &'static str| -> Option<Surface> {
            let path = out.join(format!("{name}.npy"));
            if !path.exists() {
                return None;
            }
            match read_npy_f64(&path) {
                Ok(a) => Some(Surface {
                    name,
                    z: a.data,
                    rows: a.rows,
                    cols: a.cols,
                    pitch_x_um: px,
                    pitch_y_um: py,
                }),
                Err(e) => {
                    s.problems.push(format!("{}: {e:#}", path.display()));
                    None
                }
            }
        };
        let panorama = read("panorama");
        let datum = read("datum");
        let roughness = read("roughness");
        let mut pooled = read("pooled");
        if let (Some(p), Some(q)) = (&panorama, &mut pooled) {
            // One pooled cell covers `factor` x `factor` panorama pixels.
            let factor = p.cols.div_ceil(q.cols.max(1)).max(1) as f64;
            q.pitch_x_um = px * factor;
            q.pitch_y_um = py * factor;
        }
        let reference = panorama
            .as_ref()
            .map(|p| {
                let (sum, n) = p.valid().fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
                if n > 0 {
                    sum / n as f64
                } else {
                    0.0
                }
            })
            .unwrap_or(0.0);
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
