//! STL output: size, header, and a read-back through small independent readers of both formats;
//! the read-back triangles, welded by position as a simulator would, still form a closed solid.

mod common;

use std::collections::HashMap;

use common::*;
use surfstream_mesher::stl::{binary_stl_len, stl_header};
use surfstream_mesher::{
    check_closed, write_stl_ascii, write_stl_binary, LengthUnit, SolidMesh, SolidParams,
};

/// One facet as stored: normal and three corners, f32.
type Facet = [[f32; 3]; 4];

fn read_binary(bytes: &[u8]) -> (String, Vec<Facet>) {
    assert!(bytes.len() >= 84, "shorter than a header");
    let header = String::from_utf8_lossy(&bytes[..80])
        .trim_end_matches('\0')
        .to_string();
    let count = u32::from_le_bytes(bytes[80..84].try_into().unwrap()) as usize;
    assert_eq!(
        bytes.len(),
        84 + 50 * count,
        "size disagrees with the count"
    );
    let f = |at: usize| f32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
    let facets = (0..count)
        .map(|t| {
            let at = 84 + 50 * t;
            assert_eq!(&bytes[at + 48..at + 50], &[0, 0], "attribute");
            std::array::from_fn(|r| std::array::from_fn(|c| f(at + 12 * r + 4 * c)))
        })
        .collect();
    (header, facets)
}

fn read_ascii(text: &str) -> (String, Vec<Facet>) {
    let mut lines = text.lines().map(str::trim);
    let solid = lines.next().expect("solid line");
    assert!(solid.starts_with("solid "), "{solid}");
    let mut facets = Vec::new();
    let parse3 = |words: &[&str]| -> [f32; 3] {
        std::array::from_fn(|k| words[k].parse().expect("a number"))
    };
    loop {
        let line = lines.next().expect("endsolid");
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["endsolid", ..] => break,
            ["facet", "normal", n @ ..] => {
                let normal = parse3(n);
                assert_eq!(lines.next(), Some("outer loop"));
                let mut facet = [normal, [0.0; 3], [0.0; 3], [0.0; 3]];
                for corner in facet.iter_mut().skip(1) {
                    let words: Vec<&str> = lines.next().unwrap().split_whitespace().collect();
                    assert_eq!(words[0], "vertex");
                    *corner = parse3(&words[1..]);
                }
                assert_eq!(lines.next(), Some("endloop"));
                assert_eq!(lines.next(), Some("endfacet"));
                facets.push(facet);
            }
            other => panic!("unexpected line {other:?}"),
        }
    }
    assert_eq!(lines.next(), None, "text after endsolid");
    (solid.to_string(), facets)
}

/// Welds facets by their f32 positions into an indexed mesh, as an STL importer does.
fn weld(facets: &[Facet], units: LengthUnit) -> SolidMesh {
    let mut index: HashMap<[u32; 3], u32> = HashMap::new();
    let mut vertices = Vec::new();
    let triangles = facets
        .iter()
        .map(|f| {
            std::array::from_fn(|k| {
                let p = f[k + 1];
                *index.entry(p.map(f32::to_bits)).or_insert_with(|| {
                    vertices.push(p.map(f64::from));
                    (vertices.len() - 1) as u32
                })
            })
        })
        .collect();
    SolidMesh {
        vertices,
        triangles,
        offset_um: [0.0; 3],
        units,
        filled_samples: 0,
        top_triangles: 0,
        base_depth_um: 0.0,
    }
}

fn expected_facets(mesh: &SolidMesh) -> Vec<Facet> {
    (0..mesh.triangles.len())
        .map(|t| {
            let [a, b, c] = mesh.triangle_corners(t);
            [mesh.face_normal(t), a, b, c].map(|v| v.map(|x| x as f32))
        })
        .collect()
}

fn fixture_mesh() -> SolidMesh {
    solid(field_3x4(&HEIGHTS_3X4_UM), &SolidParams::default()).unwrap()
}

