//! The mesher's one front door: [`MesherConfig`], the parameters as a graph file, the `mesh`
//! verb's flags and Python's keywords all state them (typed: every choice is an enum, so a bad
//! value is refused by serde with the key and the allowed values named), and
//! [`MesherConfig::settings`], which checks them together into the one [`MeshSettings`] that
//! `map::mesh_surface` meshes with.
//!
//! Nothing here meshes; nothing here reads a file.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::outliers::OutlierPolicy;
use crate::target::{DemEngine, EngineProfile, TargetMethod};
use crate::tolerance::{ModelMethod, ToleranceSettings};
use crate::{Epsilon, LengthUnit, MeshKind, MeshParams, MissingSamples, SolidParams, Tolerance};

/// The bound when a fixed bound is asked for without a value: 5 % of the surface's Sq.
pub const DEFAULT_EPSILON_SQ_FRACTION: f64 = 0.05;

/// What [`MeshSettings::form_removed`] says when the plane was removed (as `params --level`).
pub const LEAST_SQUARES_PLANE: &str = "least-squares plane";

/// The mesher's parameters: a graph's `params` table, the `mesh` verb's flags, Python's
/// `mesh(...)` keywords. Every field has the graph's default ([`MesherConfig::default`]).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MesherConfig {
    /// STL coordinate unit: "mm" (default), "m" or "um".
    pub units: LengthUnit,
    /// "binary" (EDEM, Rocky, MercuryDPM; default) or "ascii" (LIGGGHTS).
    pub format: StlFormat,
    /// Base of the solid below the lowest sample, um (default: from the height range).
    pub base_depth_um: Option<f64>,
    /// The STL's name in the out dir (a graph's node; the verb and Python name the path).
    pub file: String,
    /// "adaptive" (the model, default) or "grid" (two triangles per grid cell; with a target,
    /// the engine's regular grid).
    pub method: MeshMethod,
    /// Largest vertical error, um (a fixed bound instead of the tolerance).
    pub epsilon_um: Option<f64>,
    /// Largest vertical error as a fraction of the surface's Sq (a fixed bound).
    pub epsilon_sq_fraction: Option<f64>,
    /// Triangle budget of the surface (with a tolerance, the search's limit).
    pub max_triangles: Option<usize>,
    /// The model's tolerance per region, percent: "sa=1,sq=1,sz=3" or { sa = 1, sq = 1, sz = 3 }
    /// (the default when neither epsilon is given: the target's, [`ToleranceSettings::for_target`]).
    /// The mesher then finds the fewest triangles that meet it ([`crate::tolerance`]).
    pub tolerance: Option<Tolerance>,
    /// Side of the windows the tolerance is judged in, samples (default: half the map's
    /// shorter side, 64 to 1024).
    pub region_px: Option<usize>,
    /// How the tolerance search's insertion order is made: "balanced" (default) or "greedy"
    /// (the pointwise bound only; for comparison).
    pub model_method: ModelMethod,
    /// Spikes (isolated outliers, [`crate::outliers`]): "keep" (default: mesh what was
    /// measured; they are reported) or "remove" (treated as not measured, and reported).
    pub outliers: OutlierPolicy,
    /// Remove the least-squares plane before meshing, as `params --level`
    /// (`surfstream_core::metrology::level_plane`): the mesh and its tolerance are then of the
    /// levelled surface, and the report says `form_removed`. Default: the mean only.
    pub level: bool,
    /// "solid" (default) or "sheet".
    pub kind: MeshKind,
    /// "fill" (default) or "holes" (a sheet only): missing samples.
    pub missing: MissingSamples,
    /// Which surface to mesh (a graph's node).
    pub surface: SurfaceChoice,
    /// "liggghts" | "mercurydpm" | "edem" | "yade": write what that engine imports
    /// ([`crate::target`]); sets the format, units, kind, method and triangle budget
    /// (`max_triangles` still lowers the budget).
    pub target: Option<DemEngine>,
    /// With a tolerance: make the fidelity-cost curve's own meshes (default true; false: the
    /// curve is the search's meshes alone: fewer meshes made, [`ToleranceSettings::curve`]).
    pub curve: bool,
}

impl Default for MesherConfig {
    fn default() -> Self {
        Self {
            units: LengthUnit::default(),
            format: StlFormat::default(),
            base_depth_um: None,
            file: Self::DEFAULT_FILE.into(),
            method: MeshMethod::default(),
            epsilon_um: None,
            epsilon_sq_fraction: None,
            max_triangles: None,
            tolerance: None,
            region_px: None,
            model_method: ModelMethod::default(),
            outliers: OutlierPolicy::default(),
            level: false,
            kind: MeshKind::default(),
            missing: MissingSamples::default(),
            surface: SurfaceChoice::default(),
            target: None,
            curve: true,
        }
    }
}

