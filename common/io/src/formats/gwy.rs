//! Gwyddion native `.gwy` (magic `GWYP`): a tree of serialized objects.
//!
//! Layout as published in the Gwyddion user guide ("Format of Gwyddion Files"), all
//! little-endian:
//! - magic `GWYP`, then one serialized object (the top-level `GwyContainer`);
//! - an object is its type name (NUL-terminated), a u32 byte size of its components, then the
//!   components; a component is its name (NUL-terminated), a type byte and the value:
//!   `b` bool (1 byte), `c` char (1), `i` i32, `q` i64, `d` f64, `s` NUL-terminated string,
//!   `o` object; the upper-case letter is an array of that type: a u32 item count then the items
//!   (`C`, `I`, `Q`, `D`, `S`, `O`).
//! - A container holds its channels as components named `/N/data` (a `GwyDataField`), with an
//!   optional mask `/N/mask` (a `GwyDataField`, 1 = masked) and title `/N/data/title`.
//! - `GwyDataField`: `xres`, `yres` (i), `xreal`, `yreal` (d, physical size in base units),
//!   `si_unit_xy`, `si_unit_z` (`GwySIUnit` objects whose `unitstr` is e.g. `m`), `data`
//!   (`D`, `xres * yres` values, row by row from the top row).
//!
//! Read here: the channel with the smallest N. Its mask, if present, marks invalid points (NaN):
//! Gwyddion users mask what was not measured. Gwyddion's row 0 is the top of the image and y
//! points down the rows, so row index grows with y: rows are kept in file order. A missing or
//! empty unit is read as metres, with a warning in the metadata. The old `GWYO` format is not
//! read.

use anyhow::{bail, Context, Result};

use super::bytes::{checked_size, length_unit_um};
use super::{Metadata, Surface};

/// Deeper nesting than this is not a real file; bounded so a crafted file cannot overflow the stack.
const MAX_DEPTH: usize = 32;

/// A parsed object: its type name and components (values borrow the file).
struct Object<'a> {
    type_name: String,
    components: Vec<(String, Value<'a>)>,
}

enum Value<'a> {
    Int(i64),
    Double(f64),
    Str(String),
    Object(Object<'a>),
    /// `D` array: the raw little-endian bytes, 8 per item.
    Doubles(&'a [u8]),
    /// Any other atomic or array value, not needed here.
    Other,
}

impl<'a> Object<'a> {
    fn get(&self, name: &str) -> Option<&Value<'a>> {
        self.components
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v)
    }
}

struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
    /// Where the enclosing object's components end.
    end: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, len: usize, what: &str) -> Result<&'a [u8]> {
        match self.pos.checked_add(len) {
            Some(e) if e <= self.end => {
                let s = &self.data[self.pos..e];
                self.pos = e;
                Ok(s)
            }
            _ => bail!(
                "{what}: needs {len} bytes at offset {} but the enclosing object ends at {}",
                self.pos,
                self.end
            ),
        }
    }

    fn cstr(&mut self, what: &str) -> Result<String> {
        let rest = &self.data[self.pos..self.end];
        let len = rest
            .iter()
            .position(|&b| b == 0)
            .with_context(|| format!("{what} at offset {}: no terminating NUL", self.pos))?;
        let s = String::from_utf8_lossy(&rest[..len]).into_owned();
        self.pos += len + 1;
        Ok(s)
    }

    fn u32(&mut self, what: &str) -> Result<u32> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// An array of `count` fixed-size items, checked against the object before it is used.
    fn array(&mut self, item: usize, what: &str) -> Result<&'a [u8]> {
        let count = self.u32(what)? as usize;
        let len = checked_size(&[count, item], what)?;
        self.take(len, what)
    }

    fn object(&mut self, depth: usize) -> Result<Object<'a>> {
        if depth > MAX_DEPTH {
            bail!("objects nested deeper than {MAX_DEPTH} levels");
        }
        let type_name = self.cstr("object type name")?;
        let size = self.u32(&format!("object '{type_name}' size"))? as usize;
        let start = self.pos;
        let end = match start.checked_add(size) {
            Some(e) if e <= self.end => e,
            _ => bail!(
                "object '{type_name}' claims {size} bytes at offset {start} but only {} remain",
                self.end - start
            ),
        };
        let mut inner = Cursor {
            data: self.data,
            pos: start,
            end,
        };
        let mut components = Vec::new();
        while inner.pos < end {
            let name = inner.cstr("component name")?;
            let kind = inner.take(1, &format!("component '{name}' type"))?[0];
            let value = inner.value(kind, &name, depth)?;
            components.push((name, value));
        }
        self.pos = end;
        Ok(Object {
            type_name,
            components,
        })
    }

    fn value(&mut self, kind: u8, name: &str, depth: usize) -> Result<Value<'a>> {
        let what = format!("component '{name}'");
        Ok(match kind {
            b'b' | b'c' => {
                self.take(1, &what)?;
                Value::Other
            }
            b'i' => {
                let b = self.take(4, &what)?;
                Value::Int(i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as i64)
            }
            b'q' => {
                let b = self.take(8, &what)?;
                let mut a = [0u8; 8];
                a.copy_from_slice(b);
                Value::Int(i64::from_le_bytes(a))
            }
            b'd' => {
                let b = self.take(8, &what)?;
                let mut a = [0u8; 8];
                a.copy_from_slice(b);
                Value::Double(f64::from_le_bytes(a))
            }
            b's' => Value::Str(self.cstr(&what)?),
            b'o' => Value::Object(self.object(depth + 1)?),
            b'C' => {
                self.array(1, &what)?;
                Value::Other
            }
            b'I' => {
                self.array(4, &what)?;
                Value::Other
            }
            b'Q' => {
                self.array(8, &what)?;
                Value::Other
            }
            b'D' => Value::Doubles(self.array(8, &what)?),
            b'S' => {
                let count = self.u32(&what)?;
                for _ in 0..count {
                    self.cstr(&what)?;
                }
                Value::Other
            }
            b'O' => {
                let count = self.u32(&what)?;
                for _ in 0..count {
                    self.object(depth + 1)?;
                }
                Value::Other
            }
            other => bail!(
                "{what}: unknown type '{}' (expected one of b c i q d s o C I Q D S O)",
                other.escape_ascii()
            ),
        })
    }
}

