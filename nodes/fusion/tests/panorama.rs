//! Behaviour of the panorama on seeded synthetic scans: accuracy against a known surface,
//! growth, plane and z correction, NaN handling, blend weights, render == place, bad input.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_fusion::{
    overlap_quality, render, render_panorama, BlendParams, FusionError, FusionMethod, Panorama,
    PlacedRaster, PlaneCorrection, Region, TileInput, WaveletFusion,
};

const PITCH_X_UM: f64 = 0.8148;
const PITCH_Y_UM: f64 = 0.75;

fn pitch() -> Pitch {
    Pitch::new(PITCH_X_UM, PITCH_Y_UM).unwrap()
}

/// A smooth random surface: a sum of plane waves with wavelengths of 25..200 px.
struct Surface {
    /// (amplitude um, kx rad/um, ky rad/um, phase rad)
    waves: Vec<[f64; 4]>,
}

impl Surface {
    fn new(seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let waves = (0..8)
            .map(|_| {
                let wavelength_px: f64 = rng.gen_range(25.0..200.0);
                let angle: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
                let k = std::f64::consts::TAU / (wavelength_px * PITCH_X_UM);
                [
                    rng.gen_range(0.2..1.0),
                    k * angle.cos(),
                    k * angle.sin(),
                    rng.gen_range(0.0..std::f64::consts::TAU),
                ]
            })
            .collect();
        Self { waves }
    }

    fn at(&self, x_um: f64, y_um: f64) -> f64 {
        self.waves
            .iter()
            .map(|[a, kx, ky, ph]| a * (kx * x_um + ky * y_um + ph).sin())
            .sum()
    }

    /// Bound on the gradient magnitude, um per pixel (of the larger pitch).
    fn max_slope_um_per_px(&self) -> f64 {
        self.waves
            .iter()
            .map(|[a, kx, ky, _]| a * kx.hypot(*ky) * PITCH_X_UM.max(PITCH_Y_UM))
            .sum()
    }

    /// Bound on the bilinear interpolation error on this grid: (hx^2/8)|fxx| + (hy^2/8)|fyy|.
    fn bilinear_bound_um(&self) -> f64 {
        self.waves
            .iter()
            .map(|[a, kx, ky, _]| {
                a * (kx * kx * PITCH_X_UM * PITCH_X_UM + ky * ky * PITCH_Y_UM * PITCH_Y_UM) / 8.0
            })
            .sum()
    }
}

/// A tile owning its heights; `input()` borrows it as a `TileInput`.
#[derive(Clone)]
struct Tile {
    index: u32,
    heights: Vec<f32>,
    width: usize,
    height: usize,
    x_um: f64,
    y_um: f64,
    plane: PlaneCorrection,
    z_offset_um: f64,
}

impl Tile {
    fn input(&self) -> TileInput<'_> {
        TileInput {
            index: self.index,
            heights: RasterView::new(&self.heights, Shape::new(self.height, self.width)).unwrap(),
            x_um: self.x_um,
            y_um: self.y_um,
            plane: self.plane,
            z_offset_um: self.z_offset_um,
        }
    }

    /// Cut a tile whose absolute heights are `z_abs(x, y)`, stored relative to `z_offset_um`
    /// with `plane` added (what the matcher's correction then removes).
    #[allow(clippy::too_many_arguments)]
    fn cut(
        index: u32,
        z_abs: &dyn Fn(f64, f64) -> f64,
        x_um: f64,
        y_um: f64,
        width: usize,
        height: usize,
        plane: PlaneCorrection,
        z_offset_um: f64,
    ) -> Self {
        let (cx, cy) = ((width - 1) as f64 / 2.0, (height - 1) as f64 / 2.0);
        let mut heights = Vec::with_capacity(width * height);
        for r in 0..height {
            for c in 0..width {
                let z = z_abs(x_um + c as f64 * PITCH_X_UM, y_um + r as f64 * PITCH_Y_UM);
                let p = plane.piston_um
                    + plane.tilt_x_um_per_px * (c as f64 - cx)
                    + plane.tilt_y_um_per_px * (r as f64 - cy);
                heights.push((z - z_offset_um + p) as f32);
            }
        }
        Self {
            index,
            heights,
            width,
            height,
            x_um,
            y_um,
            plane,
            z_offset_um,
        }
    }

    fn set_nan(&mut self, rows: std::ops::Range<usize>, cols: std::ops::Range<usize>) {
        for r in rows {
            for c in cols.clone() {
                self.heights[r * self.width + c] = f32::NAN;
            }
        }
    }
}

const Z0_UM: f64 = 25_000.0;