/// One choice of the config from its text, the way a graph file's value is read: the error
/// names the key and the allowed values ("units = \"furlong\": unknown variant `furlong`,
/// expected one of `m`, `mm`, `um`"). For callers whose choices arrive as text (Python's
/// keywords, a verb's flag).
pub fn parse_choice<T: serde::de::DeserializeOwned>(
    key: &str,
    value: &str,
) -> std::result::Result<T, String> {
    use serde::de::value::{Error, StrDeserializer};
    use serde::de::IntoDeserializer;
    let text: StrDeserializer<'_, Error> = value.into_deserializer();
    T::deserialize(text).map_err(|e| format!("{key} = {value:?}: {e}"))
}

/// How the surface becomes triangles.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MeshMethod {
    /// The model: error-bounded greedy insertion, to a tolerance or a fixed bound.
    #[default]
    Adaptive,
    /// Two triangles per grid cell (with a target: the engine's block-averaged grid).
    Grid,
}

/// How the STL is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StlFormat {
    /// EDEM, Rocky, MercuryDPM.
    #[default]
    Binary,
    /// LIGGGHTS.
    Ascii,
}

impl StlFormat {
    pub fn name(self) -> &'static str {
        match self {
            Self::Binary => "binary",
            Self::Ascii => "ascii",
        }
    }
}

/// Which surface the mesher meshes, and the input ports that carry it: "panorama" (default:
/// the full-resolution surface, what the tolerance is judged against) or "pooled" (the
/// reference study's 4 x 4 max-pooled map, an option) arrive on the input `surface`; "datum"
/// and "roughness" on the inputs of those names; "datum+roughness" needs both and meshes their
/// sum (the panorama as the separation rebuilds it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
pub enum SurfaceChoice {
    #[serde(rename = "pooled")]
    Pooled,
    #[default]
    #[serde(rename = "panorama")]
    Panorama,
    #[serde(rename = "datum+roughness")]
    DatumPlusRoughness,
    #[serde(rename = "datum")]
    Datum,
    #[serde(rename = "roughness")]
    Roughness,
}

impl SurfaceChoice {
    /// The input ports this choice needs (and the only ones it accepts).
    pub fn ports(self) -> &'static [&'static str] {
        match self {
            Self::Pooled | Self::Panorama => &["surface"],
            Self::DatumPlusRoughness => &["datum", "roughness"],
            Self::Datum => &["datum"],
            Self::Roughness => &["roughness"],
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Pooled => "pooled",
            Self::Panorama => "panorama",
            Self::DatumPlusRoughness => "datum+roughness",
            Self::Datum => "datum",
            Self::Roughness => "roughness",
        }
    }

    /// The inputs this choice may also take: the panorama's measured roughness
    /// (`wavelet/roughness`), the reference that judges the roughness the mesh carries
    /// ([`crate::Tolerance::roughness_pct`]).
    pub fn optional_ports(self) -> &'static [&'static str] {
        match self {
            Self::Panorama => &["roughness"],
            _ => &[],
        }
    }

    /// The wiring must match the choice: a missing or an unused input is an error.
    pub fn check_wiring(self, wired: &[&str]) -> std::result::Result<(), String> {
        let needed = self.ports();
        if let Some(port) = needed.iter().find(|p| !wired.contains(p)) {
            return Err(format!(
                "surface = \"{}\" needs the input '{port}' (wired: {wired:?})",
                self.name()
            ));
        }
        let optional = self.optional_ports();
        if let Some(extra) = wired
            .iter()
            .find(|w| !needed.contains(w) && !optional.contains(w))
        {
            return Err(format!(
                "input '{extra}' is wired but surface = \"{}\" does not use it (it uses \
                 {needed:?}, and may take {optional:?})",
                self.name()
            ));
        }
        Ok(())
    }
}

/// The checked settings of a mesher: what `map::mesh_surface` meshes with, whoever
/// stated them.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshSettings {
    pub solid: SolidParams,
    /// `None`: the full-grid solid (or the engine's grid with a grid target).
    pub adaptive: Option<MeshParams>,
    pub format: StlFormat,
    pub surface: SurfaceChoice,
    /// The engine the STL is made for, when one was named.
    pub target: Option<EngineProfile>,
    /// The model from a tolerance (adaptive only; `None`: the fixed bound of `adaptive`).
    pub tolerance: Option<ToleranceSettings>,
    /// Spikes kept (default) or removed before meshing.
    pub outliers: OutlierPolicy,
    /// The least-squares plane removed before meshing ([`LEAST_SQUARES_PLANE`]).
    pub level: bool,
}

