//! Digital Surf MountainsMap documents `.mnt`: an OLE2 compound document (read with the `cfb`
//! crate) whose stream `ScopedContents` holds the document as a tree of TLV entries.
//!
//! Layout as SurfaceTopography's `IO/MNT.py` (MIT, 1.27.1) reads it, checked on the two
//! public samples (tests/data/specimens/README.md):
//!
//! - `ScopedContents` = u64 size of the rest, then entries: tag (u16 LE), size (u64 LE),
//!   body. A body is a value or nested entries, as the tag's place in the tree says. Text is a
//!   marker byte 0x04 then UTF-16 LE. The entries of the document's object list each have an
//!   extra u64 size before them.
//! - Tree (tags in hex): `0001` main { `00c8` software version { `0001` major .. `0004` build,
//!   u32 }, `00cb` software serial (text), `02bd` contents { `0002` document { `0001` objects
//!   (prefixed entries, each `0001` object) } } }.
//! - Object: `0001` class { `0001` number (u32) }, `0002` body, `0003` GUID. Only the measured
//!   surface (class 9012) holds heights; derived layers store operators and are recomputed
//!   by Mountains, studies are objects too.
//! - Surface body: `ffff` header { `0004` title }, `0001` object of class 9062 whose body is
//!   `ffff` measurement { `ffff` grid { `ffff` header { `ffff` { `0001` name } }, `0001` x axis,
//!   `0002` y axis, `0003` mask (optional) }, `0001` heights (class 9049), `0002` height axis }.
//! - Lateral axis: `ffff` { `ffff` scale, `0001` nb_grid_pts (u32) }; height axis: `ffff` scale,
//!   `0001` min, `0002` max (i32). Scale: `0001` step (f64), `0002` unit, `0003` display unit,
//!   `0004` unit ratio (f64), `0005` origin (f64, in the display unit).
//! - Array (heights, mask data): `0001` class, `0002` { `0001` count (u32), `0002` data }; data
//!   = u64 size in bytes, then blocks of element offset (u64), element count (u32), compressed
//!   size (u32) and a zlib stream, in any order. Element size = size / count (2 or 4 bytes,
//!   signed counts).
//! - Mask: `0001` class 9056, `0002` { `0001` width, `0002` height (u32, without border),
//!   `0005` array of class 9048 }: (nx + 2) x (ny + 2) bytes with a one-pixel border,
//!   9 = measured, anything else = not measured.
//!
//! Height = count * step (in the step's unit) + origin (in the display unit); a document
//! whose height unit is no length (an intensity image) is skipped. Pitch = the axis step.
//! Rows are stored x fastest, first stored row = row 0, as SurfaceTopography reads them.
//! The first measured surface of the document is read; a warning names the others.

use std::io::{Cursor, Read};

use anyhow::{anyhow, bail, Context, Result};

use super::bytes::{checked_size, length_unit_um};
use super::{Metadata, Surface};

const OLE_MAGIC: &[u8] = &[0xd0, 0xcf, 0x11, 0xe0, 0xa1, 0xb1, 0x1a, 0xe1];
const STREAM: &str = "/ScopedContents";

const CLASS_SURFACE: u32 = 9012;
const CLASS_SURFACE_DATA: u32 = 9062;
const CLASS_MASK: u32 = 9056;
const CLASS_ARRAY: u32 = 9048;
const CLASS_HEIGHTS: u32 = 9049;
const MASK_MEASURED: u8 = 9;
const TEXT_MARKER: u8 = 0x04;
/// Deflate expands at most ~1032x: a lying array size cannot reserve more than that.
const MAX_DEFLATE_RATIO: usize = 1032;

