//! Reads the legacy-VTK triangle meshes that LIGGGHTS' `dump mesh/vtk` writes: the triangles'
//! corners and their cell fields (`wear`, `area`, ...).
//!
//! LIGGGHTS 3.8 writes `# vtk DataFile Version 5.1`: POLYGONS followed by OFFSETS and
//! CONNECTIVITY arrays; older writers list each cell as `3 a b c`. Both are read.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};

/// Triangles with their per-cell fields.
#[derive(Debug, Clone, Default)]
pub struct VtkMesh {
    /// Corners of each triangle, in the file's length unit (m for LIGGGHTS in SI).
    pub triangles: Vec<[[f64; 3]; 3]>,
    /// Cell fields by name, one value per triangle (first component of multi-component fields).
    pub cell_fields: BTreeMap<String, Vec<f64>>,
}

impl VtkMesh {
    pub fn field(&self, name: &str) -> Result<&[f64]> {
        self.cell_fields
            .get(name)
            .map(Vec::as_slice)
            .ok_or_else(|| {
                anyhow!(
                    "VTK mesh has no cell field '{name}' (fields: {})",
                    self.cell_fields
                        .keys()
                        .cloned()
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            })
    }
}

pub fn read_vtk(path: &Path) -> Result<VtkMesh> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read the VTK mesh", path.display()))?;
    parse_vtk(&text).with_context(|| format!("{}", path.display()))
}

/// Parses the text of a legacy ASCII VTK POLYDATA file of triangles.
pub fn parse_vtk(text: &str) -> Result<VtkMesh> {
    let mut lines = text.lines();
    // Header: version line, title, ASCII, DATASET.
    let mut header = Vec::new();
    for _ in 0..4 {
        header.push(lines.next().unwrap_or(""));
    }
    if !header[0].starts_with("# vtk DataFile") {
        bail!("not a legacy VTK file (first line {:?})", header[0]);
    }
    if header[2].trim() != "ASCII" {
        bail!("expected an ASCII VTK file, found {:?}", header[2]);
    }
    let rest: Vec<&str> = lines.flat_map(str::split_whitespace).collect();
    let mut t = Tokens { t: &rest, i: 0 };
    let mut points: Vec<[f64; 3]> = Vec::new();
    let mut cells: Vec<[usize; 3]> = Vec::new();
    let mut fields = BTreeMap::new();
    let mut n_cells = None;
    while let Some(word) = t.next() {
        match word {
            "POINTS" => {
                let n = t.usize()?;
                t.next(); // type
                points.reserve(n);
                for _ in 0..n {
                    points.push([t.f64()?, t.f64()?, t.f64()?]);
                }
            }
            "POLYGONS" => {
                let a = t.usize()?;
                let b = t.usize()?;
                if t.peek() == Some("OFFSETS") {
                    t.next();
                    t.next(); // type
                    let offsets: Vec<usize> = (0..a).map(|_| t.usize()).collect::<Result<_>>()?;
                    if t.next() != Some("CONNECTIVITY") {
                        bail!("POLYGONS: OFFSETS not followed by CONNECTIVITY");
                    }
                    t.next();
                    let conn: Vec<usize> = (0..b).map(|_| t.usize()).collect::<Result<_>>()?;
                    for w in offsets.windows(2) {
                        if w[1] != w[0] + 3 || w[1] > conn.len() {
                            bail!("POLYGONS: a cell that is not a triangle (offsets {w:?})");
                        }
                        cells.push([conn[w[0]], conn[w[0] + 1], conn[w[0] + 2]]);
                    }
                } else {
                    for _ in 0..a {
                        let k = t.usize()?;
                        if k != 3 {
                            bail!("POLYGONS: a cell with {k} corners, expected triangles");
                        }
                        cells.push([t.usize()?, t.usize()?, t.usize()?]);
                    }
                }
            }
            "CELL_DATA" => n_cells = Some(t.usize()?),
            "POINT_DATA" => break, // nothing read past the cell data
            "FIELD" => {
                t.next(); // name
                let arrays = t.usize()?;
                for _ in 0..arrays {
                    let name = t
                        .next()
                        .ok_or_else(|| anyhow!("FIELD: missing array name"))?
                        .to_string();
                    let comps = t.usize()?;
                    let tuples = t.usize()?;
                    t.next(); // type
                    let mut v = Vec::with_capacity(tuples);
                    for _ in 0..tuples {
                        v.push(t.f64()?);
                        for _ in 1..comps {
                            t.f64()?;
                        }
                    }
                    fields.insert(name, v);
                }
            }
            "SCALARS" => {
                let name = t
                    .next()
                    .ok_or_else(|| anyhow!("SCALARS: missing name"))?
                    .to_string();
                t.next(); // type
                let mut comps = 1;
                if t.peek().is_some_and(|w| w.parse::<usize>().is_ok()) {
                    comps = t.usize()?;
                }
                if t.peek() == Some("LOOKUP_TABLE") {
                    t.next();
                    t.next();
                }
                let n = n_cells.ok_or_else(|| anyhow!("SCALARS before CELL_DATA"))?;
                let mut v = Vec::with_capacity(n);
                for _ in 0..n {
                    v.push(t.f64()?);
                    for _ in 1..comps {
                        t.f64()?;
                    }
                }
                fields.insert(name, v);
            }
            _ => {}
        }
    }
    let mut triangles = Vec::with_capacity(cells.len());
    for c in &cells {
        let p = |k: usize| {
            points
                .get(k)
                .copied()
                .ok_or_else(|| anyhow!("cell refers to point {k} of {}", points.len()))
        };
        triangles.push([p(c[0])?, p(c[1])?, p(c[2])?]);
    }
    for (name, v) in &fields {
        if v.len() != triangles.len() {
            bail!(
                "cell field '{name}' has {} values for {} triangles",
                v.len(),
                triangles.len()
            );
        }
    }
    Ok(VtkMesh {
        triangles,
        cell_fields: fields,
    })
}