impl MeshSettings {
    /// The form removed before meshing, as the report states it (`None`: the mean only).
    pub fn form_removed(&self) -> Option<&'static str> {
        self.level.then_some(LEAST_SQUARES_PLANE)
    }

    /// The STL header's label of a map meshed outside a graph (the `mesh` verb and Python
    /// write the same bytes): "surfstream mesh", "for ENGINE" with an engine's grid.
    pub fn map_stl_label(&self) -> String {
        match self.grid_target() {
            Some(p) => format!("surfstream mesh for {}", p.engine.name()),
            None => "surfstream mesh".to_string(),
        }
    }

    /// The engine's regular grid, when the target asks for it.
    pub fn grid_target(&self) -> Option<EngineProfile> {
        self.target.filter(|p| p.method == TargetMethod::Grid)
    }
}

/// `mesh` writes STL: a path named otherwise (`x.obj`) is refused, not filled with STL.
pub fn check_stl_path(stl: &Path) -> std::result::Result<(), String> {
    if stl.file_name().is_none()
        || !stl
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("stl"))
    {
        return Err(format!(
            "{}: mesh writes STL; expected a path ending in .stl (the statistics go to the same \
             name with .json)",
            stl.display()
        ));
    }
    Ok(())
}

impl MesherConfig {
    /// The graph key of [`MesherConfig::tolerance`], for the launcher's `--tolerance`, which
    /// sets it on every mesher node (the mesher's lib has no TOML: the launcher writes it).
    pub const TOLERANCE_KEY: &'static str = "tolerance";
    /// The key of [`MesherConfig::file`] (the graph reader keeps every output file inside
    /// the out dir, and no two alike).
    pub const FILE_KEY: &'static str = "file";
    /// [`MesherConfig::file`] when not given.
    pub const DEFAULT_FILE: &'static str = "surface.stl";