/// An R x C serpentine of `w x h` tiles of `surface` (absolute height Z0 + f) with `overlap`,
/// random sub-pixel jitter of up to `jitter_px`, random planes and z offsets.
fn serpentine(
    surface: &Surface,
    rows: usize,
    cols: usize,
    (w, h): (usize, usize),
    overlap: f64,
    jitter_px: f64,
    seed: u64,
) -> Vec<Tile> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let step_x = w as f64 * (1.0 - overlap) * PITCH_X_UM;
    let step_y = h as f64 * (1.0 - overlap) * PITCH_Y_UM;
    let z_abs = |x: f64, y: f64| Z0_UM + surface.at(x, y);
    let mut tiles = Vec::new();
    for r in 0..rows {
        for i in 0..cols {
            let c = if r % 2 == 0 { i } else { cols - 1 - i };
            let x = 13.7 + c as f64 * step_x + rng.gen_range(-jitter_px..=jitter_px) * PITCH_X_UM;
            let y = -4.2 + r as f64 * step_y + rng.gen_range(-jitter_px..=jitter_px) * PITCH_Y_UM;
            let plane = PlaneCorrection {
                piston_um: rng.gen_range(-3.0..3.0),
                tilt_x_um_per_px: rng.gen_range(-0.01..0.01),
                tilt_y_um_per_px: rng.gen_range(-0.01..0.01),
            };
            let z_offset = Z0_UM + rng.gen_range(-5.0..5.0);
            tiles.push(Tile::cut(
                tiles.len() as u32,
                &z_abs,
                x,
                y,
                w,
                h,
                plane,
                z_offset,
            ));
        }
    }
    tiles
}

fn place_all(pano: &mut Panorama, tiles: &[Tile]) -> Vec<Region> {
    tiles
        .iter()
        .map(|t| pano.place(t.input()).expect("valid tile"))
        .collect()
}

fn value_at(raster: &PlacedRaster, col: usize, row: usize) -> f32 {
    raster.heights.values()[row * raster.heights.cols() + col]
}

/// Scan position of raster pixel (col, row).
fn pos_um(raster: &PlacedRaster, col: usize, row: usize) -> (f64, f64) {
    (
        raster.origin_x_um + col as f64 * raster.pitch.x_um(),
        raster.origin_y_um + row as f64 * raster.pitch.y_um(),
    )
}

#[test]
fn reproduces_a_smooth_surface_across_seams_and_corners() {
    let surface = Surface::new(1);
    let (w, h) = (64, 48);
    let tiles = serpentine(&surface, 3, 3, (w, h), 0.2, 3.0, 2);
    let params = BlendParams::from_overlap_fraction(w, h, 0.2);
    let mut pano = Panorama::new(pitch(), params).unwrap();
    place_all(&mut pano, &tiles);
    let raster = pano.to_raster();
    assert_eq!(raster.z_offset_um, tiles[0].z_offset_um);

    // Bilinear error of the surface, plus f32 rounding of raw heights (|z| < 15 um).
    let bound = surface.bilinear_bound_um() + 1e-5;
    assert!(
        bound < 0.05,
        "the surface is not smooth enough to test: {bound}"
    );
    // The part the jittered layout covers for sure: inside the outermost tiles' inner edges.
    let (wx, hy) = ((w - 1) as f64 * PITCH_X_UM, (h - 1) as f64 * PITCH_Y_UM);
    let min_x = tiles.iter().map(|t| t.x_um).fold(f64::INFINITY, f64::min);
    let max_x = tiles
        .iter()
        .map(|t| t.x_um)
        .fold(f64::NEG_INFINITY, f64::max);
    let min_y = tiles.iter().map(|t| t.y_um).fold(f64::INFINITY, f64::min);
    let max_y = tiles
        .iter()
        .map(|t| t.y_um)
        .fold(f64::NEG_INFINITY, f64::max);
    let jitter_x = 6.0 * PITCH_X_UM;
    let jitter_y = 6.0 * PITCH_Y_UM;
    let (mut checked, mut max_err, mut seams) = (0usize, 0.0f64, 0usize);
    for row in 0..raster.heights.rows() {
        for col in 0..raster.heights.cols() {
            let (x, y) = pos_um(&raster, col, row);
            let v = value_at(&raster, col, row);
            let inside = x > min_x + jitter_x
                && x < max_x + wx - jitter_x
                && y > min_y + jitter_y
                && y < max_y + hy - jitter_y;
            if inside {
                assert!(
                    !v.is_nan(),
                    "hole at ({col}, {row}) inside the covered area"
                );
            }
            if v.is_nan() {
                continue;
            }
            let covering = tiles
                .iter()
                .filter(|t| {
                    x >= t.x_um
                        && x <= t.x_um + (w - 1) as f64 * PITCH_X_UM
                        && y >= t.y_um
                        && y <= t.y_um + (h - 1) as f64 * PITCH_Y_UM
                })
                .count();
            if covering > 1 {
                seams += 1;
            }
            let truth = Z0_UM + surface.at(x, y) - raster.z_offset_um;
            let err = (v as f64 - truth).abs();
            max_err = max_err.max(err);
            assert!(
                err <= bound,
                "pixel ({col}, {row}) covered by {covering} tiles: error {err} > bound {bound}"
            );
            checked += 1;
        }
    }
    assert!(checked > raster.heights.cols() * raster.heights.rows() * 9 / 10);
    assert!(seams > checked / 5, "the scan has too few overlap pixels");
    eprintln!("max error {max_err:.2e} um, bound {bound:.2e} um, {seams} overlap px");
}

#[test]
fn on_grid_tile_is_copied_exactly() {
    let surface = Surface::new(3);
    let z_abs = |x: f64, y: f64| surface.at(x, y);
    let tile = Tile::cut(0, &z_abs, 5.0, 7.0, 20, 10, PlaneCorrection::default(), 0.0);
    let raster = render(
        pitch(),
        &[tile.input()],
        BlendParams::from_overlap_px(4.0, 4.0),
    )
    .unwrap();
    assert_eq!((raster.heights.cols(), raster.heights.rows()), (20, 10));
    assert_eq!((raster.origin_x_um, raster.origin_y_um), (5.0, 7.0));
    assert_eq!(raster.heights.values(), tile.heights);
}