pub fn parse(data: &[u8]) -> Result<Surface> {
    if data.starts_with(b"GWYO") {
        bail!("magic 'GWYO': the old Gwyddion 1 format is not read (expected 'GWYP')");
    }
    if !data.starts_with(b"GWYP") {
        bail!("magic: expected 'GWYP'");
    }
    let mut cursor = Cursor {
        data,
        pos: 4,
        end: data.len(),
    };
    let root = cursor.object(0)?;
    // The channel with the smallest id: components named "/N/data" holding a GwyDataField.
    let channel = root
        .components
        .iter()
        .filter_map(|(name, v)| {
            let id = name.strip_prefix('/')?.strip_suffix("/data")?;
            let id: u64 = id.parse().ok()?;
            match v {
                Value::Object(o) if o.type_name == "GwyDataField" => Some((id, o)),
                _ => None,
            }
        })
        .min_by_key(|(id, _)| *id);
    let (id, field) = match channel {
        Some(c) => c,
        None if root.type_name == "GwyDataField" => (0, &root),
        None => bail!(
            "no channel: expected a GwyDataField component named '/0/data' (or '/N/data') in the top-level '{}'",
            root.type_name
        ),
    };
    let mut metadata = Metadata {
        format: "gwy".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    metadata.extra.insert("channel".into(), id.to_string());
    if let Some(Value::Str(t)) = root.get(&format!("/{id}/data/title")) {
        metadata.extra.insert("title".into(), t.clone());
    }
    let (width, height, heights) = field_values(field, "data")?;
    let xreal = positive_double(field, "xreal")?;
    let yreal = positive_double(field, "yreal")?;
    let uxy = unit_um(field, "si_unit_xy", &mut metadata)?;
    let uz = unit_um(field, "si_unit_z", &mut metadata)?;
    // xoff / yoff are optional (0 when absent); a file that has both says where it lies.
    if let (Some(Value::Double(x)), Some(Value::Double(y))) = (field.get("xoff"), field.get("yoff"))
    {
        if x.is_finite() && y.is_finite() {
            metadata.stage_position_um = Some([x * uxy, y * uxy]);
        }
    }
    let mut heights_um: Vec<f64> = heights.map(|z| z * uz).collect();
    if let Some(Value::Object(mask)) = root.get(&format!("/{id}/mask")) {
        let (mw, mh, marks) = field_values(mask, "mask")?;
        if (mw, mh) != (width, height) {
            bail!("mask '/{id}/mask' is {mw} x {mh}, expected the channel's {width} x {height}");
        }
        for (z, m) in heights_um.iter_mut().zip(marks) {
            if m > 0.5 {
                *z = f64::NAN;
            }
        }
    }
    Ok(Surface {
        width,
        height,
        pitch_x_um: xreal * uxy / width as f64,
        pitch_y_um: yreal * uxy / height as f64,
        heights_um,
        metadata,
    })
}

/// `xres`, `yres` and the `data` values of a GwyDataField, sizes checked.
fn field_values<'o>(
    field: &'o Object<'_>,
    what: &str,
) -> Result<(usize, usize, impl Iterator<Item = f64> + 'o)> {
    let res = |name: &str| -> Result<usize> {
        match field.get(name) {
            Some(Value::Int(v)) if *v > 0 => Ok(*v as usize),
            Some(Value::Int(v)) => bail!("{what} field '{name}' is {v}, expected positive"),
            _ => bail!("{what} field '{name}' missing (expected an integer)"),
        }
    };
    let (xres, yres) = (res("xres")?, res("yres")?);
    let n = checked_size(&[xres, yres], "xres * yres")?;
    let bytes = match field.get("data") {
        Some(Value::Doubles(b)) => *b,
        _ => bail!("{what} field 'data' missing (expected an array of doubles)"),
    };
    if bytes.len() / 8 != n {
        bail!(
            "{what} field 'data' has {} values, expected xres x yres = {xres} x {yres} = {n}",
            bytes.len() / 8
        );
    }
    let values = bytes.chunks_exact(8).map(|c| {
        let mut a = [0u8; 8];
        a.copy_from_slice(c);
        f64::from_le_bytes(a)
    });
    Ok((xres, yres, values))
}

fn positive_double(field: &Object, name: &str) -> Result<f64> {
    match field.get(name) {
        Some(Value::Double(v)) if v.is_finite() && *v > 0.0 => Ok(*v),
        Some(Value::Double(v)) => bail!("field '{name}' is {v}, expected a finite positive number"),
        _ => bail!("field '{name}' missing (expected a double)"),
    }
}

/// Micrometres per the field's unit (`GwySIUnit.unitstr`); none or empty = metres (warned).
fn unit_um(field: &Object, name: &str, metadata: &mut Metadata) -> Result<f64> {
    let unit = match field.get(name) {
        Some(Value::Object(u)) => match u.get("unitstr") {
            Some(Value::Str(s)) => s.trim().to_string(),
            _ => String::new(),
        },
        _ => String::new(),
    };
    if unit.is_empty() {
        metadata
            .warnings
            .push(format!("'{name}' has no unit: taken as metres"));
        return Ok(1e6);
    }
    length_unit_um(&unit).with_context(|| {
        format!("field '{name}' unit is '{unit}', expected a length unit (m, mm, um, nm, ...)")
    })
}
