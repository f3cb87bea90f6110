//! How well a mesh represents its height field in ISO 25178 terms: Sa, Sq, Sz and Sdr of the
//! height field beside those of the mesh resampled on the same grid (the reference study's
//! Table 6, one stage further).
//!
//! The parameters and the plane fit are the project's metrology ([`surfstream_core::metrology`],
//! checked against surfalize); this module only decides what is compared: both surfaces are
//! levelled by the same least-squares plane (fitted to the height field), so the comparison
//! sees only what the mesh changed. Missing samples (NaN) are left out; Sdr counts only grid
//! cells with four measured corners.

use surfstream_core::metrology::{fit_plane_f32, Params, ParamsByRows};
use surfstream_core::raster::RasterView;
use surfstream_core::{Pitch, Sampling};

/// Areal parameters of one surface, um (Sdr in %): the report's record itself, so the
/// fidelity written is the one its readers read.
pub use surfstream_core::record::LevelledParams as AreaParams;

fn area_params(p: Params) -> AreaParams {
    AreaParams {
        sa_um: p.sa,
        sq_um: p.sq,
        sz_um: p.sz,
        sdr_percent: if p.sdr.is_nan() { 0.0 } else { p.sdr },
    }
}

/// The parameters of the height field alone (samples `pitch` apart), levelled by its
/// least-squares plane; `None` when no sample is valid.
pub fn field_params(field: RasterView<'_, f32>, pitch: Pitch) -> Option<AreaParams> {
    level_field(field, pitch)?.params
}

/// A height field's least-squares plane and its parameters about that plane: the field's side
/// of [`compare`], kept so that the mesh's side can be computed later ([`FieldLevel::mesh_params`])
/// without holding both surfaces in f64 at once.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FieldLevel {
    /// z = a + b x + c y (um), as [`fit_plane_f32`] gives it.
    plane: (f64, f64, f64),
    sampling: Sampling,
    /// The field's parameters, levelled by the plane.
    pub(crate) params: Option<AreaParams>,
}

/// The parameters of `z` widened to f64 minus the plane (evaluated as
/// [`surfstream_core::metrology::level_plane`] does; with `measured`, only where it is not
/// NaN), levelled one row at a time and fed to [`ParamsByRows`] twice: the same bits as
/// [`surfstream_core::metrology::params`] of the whole levelled copy, holding one row of it.
fn levelled_params(
    z: &[f32],
    measured: Option<&[f32]>,
    sampling: Sampling,
    plane: (f64, f64, f64),
    bx: f64,
    by: f64,
) -> Option<AreaParams> {
    let cols = sampling.cols();
    if cols == 0 || z.len() != sampling.shape().len() {
        return None;
    }
    let mut by_rows = ParamsByRows::new(cols, sampling.pitch_x_um(), sampling.pitch_y_um()).ok()?;
    let mut row: Vec<f64> = Vec::with_capacity(cols);
    let level = |r: usize, row: &mut Vec<f64>| {
        row.clear();
        let base = plane.0 + by * r as f64;
        let k = r * cols;
        row.extend(z[k..k + cols].iter().enumerate().map(|(i, &h)| {
            let h = match measured {
                Some(m) if m[k + i].is_nan() => f64::NAN,
                _ => f64::from(h),
            };
            h - (base + bx * i as f64)
        }));
    };
    let rows = sampling.rows();
    for r in 0..rows {
        level(r, &mut row);
        by_rows.push_first(&row).ok()?;
    }
    by_rows.end_first();
    for r in 0..rows {
        level(r, &mut row);
        by_rows.push_second(&row).ok()?;
    }
    by_rows.finish().ok().map(area_params)
}

/// The field's plane and levelled parameters; `None` when the field has no valid sample.
/// The plane is fitted on the float32 field itself (no copy); the parameters are computed by
/// rows ([`levelled_params`]).
pub(crate) fn level_field(field: RasterView<'_, f32>, pitch: Pitch) -> Option<FieldLevel> {
    let sampling = Sampling::of(field.shape(), pitch);
    let plane = fit_plane_f32(field.values(), sampling).ok()?;
    let (bx, by) = (plane.1 * pitch.x_um(), plane.2 * pitch.y_um());
    let params = levelled_params(field.values(), None, sampling, plane, bx, by);
    Some(FieldLevel {
        plane,
        sampling,
        params,
    })
}

/// The form every region is judged without: the measured field's least-squares plane on the
/// grid, `z = at_origin_um + per_col_um * col + per_row_um * row` (um, relative to the
/// heights' own zero), the form `params --level` removes. Subtracted from the measurement and
/// the mesh alike, so a tilt does not dominate a region's Sa and Sq and hide its roughness
/// from the bounds (issue 33: form before roughness). The mesh is made of the heights as
/// they are (a triangle interpolates a plane exactly, so the plane changes no error), and the
/// STL keeps the tilt unless the settings level it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GridPlane {
    pub at_origin_um: f64,
    pub per_col_um: f64,
    pub per_row_um: f64,
}

impl GridPlane {
    /// The plane a record states (`tolerance::ToleranceReport::judged_plane`) on a grid of `pitch`
    /// whose heights are relative to `z_offset_um`.
    pub fn of_record(
        p: &surfstream_core::record::FormPlane,
        pitch: surfstream_core::Pitch,
        z_offset_um: f64,
    ) -> Self {
        Self {
            at_origin_um: p.z_um - z_offset_um,
            per_col_um: p.slope_x_um_per_um * pitch.x_um(),
            per_row_um: p.slope_y_um_per_um * pitch.y_um(),
        }
    }

