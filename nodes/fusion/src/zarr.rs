//! The panorama as a Zarr v3 array (issue 17): a chunked format that zarr-python, xarray,
//! napari and other standard tools open without reading the whole file, for scans whose
//! panorama is too large for a single `.npy` to be handy.
//!
//! Written by hand rather than through a Zarr crate: an uncompressed Zarr v3 array is one
//! JSON document and one raw file per chunk (Zarr v3 core specification: regular chunk grid,
//! default chunk key encoding with "/", the `bytes` codec, little endian), and the Rust Zarr
//! implementation would add about a hundred crates to the build for that.
//!
//! Layout of `NAME.zarr/`:
//! - `zarr.json`: `shape` [rows, cols], `data_type` "float32" or "float64" (absolute heights
//!   in um, the dtype of `panorama.npy`: float32 when the frames carry no z offset), `chunk_grid` regular with `chunk_shape` [[`ZARR_CHUNK_PX`]; 2],
//!   `fill_value` "NaN" (not measured), `dimension_names` ["y", "x"] (row index grows with
//!   y), and `attributes` with the pitch and the scan position of pixel (0, 0) in um.
//! - `c/<i>/<j>`: chunk (row block i, column block j), `ZARR_CHUNK_PX^2` little-endian values,
//!   row-major; edge chunks are padded with NaN to the full chunk shape, as the spec asks.
//!   Chunks with no measured pixel are not written (they read as the fill value).
//!
//! The store is written into `NAME.zarr.partial/` and renamed when complete: a failed write
//! leaves no half store under the final name.

use std::path::Path;

use anyhow::{Context, Result};
use serde::Serialize;
use surfstream_core::Sampling;

/// Chunk side of the written array, px.
pub const ZARR_CHUNK_PX: usize = 512;

/// zarr.json of the panorama's array (Zarr v3 array metadata).
#[derive(Serialize)]
struct ZarrArrayMeta {
    zarr_format: u32,
    node_type: &'static str,
    shape: [usize; 2],
    data_type: &'static str,
    chunk_grid: Named<ChunkShape>,
    chunk_key_encoding: Named<Separator>,
    fill_value: &'static str,
    codecs: [Named<Endian>; 1],
    dimension_names: [&'static str; 2],
    attributes: Attributes,
}

/// Zarr's `{"name": .., "configuration": {..}}` of a grid, key encoding or codec.
#[derive(Serialize)]
struct Named<C> {
    name: &'static str,
    configuration: C,
}

#[derive(Serialize)]
struct ChunkShape {
    chunk_shape: [usize; 2],
}

#[derive(Serialize)]
struct Separator {
    separator: &'static str,
}

#[derive(Serialize)]
struct Endian {
    endian: &'static str,
}

#[derive(Serialize)]
struct Attributes {
    surfstream: PanoramaAttributes,
}

/// What surfstream adds to the array: what the heights are, the pitch and origin, um.
#[derive(Serialize)]
struct PanoramaAttributes {
    what: &'static str,
    pitch_x_um: f64,
    pitch_y_um: f64,
    origin_x_um: f64,
    origin_y_um: f64,
}

/// Writes `dir/NAME.zarr` from f32 frame heights (row-major, relative to `z_offset_um`,
/// sampled as `at` says: its shape, and the pitch and origin written to the attributes) as
/// absolute heights `f64::from(z) + z_offset_um`, the same values and dtype as the `.npy`
/// (float32 without an offset, [`surfstream_io::npy::absolute_fits_f32`]). Returns the store's
/// name.
pub fn write_zarr_abs(
    dir: &Path,
    name: &str,
    heights: &[f32],
    at: &Sampling,
    z_offset_um: f64,
) -> Result<String> {
    let (rows, cols) = (at.rows(), at.cols());
    let store = format!("{name}.zarr");
    let final_path = dir.join(&store);
    let partial = dir.join(format!("{store}.partial"));
    if heights.len() != rows * cols {
        anyhow::bail!(
            "{}: cannot write {rows} x {cols} array: got {} values",
            final_path.display(),
            heights.len()
        );
    }
    if partial.exists() {
        std::fs::remove_dir_all(&partial)
            .with_context(|| format!("{}: cannot remove", partial.display()))?;
    }
    std::fs::create_dir_all(&partial)
        .with_context(|| format!("{}: cannot create", partial.display()))?;
    let c = ZARR_CHUNK_PX;
    let f32_data = surfstream_io::npy::absolute_fits_f32(z_offset_um);
    let meta = ZarrArrayMeta {
        zarr_format: 3,
        node_type: "array",
        shape: [rows, cols],
        data_type: if f32_data { "float32" } else { "float64" },
        chunk_grid: Named {
            name: "regular",
            configuration: ChunkShape {
                chunk_shape: [c, c],
            },
        },
        chunk_key_encoding: Named {
            name: "default",
            configuration: Separator { separator: "/" },
        },
        fill_value: "NaN",
        codecs: [Named {
            name: "bytes",
            configuration: Endian { endian: "little" },
        }],
        dimension_names: ["y", "x"],
        attributes: Attributes {
            surfstream: PanoramaAttributes {
                what:
                    "panorama: absolute heights in um, NaN = not measured, row index grows with y",
                pitch_x_um: at.pitch_x_um(),
                pitch_y_um: at.pitch_y_um(),
                origin_x_um: at.origin_x_um(),
                origin_y_um: at.origin_y_um(),
            },
        },
    };
    // Through a JSON value: its keys sorted, as the file has always had them.
    let meta = serde_json::to_value(&meta)?;
    let meta_path = partial.join("zarr.json");
    std::fs::write(&meta_path, serde_json::to_vec_pretty(&meta)?)
        .with_context(|| format!("{}: write failed", meta_path.display()))?;
    let mut buf: Vec<u8> = Vec::with_capacity(c * c * 8);
    for bi in 0..rows.div_ceil(c) {
        let row_dir = partial.join("c").join(bi.to_string());
        let mut made = false;
        for bj in 0..cols.div_ceil(c) {
            surfstream_core::liveness::beat();
            buf.clear();
            let mut measured = false;
            for r in bi * c..(bi + 1) * c {
                for col in bj * c..(bj + 1) * c {
                    let v = if r < rows && col < cols {
                        let z = heights[r * cols + col];
                        measured |= !z.is_nan();
                        z
                    } else {
                        f32::NAN
                    };
                    if f32_data {
                        buf.extend_from_slice(&v.to_le_bytes());
                    } else {
                        buf.extend_from_slice(&(f64::from(v) + z_offset_um).to_le_bytes());
                    }
                }
            }
            if !measured {
                continue;
            }
            if !made {
                std::fs::create_dir_all(&row_dir)
                    .with_context(|| format!("{}: cannot create", row_dir.display()))?;
                made = true;
            }
            let p = row_dir.join(bj.to_string());
            std::fs::write(&p, &buf).with_context(|| format!("{}: write failed", p.display()))?;
        }
    }
    if final_path.exists() {
        std::fs::remove_dir_all(&final_path)
            .with_context(|| format!("{}: cannot replace", final_path.display()))?;
    }
    std::fs::rename(&partial, &final_path)
        .with_context(|| format!("{}: cannot move into place", final_path.display()))?;
    Ok(store)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;
    use surfstream_core::Shape;

    #[test]
    fn the_typed_metadata_is_byte_identical_to_the_json_value_it_replaces() {
        let dir = tempfile::tempdir().unwrap();
        let at = Sampling::new(Shape::new(2, 3), 0.5, 0.25)
            .unwrap()
            .with_origin(1.0, -2.0)
            .unwrap();
        let name = write_zarr_abs(dir.path(), "p", &[0.0; 6], &at, 100.0).unwrap();
        let c = ZARR_CHUNK_PX;
        let old = json!({
            "zarr_format": 3,
            "node_type": "array",
            "shape": [2, 3],
            "data_type": "float64",
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [c, c]}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": "NaN",
            "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}],
            "dimension_names": ["y", "x"],
            "attributes": {
                "surfstream": {
                    "what": "panorama: absolute heights in um, NaN = not measured, row index grows with y",
                    "pitch_x_um": 0.5,
                    "pitch_y_um": 0.25,
                    "origin_x_um": 1.0,
                    "origin_y_um": -2.0,
                }
            },
        });
        let text = std::fs::read(dir.path().join(name).join("zarr.json")).unwrap();
        assert_eq!(text, serde_json::to_vec_pretty(&old).unwrap());
    }