struct Tokens<'a> {
    t: &'a [&'a str],
    i: usize,
}

impl<'a> Tokens<'a> {
    fn next(&mut self) -> Option<&'a str> {
        let w = self.t.get(self.i).copied();
        self.i += 1;
        w
    }
    fn peek(&self) -> Option<&'a str> {
        self.t.get(self.i).copied()
    }
    fn usize(&mut self) -> Result<usize> {
        let w = self
            .next()
            .ok_or_else(|| anyhow!("unexpected end of file"))?;
        w.parse()
            .map_err(|_| anyhow!("expected a count, found {w:?}"))
    }
    fn f64(&mut self) -> Result<f64> {
        let w = self
            .next()
            .ok_or_else(|| anyhow!("unexpected end of file"))?;
        w.parse()
            .map_err(|_| anyhow!("expected a number, found {w:?}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_version_5_offsets_and_the_old_cell_list() {
        let v5 = "# vtk DataFile Version 5.1\nGenerated by LIGGGHTS\nASCII\nDATASET POLYDATA\n\
            POINTS 6 float\n0 0 0 1 0 0 1 1 0\n0 0 0 1 1 0 0 1 0\n\
            POLYGONS 3 6\nOFFSETS vtktypeint64\n0 3 6\nCONNECTIVITY vtktypeint64\n0 1 2 3 4 5\n\
            CELL_DATA 2\nFIELD FieldData 2\nwear 1 2 double\n1e-9 0\narea 1 2 double\n0.5 0.5\n";
        let m = parse_vtk(v5).unwrap();
        assert_eq!(m.triangles.len(), 2);
        assert_eq!(m.triangles[1][1], [1.0, 1.0, 0.0]);
        assert_eq!(m.field("wear").unwrap(), &[1e-9, 0.0]);
        assert!(m.field("stress").unwrap_err().to_string().contains("wear"));
        let old = "# vtk DataFile Version 2.0\nx\nASCII\nDATASET POLYDATA\n\
            POINTS 3 float\n0 0 0 1 0 0 1 1 0\nPOLYGONS 1 4\n3 0 1 2\n\
            CELL_DATA 1\nSCALARS wear double 1\nLOOKUP_TABLE default\n2.5\n";
        let m = parse_vtk(old).unwrap();
        assert_eq!(m.field("wear").unwrap(), &[2.5]);
        assert!(parse_vtk("hello").is_err());
        let short = v5.replace("0.5 0.5\n", "0.5\n");
        assert!(parse_vtk(&short).is_err());
    }
}