    /// The plane's height at the start of `row`, and its step per column.
    pub(crate) fn row(&self, row: usize) -> (f64, f64) {
        (
            self.at_origin_um + self.per_row_um * row as f64,
            self.per_col_um,
        )
    }
}

impl FieldLevel {
    /// The plane on the grid (height at sample (0, 0), step per column and per row): the
    /// form the tolerance judges every region without.
    pub(crate) fn grid_plane(&self) -> GridPlane {
        GridPlane {
            at_origin_um: self.plane.0,
            per_col_um: self.plane.1 * self.sampling.pitch_x_um(),
            per_row_um: self.plane.2 * self.sampling.pitch_y_um(),
        }
    }

    /// The plane as the record states it (absolute z at sample (0, 0), slopes per um).
    pub(crate) fn form_plane(&self, z_offset_um: f64) -> surfstream_core::record::FormPlane {
        surfstream_core::record::FormPlane {
            z_um: self.plane.0 + z_offset_um,
            slope_x_um_per_um: self.plane.1,
            slope_y_um_per_um: self.plane.2,
        }
    }

    /// The parameters of `mesh_um` (the field's shape, NaN where not compared) levelled by
    /// the field's plane.
    pub(crate) fn mesh_params(&self, mesh_um: &[f32]) -> Option<AreaParams> {
        self.mesh_params_where(mesh_um, None)
    }

    /// [`FieldLevel::mesh_params`] of `mesh_um` at the samples `measured` (the field) holds,
    /// without a masked copy.
    pub(crate) fn mesh_params_at_measured(
        &self,
        mesh_um: &[f32],
        measured: &[f32],
    ) -> Option<AreaParams> {
        self.mesh_params_where(mesh_um, Some(measured))
    }

    fn mesh_params_where(&self, mesh_um: &[f32], measured: Option<&[f32]>) -> Option<AreaParams> {
        let s = self.sampling;
        if mesh_um.len() != s.shape().len() || measured.is_some_and(|m| m.len() != mesh_um.len()) {
            return None;
        }
        let (bx, by) = (self.plane.1 * s.pitch_x_um(), self.plane.2 * s.pitch_y_um());
        levelled_params(mesh_um, measured, s, self.plane, bx, by)
    }
}

/// The parameters of the height field and of the resampled mesh (`mesh_um`, the field's shape,
/// NaN where the mesh is not compared), both levelled by the height field's least-squares
/// plane (samples `pitch` apart).
pub fn compare(
    field: RasterView<'_, f32>,
    mesh_um: &[f32],
    pitch: Pitch,
) -> (Option<AreaParams>, Option<AreaParams>) {
    if mesh_um.len() != field.shape().len() {
        return (None, None);
    }
    match level_field(field, pitch) {
        Some(level) => (level.params, level.mesh_params(mesh_um)),
        None => (None, None),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::raster::Shape;

    fn pitch(um: f64) -> Pitch {
        Pitch::square(um).unwrap()
    }

    fn view(h: &[f32], rows: usize, cols: usize) -> RasterView<'_, f32> {
        RasterView::new(h, Shape::new(rows, cols)).unwrap()
    }

    #[test]
    fn tilted_plane_levels_to_zero_and_sine_matches_theory() {
        let (w, h) = (64, 48);
        let tilted: Vec<f32> = (0..w * h)
            .map(|k| (3.0 + 0.01 * (k % w) as f64 - 0.02 * (k / w) as f64) as f32)
            .collect();
        let (field, mesh) = compare(view(&tilted, h, w), &tilted, pitch(0.5));
        let (field, mesh) = (field.unwrap(), mesh.unwrap());
        assert!(field.sq_um < 1e-5 && field.sz_um < 1e-5, "{field:?}");
        assert_eq!(field, mesh);
        // A sine of amplitude A along x over whole periods: Sq = A / sqrt 2, Sa = 2 A / pi;
        // a mesh at half the amplitude loses half of Sq and some of the area.
        let a = 2.0f64;
        // Even about the grid's centre, so that the fitted plane is flat; its samples sit half
        // a pixel off the crests, so Sz is 2 A cos(pi / 16).
        let centre = (w - 1) as f64 / 2.0;
        let phase = |k: usize| 2.0 * std::f64::consts::PI * ((k % w) as f64 - centre) / 16.0;
        let sine: Vec<f32> = (0..w * h).map(|k| (a * phase(k).cos()) as f32).collect();
        let half: Vec<f32> = sine.iter().map(|&z| 0.5 * z).collect();
        let (field, mesh) = compare(view(&sine, h, w), &half, pitch(1.0));
        let (field, mesh) = (field.unwrap(), mesh.unwrap());
        assert!((field.sq_um - a / 2f64.sqrt()).abs() < 1e-3, "{field:?}");
        assert!(
            (field.sa_um - 2.0 * a / std::f64::consts::PI).abs() < 0.02,
            "{field:?}"
        );
        let sz = 2.0 * a * (std::f64::consts::PI / 16.0).cos();
        assert!((field.sz_um - sz).abs() < 1e-5, "{field:?}");
        assert!((mesh.sq_um - 0.5 * field.sq_um).abs() < 1e-3, "{mesh:?}");
        assert!(field.sdr_percent > mesh.sdr_percent && mesh.sdr_percent > 0.0);
        assert_eq!(
            compare(view(&[f32::NAN; 6], 2, 3), &[0.0; 6], pitch(1.0)),
            (None, None)
        );
    }
}