pub fn parse(data: &[u8]) -> Result<Surface> {
    if !data.starts_with(OLE_MAGIC) {
        bail!("field 'signature' (bytes 0..8) is not the OLE2 compound document signature D0 CF 11 E0 A1 B1 1A E1: not a MountainsMap .mnt document");
    }
    let mut ole = cfb::CompoundFile::open(Cursor::new(data))
        .map_err(|e| anyhow!("the OLE2 compound document is corrupt: {e}"))?;
    if !ole.is_stream(STREAM) {
        bail!("the compound document has no stream 'ScopedContents': not a MountainsMap document");
    }
    let mut contents = Vec::new();
    ole.open_stream(STREAM)
        .and_then(|mut s| s.read_to_end(&mut contents))
        .map_err(|e| anyhow!("stream 'ScopedContents' cannot be read: {e}"))?;
    if contents.len() < 8 {
        bail!(
            "stream 'ScopedContents' has {} bytes, expected at least its 8-byte size field",
            contents.len()
        );
    }
    let root = Node {
        body: &contents[8..],
        path: "ScopedContents".into(),
    };
    let main = root.child(0x0001, "main")?;
    let objects = main
        .child(0x02bd, "contents")?
        .child(0x0002, "document")?
        .child(0x0001, "objects")?;

    let mut surfaces = Vec::new();
    for (i, object) in objects.prefixed_entries().into_iter().enumerate() {
        if object.tag != 0x0001 {
            continue;
        }
        let object = Node {
            body: object.body,
            path: format!("{}/object {i}", objects.path),
        };
        if class_number(&object)? != Some(CLASS_SURFACE) {
            continue;
        }
        if let Some(s) = surface(&object.child(0x0002, "body")?)? {
            surfaces.push(s);
        }
    }
    let n_surfaces = surfaces.len();
    let mut s = surfaces.into_iter().next().with_context(|| {
        format!(
            "{}: the document holds no measured height map (an object of class {CLASS_SURFACE} with a length unit)",
            objects.path
        )
    })?;
    if n_surfaces > 1 {
        s.metadata.warnings.push(format!(
            "the document holds {n_surfaces} measured surfaces; only the first is read"
        ));
    }
    if let Some(v) = main.opt_child(0x00c8, "software version") {
        let part = |tag, name| v.opt_child(tag, name).and_then(|p| p.u32().ok());
        if let (Some(a), Some(b), Some(c), Some(d)) = (
            part(0x0001, "major"),
            part(0x0002, "minor"),
            part(0x0003, "patch"),
            part(0x0004, "build"),
        ) {
            s.metadata
                .extra
                .insert("software_version".into(), format!("{a}.{b}.{c}.{d}"));
        }
    }
    if let Some(serial) = main
        .opt_child(0x00cb, "software serial")
        .and_then(|n| n.text().ok())
        .filter(|t| !t.is_empty())
    {
        // The serial number of the Mountains installation, not of the instrument.
        s.metadata.extra.insert("software_serial".into(), serial);
    }
    Ok(s)
}