    #[test]
    fn chunks_are_padded_and_empty_ones_left_out() {
        let dir = tempfile::tempdir().unwrap();
        let (rows, cols) = (3, ZARR_CHUNK_PX + 2);
        let mut h = vec![f32::NAN; rows * cols];
        h[1] = 1.5; // chunk (0, 0)
        let at = Sampling::new(Shape::new(rows, cols), 0.5, 0.25)
            .unwrap()
            .with_origin(1.0, -2.0)
            .unwrap();
        let name = write_zarr_abs(dir.path(), "p", &h, &at, 100.0).unwrap();
        let store = dir.path().join(name);
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(store.join("zarr.json")).unwrap()).unwrap();
        assert_eq!(meta["shape"], json!([rows, cols]));
        assert_eq!(meta["attributes"]["surfstream"]["pitch_y_um"], json!(0.25));
        let chunk = std::fs::read(store.join("c/0/0")).unwrap();
        assert_eq!(chunk.len(), ZARR_CHUNK_PX * ZARR_CHUNK_PX * 8);
        let v1 = f64::from_le_bytes(chunk[8..16].try_into().unwrap());
        assert_eq!(v1, 101.5);
        let pad = f64::from_le_bytes(chunk[(ZARR_CHUNK_PX * 3) * 8..][..8].try_into().unwrap());
        assert!(pad.is_nan());
        assert!(
            !store.join("c/0/1").exists(),
            "an all-NaN chunk is the fill value"
        );
        assert!(!dir.path().join("p.zarr.partial").exists());
        assert_eq!(meta["data_type"], json!("float64"));
        // Without an offset the heights are f32 exactly: a float32 store, as panorama.npy.
        let name = write_zarr_abs(dir.path(), "q", &h, &at, 0.0).unwrap();
        let store = dir.path().join(name);
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(store.join("zarr.json")).unwrap()).unwrap();
        assert_eq!(meta["data_type"], json!("float32"));
        let chunk = std::fs::read(store.join("c/0/0")).unwrap();
        assert_eq!(chunk.len(), ZARR_CHUNK_PX * ZARR_CHUNK_PX * 4);
        assert_eq!(f32::from_le_bytes(chunk[4..8].try_into().unwrap()), 1.5);
        assert!(f32::from_le_bytes(chunk[..4].try_into().unwrap()).is_nan());
    }
}
