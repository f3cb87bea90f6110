//! FRT MicroProf `.frt` (FRT / FormFactor optical profilometers), binary, little-endian.
//!
//! Layout as SurfaceTopography's `IO/FRT.py` (MIT, 1.27.1) reads it, checked on the two
//! public samples (tests/data/specimens/README.md); Gwyddion's `microprof.c` (GPL: read for
//! behaviour only) names the same blocks:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 12 | magic "FRTM_GLIDERV" |
//! | 12 | 4 | version "1.00" (block sizes u32) or "1.01" (block sizes u64) |
//! | 16 | 2 | number of blocks (u16) |
//! | 18 | ... | blocks: id (u16), size (u32 or u64), `size` bytes of body |
//!
//! Blocks read here:
//!
//! | id | body |
//! |---|---|
//! | 0x0066 | nb_grid_pts_x, nb_grid_pts_y, bits_per_pixel (u32; 16 or 32) |
//! | 0x0067 | physical_size_x, physical_size_y (f64, metres), offsets, factor_y, scan direction |
//! | 0x006c | meas_range (u32), height_scale_factor (f64, metres per count) |
//! | 0x000b | the topography: nx * ny counts, u16 (16 bits) or i32 (32 bits), x fastest |
//! | 0x007d | multi-image block (fallback when 0x000b is absent): 8 bytes of buffer ids, then images, each data_type, nx, ny, bits (u32) and its counts |
//! | 0x0072 | meas_started, meas_ended (u32 POSIX seconds; 0 / 0xffffffff = unset), meas_time |
//! | 0x008e | serial number (u32 length + text), ... |
//!
//! Height in metres = count * height_scale_factor; a count of 1 marks a point not measured
//! (SurfaceTopography's rule; block 0x0070 also gives a valid range, which would flag the
//! last stored row of frt-1.frt, 500 counts of 0, too: not applied, to stay with the
//! reference). Pitch = physical
//! size / number of points (SurfaceTopography's physical_sizes / nb_grid_pts).
//!
//! In the multi-image block, height-like images have a data type with one of the bits 0x4
//! (topography), 0x80 (thickness), 0x800 (sample thickness), 0x1000 (AFM); the first such
//! image is read. Its first image duplicates block 0x000b in both samples (checked).
//!
//! Orientation: rows are kept in stored order (first stored row = row 0), the rule of every
//! reader here. SurfaceTopography 1.27 flips y to Gwyddion's image orientation (the first
//! stored row is the bottom line of the image), so its row `ny - 1 - r` is our row `r`.

