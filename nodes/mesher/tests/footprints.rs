//! Issue 33: the tolerance search judges Table 6's tile footprints as regions beside its
//! windows. A surface whose hardest region is a tile footprint that lies between the windows
//! (a quarter of a window off every one of them): judged on its windows alone the search
//! passes and the footprint fails; given the footprint, the mesh chosen meets it too. The
//! footprint is judged here with Table 6's own code (`surfstream_core::deviation::Table6`,
//! f64, ISO 25178 parameters) as well as the mesher's.

use surfstream_core::deviation::{Measured, ModelStage, Region, Table6};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_mesher::tolerance::{judge_regions, windows, GridPlane, Window, DEFAULT_TOLERANCE};
use surfstream_mesher::{
    mesh_streaming_to_tolerance, mesh_to_tolerance, AdaptiveMesh, Epsilon, LengthUnit, MeshKind,
    MeshParams, MissingSamples, ScanPlacement, SolidParams, ToleranceReport, ToleranceSettings,
};

const N: usize = 256;
/// The windows' side: windows start at rows and columns 0, 64 and 128.
const REGION_PX: usize = 128;
/// The footprint: a window's size, a quarter of a window off the windows' grid.
const F0: usize = 32;

fn footprint() -> Window {
    Window {
        name: "S1".into(),
        row0: F0,
        col0: F0,
        rows: REGION_PX,
        cols: REGION_PX,
    }
}

/// A fine, low texture everywhere (Sq about 0.06 um) under a large smooth form (Sq about
/// 1 um) that is absent from the footprint (ramping in over 12 px outside it): every window
/// holds at least 7/16 of its area of form, so an error on the texture is a small share of
/// its parameters, while in the footprint the texture is all there is.
fn surface() -> Vec<f32> {
    let (lo, hi) = (F0 as f64, (F0 + REGION_PX) as f64);
    (0..N * N)
        .map(|k| {
            let (x, y) = ((k % N) as f64, (k / N) as f64);
            let texture = 0.06
                * ((x * std::f64::consts::TAU / 7.3).sin()
                    * (y * std::f64::consts::TAU / 6.1).cos()
                    + 0.5 * ((x + y) * std::f64::consts::TAU / 4.7).sin());
            let outside = |v: f64| (lo - v).max(v - (hi - 1.0)).max(0.0);
            let d = outside(x).max(outside(y));
            let s = (d / 12.0).min(1.0);
            let w = s * s * (3.0 - 2.0 * s);
            let form = 3.0 * (x / 11.0).sin() * (y / 13.0).cos();
            (texture + w * form) as f32
        })
        .collect()
}

fn params() -> MeshParams {
    MeshParams {
        epsilon: Epsilon::SqFraction(0.05),
        max_triangles: None,
        kind: MeshKind::Sheet,
        missing: MissingSamples::Fill,
        solid: SolidParams {
            units: LengthUnit::Um,
            base_depth_um: None,
            recentre: false,
        },
        block_samples: None,
    }
}

fn settings() -> ToleranceSettings {
    ToleranceSettings {
        region_px: Some(REGION_PX),
        ..Default::default()
    }
}

fn search(z: &[f32], footprints: &[Window]) -> (AdaptiveMesh, ToleranceReport) {
    let heights = RasterView::new(z, Shape::new(N, N)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).unwrap());
    mesh_to_tolerance(heights, None, &at, &params(), &settings(), footprints).unwrap()
}

/// The plane the search judged its regions without, on the tests' grid.
fn judged_plane(r: &ToleranceReport) -> GridPlane {
    let p = r.judged_plane.expect("the plane judged without is stated");
    GridPlane::of_record(&p, Pitch::new(1.0, 1.0).unwrap(), 0.0)
}

/// Table 6's Sa, Sq, Sz deviations (%) of the mesh in the footprint (Table 6's code, f64),
/// both less the plane the search judged without, as the graph's Table 6 has them.
fn table6_in_footprint(z: &[f32], m: &AdaptiveMesh, plane: &GridPlane) -> [f64; 3] {
    let less_plane = |v: &[f32]| -> Vec<f64> {
        (v.iter().enumerate())
            .map(|(k, &h)| {
                let (row, col) = (k / N, k % N);
                f64::from(h)
                    - (plane.at_origin_um
                        + plane.per_col_um * col as f64
                        + plane.per_row_um * row as f64)
            })
            .collect()
    };
    let measured = less_plane(z);
    let model = less_plane(&m.resampled_um);
    let shape = Shape::new(N, N);
    let f = footprint();
    let region = Region {
        name: f.name,
        row0: f.row0,
        col0: f.col0,
        rows: f.rows,
        cols: f.cols,
    };
    let t = Table6::judge(
        Measured {
            heights_um: RasterView::new(&measured, shape).unwrap(),
            pitch_x_um: 1.0,
            pitch_y_um: 1.0,
        },
        &[ModelStage::on_measured_grid(
            "mesh",
            RasterView::new(&model, shape).unwrap(),
        )],
        &[region],
        5.0,
    )
    .unwrap();
    let r = &t.stages[0].regions[0];
    ["Sa", "Sq", "Sz"].map(|k| {
        (r.deviation_pct.iter())
            .find(|(n, _)| *n == k)
            .and_then(|(_, d)| *d)
            .unwrap()
    })
}