#[test]
fn growth_left_and_up_keeps_content() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let (w, h) = (32, 24);
    let mut random_tile = |index: u32, x_um: f64, y_um: f64| Tile {
        index,
        heights: (0..w * h).map(|_| rng.gen_range(-2.0f32..2.0)).collect(),
        width: w,
        height: h,
        x_um,
        y_um,
        plane: PlaneCorrection::default(),
        z_offset_um: 0.0,
    };
    let a = random_tile(0, 100.0, 200.0);
    let mut pano = Panorama::new(pitch(), BlendParams::average()).unwrap();
    let region_a = pano.place(a.input()).unwrap();
    assert_eq!(
        region_a,
        Region {
            x0: 0,
            y0: 0,
            width: w,
            height: h
        }
    );
    assert_eq!(pano.canvas_origin_um(), (100.0, 200.0));

    // Around A without touching it: left-up, up, right, down-left; fractional offsets.
    let others = [(-40.3, -30.6), (0.0, -55.2), (60.7, 3.1), (-90.45, 70.9)];
    let mut placed = vec![a.clone()];
    for (k, (dx_px, dy_px)) in others.iter().enumerate() {
        let t = random_tile(
            k as u32 + 1,
            100.0 + dx_px * PITCH_X_UM,
            200.0 + dy_px * PITCH_Y_UM,
        );
        let (w_before, h_before) = (pano.width(), pano.height());
        let region = pano.place(t.input()).unwrap();
        // Amortised growth: a side that had to move moved by at least a tile or 50 %.
        if pano.width() != w_before {
            assert!(pano.width() >= w_before + w.max(w_before / 2) - 1);
        }
        if pano.height() != h_before {
            assert!(pano.height() >= h_before + h.max(h_before / 2) - 1);
        }
        // The region is where the tile went.
        let (rx, ry) = pano.region_origin_um(&region);
        assert!(rx >= t.x_um - 1e-9 && rx < t.x_um + PITCH_X_UM);
        assert!(ry >= t.y_um - 1e-9 && ry < t.y_um + PITCH_Y_UM);
        placed.push(t);

        // A is still there, bit for bit, wherever the canvas origin moved to.
        let (ox, oy) = pano.canvas_origin_um();
        let now_a = Region {
            x0: ((100.0 - ox) / PITCH_X_UM).round() as usize,
            y0: ((200.0 - oy) / PITCH_Y_UM).round() as usize,
            width: w,
            height: h,
        };
        assert_eq!(pano.extract(now_a), a.heights, "after tile {}", k + 1);
    }
    // The growth happened: the canvas starts left of and above every tile.
    let (ox, oy) = pano.canvas_origin_um();
    assert!(placed
        .iter()
        .all(|t| ox <= t.x_um + 1e-9 && oy <= t.y_um + 1e-9));
    // The raster is trimmed to the placed footprints, whatever headroom the canvas has.
    let raster = pano.to_raster();
    let content = pano.content_region().unwrap();
    assert_eq!(
        (raster.heights.cols(), raster.heights.rows()),
        (content.width, content.height)
    );
    assert!(raster.heights.cols() < pano.width() || raster.heights.rows() < pano.height());
    assert!((raster.origin_x_um - (100.0 - 90.45 * PITCH_X_UM)).abs() < PITCH_X_UM);
    assert!((raster.origin_y_um - (200.0 - 55.2 * PITCH_Y_UM)).abs() < PITCH_Y_UM);
}

#[test]
fn pistons_tilts_and_z_offsets_corrected_give_an_exactly_flat_panorama() {
    // Dyadic numbers, so raw = level + plane is exact in f32 and any error is the library's.
    let level_um = 1.25;
    let z_canvas_um = 1000.5;
    let mut tiles = Vec::new();
    let planes = [
        (0.5, 1.0 / 1024.0, -1.0 / 512.0, 1000.5),
        (-1.25, -1.0 / 256.0, 0.0, 1000.25),
        (3.0, 0.0, 1.0 / 128.0, 998.0),
        (-0.75, 1.0 / 2048.0, 1.0 / 1024.0, 1003.75),
    ];
    let positions = [(0.0, 0.0), (40.3, 0.7), (39.6, 30.45), (-0.35, 29.8)];
    for (i, ((piston, tx, ty, z_off), (dx, dy))) in planes.iter().zip(positions).enumerate() {
        let plane = PlaneCorrection {
            piston_um: *piston,
            tilt_x_um_per_px: *tx,
            tilt_y_um_per_px: *ty,
        };
        let z_abs = |_: f64, _: f64| z_canvas_um + level_um;
        tiles.push(Tile::cut(
            i as u32,
            &z_abs,
            dx * PITCH_X_UM,
            dy * PITCH_Y_UM,
            64,
            48,
            plane,
            *z_off,
        ));
    }
    let params = BlendParams::from_overlap_px(24.0, 18.0);
    let raster = render(
        pitch(),
        &tiles.iter().map(Tile::input).collect::<Vec<_>>(),
        params,
    )
    .unwrap();
    assert_eq!(raster.z_offset_um, z_canvas_um);
    let valid: Vec<f32> = raster
        .heights
        .values()
        .iter()
        .copied()
        .filter(|v| !v.is_nan())
        .collect();
    assert!(valid.len() > raster.heights.values().len() * 9 / 10);
    assert!(
        valid.iter().all(|&v| v == level_um as f32),
        "not flat: {:?}",
        valid.iter().find(|&&v| v != level_um as f32)
    );
}