#[test]
fn binary_stl_has_the_right_size_and_reads_back() {
    let mesh = fixture_mesh();
    let mut bytes = Vec::new();
    write_stl_binary(&mut bytes, &mesh, "surfstream solid").unwrap();
    assert_eq!(bytes.len(), 84 + 50 * 42);
    assert_eq!(bytes.len() as u64, binary_stl_len(mesh.triangles.len()));

    let (header, facets) = read_binary(&bytes);
    assert_eq!(header, stl_header(&mesh, "surfstream solid"));
    assert!(
        header.starts_with("surfstream solid, units=mm, offset_um=12346.350,-7889.300,"),
        "{header}"
    );
    assert_eq!(facets, expected_facets(&mesh));
    for f in &facets {
        let len = f[0].iter().map(|c| c * c).sum::<f32>().sqrt();
        assert!((len - 1.0).abs() < 1e-6, "unit normal");
    }

    // What a simulator sees after welding by position is still a closed, outward solid.
    let welded = weld(&facets, mesh.units);
    assert_eq!(welded.vertices.len(), mesh.vertices.len());
    let check = check_closed(&welded);
    assert!(check.watertight && check.signed_volume > 0.0, "{check:?}");
    let original = check_closed(&mesh).signed_volume;
    assert!((check.signed_volume - original).abs() < 1e-6 * original);
}

#[test]
fn ascii_stl_reads_back_to_the_binary_triangles() {
    let mesh = fixture_mesh();
    let mut text = Vec::new();
    write_stl_ascii(&mut text, &mesh, "surfstream solid").unwrap();
    let text = String::from_utf8(text).unwrap();
    let (solid, facets) = read_ascii(&text);
    assert_eq!(
        solid,
        format!(
            "solid surfstream_solid units=mm offset_um={:.3},{:.3},{:.3}",
            mesh.offset_um[0], mesh.offset_um[1], mesh.offset_um[2]
        )
    );
    assert!(text.ends_with("endsolid surfstream_solid\n"));

    let mut bytes = Vec::new();
    write_stl_binary(&mut bytes, &mesh, "surfstream solid").unwrap();
    let (_, binary) = read_binary(&bytes);
    // Bit-identical f32 values: both formats describe the very same triangles.
    assert_eq!(facets, binary);
}

#[test]
fn larger_mesh_survives_both_formats_in_every_unit() {
    let (w, h) = (40, 33);
    let heights = wavy_heights_um(h, w);
    let map = Map::new(&heights, h, w, 0.8148, 0.8148).with_origin(2.0e4, 1.0e4);
    for units in [LengthUnit::M, LengthUnit::Mm, LengthUnit::Um] {
        let params = SolidParams {
            units,
            ..SolidParams::default()
        };
        let mesh = solid(map, &params).unwrap();
        let mut bytes = Vec::new();
        write_stl_binary(&mut bytes, &mesh, "").unwrap();
        let (header, facets) = read_binary(&bytes);
        assert!(
            header.starts_with(&format!("units={}, ", units.symbol())),
            "{header}"
        );
        let mut text = Vec::new();
        write_stl_ascii(&mut text, &mesh, "").unwrap();
        let (solid, ascii) = read_ascii(std::str::from_utf8(&text).unwrap());
        assert!(solid.starts_with("solid surfstream units="), "{solid}");
        assert_eq!(facets, ascii);
        let welded = check_closed(&weld(&facets, units));
        assert!(
            welded.watertight && welded.signed_volume > 0.0,
            "{units:?}: {welded:?}"
        );
    }
}

#[test]
fn writes_to_a_file() {
    // An unbuffered File is fine: the writers hand over large blocks.
    let mesh = fixture_mesh();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("surface.stl");
    let file = std::fs::File::create(&path).unwrap();
    write_stl_binary(file, &mesh, "surfstream solid").unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(bytes.len() as u64, binary_stl_len(mesh.triangles.len()));
    assert_eq!(read_binary(&bytes).1, expected_facets(&mesh));
}
