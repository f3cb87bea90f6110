//! Archard wear from LIGGGHTS' contact dump.
//!
//! LIGGGHTS has no Archard model; `compute wall/gran/local pos vel id force` dumped with
//! `dump local` every `every` steps gives, per particle-wall contact, the contact point on the
//! wall, the particle's centre, both velocities, the triangle and the force. Archard's law,
//! V = (K / H) * F_n * s, is summed over the samples: each sample stands for `every * dt` of
//! sliding at its slip speed. The normal is the direction from the contact point to the
//! particle's centre; the slip is the tangential part of the relative velocity of the centres
//! (the particle's spin is not in the dump, so rolling is counted as sliding). A negative
//! normal force (the damping term pulling on separation) is clipped to zero.

use std::io::BufRead;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};

/// Columns of `compute wall/gran/local pos vel id force`.
pub const CONTACT_COLUMNS: usize = 18;

/// One sampled contact's Archard volume, placed at its contact point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactWear {
    /// Contact point on the wall, m.
    pub x_m: f64,
    pub y_m: f64,
    /// Archard volume this sample stands for, m^3.
    pub volume_m3: f64,
    /// Normal force, N (clipped at 0).
    pub normal_force_n: f64,
}

/// What the dump held.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct ContactSummary {
    pub samples: usize,
    pub snapshots: usize,
    pub clipped_negative_normal_forces: usize,
    pub max_normal_force_n: f64,
    pub total_volume_m3: f64,
    /// Most contacts of the medium in one snapshot (one per medium when the mesh's triangles
    /// are one surface to LIGGGHTS, [`crate::passes`]).
    pub max_contacts_per_snapshot: usize,
    /// Largest sum of the normal forces of one snapshot, N.
    pub max_snapshot_normal_force_n: f64,
}

/// Reads a `dump local` file of [`CONTACT_COLUMNS`] columns and returns the Archard volume of
/// every sample, with `k_over_h_per_pa` = K / H (1/Pa) and `sample_dt_s` = dump interval x dt.
pub fn archard_from_dump(
    path: &Path,
    k_over_h_per_pa: f64,
    sample_dt_s: f64,
) -> Result<(Vec<ContactWear>, ContactSummary)> {
    let file = std::fs::File::open(path)
        .with_context(|| format!("{}: cannot read the contact dump", path.display()))?;
    let mut out = Vec::new();
    let mut summary = ContactSummary::default();
    let mut lines = std::io::BufReader::new(file).lines();
    let mut line_no = 0usize;
    while let Some(line) = lines.next() {
        let line = line.with_context(|| format!("{}: read failed", path.display()))?;
        line_no += 1;
        if !line.starts_with("ITEM: NUMBER OF ENTRIES") {
            continue;
        }
        let count_line = lines
            .next()
            .ok_or_else(|| anyhow!("{}: truncated after line {line_no}", path.display()))??;
        line_no += 1;
        let count: usize = count_line.trim().parse().map_err(|_| {
            anyhow!(
                "{}: line {line_no}: expected an entry count, found {count_line:?}",
                path.display()
            )
        })?;
        summary.snapshots += 1;
        summary.max_contacts_per_snapshot = summary.max_contacts_per_snapshot.max(count);
        let mut snapshot_force = 0.0;
        // Skip to the ENTRIES line (box bounds in between).
        loop {
            let l = lines
                .next()
                .ok_or_else(|| anyhow!("{}: truncated after line {line_no}", path.display()))??;
            line_no += 1;
            if l.starts_with("ITEM: ENTRIES") {
                break;
            }
        }
        for _ in 0..count {
            let l = lines
                .next()
                .ok_or_else(|| anyhow!("{}: truncated after line {line_no}", path.display()))??;
            line_no += 1;
            let v: Vec<f64> = l
                .split_whitespace()
                .map(str::parse)
                .collect::<Result<_, _>>()
                .map_err(|_| anyhow!("{}: line {line_no}: not numbers", path.display()))?;
            if v.len() != CONTACT_COLUMNS {
                bail!(
                    "{}: line {line_no}: {} columns, expected {CONTACT_COLUMNS} (pos vel id force)",
                    path.display(),
                    v.len()
                );
            }
            let w = contact_wear(&v, k_over_h_per_pa, sample_dt_s);
            if w.normal_force_n == 0.0 && raw_normal_force(&v) < 0.0 {
                summary.clipped_negative_normal_forces += 1;
            }
            summary.samples += 1;
            summary.max_normal_force_n = summary.max_normal_force_n.max(w.normal_force_n);
            summary.total_volume_m3 += w.volume_m3;
            snapshot_force += w.normal_force_n;
            out.push(w);
        }
        summary.max_snapshot_normal_force_n =
            summary.max_snapshot_normal_force_n.max(snapshot_force);
    }
    Ok((out, summary))
}