#[test]
fn nan_pixels_are_filled_from_the_other_tile_and_stay_nan_where_none_has_data() {
    let surface = Surface::new(5);
    let z_abs = |x: f64, y: f64| 10.0 + surface.at(x, y);
    let (w, h) = (40, 30);
    let bound = surface.bilinear_bound_um() + 1e-5;
    let loose = bound + surface.max_slope_um_per_px() * 1.5;
    for b_offset_px in [(28.0, 0.0), (27.6, 0.3)] {
        // A at the anchor; B to its right, overlapping A's columns 28..40 (12 px).
        let mut a = Tile::cut(0, &z_abs, 0.0, 0.0, w, h, PlaneCorrection::default(), 0.0);
        let mut b = Tile::cut(
            1,
            &z_abs,
            b_offset_px.0 * PITCH_X_UM,
            b_offset_px.1 * PITCH_Y_UM,
            w,
            h,
            PlaneCorrection::default(),
            0.0,
        );
        a.set_nan(10..15, 31..36); // in the overlap: B has data there
        a.set_nan(5..9, 5..10); // outside the overlap: nobody has data
        b.set_nan(18..24, 2..7); // in the overlap: A has data there
        b.set_nan(0..30, 0..1); // B's first column: A covers it
        let mut pano = Panorama::new(pitch(), BlendParams::from_overlap_px(12.0, 9.0)).unwrap();
        place_all(&mut pano, &[a.clone(), b.clone()]);
        let raster = pano.to_raster();
        assert_eq!((raster.origin_x_um, raster.origin_y_um), (0.0, 0.0));
        let at = |col: usize, row: usize| value_at(&raster, col, row);
        // A sits on the grid: its hole outside the overlap is exactly where it was.
        for row in 0..h {
            for col in 0..28 {
                let in_hole = (5..9).contains(&row) && (5..10).contains(&col);
                assert_eq!(at(col, row).is_nan(), in_hole, "({col}, {row})");
            }
        }
        // The holes in the overlap are filled by the other tile alone (A exact on the grid,
        // B bilinear), so the tight bound holds. Rows/cols are canvas pixels; B's hole is
        // shrunk by the pixels where B's remaining corners still carry >= half the weight.
        let holes = [(10..15, 31..36), (19..24, 30..34), (1..29, 28..29)];
        for (rows, cols) in holes {
            for row in rows {
                for col in cols.clone() {
                    let v = at(col, row);
                    let (x, y) = pos_um(&raster, col, row);
                    let err = (v as f64 - z_abs(x, y)).abs();
                    assert!(
                        err <= bound,
                        "({col}, {row}) = {v}: error {err}, {b_offset_px:?}"
                    );
                }
            }
        }
        // Everywhere else: no NaN leaked in as a value (the surface sits 10 um up, so a NaN
        // read as 0 would be far off). Next to a hole, a renormalised bilinear sample may be
        // off by up to the slope over one pixel.
        for row in 0..raster.heights.rows() {
            for col in 0..raster.heights.cols() {
                let v = at(col, row);
                if !v.is_nan() {
                    let (x, y) = pos_um(&raster, col, row);
                    let err = (v as f64 - z_abs(x, y)).abs();
                    assert!(err <= loose, "({col}, {row}) = {v}: error {err}");
                }
            }
        }
    }
}

#[test]
fn blend_is_linear_across_a_horizontal_overlap() {
    let constant = |v: f64| move |_: f64, _: f64| v;
    let (w, h) = (40, 16);
    for dx_px in [30.0, 30.4, 29.75] {
        let a = Tile::cut(
            0,
            &constant(0.0),
            0.0,
            0.0,
            w,
            h,
            PlaneCorrection::default(),
            0.0,
        );
        let b = Tile::cut(
            1,
            &constant(1.0),
            dx_px * PITCH_X_UM,
            0.0,
            w,
            h,
            PlaneCorrection::default(),
            0.0,
        );
        // Ramp = overlap (10 px); the vertical ramp is the same for both tiles, so it cancels.
        let params = BlendParams::from_overlap_px(10.0, 5.0);
        let raster = render(pitch(), &[a.input(), b.input()], params).unwrap();
        let first_b = dx_px.ceil() as usize;
        for row in 0..h {
            let line: Vec<f64> = (0..raster.heights.cols())
                .map(|c| value_at(&raster, c, row) as f64)
                .collect();
            assert!(line[..first_b].iter().all(|&v| v == 0.0));
            assert!(line[w..].iter().all(|&v| v == 1.0));
            let overlap = &line[first_b..w];
            if dx_px == 30.0 {
                // On the grid the weights add to 1: column j of the overlap is (j + 0.5) / 10.
                for (j, v) in overlap.iter().enumerate() {
                    assert!(
                        (v - (j as f64 + 0.5) / 10.0).abs() < 1e-6,
                        "row {row}: {line:?}"
                    );
                }
            }
            let step = overlap[1] - overlap[0];
            assert!(step > 0.08 && step < 0.12, "step {step}");
            for pair in overlap.windows(2) {
                assert!(
                    ((pair[1] - pair[0]) - step).abs() < 1e-6,
                    "not linear: {overlap:?}"
                );
            }
        }
    }
}

