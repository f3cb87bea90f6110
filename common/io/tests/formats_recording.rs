//! Recordings describe themselves: a reader that knows nothing of surfstream (Python's `mcap`
//! package, `json` and `base64`) decodes a tile from the JSON Schema stored in the file alone
//! and gets the heights the recorder was given, bit for bit.

use std::collections::BTreeMap;
use std::process::Command;

use surfstream_core::frame::{placed_by, FrameHeader, FrameKind, TileRegistration};
use surfstream_io::recording::{read_recording, Recorded, Recorder};
mod support;
use support::python;

/// Decodes every message of the file by walking its schema: base64 strings (contentEncoding)
/// become bytes, `oneOf` constants their titles, non-finite floats their values; grid cells are
/// unpacked with the field types the schema names. Prints one JSON line per message.
const SCHEMA_DRIVEN_DECODER: &str = r#"
import sys, json, base64, struct
from mcap.reader import make_reader

def decode(value, schema):
    if schema.get("contentEncoding") == "base64":
        return base64.b64decode(value)
    if "oneOf" in schema and all("const" in o for o in schema["oneOf"]):
        return next(o["title"] for o in schema["oneOf"] if o["const"] == value)
    kinds = schema.get("type")
    kinds = kinds if isinstance(kinds, list) else [kinds]
    if isinstance(value, dict):
        props = schema.get("properties", {})
        return {k: decode(v, props.get(k, {})) for k, v in value.items()}
    if isinstance(value, list):
        return [decode(v, schema.get("items", {})) for v in value]
    if isinstance(value, str) and "number" in kinds:
        return float(value)  # "NaN", "inf", "-inf"
    return value

FORMATS = {"UINT8": "B", "INT8": "b", "UINT16": "H", "INT16": "h", "UINT32": "I",
           "INT32": "i", "FLOAT32": "f", "FLOAT64": "d"}

def cells(grid):
    """Each field's values, row-major, by the grid's own layout description."""
    data, rs, cs = grid["data"], grid["row_stride"], grid["cell_stride"]
    rows = len(data) // rs if rs else 0
    out = {}
    for f in grid["fields"]:
        fmt = "<" + FORMATS[f["type"]]
        values = [struct.unpack_from(fmt, data, r * rs + c * cs + f["offset"])[0]
                  for r in range(rows) for c in range(grid["column_count"])]
        out[f["name"]] = [v if v == v else None for v in values]  # NaN: JSON null
    return rows, out

with open(sys.argv[1], "rb") as fh:
    for schema, channel, message in make_reader(fh).iter_messages():
        assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
        s = json.loads(schema.data)
        m = decode(json.loads(message.data), s)
        line = {"topic": channel.topic, "schema": schema.name, "title": s.get("title")}
        if "column_count" in m:
            rows, fields = cells(m)
            line.update(rows=rows, cols=m["column_count"], fields=fields,
                        pose=m["pose"]["position"], cell_size=m["cell_size"],
                        header=m.get("surfstream"))
        else:
            line["message"] = m
        print(json.dumps(line))
"#;

#[test]
fn python_decodes_a_tile_from_the_schema_in_the_file_alone() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rec.mcap");
    // 4 columns x 3 rows, asymmetric, NaN = not measured, -0.0 and a subnormal kept exactly.
    let (w, h) = (4u32, 3u32);
    let heights: Vec<f32> = vec![
        0.5,
        -1.25,
        f32::NAN,
        3.0e-3,
        7.5,
        -0.0,
        1.0e-40,
        2.0,
        f32::NAN,
        -9.875,
        123.456,
        0.1,
    ];
    let header = FrameHeader {
        kind: FrameKind::Tile as u32,
        flags: 0,
        scan_id: 0x1234_5678_9abc_def0,
        sequence: 0,
        tile_index: 2,
        tile_row: 1,
        tile_col: 0,
        width: w,
        height: h,
        _pad: 0,
        pitch_x_um: 0.8148,
        pitch_y_um: 0.8149,
        origin_x_um: 114.21,
        origin_y_um: -26.36,
        z_offset_um: 25_000.123_456_789,
        t_acquired_ns: 1_000,
        t_sent_ns: 2_000_000_123,
    };
    let reg = TileRegistration {
        scan_id: header.scan_id,
        tile_index: 2,
        placed_by: placed_by::REGISTRATION,
        links_accepted: 1,
        links_tried: 2,
        x_um: 117.5,
        y_um: 25.9,
        quality: 0.97,
        ..Default::default()
    };
    let mut rec = Recorder::create(&path).unwrap();
    let tiles = rec
        .add_frame_channel("stage/tiles", BTreeMap::new())
        .unwrap();
    let regs = rec
        .add_registration_channel("matcher/registrations", BTreeMap::new())
        .unwrap();
    rec.write_frame(tiles, &header, &heights, 10).unwrap();
    rec.write_registration(regs, &reg, 20).unwrap();
    let eos = FrameHeader::end_of_scan(header.scan_id, 1, 2, 77);
    rec.write_frame(tiles, &eos, &[], 30).unwrap();
    rec.finish().unwrap();

    let out = Command::new(python())
        .arg("-c")
        .arg(SCHEMA_DRIVEN_DECODER)
        .arg(&path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "python failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<serde_json::Value> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3, "{lines:?}");

    let tile = &lines[0];
    assert_eq!(tile["topic"], "stage/tiles");
    assert_eq!(tile["schema"], "foxglove.Grid");
    assert_eq!(
        (tile["rows"].as_u64(), tile["cols"].as_u64()),
        (Some(3), Some(4))
    );
    assert_eq!(tile["header"]["kind"], "tile");
    // Python's json prints NaN as NaN, which serde_json does not read: compare as text.
    let got: Vec<String> = tile["fields"]["height_um"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.to_string())
        .collect();
    assert_eq!(got.len(), heights.len());
    for (i, (g, want)) in got.iter().zip(&heights).enumerate() {
        if want.is_nan() {
            assert_eq!(g, "null", "cell {i}");
        } else {
            // Python decodes f32 to a double: exactly the f32's value.
            let g: f64 = g.parse().unwrap();
            assert_eq!(
                g.to_bits(),
                (*want as f64).to_bits(),
                "cell {i}: {g} vs {want}"
            );
        }
    }
    // The exact offset, and the display pose in metres.
    assert_eq!(
        tile["header"]["z_offset_um"].as_f64(),
        Some(25_000.123_456_789)
    );
    assert!((tile["pose"]["z"].as_f64().unwrap() - 0.025_000_123_456_789).abs() < 1e-15);
    assert!((tile["cell_size"]["x"].as_f64().unwrap() - 0.8148e-6).abs() < 1e-18);
    assert_eq!(
        tile["header"]["scan_id"].as_u64(),
        Some(0x1234_5678_9abc_def0)
    );

    let r = &lines[1];
    assert_eq!(r["schema"], "surfstream.TileRegistration");
    assert_eq!(r["message"]["placed_by"], "registration");
    assert_eq!(r["message"]["x_um"].as_f64(), Some(117.5));

    let end = &lines[2];
    assert_eq!(
        (end["rows"].as_u64(), end["cols"].as_u64()),
        (Some(0), Some(0))
    );
    assert_eq!(end["header"]["kind"], "marker");
    assert_eq!(end["header"]["flags"].as_u64(), Some(2), "end of scan");

    // And our own reader gets the same frames back.
    let back = read_recording(&path).unwrap();
    let Recorded::Frame(f) = &back.messages[0].message else {
        panic!("frame expected")
    };
    assert_eq!(f.header, header);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&f.heights), bits(&heights));
}
