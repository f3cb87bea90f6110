//! The setting of a finishing simulation: the media, the workpiece, and the machine's action on
//! the part (relative media velocity and pressure), derived from centrifugal barrel kinematics
//! or given directly. The setting's types, with every default stated, are finish.json's records
//! (`surfstream_core::record::finish`, re-exported here); their physics is here, as extension
//! traits: [`MediaPhysics`], [`PartMaterialPhysics`], [`BarrelKinematics`].

use anyhow::{bail, Result};

pub use surfstream_core::record::finish::{Action, BarrelMachine, Media, PartMaterial, Workpiece};

/// The part's material as the DEM's wall and a checked setting.
pub trait PartMaterialPhysics {
    /// The wall's elasticity for the DEM.
    fn workpiece(&self) -> Workpiece;

    /// Refuses a material that cannot run, naming the field.
    fn check(&self) -> Result<()>;
}

impl PartMaterialPhysics for PartMaterial {
    fn workpiece(&self) -> Workpiece {
        Workpiece {
            youngs_modulus_pa: self.youngs_modulus_pa,
            poisson_ratio: self.poisson_ratio,
        }
    }

    fn check(&self) -> Result<()> {
        for (field, v) in [
            ("youngs_modulus_pa", self.youngs_modulus_pa),
            ("hardness_pa", self.hardness_pa),
        ] {
            if !(v.is_finite() && v > 0.0) {
                bail!("part_material.{field} = {v}: expected a finite number > 0");
            }
        }
        if !(0.0..0.5).contains(&self.poisson_ratio) {
            bail!(
                "part_material.poisson_ratio = {}: expected 0 <= nu < 0.5",
                self.poisson_ratio
            );
        }
        Ok(())
    }
}

/// Default angle between the media's velocity and the part's plane: the bed slides along the
/// part, with a glancing normal component (an assumption; the DEM of the whole barrel would
/// give a distribution).
pub const DEFAULT_IMPACT_ANGLE_DEG: f64 = 20.0;

/// The centrifugal barrel's kinematics: what the machine does to the part.
pub trait BarrelKinematics {
    /// The relative velocity and pressure from the kinematics.
    ///
    /// With the barrel counter-rotating at `counter_rotation_rpm` relative to the turret, the
    /// centrifugal field (magnitude Omega^2 R from the turret's revolution) turns relative to
    /// the barrel at the counter-rotation rate omega: the media bed, which follows the field,
    /// slides past the barrel wall and the part held near it at v = omega * r_barrel. The bed
    /// presses on the part with p = packing * density * Omega^2 R * bed depth.
    fn action(&self, media: &Media, impact_angle_deg: f64) -> Result<Action>;
}

impl BarrelKinematics for BarrelMachine {
    fn action(&self, media: &Media, impact_angle_deg: f64) -> Result<Action> {
        for (name, v) in [
            ("revolution_rpm", self.revolution_rpm),
            ("revolution_radius_mm", self.revolution_radius_mm),
            ("counter_rotation_rpm", self.counter_rotation_rpm),
            ("barrel_radius_mm", self.barrel_radius_mm),
            ("bed_depth_mm", self.bed_depth_mm),
            ("packing_fraction", self.packing_fraction),
        ] {
            if !(v.is_finite() && v > 0.0) {
                bail!("machine.{name} = {v}: expected a finite number > 0");
            }
        }
        let omega_rev = self.revolution_rpm * std::f64::consts::TAU / 60.0;
        let omega_rot = self.counter_rotation_rpm * std::f64::consts::TAU / 60.0;
        let accel = omega_rev * omega_rev * self.revolution_radius_mm * 1e-3;
        Ok(Action {
            media_velocity_m_s: omega_rot * self.barrel_radius_mm * 1e-3,
            impact_angle_deg,
            pressure_pa: self.packing_fraction
                * media.density_kg_m3
                * accel
                * self.bed_depth_mm
                * 1e-3,
            acceleration_m_s2: accel,
            source: format!(
                "centrifugal barrel: {} r/min revolution at {} mm, {} r/min counter-rotation, \
                 barrel radius {} mm, bed {} mm at packing {}",
                self.revolution_rpm,
                self.revolution_radius_mm,
                self.counter_rotation_rpm,
                self.barrel_radius_mm,
                self.bed_depth_mm,
                self.packing_fraction
            ),
        })
    }
}