/// The height map of a measured-surface object's body, or None when it holds none (no
/// measurement object, or heights that are no length).
fn surface(body: &Node) -> Result<Option<Surface>> {
    let measurement_object = match body.opt_child(0x0001, "measurement object") {
        Some(m) => m,
        None => return Ok(None),
    };
    if class_number(&measurement_object)? != Some(CLASS_SURFACE_DATA) {
        return Ok(None);
    }
    let measurement = measurement_object
        .child(0x0002, "body")?
        .child(0xffff, "measurement")?;
    let grid = measurement.child(0xffff, "grid")?;
    let x_axis = grid.child(0x0001, "x axis")?.child(0xffff, "axis")?;
    let y_axis = grid.child(0x0002, "y axis")?.child(0xffff, "axis")?;
    let heights = measurement.child(0x0001, "heights")?;
    if class_number(&heights)? != Some(CLASS_HEIGHTS) {
        bail!(
            "{}: class is {:?}, expected {CLASS_HEIGHTS} (height counts)",
            heights.path,
            class_number(&heights)?
        );
    }
    let height_axis = measurement.child(0x0002, "height axis")?;
    let x = Scale::read(&x_axis.child(0xffff, "scale")?)?;
    let y = Scale::read(&y_axis.child(0xffff, "scale")?)?;
    let z = Scale::read(&height_axis.child(0xffff, "scale")?)?;
    let display_unit = z.display_unit.clone().unwrap_or_else(|| z.unit.clone());
    let Some(display_um) = length_unit_um(&display_unit) else {
        // Not a height map (an intensity image, ...).
        return Ok(None);
    };
    let z_step_um = z.step * z.unit_um()?;
    let origin_um = z.origin.unwrap_or(0.0) * display_um;
    let (pitch_x_um, pitch_y_um) = (x.step * x.unit_um()?, y.step * y.unit_um()?);
    for (name, v) in [("x", pitch_x_um), ("y", pitch_y_um)] {
        if !v.is_finite() || v <= 0.0 {
            bail!("{name} axis: field 'step' gives a pitch of {v} um, expected finite positive");
        }
    }
    if !z_step_um.is_finite() || z_step_um == 0.0 || !origin_um.is_finite() {
        bail!(
            "{}: fields 'step' {} {} / 'origin' {:?}, expected a finite non-zero step and a finite origin",
            height_axis.path,
            z.step,
            z.unit,
            z.origin
        );
    }
    let nx = x_axis.child(0x0001, "nb_grid_pts")?.u32()? as usize;
    let ny = y_axis.child(0x0001, "nb_grid_pts")?.u32()? as usize;
    if nx == 0 || ny == 0 {
        bail!(
            "{}: fields 'nb_grid_pts' are {nx} x {ny}, expected positive",
            grid.path
        );
    }
    let n = checked_size(&[nx, ny], "nb_grid_pts x * y")?;
    let array = heights.child(0x0002, "array")?;
    let count = array.child(0x0001, "count")?.u32()? as usize;
    if count != n {
        bail!(
            "{}: field 'count' is {count}, but the grid is {nx} x {ny} = {n} points",
            array.path
        );
    }
    let (counts, element_size) = block_array(&array.child(0x0002, "data")?, count)?;
    let heights_of = |c: i64| c as f64 * z_step_um + origin_um;
    let mut heights_um: Vec<f64> = match element_size {
        2 => counts
            .chunks_exact(2)
            .map(|c| heights_of(i16::from_le_bytes([c[0], c[1]]) as i64))
            .collect(),
        4 => counts
            .chunks_exact(4)
            .map(|c| heights_of(i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as i64))
            .collect(),
        other => bail!(
            "{}: heights of {other} bytes each, expected 2 or 4",
            array.path
        ),
    };

    if let Some(mask) = grid.opt_child(0x0003, "mask") {
        if class_number(&mask)? == Some(CLASS_MASK) {
            apply_mask(&mask, nx, ny, &mut heights_um)?;
        }
    }

    let mut metadata = Metadata {
        format: "mnt".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    let title = body
        .opt_child(0xffff, "header")
        .and_then(|h| h.opt_child(0x0004, "title"))
        .and_then(|t| t.text().ok());
    let name = grid
        .opt_child(0xffff, "header")
        .and_then(|h| h.opt_child(0xffff, "description"))
        .and_then(|d| d.opt_child(0x0001, "name"))
        .and_then(|t| t.text().ok());
    for (key, v) in [("title", title), ("name", name)] {
        if let Some(v) = v.filter(|v| !v.is_empty()) {
            metadata.extra.insert(key.into(), v);
        }
    }
    metadata.extra.insert("height_unit".into(), display_unit);
    metadata
        .extra
        .insert("height_step_um".into(), format!("{z_step_um:e}"));
    metadata
        .extra
        .insert("height_origin_um".into(), format!("{origin_um}"));
    metadata
        .extra
        .insert("count_bytes".into(), element_size.to_string());
    Ok(Some(Surface {
        width: nx,
        height: ny,
        pitch_x_um,
        pitch_y_um,
        heights_um,
        metadata,
    }))
}

/// Marks the points the mask image calls not measured.
fn apply_mask(mask: &Node, nx: usize, ny: usize, heights_um: &mut [f64]) -> Result<()> {
    let m = mask.child(0x0002, "mask")?;
    let w = m.child(0x0001, "width")?.u32()? as usize;
    let h = m.child(0x0002, "height")?.u32()? as usize;
    if (w, h) != (nx, ny) {
        bail!(
            "{}: fields 'width' x 'height' are {w} x {h}, but the grid is {nx} x {ny}",
            m.path
        );
    }
    let array = m.child(0x0005, "array")?;
    if class_number(&array)? != Some(CLASS_ARRAY) {
        bail!(
            "{}: class is {:?}, expected {CLASS_ARRAY} (data array)",
            array.path,
            class_number(&array)?
        );
    }
    let inner = array.child(0x0002, "array")?;
    let count = inner.child(0x0001, "count")?.u32()? as usize;
    let (bytes, _) = block_array(&inner.child(0x0002, "data")?, count)?;
    let (bw, bh) = (nx + 2, ny + 2);
    if bytes.len() != checked_size(&[bw, bh], "mask size")? {
        bail!(
            "{}: the mask image has {} bytes, expected (nx + 2) x (ny + 2) = {bw} x {bh}",
            inner.path,
            bytes.len()
        );
    }
    for (r, row) in heights_um.chunks_exact_mut(nx).enumerate() {
        let mask_row = &bytes[(r + 1) * bw + 1..(r + 1) * bw + 1 + nx];
        for (z, &v) in row.iter_mut().zip(mask_row) {
            if v != MASK_MEASURED {
                *z = f64::NAN;
            }
        }
    }
    Ok(())
}

/// The elements of a block array (see the module doc), and the size of one element.
fn block_array(data: &Node, count: usize) -> Result<(Vec<u8>, usize)> {
    let d = data.body;
    let field = |what: &str| format!("{}: {what}", data.path);
    if d.len() < 8 {
        bail!(
            "{} has {} bytes, expected at least its 8-byte size",
            field("array data"),
            d.len()
        );
    }
    let total = u64::from_le_bytes(le8(&d[..8]));
    let bound = d.len().saturating_mul(MAX_DEFLATE_RATIO) as u64;
    if count == 0 || !total.is_multiple_of(count as u64) || total > bound {
        bail!(
            "{} is {total} bytes, expected a multiple of the {count} elements, at most {bound} (what its {} compressed bytes can hold)",
            field("field 'size'"),
            d.len()
        );
    }
    let total = total as usize;
    let element_size = total / count;
    let mut out = vec![0u8; total];
    let mut filled = 0usize;
    let mut at = 8usize;
    let mut index = 0;
    while at < d.len() {
        if d.len() - at < 16 {
            bail!(
                "{} at byte {at} is cut: {} bytes of its 16-byte header",
                field(&format!("block {index}")),
                d.len() - at
            );
        }
        let offset = u64::from_le_bytes(le8(&d[at..at + 8]));
        let elements = u32::from_le_bytes(le4(&d[at + 8..at + 12])) as u64;
        let zip_len = u32::from_le_bytes(le4(&d[at + 12..at + 16])) as usize;
        at += 16;
        if zip_len > d.len() - at {
            bail!(
                "{} declares {zip_len} compressed bytes, but {} remain",
                field(&format!("block {index}")),
                d.len() - at
            );
        }
        let start = offset.saturating_mul(element_size as u64);
        let len = elements.saturating_mul(element_size as u64);
        if start.saturating_add(len) > total as u64 {
            bail!(
                "{} covers elements {offset}..{} of an array of {count}",
                field(&format!("block {index}")),
                offset.saturating_add(elements)
            );
        }
        let (start, len) = (start as usize, len as usize);
        let target = &mut out[start..start + len];
        let mut z = flate2::read::ZlibDecoder::new(&d[at..at + zip_len]);
        z.read_exact(target).with_context(|| {
            format!(
                "{} does not inflate to its {len} bytes",
                field(&format!("block {index}"))
            )
        })?;
        filled += len;
        at += zip_len;
        index += 1;
    }
    if filled != total {
        bail!(
            "{} blocks hold {filled} bytes, expected {total}",
            field("array data")
        );
    }
    Ok((out, element_size))
}

fn le8(s: &[u8]) -> [u8; 8] {
    let mut a = [0u8; 8];
    a.copy_from_slice(s);
    a
}

fn le4(s: &[u8]) -> [u8; 4] {
    let mut a = [0u8; 4];
    a.copy_from_slice(s);
    a
}

/// An object's class number (`0001` class { `0001` number }), or None without one.
fn class_number(object: &Node) -> Result<Option<u32>> {
    match object
        .opt_child(0x0001, "class")
        .and_then(|c| c.opt_child(0x0001, "number"))
    {
        Some(n) => n.u32().map(Some),
        None => Ok(None),
    }
}

/// An axis scale (see the module doc).
struct Scale {
    step: f64,
    unit: String,
    display_unit: Option<String>,
    origin: Option<f64>,
    path: String,
}

impl Scale {
    fn read(n: &Node) -> Result<Scale> {
        Ok(Scale {
            step: n.child(0x0001, "step")?.f64()?,
            unit: n.child(0x0002, "unit")?.text()?,
            display_unit: n
                .opt_child(0x0003, "display unit")
                .and_then(|u| u.text().ok())
                .filter(|u| !u.is_empty()),
            origin: n.opt_child(0x0005, "origin").and_then(|o| o.f64().ok()),
            path: n.path.clone(),
        })
    }

    fn unit_um(&self) -> Result<f64> {
        length_unit_um(&self.unit).with_context(|| {
            format!(
                "{}: field 'unit' is '{}', expected a length unit (m, mm, um, nm, ...)",
                self.path, self.unit
            )
        })
    }
}

/// One TLV entry.
struct Entry<'a> {
    tag: u16,
    body: &'a [u8],
}