fn normal_of(v: &[f64]) -> [f64; 3] {
    let n = [v[3] - v[0], v[4] - v[1], v[5] - v[2]];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 {
        [n[0] / len, n[1] / len, n[2] / len]
    } else {
        [0.0, 0.0, 1.0]
    }
}

fn raw_normal_force(v: &[f64]) -> f64 {
    let n = normal_of(v);
    v[15] * n[0] + v[16] * n[1] + v[17] * n[2]
}

/// Archard volume of one dumped contact row (see the module doc for the columns).
pub fn contact_wear(v: &[f64], k_over_h_per_pa: f64, sample_dt_s: f64) -> ContactWear {
    let n = normal_of(v);
    let fn_ = raw_normal_force(v).max(0.0);
    let rel = [v[9] - v[6], v[10] - v[7], v[11] - v[8]];
    let vn = rel[0] * n[0] + rel[1] * n[1] + rel[2] * n[2];
    let t = [rel[0] - vn * n[0], rel[1] - vn * n[1], rel[2] - vn * n[2]];
    let slip = (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt();
    ContactWear {
        x_m: v[0],
        y_m: v[1],
        volume_m3: k_over_h_per_pa * fn_ * slip * sample_dt_s,
        normal_force_n: fn_,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn archard_is_k_over_h_times_normal_force_times_slip() {
        // Contact at (1, 2, 0), particle above, sliding 2 m/s along x and approaching at 1 m/s;
        // force 3 N normal, 0.5 N tangential.
        let row = [
            1.0, 2.0, 0.0, 1.0, 2.0, 1.5, 0.0, 0.0, 0.0, 2.0, 0.0, -1.0, 0.0, 7.0, 1.0, -0.5, 0.0,
            3.0,
        ];
        let w = contact_wear(&row, 1e-3, 0.1);
        assert!(
            (w.volume_m3 - 1e-3 * 3.0 * 2.0 * 0.1).abs() < 1e-15,
            "{w:?}"
        );
        assert_eq!((w.x_m, w.y_m), (1.0, 2.0));
        let mut pulling = row;
        pulling[17] = -3.0;
        assert_eq!(contact_wear(&pulling, 1e-3, 0.1).volume_m3, 0.0);
    }

    #[test]
    fn reads_a_dump_and_names_a_bad_row() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.txt");
        let row = "1 2 0 1 2 1.5 0 0 0 2 0 -1 0 7 1 0 0 3";
        std::fs::write(
            &p,
            format!(
                "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ENTRIES\n0\nITEM: BOX BOUNDS ff ff ff\n0 1\n0 1\n0 1\nITEM: ENTRIES a\n\
                 ITEM: TIMESTEP\n5\nITEM: NUMBER OF ENTRIES\n2\nITEM: BOX BOUNDS ff ff ff\n0 1\n0 1\n0 1\nITEM: ENTRIES a\n{row}\n{row}\n"
            ),
        )
        .unwrap();
        let (w, s) = archard_from_dump(&p, 1.0, 1.0).unwrap();
        assert_eq!((w.len(), s.snapshots), (2, 2));
        assert_eq!(s.max_contacts_per_snapshot, 2);
        assert!((s.max_snapshot_normal_force_n - 6.0).abs() < 1e-12);
        assert!((s.total_volume_m3 - 12.0).abs() < 1e-12);
        std::fs::write(&p, "ITEM: NUMBER OF ENTRIES\n1\nITEM: ENTRIES a\n1 2 3\n").unwrap();
        let e = archard_from_dump(&p, 1.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("3 columns, expected 18"), "{e}");
    }
}