#[test]
fn a_footprint_between_the_windows_is_met_when_the_search_judges_it() {
    let z = surface();
    let t = DEFAULT_TOLERANCE;
    let f = footprint();
    // The footprint lies between the windows: a quarter of a window off every one.
    let w = windows(Shape::new(N, N), REGION_PX);
    assert_eq!(w.len(), 10);
    assert!(w
        .iter()
        .all(|w| w.row0.abs_diff(f.row0) >= 32 && w.col0.abs_diff(f.col0) >= 32));

    // Windows alone: every window passes, the footprint fails, by Table 6's code too.
    let (blind_mesh, blind) = search(&z, &[]);
    assert!(blind.met, "{:?}", blind.reason);
    assert_eq!((blind.regions, blind.footprints), (10, 0));
    assert!(blind.region_fits.iter().all(|r| r.region != "S1"));
    let fit = &judge_regions(
        &z,
        &blind_mesh.resampled_um,
        None,
        Shape::new(N, N),
        std::slice::from_ref(&f),
        Some(judged_plane(&blind)),
    )[0];
    let (param, d, limit) = fit.excess(&t, 1.0).expect("the footprint fails");
    eprintln!(
        "windows alone, {} surface triangles: S1 {param} {d:+.2} % (limit {limit} %), {fit:?}",
        blind.surface_triangles
    );
    let dev = table6_in_footprint(&z, &blind_mesh, &judged_plane(&blind));
    eprintln!(
        "windows alone: Table 6 in S1: Sa {:+.2} %, Sq {:+.2} %, Sz {:+.2} %",
        dev[0], dev[1], dev[2]
    );
    assert!(
        dev[0].abs() > t.sa_pct || dev[1].abs() > t.sq_pct,
        "Table 6 passes the footprint: {dev:?}"
    );

    // Given the footprint, the mesh chosen meets it: named S1 among the regions, within the
    // tolerance by the search's criteria and by Table 6's.
    let (mesh, r) = search(&z, std::slice::from_ref(&f));
    assert!(r.met, "{:?}", r.reason);
    assert_eq!((r.regions, r.footprints), (11, 1));
    let s1 = r
        .region_fits
        .iter()
        .find(|x| x.region == "S1")
        .expect("S1 judged");
    assert!(s1.excess(&t, 1.0).is_none(), "{s1:?}");
    assert_eq!(
        &judge_regions(
            &z,
            &mesh.resampled_um,
            None,
            Shape::new(N, N),
            std::slice::from_ref(&f),
            Some(judged_plane(&r)),
        )[0],
        s1
    );
    let dev = table6_in_footprint(&z, &mesh, &judged_plane(&r));
    eprintln!(
        "with S1, {} surface triangles: Table 6 in S1: Sa {:+.2} %, Sq {:+.2} %, Sz {:+.2} %",
        r.surface_triangles, dev[0], dev[1], dev[2]
    );
    assert!(
        dev[0].abs() <= t.sa_pct && dev[1].abs() <= t.sq_pct && dev[2].abs() <= t.sz_pct,
        "{dev:?}"
    );
    // The worst region is the footprint, and it costs triangles the windows did not ask for.
    assert_eq!(r.region_fits[0].region, "S1", "{:?}", r.region_fits[0]);
    assert!(r.surface_triangles > blind.surface_triangles);

    // The streamed search (the product) chooses the same mesh.
    let heights = RasterView::new(&z, Shape::new(N, N)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).unwrap());
    let dir = tempfile::tempdir().unwrap();
    let (sm, sr) =
        mesh_streaming_to_tolerance(heights, None, &at, &params(), &settings(), &[f], dir.path())
            .unwrap();
    assert_eq!(sr.curve, r.curve);
    assert_eq!(sm.counts.top_triangles, mesh.surface_triangles);
}

#[test]
fn a_footprint_beyond_the_map_is_refused_by_name() {
    let z = surface();
    let heights = RasterView::new(&z, Shape::new(N, N)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).unwrap());
    let off = Window {
        row0: N - 10,
        ..footprint()
    };
    let e = mesh_to_tolerance(heights, None, &at, &params(), &settings(), &[off]).unwrap_err();
    assert!(
        e.to_string().contains("footprint S1") && e.to_string().contains("rectangle within the"),
        "{e}"
    );
}