/// A node of the TLV tree: its body and its path from `ScopedContents`, for messages.
struct Node<'a> {
    body: &'a [u8],
    path: String,
}

impl<'a> Node<'a> {
    /// The entries of this node's body, read as a container. Like SurfaceTopography's reader,
    /// reading stops at an entry that does not fit (a leaf read as a container holds none).
    fn entries_with(&self, prefixed: bool) -> Vec<Entry<'a>> {
        let d = self.body;
        let mut out = Vec::new();
        let mut at = 0usize;
        let head = if prefixed { 18 } else { 10 };
        while d.len() - at >= head {
            let p = at + head - 10;
            let tag = u16::from_le_bytes([d[p], d[p + 1]]);
            let size = u64::from_le_bytes(le8(&d[p + 2..p + 10]));
            let start = at + head;
            if size > (d.len() - start) as u64 {
                break;
            }
            let end = start + size as usize;
            out.push(Entry {
                tag,
                body: &d[start..end],
            });
            at = end;
        }
        out
    }

    fn prefixed_entries(&self) -> Vec<Entry<'a>> {
        self.entries_with(true)
    }

    fn opt_child(&self, tag: u16, name: &str) -> Option<Node<'a>> {
        self.entries_with(false)
            .into_iter()
            .find(|e| e.tag == tag)
            .map(|e| Node {
                body: e.body,
                path: format!("{}/{name} ({tag:#06x})", self.path),
            })
    }

    /// The first entry `tag`, or an error naming the path to it.
    fn child(&self, tag: u16, name: &str) -> Result<Node<'a>> {
        self.opt_child(tag, name).with_context(|| {
            format!(
                "{}: entry '{name}' (tag {tag:#06x}) is missing or cut",
                self.path
            )
        })
    }

    fn fixed<const N: usize>(&self, what: &str) -> Result<[u8; N]> {
        if self.body.len() != N {
            bail!(
                "{} is {} bytes, expected {N} ({what})",
                self.path,
                self.body.len()
            );
        }
        let mut a = [0u8; N];
        a.copy_from_slice(self.body);
        Ok(a)
    }

    fn u32(&self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.fixed("a u32")?))
    }

    fn f64(&self) -> Result<f64> {
        Ok(f64::from_le_bytes(self.fixed("an f64")?))
    }

    /// Marker byte 0x04, then UTF-16 LE; trailing NULs dropped.
    fn text(&self) -> Result<String> {
        let d = self.body;
        if d.first() != Some(&TEXT_MARKER) || !(d.len() - 1).is_multiple_of(2) {
            bail!(
                "{} is no text entry (expected the marker byte 0x04 and UTF-16 LE)",
                self.path
            );
        }
        let units: Vec<u16> = d[1..]
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        let text =
            String::from_utf16(&units).map_err(|_| anyhow!("{} is not valid UTF-16", self.path))?;
        Ok(text.trim_end_matches('\0').to_string())
    }
}