#[test]
fn four_tile_corner_fades_smoothly() {
    let (w, h) = (48, 48);
    let values = [0.0, 1.0, 3.0, 2.0];
    let positions = [(0.0, 0.0), (28.0, 0.0), (28.0, 28.0), (0.0, 28.0)];
    let tiles: Vec<Tile> = values
        .iter()
        .zip(positions)
        .enumerate()
        .map(|(i, (&v, (dx, dy)))| {
            let z = move |_: f64, _: f64| v;
            let p = PlaneCorrection::default();
            Tile::cut(i as u32, &z, dx * PITCH_X_UM, dy * PITCH_Y_UM, w, h, p, 0.0)
        })
        .collect();
    let inputs: Vec<TileInput> = tiles.iter().map(Tile::input).collect();
    let max_jump = |raster: &PlacedRaster| {
        let mut jump = 0.0f32;
        for row in 0..raster.heights.rows() {
            for col in 0..raster.heights.cols() {
                let v = value_at(raster, col, row);
                if col + 1 < raster.heights.cols() {
                    jump = jump.max((value_at(raster, col + 1, row) - v).abs());
                }
                if row + 1 < raster.heights.rows() {
                    jump = jump.max((value_at(raster, col, row + 1) - v).abs());
                }
            }
        }
        jump
    };
    let ramped = render(pitch(), &inputs, BlendParams::from_overlap_px(20.0, 20.0)).unwrap();
    assert!(ramped.heights.values().iter().all(|v| !v.is_nan()));
    let averaged = render(pitch(), &inputs, BlendParams::average()).unwrap();
    // A 0..3 step spread over a 20 px ramp moves at most ~3 / 20 per pixel, even at the
    // corner where all four tiles meet; a plain average jumps wherever a tile begins.
    let (jr, ja) = (max_jump(&ramped), max_jump(&averaged));
    assert!(jr <= 0.2, "ramped blend jumps by {jr}");
    assert!(ja >= 0.5, "plain average jumps by only {ja}");
}

#[test]
fn render_equals_sequential_place_bit_for_bit() {
    let surface = Surface::new(6);
    let (w, h) = (50, 40);
    let mut tiles = serpentine(&surface, 3, 4, (w, h), 0.15, 2.5, 7);
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    for t in &mut tiles {
        // Dropouts: scattered pixels and a block, so the NaN rule is exercised.
        for _ in 0..40 {
            let i = rng.gen_range(0..w * h);
            t.heights[i] = f32::NAN;
        }
        let (r, c) = (rng.gen_range(0..h - 6), rng.gen_range(0..w - 6));
        t.set_nan(r..r + 6, c..c + 6);
    }
    let params = BlendParams::from_overlap_fraction(w, h, 0.15);
    let mut pano = Panorama::new(pitch(), params).unwrap();
    place_all(&mut pano, &tiles);
    let sequential = pano.to_raster();

    // Slice order does not matter; index order does.
    let mut shuffled: Vec<TileInput> = tiles.iter().map(Tile::input).collect();
    shuffled.reverse();
    shuffled.swap(1, 5);
    let rendered = render(pitch(), &shuffled, params).unwrap();
    // And the thread count does not matter either.
    let single = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| render(pitch(), &shuffled, params).unwrap());

    for other in [&rendered, &single] {
        assert_eq!(
            (
                other.heights.cols(),
                other.heights.rows(),
                other.z_offset_um
            ),
            (
                sequential.heights.cols(),
                sequential.heights.rows(),
                sequential.z_offset_um
            )
        );
        assert_eq!(
            other.origin_x_um.to_bits(),
            sequential.origin_x_um.to_bits()
        );
        assert_eq!(
            other.origin_y_um.to_bits(),
            sequential.origin_y_um.to_bits()
        );
        let bits = |r: &PlacedRaster| {
            r.heights
                .values()
                .iter()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(other), bits(&sequential));
    }
    assert!(sequential.heights.values().iter().any(|v| v.is_nan()));
    assert!(
        sequential
            .heights
            .values()
            .iter()
            .filter(|v| !v.is_nan())
            .count()
            > 1000
    );
}