/// The media as spheres: their size, mass and load, and a checked setting.
pub trait MediaPhysics {
    fn radius_m(&self) -> f64;
    fn mass_kg(&self) -> f64;
    /// Refuses media that cannot run, naming the field.
    fn validate(&self) -> Result<()>;
    /// The normal load one medium carries: the pressure over its share of a hexagonally packed
    /// layer (2 sqrt(3) r^2), N.
    fn load_n(&self, pressure_pa: f64) -> f64;
}

impl MediaPhysics for Media {
    fn radius_m(&self) -> f64 {
        self.diameter_mm * 0.5e-3
    }

    fn mass_kg(&self) -> f64 {
        let r = self.radius_m();
        self.density_kg_m3 * 4.0 / 3.0 * std::f64::consts::PI * r * r * r
    }

    fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("diameter_mm", self.diameter_mm),
            ("density_kg_m3", self.density_kg_m3),
            ("youngs_modulus_pa", self.youngs_modulus_pa),
            ("restitution", self.restitution),
        ] {
            if !(v.is_finite() && v > 0.0) {
                bail!("media.{name} = {v}: expected a finite number > 0");
            }
        }
        if !(0.0..0.5).contains(&self.poisson_ratio) {
            bail!(
                "media.poisson_ratio = {}: expected 0 <= nu < 0.5",
                self.poisson_ratio
            );
        }
        if self.restitution > 1.0 {
            bail!(
                "media.restitution = {}: expected 0 < e <= 1",
                self.restitution
            );
        }
        if !(self.friction.is_finite() && self.friction >= 0.0) {
            bail!("media.friction = {}: expected >= 0", self.friction);
        }
        Ok(())
    }

    fn load_n(&self, pressure_pa: f64) -> f64 {
        let r = self.radius_m();
        pressure_pa * 2.0 * 3f64.sqrt() * r * r
    }
}

/// Hertz: effective modulus of media against the part, Pa.
pub fn effective_modulus_pa(media: &Media, part: &Workpiece) -> f64 {
    1.0 / ((1.0 - media.poisson_ratio.powi(2)) / media.youngs_modulus_pa
        + (1.0 - part.poisson_ratio.powi(2)) / part.youngs_modulus_pa)
}

/// Duration of a Hertz sphere-plane impact at normal speed `v_n`, s
/// (2.87 (m^2 / (R E*^2 v_n))^(1/5)).
pub fn hertz_contact_time_s(media: &Media, part: &Workpiece, v_n: f64) -> f64 {
    let m = media.mass_kg();
    let e = effective_modulus_pa(media, part);
    2.87 * (m * m / (media.radius_m() * e * e * v_n.max(1e-3))).powf(0.2)
}

/// The Rayleigh time of the media, s: the stability bound DEM codes quote for the time step.
pub fn rayleigh_time_s(media: &Media) -> f64 {
    let g = media.youngs_modulus_pa / (2.0 * (1.0 + media.poisson_ratio));
    std::f64::consts::PI * media.radius_m() * (media.density_kg_m3 / g).sqrt()
        / (0.1631 * media.poisson_ratio + 0.8766)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_papers_barrel_gives_its_velocity_and_pressure() {
        let m = Media::default();
        let a = BarrelMachine::default().action(&m, 20.0).unwrap();
        // Omega = 10 pi rad/s; Omega^2 R = 133.2 m/s^2 (13.6 g); v = 10 pi * 0.05 = 1.571 m/s.
        assert!((a.acceleration_m_s2 - 133.24).abs() < 0.05, "{a:?}");
        // 0.05 m x 10 pi rad/s = pi / 2 m/s.
        assert!(
            (a.media_velocity_m_s - std::f64::consts::FRAC_PI_2).abs() < 1e-9,
            "{a:?}"
        );
        // 0.6 * 2500 * 133.24 * 0.02 = 3997 Pa.
        assert!((a.pressure_pa - 3997.2).abs() < 1.0, "{a:?}");
        let bad = BarrelMachine {
            barrel_radius_mm: -1.0,
            ..Default::default()
        };
        assert!(bad
            .action(&m, 20.0)
            .unwrap_err()
            .to_string()
            .contains("machine.barrel_radius_mm = -1"));
    }

    #[test]
    fn contact_times_are_microseconds_for_millimetre_ceramic_spheres() {
        let m = Media::default();
        let t = hertz_contact_time_s(&m, &Workpiece::default(), 0.5);
        assert!(t > 1e-6 && t < 3e-5, "{t}");
        let r = rayleigh_time_s(&m);
        assert!(r > 1e-7 && r < 1e-5, "{r}");
    }
}