    /// The checked settings; the error says which parameter is wrong and what was expected.
    pub fn settings(&self) -> std::result::Result<MeshSettings, String> {
        check_stl_path(Path::new(&self.file)).map_err(|e| format!("file = {e}"))?;
        let solid = SolidParams {
            units: self.units,
            base_depth_um: self.base_depth_um,
            recentre: true,
        };
        solid.validate().map_err(|e| e.to_string())?;
        let fixed_bound = self.epsilon_um.is_some() || self.epsilon_sq_fraction.is_some();
        if self.tolerance.is_some() && fixed_bound {
            return Err(
                "give a tolerance or a fixed bound (epsilon_um / epsilon_sq_fraction), not both"
                    .into(),
            );
        }
        let adaptive = self.method == MeshMethod::Adaptive;
        if self.tolerance.is_some() && !adaptive {
            return Err(
                "tolerance needs method = \"adaptive\" (method = \"grid\" meshes every sample)"
                    .into(),
            );
        }
        if self.missing == MissingSamples::Holes && self.kind == MeshKind::Solid {
            return Err(
                "missing = \"holes\" needs kind = \"sheet\" (a solid is closed)".to_string(),
            );
        }
        if let Some(px) = self.region_px {
            if px < 16 {
                return Err(format!(
                    "region_px = {px}: expected at least 16 (samples per side of a judged window)"
                ));
            }
        }
        let mut tolerance = (adaptive && !fixed_bound).then(|| ToleranceSettings {
            // Unless stated, the target's own (an angle-bounded one has no pointwise
            // maximum, [`EngineProfile::default_tolerance`]).
            tolerance: self.tolerance.unwrap_or_else(|| {
                let profile = self.target.map(EngineProfile::for_engine);
                ToleranceSettings::for_target(profile.as_ref()).tolerance
            }),
            region_px: self.region_px,
            method: self.model_method,
            min_angle_deg: None,
            curve: self.curve,
        });
        let adaptive = match self.method {
            MeshMethod::Grid => None,
            MeshMethod::Adaptive => {
                let epsilon = match (self.epsilon_um, self.epsilon_sq_fraction) {
                    (Some(_), Some(_)) => {
                        return Err("give epsilon_um or epsilon_sq_fraction, not both".into())
                    }
                    (Some(e), None) => Epsilon::Um(e),
                    (None, f) => Epsilon::SqFraction(f.unwrap_or(DEFAULT_EPSILON_SQ_FRACTION)),
                };
                Some(MeshParams {
                    epsilon,
                    max_triangles: self.max_triangles,
                    kind: self.kind,
                    missing: self.missing,
                    solid: solid.clone(),
                    block_samples: None,
                })
            }
        };
        let mut settings = MeshSettings {
            solid,
            adaptive,
            format: self.format,
            surface: self.surface,
            target: None,
            tolerance: None,
            outliers: self.outliers,
            level: self.level,
        };
        if let Some(engine) = self.target {
            let mut profile = EngineProfile::with_budget(engine, self.max_triangles);
            // method = "grid" asks for the engine's regular grid instead of its adaptive mesh.
            if self.method == MeshMethod::Grid {
                profile.method = TargetMethod::Grid;
            }
            // An engine's regular grid is sized by its budget, not by a tolerance.
            if profile.method == TargetMethod::Grid {
                if self.tolerance.is_some() || fixed_bound {
                    return Err(format!(
                        "target = {:?} with method = \"grid\" meshes a regular grid within \
                         its triangle budget; a tolerance or a fixed bound applies to the \
                         adaptive mesh (remove one of them)",
                        engine.name()
                    ));
                }
                tolerance = None;
            } else if profile.min_angle_deg > 0.0 {
                // The angle bound refines the tolerance search's meshes; a fixed bound's
                // mesh has none.
                match tolerance.as_mut() {
                    Some(t) => t.min_angle_deg = Some(profile.min_angle_deg),
                    None => {
                        return Err(format!(
                            "target = {:?} needs the model from a tolerance (its smallest \
                             triangle angle is bounded there) or method = \"grid\"; remove \
                             epsilon_um / epsilon_sq_fraction",
                            engine.name()
                        ))
                    }
                }
            }
            settings.format = if profile.ascii {
                StlFormat::Ascii
            } else {
                StlFormat::Binary
            };
            settings.solid.units = profile.units;
            if let Some(a) = settings.adaptive.as_mut() {
                a.solid.units = profile.units;
                a.kind = if profile.solid {
                    MeshKind::Solid
                } else {
                    MeshKind::Sheet
                };
                a.max_triangles = Some(profile.max_triangles);
            }
            settings.target = Some(profile);
        }
        settings.tolerance = tolerance;
        Ok(settings)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tolerance_key_is_the_one_the_config_reads() {
        let mut t = toml::Table::new();
        t.insert(MesherConfig::TOLERANCE_KEY.into(), "sa=2,sq=2,sz=5".into());
        let c: MesherConfig = toml::from_str(&toml::to_string(&t).unwrap()).unwrap();
        assert_eq!(c.tolerance, Some("sa=2,sq=2,sz=5".parse().unwrap()));
    }

    /// A graph's `curve = false` reaches the search; without the key the curve is made.
    #[test]
    fn the_curve_key_reaches_the_search() {
        let curve = |text: &str| {
            let c: MesherConfig = toml::from_str(text).unwrap();
            c.settings().unwrap().tolerance.map(|t| t.curve)
        };
        assert_eq!(curve(""), Some(true));
        assert_eq!(curve("curve = false"), Some(false));
        assert!(toml::from_str::<MesherConfig>("curve = \"off\"").is_err());
    }

    /// A choice given as text is refused with its key and the allowed values, as a graph
    /// file's value is.
    #[test]
    fn a_bad_choice_names_the_key_and_the_allowed_values() {
        let e = parse_choice::<LengthUnit>("units", "furlong").unwrap_err();
        assert!(e.starts_with("units = \"furlong\": "), "{e}");
        assert!(e.contains("`m`, `mm`, `um`"), "{e}");
        assert_eq!(
            parse_choice::<ModelMethod>("model_method", "greedy"),
            Ok(ModelMethod::Greedy)
        );
        let e = parse_choice::<StlFormat>("format", "obj").unwrap_err();
        assert!(e.contains("expected `binary` or `ascii`"), "{e}");
    }

    #[test]
    fn holes_need_a_sheet_and_the_stl_an_stl_name() {
        let holes = MesherConfig {
            missing: MissingSamples::Holes,
            ..MesherConfig::default()
        };
        assert!(holes
            .settings()
            .unwrap_err()
            .contains("needs kind = \"sheet\""));
        let sheet = MesherConfig {
            kind: MeshKind::Sheet,
            ..holes
        };
        assert!(sheet.settings().is_ok());
        let obj = MesherConfig {
            file: "wall.obj".into(),
            ..MesherConfig::default()
        };
        let e = obj.settings().unwrap_err();
        assert!(e.contains("wall.obj") && e.contains(".stl"), "{e}");
        let level = MesherConfig {
            level: true,
            ..MesherConfig::default()
        };
        assert_eq!(
            level.settings().unwrap().form_removed(),
            Some(LEAST_SQUARES_PLANE)
        );
    }
}