#[test]
fn place_changes_only_the_returned_region() {
    let surface = Surface::new(9);
    let z_abs = |x: f64, y: f64| surface.at(x, y);
    let p = PlaneCorrection::default();
    let big = Tile::cut(0, &z_abs, 0.0, 0.0, 60, 50, p, 0.0);
    let small = Tile::cut(1, &|x, y| z_abs(x, y) + 0.5, 20.3, 15.1, 12, 9, p, 0.0);
    let mut pano = Panorama::new(pitch(), BlendParams::from_overlap_px(3.0, 3.0)).unwrap();
    pano.place(big.input()).unwrap();
    let all = Region {
        x0: 0,
        y0: 0,
        width: pano.width(),
        height: pano.height(),
    };
    let before = pano.extract(all);
    let region = pano.place(small.input()).unwrap();
    assert_eq!(
        (pano.width(), pano.height()),
        (60, 50),
        "no growth expected"
    );
    // 20.3 um / 0.8148 um = 24.9 px: first covered canvas column 25, 11 columns (w - 1).
    assert_eq!((region.x0, region.width), (25, 11));
    assert_eq!((region.y0, region.height), (21, 8));
    let after = pano.extract(all);
    for row in 0..50 {
        for col in 0..60 {
            let inside = (region.x0..region.x0 + region.width).contains(&col)
                && (region.y0..region.y0 + region.height).contains(&row);
            let (b, a) = (before[row * 60 + col], after[row * 60 + col]);
            assert_eq!(a.to_bits() != b.to_bits(), inside, "({col}, {row})");
        }
    }
    assert_eq!(pano.extract(region), {
        let mut v = Vec::new();
        for row in region.y0..region.y0 + region.height {
            v.extend_from_slice(&after[row * 60 + region.x0..row * 60 + region.x0 + region.width]);
        }
        v
    });
    // Outside the canvas, extract gives NaN rather than panicking.
    let outside = pano.extract(Region {
        x0: 58,
        y0: 49,
        width: 4,
        height: 2,
    });
    assert_eq!(outside.len(), 8);
    assert!(!outside[0].is_nan() && !outside[1].is_nan());
    assert!(outside[2..].iter().all(|v| v.is_nan()));
}

#[test]
fn bad_input_is_a_clear_error_naming_the_field() {
    let ok_params = BlendParams::from_overlap_px(4.0, 4.0);
    for (px, py, field) in [
        (0.0, 1.0, "pitch_x_um"),
        (-0.5, 1.0, "pitch_x_um"),
        (f64::NAN, 1.0, "pitch_x_um"),
        (1.0, f64::INFINITY, "pitch_y_um"),
    ] {
        // The panorama takes a checked Pitch: a bad one cannot reach it, and the error of the
        // one check names the axis.
        let err = Pitch::new(px, py).unwrap_err();
        assert!(err.to_string().contains(field), "{err}");
    }
    for (params, field) in [
        (BlendParams::from_overlap_px(-1.0, 4.0), "overlap_x_px"),
        (BlendParams::from_overlap_px(4.0, f64::NAN), "overlap_y_px"),
        (ok_params.with_ramp_px(1e9, 1.0), "ramp_x_px"),
    ] {
        let err = Panorama::new(Pitch::square(1.0).unwrap(), params).unwrap_err();
        assert!(err.to_string().contains(field), "{err}");
    }
    assert_eq!(
        render(Pitch::square(1.0).unwrap(), &[], ok_params).unwrap_err(),
        FusionError::NoTiles
    );

    let heights = vec![0.5f32; 12];
    let shape = Shape::new(3, 4);
    // A payload that does not fit its size cannot even become a tile: the raster view refuses.
    assert!(RasterView::new(&heights[..11], shape).is_err());
    assert!(RasterView::<f32>::new(&[], Shape::new(3, 0)).is_err());
    assert!(RasterView::new(&heights, Shape::new(2, usize::MAX)).is_err());
    let good = TileInput {
        index: 3,
        heights: RasterView::new(&heights, shape).unwrap(),
        x_um: 0.0,
        y_um: 0.0,
        plane: PlaneCorrection::default(),
        z_offset_um: 0.0,
    };
    let with_inf = {
        let mut h = heights.clone();
        h[6] = f32::NEG_INFINITY;
        h
    };
    let cases: Vec<(TileInput, &str)> = vec![
        (
            TileInput {
                x_um: f64::NAN,
                ..good
            },
            "x_um",
        ),
        (
            TileInput {
                y_um: f64::INFINITY,
                ..good
            },
            "y_um",
        ),
        (
            TileInput {
                z_offset_um: f64::NAN,
                ..good
            },
            "z_offset_um",
        ),
        (
            TileInput {
                plane: PlaneCorrection {
                    tilt_y_um_per_px: f64::NAN,
                    ..Default::default()
                },
                ..good
            },
            "plane.tilt_y_um_per_px",
        ),
        (
            TileInput {
                heights: RasterView::new(&with_inf, shape).unwrap(),
                ..good
            },
            "heights[1][2]",
        ),
    ];
    for (tile, needle) in cases {
        let mut pano = Panorama::new(Pitch::square(1.0).unwrap(), ok_params).unwrap();
        let err = pano.place(tile).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains(needle) && msg.contains("tile 3"), "{msg}");
        assert_eq!(pano.tiles_placed(), 0);
        assert_eq!((pano.width(), pano.height()), (0, 0));
        let err = render(Pitch::square(1.0).unwrap(), &[good, tile], ok_params).unwrap_err();
        assert!(err.to_string().contains(needle), "{err}");
    }

    // Errors after the first tile leave the panorama unchanged.
    let mut pano = Panorama::new(Pitch::square(1.0).unwrap(), ok_params).unwrap();
    pano.place(good).unwrap();
    let before = pano.to_raster();
    let err = pano.place(good).unwrap_err();
    assert_eq!(err, FusionError::DuplicateTile { index: 3 });
    let far = TileInput {
        index: 4,
        x_um: 1e300,
        ..good
    };
    let err = pano.place(far).unwrap_err();
    assert!(err.to_string().contains("x_um"), "{err}");
    pano.set_max_canvas_px(10_000);
    let big_jump = TileInput {
        index: 5,
        y_um: 1e6,
        ..good
    };
    let err = pano.place(big_jump).unwrap_err();
    assert!(
        matches!(err, FusionError::CanvasTooLarge { index: 5, .. }),
        "{err}"
    );
    assert_eq!(pano.to_raster(), before);
    assert_eq!(pano.tiles_placed(), 1);
}