use anyhow::{bail, Context, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const MAGIC: &[u8] = b"FRTM_GLIDERV";
/// Count that marks a point not measured.
const UNDEFINED_COUNT: i64 = 1;

const BLOCK_TOPOGRAPHY: u16 = 0x000b;
const BLOCK_GRID: u16 = 0x0066;
const BLOCK_SIZE: u16 = 0x0067;
const BLOCK_SENSOR: u16 = 0x006c;
const BLOCK_TIME: u16 = 0x0072;
const BLOCK_MULTI_IMAGE: u16 = 0x007d;
const BLOCK_SERIAL: u16 = 0x008e;
const BLOCK_COMMENT: u16 = 0x0065;
const BLOCK_PARAMETER_SET: u16 = 0x0077;

/// Data-type bits of the height-like images of block 0x007d.
const HEIGHT_IMAGE_TYPES: u32 = 0x0004 | 0x0080 | 0x0800 | 0x1000;

/// One block of the tag list: id and its body's place in the file.
struct Block {
    id: u16,
    start: usize,
    len: usize,
}

/// The grid of one image: counts, bits per count and where they are.
struct Image {
    nx: usize,
    ny: usize,
    bits: u32,
    start: usize,
    /// Which block (and image) the counts come from, for messages and metadata.
    source: String,
}

pub fn parse(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    let magic = b.slice(0, MAGIC.len(), "magic")?;
    if magic != MAGIC {
        bail!(
            "field 'magic' is {:?}, expected \"FRTM_GLIDERV\" (an FRT MicroProf file)",
            String::from_utf8_lossy(magic)
        );
    }
    let version = b.text(12, 4, "version")?;
    let wide_sizes = match version.as_str() {
        "1.00" => false,
        "1.01" => true,
        other => bail!("field 'version' is '{other}', expected '1.00' or '1.01'"),
    };
    let n_blocks = b.u16_le(16, "number of blocks")?;
    let blocks = block_list(&b, n_blocks, wide_sizes)?;
    let find = |id: u16| blocks.iter().find(|k| k.id == id);
    let need = |id: u16, what: &str| {
        find(id).with_context(|| {
            format!("block {id:#06x} ({what}) is missing: the file holds no topography")
        })
    };

    let image = match find(BLOCK_TOPOGRAPHY) {
        Some(topo) => {
            let grid = need(BLOCK_GRID, "grid size")?;
            let field =
                |i: usize, name: &str| body_u32(&b, grid, i * 4, &format!("block 0x0066 {name}"));
            let image = Image {
                nx: field(0, "nb_grid_pts_x")? as usize,
                ny: field(1, "nb_grid_pts_y")? as usize,
                bits: field(2, "bits_per_pixel")?,
                start: topo.start,
                source: "block 0x000b".into(),
            };
            let need = image_len(&image)?;
            if need != topo.len {
                bail!(
                    "block 0x000b holds {} bytes, but block 0x0066's grid of {} x {} points at {} bits needs {need}",
                    topo.len,
                    image.nx,
                    image.ny,
                    image.bits
                );
            }
            image
        }
        None => {
            let multi = need(BLOCK_MULTI_IMAGE, "topography 0x000b nor multi-image")?;
            height_image(&b, multi)?
        }
    };
    let Image { nx, ny, bits, .. } = image;

    let size = need(BLOCK_SIZE, "physical size")?;
    let size_x_m = body_f64(&b, size, 0, "block 0x0067 physical_size_x")?;
    let size_y_m = body_f64(&b, size, 8, "block 0x0067 physical_size_y")?;
    for (name, v) in [("physical_size_x", size_x_m), ("physical_size_y", size_y_m)] {
        if !v.is_finite() || v <= 0.0 {
            bail!("field 'block 0x0067 {name}' is {v}, expected a finite positive size in metres");
        }
    }
    let sensor = need(BLOCK_SENSOR, "height scale")?;
    let scale_m = body_f64(&b, sensor, 4, "block 0x006c height_scale_factor")?;
    if !scale_m.is_finite() || scale_m == 0.0 {
        bail!(
            "field 'block 0x006c height_scale_factor' is {scale_m}, expected a finite non-zero number of metres per count"
        );
    }

    let n = checked_size(&[nx, ny], "nb_grid_pts_x * nb_grid_pts_y")?;
    let bytes_per_count = (bits / 8) as usize;
    let raw = b.slice(
        image.start,
        checked_size(&[n, bytes_per_count], "height data size")?,
        &format!("{} height data", image.source),
    )?;
    let scale_um = scale_m * 1e6;
    let height = |count: i64| {
        if count == UNDEFINED_COUNT {
            f64::NAN
        } else {
            count as f64 * scale_um
        }
    };
    let heights_um: Vec<f64> = if bits == 16 {
        raw.chunks_exact(2)
            .map(|c| height(u16::from_le_bytes([c[0], c[1]]) as i64))
            .collect()
    } else {
        raw.chunks_exact(4)
            .map(|c| height(i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as i64))
            .collect()
    };

    let mut metadata = Metadata {
        format: "frt".into(),
        pitch_known: true,
        instrument: Some("FRT MicroProf".into()),
        ..Metadata::default()
    };
    metadata.extra.insert("version".into(), version);
    metadata.extra.insert("heights_from".into(), image.source);
    metadata
        .extra
        .insert("height_scale_factor_m".into(), format!("{scale_m:e}"));
    for (id, key) in [
        (BLOCK_COMMENT, "comment"),
        (BLOCK_PARAMETER_SET, "parameter_set"),
    ] {
        if let Some(k) = find(id) {
            let text = b.text(k.start, k.len, key)?;
            if !text.is_empty() {
                metadata.extra.insert(key.into(), text);
            }
        }
    }
    if let Some(k) = find(BLOCK_SERIAL) {
        metadata.serial = serial_number(&b, k);
    }
    if let Some(k) = find(BLOCK_TIME) {
        let started = body_u32(&b, k, 0, "block 0x0072 meas_started")?;
        if started != 0 && started != u32::MAX {
            metadata.date = Some(posix_utc(started as i64));
        }
    }
    Ok(Surface {
        width: nx,
        height: ny,
        pitch_x_um: size_x_m * 1e6 / nx as f64,
        pitch_y_um: size_y_m * 1e6 / ny as f64,
        heights_um,
        metadata,
    })
}

/// The tag list: every block's id and body, each checked to lie inside the file. A file that
/// ends before the announced number of blocks is refused as truncated (SurfaceTopography
/// stops there silently; both samples hold exactly the announced number).
fn block_list(b: &Bytes, n_blocks: u16, wide_sizes: bool) -> Result<Vec<Block>> {
    let mut blocks = Vec::with_capacity(n_blocks as usize);
    let mut at = 18usize;
    let header_len = if wide_sizes { 10 } else { 6 };
    for i in 0..n_blocks {
        if at + header_len > b.data.len() {
            bail!(
                "the file announces {n_blocks} blocks (field 'number of blocks') but ends at byte {} after {i} whole blocks: truncated",
                b.data.len()
            );
        }
        let id = b.u16_le(at, "block id")?;
        let len = if wide_sizes {
            usize::try_from(b.u64_le(at + 2, "block size")?).unwrap_or(usize::MAX)
        } else {
            b.u32_le(at + 2, "block size")? as usize
        };
        let start = at + header_len;
        if len > b.data.len() - start {
            bail!(
                "block {i} (id {id:#06x}) at byte {at} declares {len} bytes, but the file ends {} bytes after its header: truncated",
                b.data.len() - start
            );
        }
        blocks.push(Block { id, start, len });
        at = start + len;
    }
    Ok(blocks)
}

/// The bytes the counts of `image` take, its grid and bits checked.
fn image_len(image: &Image) -> Result<usize> {
    if image.nx == 0 || image.ny == 0 {
        bail!(
            "{}: fields 'nb_grid_pts_x' x 'nb_grid_pts_y' are {} x {}, expected positive",
            image.source,
            image.nx,
            image.ny
        );
    }
    let bytes_per_count = match image.bits {
        16 => 2,
        32 => 4,
        other => bail!(
            "{}: field 'bits_per_pixel' is {other}, expected 16 or 32",
            image.source
        ),
    };
    checked_size(
        &[image.nx, image.ny, bytes_per_count],
        "nb_grid_pts_x * nb_grid_pts_y * bytes per count",
    )
}

/// The first height-like image of the multi-image block 0x007d.
fn height_image(b: &Bytes, multi: &Block) -> Result<Image> {
    let end = multi.start + multi.len;
    let mut at = multi.start + 8; // four u16 buffer ids
    let mut index = 0;
    let mut types = Vec::new();
    while at + 16 <= end {
        let field =
            |o: usize, name: &str| b.u32_le(at + o, &format!("block 0x007d image {index} {name}"));
        let data_type = field(0, "data_type")?;
        let image = Image {
            nx: field(4, "nb_grid_pts_x")? as usize,
            ny: field(8, "nb_grid_pts_y")? as usize,
            bits: field(12, "bits_per_pixel")?,
            start: at + 16,
            source: format!("block 0x007d image {index} (data type {data_type:#x})"),
        };
        let len = image_len(&image)?;
        if len > end - image.start {
            bail!(
                "{}: {} x {} points need {len} bytes, but the block has only {} left",
                image.source,
                image.nx,
                image.ny,
                end - image.start
            );
        }
        if data_type & HEIGHT_IMAGE_TYPES != 0 {
            return Ok(image);
        }
        types.push(format!("{data_type:#x}"));
        at = image.start + len;
        index += 1;
    }
    bail!(
        "block 0x007d holds no height image (data types {}; heights have bit 0x4, 0x80, 0x800 or 0x1000), and block 0x000b is missing",
        if types.is_empty() {
            "none".to_string()
        } else {
            types.join(", ")
        }
    )
}

/// The file offset of `field`, `size` bytes at `offset` into `block`'s body, when it lies
/// within the block.
fn in_body(block: &Block, offset: usize, size: usize, field: &str) -> Result<usize> {
    if offset + size > block.len {
        bail!(
            "field '{field}' lies at byte {offset} of a block of {} bytes",
            block.len
        );
    }
    Ok(block.start + offset)
}

fn body_u32(b: &Bytes, block: &Block, offset: usize, field: &str) -> Result<u32> {
    b.u32_le(in_body(block, offset, 4, field)?, field)
}

fn body_f64(b: &Bytes, block: &Block, offset: usize, field: &str) -> Result<f64> {
    b.f64_le(in_body(block, offset, 8, field)?, field)
}

/// Block 0x008e starts with the serial number: a u32 length, then that many bytes of text.
fn serial_number(b: &Bytes, block: &Block) -> Option<String> {
    let len = body_u32(b, block, 0, "serial length").ok()? as usize;
    if len == 0 || len > block.len - 4 {
        return None;
    }
    let text = b.text(block.start + 4, len, "serial number").ok()?;
    (!text.is_empty()).then_some(text)
}

/// POSIX seconds as an ISO 8601 UTC date-time ("YYYY-MM-DDTHH:MM:SSZ").
fn posix_utc(seconds: i64) -> String {
    let days = seconds.div_euclid(86_400);
    let secs = seconds.rem_euclid(86_400);
    // Days since 1970-01-01 to a civil date (Howard Hinnant's days_from_civil, inverted).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        secs / 3600,
        secs % 3600 / 60,
        secs % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn posix_seconds_read_as_utc_dates() {
        assert_eq!(posix_utc(0), "1970-01-01T00:00:00Z");
        // 2023-03-10 16:35:59 UTC (date -u -d @1678466159).
        assert_eq!(posix_utc(1_678_466_159), "2023-03-10T16:35:59Z");
        assert_eq!(posix_utc(951_782_400), "2000-02-29T00:00:00Z");
        assert_eq!(posix_utc(4_102_444_799), "2099-12-31T23:59:59Z");
    }
}