#[test]
fn empty_panorama_is_a_zero_raster() {
    let pano = Panorama::new(Pitch::square(1.0).unwrap(), BlendParams::average()).unwrap();
    let raster = pano.to_raster();
    assert_eq!((raster.heights.cols(), raster.heights.rows()), (0, 0));
    assert!(raster.heights.values().is_empty());
    assert_eq!(pano.content_region(), None);
    assert!(pano
        .extract(Region {
            x0: 0,
            y0: 0,
            width: 2,
            height: 1
        })
        .iter()
        .all(|v| v.is_nan()));
}

#[test]
fn reserve_pre_sizes_the_canvas_and_changes_no_value() {
    let surface = Surface::new(10);
    let (w, h) = (40, 30);
    let tiles = serpentine(&surface, 2, 3, (w, h), 0.2, 1.5, 11);
    let params = BlendParams::from_overlap_fraction(w, h, 0.2);
    let mut grown = Panorama::new(pitch(), params).unwrap();
    place_all(&mut grown, &tiles);

    let mut reserved = Panorama::new(pitch(), params).unwrap();
    let err = reserved.reserve_um(0.0, 0.0, -1.0, 5.0).unwrap_err();
    assert!(err.to_string().contains("x_max_um"), "{err}");
    let err = reserved.reserve_um(f64::NAN, 0.0, 1.0, 5.0).unwrap_err();
    assert!(err.to_string().contains("x_min_um"), "{err}");
    // The nominal extent, generously: every tile lands inside.
    reserved.reserve_um(-20.0, -20.0, 120.0, 60.0).unwrap();
    let mut sizes = Vec::new();
    for t in &tiles {
        reserved.place(t.input()).unwrap();
        sizes.push((reserved.width(), reserved.height()));
    }
    assert!(
        sizes.iter().all(|&s| s == sizes[0]),
        "the canvas grew: {sizes:?}"
    );
    assert!(sizes[0].0 >= (140.0 / PITCH_X_UM) as usize);
    let (a, b) = (grown.to_raster(), reserved.to_raster());
    assert_eq!(
        (a.heights.cols(), a.heights.rows(), a.origin_x_um),
        (b.heights.cols(), b.heights.rows(), b.origin_x_um)
    );
    let bits = |r: &PlacedRaster| {
        r.heights
            .values()
            .iter()
            .map(|v| v.to_bits())
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(&a), bits(&b));

    // After the first tile a reservation grows the canvas at once; one over the limit is
    // ignored.
    let mut late = Panorama::new(pitch(), params).unwrap();
    late.place(tiles[0].input()).unwrap();
    late.reserve_um(-50.0, 0.0, 10.0, 10.0).unwrap();
    assert!(late.canvas_origin_um().0 <= -50.0 + PITCH_X_UM);
    late.set_max_canvas_px(100_000);
    let before = (late.width(), late.height());
    late.reserve_um(0.0, 0.0, 1e6, 1e6).unwrap();
    assert_eq!((late.width(), late.height()), before);
}

/// All three methods on a noisy 3 x 3 scan of a known surface: the panorama reproduces the
/// truth, holes never leak, coverage is the union, the wavelet method is deterministic
/// (render equals sequential placement), and every overlap gets an SSIM near 1.
#[test]
fn three_methods_reproduce_the_truth_and_score_every_overlap() {
    let surface = Surface::new(11);
    let (w, h) = (64, 48);
    let mut tiles = serpentine(&surface, 3, 3, (w, h), 0.3, 1.0, 4);
    // Measurement noise (so the methods differ) and a hole in an overlap of tile 4.
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for t in &mut tiles {
        for z in &mut t.heights {
            *z += rng.gen_range(-0.02f32..0.02);
        }
    }
    tiles[4].set_nan(20..26, 0..6);
    let bound = surface.bilinear_bound_um() + 0.02 + 1e-5;
    for method in FusionMethod::ALL {
        let params = match method {
            FusionMethod::Gradual => BlendParams::from_overlap_fraction(w, h, 0.3),
            _ => BlendParams::average(),
        };
        let wavelet = (method == FusionMethod::Wavelet).then(WaveletFusion::default);
        let mut pano = Panorama::new(pitch(), params).unwrap();
        pano.set_wavelet_fusion(wavelet);
        place_all(&mut pano, &tiles);
        let raster = pano.to_raster();
        let inputs: Vec<TileInput<'_>> = tiles.iter().map(Tile::input).collect();
        let rendered = render_panorama(pitch(), &inputs, params, wavelet)
            .unwrap()
            .to_raster();
        assert!(
            raster
                .heights
                .values()
                .iter()
                .zip(rendered.heights.values())
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "{method}: render differs from sequential placement"
        );
        let (mut n, mut sq, mut max_err) = (0usize, 0.0f64, 0.0f64);
        for row in 0..raster.heights.rows() {
            for col in 0..raster.heights.cols() {
                let v = value_at(&raster, col, row);
                if v.is_nan() {
                    continue;
                }
                let (x, y) = pos_um(&raster, col, row);
                let err = v as f64 - (Z0_UM + surface.at(x, y) - raster.z_offset_um);
                sq += err * err;
                max_err = max_err.max(err.abs());
                n += 1;
            }
        }
        let rms = (sq / n as f64).sqrt();
        // Noise +-0.02 um (rms 0.0115): fusion must not add error beyond interpolation.
        assert!(rms < 0.015, "{method}: rms error {rms}");
        assert!(max_err < 2.0 * bound, "{method}: max error {max_err}");
        let pairs = overlap_quality(&pano, &inputs).unwrap();
        // 3 x 3 grid: 12 edge neighbours and 8 diagonal corners (30 % overlap = 19 x 14 px
        // less jitter, each >= 11 px, so every one is scored).
        assert_eq!(pairs.len(), 20, "{method}: {pairs:?}");
        for p in &pairs {
            assert!(p.tile_a < p.tile_b);
            assert!(
                p.ssim_mean > 0.9 && p.ssim_mean <= 1.0,
                "{method}: pair {p:?}"
            );
        }
        eprintln!(
            "{method}: rms {rms:.4} um, max {max_err:.4} um, mean SSIM {:.4}",
            pairs.iter().map(|p| p.ssim_mean).sum::<f64>() / pairs.len() as f64
        );
    }
}

/// Tiles larger than a chunk, straddling chunk borders in both directions: the chunked
/// accumulators give the surface back within the bilinear bound everywhere (a span written to
/// the wrong chunk or offset would not be), and a memory budget of one chunk, which spills and
/// reloads chunks all along the scan, changes no bit of the panorama or of the overlap scores,
/// for the weighted mean and for the wavelet fusion.
#[test]
fn chunked_panorama_is_exact_and_a_budget_changes_no_bit() {
    use surfstream_fusion::{CHUNK_BYTES, CHUNK_PX};
    let surface = Surface::new(11);
    let (w, h) = (300, 260);
    let clean = serpentine(&surface, 3, 4, (w, h), 0.15, 3.0, 12);
    let mut tiles = clean.clone();
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    for t in &mut tiles {
        let (r, c) = (rng.gen_range(0..h - 9), rng.gen_range(0..w - 9));
        t.set_nan(r..r + 9, c..c + 9);
    }
    let params = BlendParams::from_overlap_fraction(w, h, 0.15);
    let bits = |r: &PlacedRaster| {
        r.heights
            .values()
            .iter()
            .map(|v| v.to_bits())
            .collect::<Vec<_>>()
    };
    let spill_dir = tempfile::tempdir().unwrap();
    for wavelet in [None, Some(WaveletFusion::default())] {
        let build = |budget: Option<usize>| {
            let mut p = Panorama::new(pitch(), params).unwrap();
            p.set_wavelet_fusion(wavelet);
            p.set_memory_budget_bytes(budget, Some(spill_dir.path().into()));
            place_all(&mut p, &tiles);
            p
        };
        let whole = build(None);
        let spilled = build(Some(CHUNK_BYTES));
        let (a, b) = (whole.to_raster(), spilled.to_raster());
        assert!(a.heights.cols() > 2 * CHUNK_PX && a.heights.rows() > CHUNK_PX);
        assert_eq!(
            (a.origin_x_um, a.origin_y_um),
            (b.origin_x_um, b.origin_y_um)
        );
        assert_eq!(bits(&a), bits(&b), "wavelet fusion: {}", wavelet.is_some());
        let (sw, ss) = (whole.chunk_stats(), spilled.chunk_stats());
        assert_eq!(sw.spills, 0);
        assert!(sw.chunks >= 6, "{sw:?}");
        assert!(ss.spills > 0 && ss.reloads > 0, "{ss:?}");
        // One tile's chunks at most (4, or 6 when the footprint straddles 3 columns).
        assert!(ss.peak_resident_chunks <= 7, "{ss:?}");
        let inputs: Vec<TileInput> = tiles.iter().map(Tile::input).collect();
        let qa = overlap_quality(&whole, &inputs).unwrap();
        let qb = overlap_quality(&spilled, &inputs).unwrap();
        assert_eq!(qa, qb);
        assert!(qa.len() >= 17, "{} pairs", qa.len());
        if wavelet.is_some() {
            continue;
        }
        // Without holes (their renormalised edges are not bilinear), against the truth.
        let mut p = Panorama::new(pitch(), params).unwrap();
        place_all(&mut p, &clean);
        let a = p.to_raster();
        let bound = surface.bilinear_bound_um() + 1e-5;
        let mut checked = 0;
        for row in 0..a.heights.rows() {
            for col in 0..a.heights.cols() {
                let v = value_at(&a, col, row);
                if v.is_nan() {
                    continue;
                }
                let (x, y) = pos_um(&a, col, row);
                let truth = Z0_UM + surface.at(x, y) - a.z_offset_um;
                let err = (v as f64 - truth).abs();
                assert!(err <= bound, "pixel ({col}, {row}): error {err} > {bound}");
                checked += 1;
            }
        }
        assert!(checked > a.heights.values().len() * 9 / 10);
    }
    // The spill files are unnamed: nothing is left behind.
    assert_eq!(std::fs::read_dir(spill_dir.path()).unwrap().count(), 0);
}
