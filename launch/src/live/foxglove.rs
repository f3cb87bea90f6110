//! The live stream over the Foxglove WebSocket protocol (`foxglove.websocket.v1`,
//! https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md): the subscribe / message
//! flow a viewer needs, on tungstenite (the `foxglove` crate's server would add ~130 crates,
//! tokio and prost among them, for the same four channels; this one adds tungstenite's ~30).
//!
//! Channels, all JSON-encoded with JSON Schema schemas, like the recorder's MCAP:
//! - `/tiles` (`foxglove.Grid`): the newest tile at full resolution, the recorder's exact
//!   message ([`surfstream_io::recording::encode_frame_json`]);
//! - `/panorama/patches` (`foxglove.Grid`): the newest preview patch of the panorama;
//! - `/panorama/preview` (`foxglove.CompressedImage`): the whole preview as a PNG;
//! - `/tiles/boxes` (`foxglove.SceneUpdate`): every tile's box at its registered position,
//!   coloured by placement, and its planned position as a flat outline;
//! - `/progress` (`surfstream.Progress`): tiles registered / planned, fields per second, ETA,
//!   tile -> panorama latency, pairs decided, weak links, stage fallbacks, the verdict (for
//!   Foxglove's Raw Messages, Plot and Indicator panels).
//!
//! Latest wins per client: a client that reads slowly gets the newest message of each channel
//! when it is ready (the skipped ones counted in the state's drops); nothing waits on it.

use std::net::{TcpListener, TcpStream};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use base64::Engine as _;
use serde::Serialize;
use surfstream_core::frame::HeightMap;
use surfstream_io::recording::{
    encode_frame_json, FoxgloveTime, Pose, Quaternion, Vector3, FRAME_JSON_SCHEMA, SCAN_FRAME_ID,
};
use tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tungstenite::{Message, WebSocket};

use super::messages::{
    ChannelAd, ClientOp, Color, CompressedImage, CubePrimitive, Empty, KeyValuePair, LinePrimitive,
    Progress, SceneEntity, SceneUpdate, ServerOp,
};
use super::state::{LiveState, Placement};
use super::Shared;

/// The protocol's subprotocol name.
pub const SUBPROTOCOL: &str = "foxglove.websocket.v1";
/// Clients served at once.
const MAX_CLIENTS: usize = 8;
/// How long a client's read waits before the sender looks at the state again.
const POLL: Duration = Duration::from_millis(50);
const WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// The progress message at most this often per client (the newest state when it goes).
const PROGRESS_INTERVAL: Duration = Duration::from_millis(200);
/// The whole-preview image at most this often per client.
const IMAGE_INTERVAL: Duration = Duration::from_millis(500);

/// The advertised channels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Channel {
    Tiles = 1,
    Patches = 2,
    Preview = 3,
    Boxes = 4,
    Progress = 5,
}

const CHANNELS: [Channel; 5] = [
    Channel::Tiles,
    Channel::Patches,
    Channel::Preview,
    Channel::Boxes,
    Channel::Progress,
];

impl Channel {
    fn from_id(id: u64) -> Option<Channel> {
        CHANNELS.into_iter().find(|c| *c as u64 == id)
    }
    fn topic(self) -> &'static str {
        match self {
            Channel::Tiles => "/tiles",
            Channel::Patches => "/panorama/patches",
            Channel::Preview => "/panorama/preview",
            Channel::Boxes => "/tiles/boxes",
            Channel::Progress => "/progress",
        }
    }
    fn schema_name(self) -> &'static str {
        match self {
            Channel::Tiles | Channel::Patches => "foxglove.Grid",
            Channel::Preview => "foxglove.CompressedImage",
            Channel::Boxes => "foxglove.SceneUpdate",
            Channel::Progress => "surfstream.Progress",
        }
    }
    fn schema(self) -> &'static str {
        match self {
            Channel::Tiles | Channel::Patches => FRAME_JSON_SCHEMA,
            Channel::Preview => COMPRESSED_IMAGE_SCHEMA,
            Channel::Boxes => SCENE_UPDATE_SCHEMA,
            Channel::Progress => PROGRESS_SCHEMA,
        }
    }
}

/// JSON Schema of `foxglove.CompressedImage` (the properties this bridge sends).
const COMPRESSED_IMAGE_SCHEMA: &str = r#"{"title": "foxglove.CompressedImage", "type": "object",
 "description": "The panorama preview: heights as viridis over its robust range (see frame_id)",
 "properties": {
  "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
  "frame_id": {"type": "string"},
  "data": {"type": "string", "contentEncoding": "base64"},
  "format": {"type": "string"}}}"#;

/// JSON Schema of `foxglove.SceneUpdate` (the properties this bridge sends).
const SCENE_UPDATE_SCHEMA: &str = r#"{"title": "foxglove.SceneUpdate", "type": "object",
 "description": "Tile boxes at their registered positions (metres, scan frame), coloured by placement: green registration, amber weak link, red stage fallback; grey outlines at the stage's planned positions",
 "properties": {
  "deletions": {"type": "array", "items": {"type": "object"}},
  "entities": {"type": "array", "items": {"title": "foxglove.SceneEntity", "type": "object",
   "properties": {
    "timestamp": {"type": "object"}, "frame_id": {"type": "string"}, "id": {"type": "string"},
    "lifetime": {"type": "object"}, "frame_locked": {"type": "boolean"},
    "metadata": {"type": "array"}, "cubes": {"type": "array"}, "lines": {"type": "array"}}}}}}"#;

/// JSON Schema of the `/progress` messages ([`progress`]).
const PROGRESS_SCHEMA: &str = r#"{"title": "surfstream.Progress", "type": "object",
 "description": "The run's progress, as /state.json has it: tiles registered of planned (null: the source does not say), pace, ETA, tile -> panorama latency, pairs, weak links, stage fallbacks, the verdict (null until the run ended)",
 "properties": {
  "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
  "tiles_planned": {"type": ["integer", "null"]},
  "tiles_registered": {"type": "integer"},
  "fields_per_s": {"type": ["number", "null"]},
  "eta_s": {"type": ["number", "null"]},
  "tile_to_panorama_ms": {"type": ["number", "null"], "description": "the newest tile's"},
  "pairs": {"type": "integer"},
  "weak_links": {"type": "integer"},
  "stage_fallbacks": {"type": "integer"},
  "scan_ended": {"type": "boolean"},
  "verdict": {"type": ["string", "null"]}}}"#;

/// The `/progress` message of the state now.
pub fn progress(s: &LiveState) -> Progress {
    let placed = |p: Placement| s.tiles.values().filter(|t| t.placement == Some(p)).count();
    Progress {
        timestamp: stamp(),
        tiles_planned: s.tiles_planned,
        tiles_registered: s.tiles_registered(),
        fields_per_s: s.fields_per_s(),
        eta_s: s.eta_s(),
        tile_to_panorama_ms: s.tiles.values().rev().find_map(|t| t.tile_to_panorama_ms),
        pairs: s.pairs.len(),
        weak_links: s.pairs.iter().filter(|p| p.accepted && p.weak_link).count(),
        stage_fallbacks: placed(Placement::StageFallback),
        scan_ended: s.scan_ended,
        verdict: s.verdict.as_ref().map(|v| v.verdict),
    }
}

/// A message's JSON text (a typed message always serializes: string keys, no custom
/// serializer that fails; an empty object if one ever did, never a panic).
fn json_bytes<T: Serialize>(message: &T) -> Vec<u8> {
    serde_json::to_vec(message).unwrap_or_else(|_| b"{}".to_vec())
}

/// Serves Foxglove clients on a thread of its own (one thread per client).
pub fn spawn(listener: TcpListener, shared: Arc<Shared>) -> Result<()> {
    let clients = Arc::new(std::sync::atomic::AtomicUsize::new(0));
    std::thread::Builder::new()
        .name("live-foxglove".into())
        .spawn(move || {
            use std::sync::atomic::Ordering::SeqCst;
            for stream in listener.incoming() {
                let Ok(stream) = stream else { continue };
                if clients.load(SeqCst) >= MAX_CLIENTS {
                    continue; // dropped: the client sees the connection close
                }
                clients.fetch_add(1, SeqCst);
                let (mine, count) = (shared.clone(), clients.clone());
                let spawned = std::thread::Builder::new()
                    .name("live-foxglove-client".into())
                    .spawn(move || {
                        let _ = serve(stream, &mine);
                        count.fetch_sub(1, SeqCst);
                    });
                if spawned.is_err() {
                    clients.fetch_sub(1, SeqCst);
                }
            }
        })
        .map(|_| ())
        .map_err(|e| anyhow!("cannot start the Foxglove server thread: {e}"))
}

/// Accepts the handshake only with the protocol's subprotocol, and selects it.
#[allow(clippy::result_large_err)] // tungstenite's callback signature
fn select_subprotocol(
    req: &Request,
    mut resp: Response,
) -> std::result::Result<Response, ErrorResponse> {
    let offered = req
        .headers()
        .get_all("sec-websocket-protocol")
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|p| p.trim() == SUBPROTOCOL);
    if !offered {
        let mut e = ErrorResponse::new(Some(format!(
            "this server speaks the WebSocket subprotocol {SUBPROTOCOL} only"
        )));
        *e.status_mut() = tungstenite::http::StatusCode::BAD_REQUEST;
        return Err(e);
    }
    if let Ok(v) = SUBPROTOCOL.parse() {
        resp.headers_mut().insert("sec-websocket-protocol", v);
    }
    Ok(resp)
}

/// What a client was last sent, per channel (the state's version of it).
#[derive(Default)]
struct Sent {
    /// subscription id by channel
    subscriptions: Vec<(u32, Channel)>,
    tile: u64,
    patch: u64,
    boxes: u64,
    canvas: u64,
    image_at: Option<Instant>,
    progress: u64,
    progress_at: Option<Instant>,
}

fn serve(stream: TcpStream, shared: &Shared) -> Result<()> {
    stream.set_write_timeout(Some(WRITE_TIMEOUT))?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    let mut ws = tungstenite::accept_hdr(stream, select_subprotocol)
        .map_err(|e| anyhow!("Foxglove handshake: {e}"))?;
    ws.get_ref().set_read_timeout(Some(POLL))?;
    shared.update(|s| s.viewers.foxglove_clients += 1);
    let served = stream_to(&mut ws, shared);
    shared.update(|s| s.viewers.foxglove_clients = s.viewers.foxglove_clients.saturating_sub(1));
    served
}

fn stream_to(ws: &mut WebSocket<TcpStream>, shared: &Shared) -> Result<()> {
    send_text(ws, &server_info())?;
    send_text(ws, &advertise())?;
    let mut sent = Sent::default();
    loop {
        match ws.read() {
            Ok(Message::Text(t)) => on_client_message(t.as_str(), &mut sent, ws)?,
            Ok(Message::Close(_)) => return Ok(()),
            Ok(_) => {}
            Err(tungstenite::Error::Io(e))
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(e) => return Err(anyhow!("Foxglove client: {e}")),
        }
        send_updates(ws, shared, &mut sent)?;
    }
}

fn send_text(ws: &mut WebSocket<TcpStream>, op: &ServerOp) -> Result<()> {
    let text = serde_json::to_string(op).map_err(|e| anyhow!("Foxglove message: {e}"))?;
    ws.send(Message::Text(text.into()))
        .map_err(|e| anyhow!("Foxglove client: {e}"))
}

fn server_info() -> ServerOp {
    ServerOp::ServerInfo {
        name: format!("surfstream {}", env!("CARGO_PKG_VERSION")),
        capabilities: [],
        supported_encodings: [],
        metadata: Empty {},
        session_id: format!("{}", surfstream_core::frame::monotonic_ns()),
    }
}

fn advertise() -> ServerOp {
    let channels = CHANNELS
        .iter()
        .map(|c| ChannelAd {
            id: *c as u64,
            topic: c.topic(),
            encoding: "json",
            schema_name: c.schema_name(),
            schema: c.schema(),
            schema_encoding: "jsonschema",
        })
        .collect();
    ServerOp::Advertise { channels }
}

/// `subscribe` / `unsubscribe`; anything else is answered with a status warning.
fn on_client_message(text: &str, sent: &mut Sent, ws: &mut WebSocket<TcpStream>) -> Result<()> {
    match serde_json::from_str::<ClientOp>(text) {
        Ok(ClientOp::Subscribe { subscriptions }) => {
            for sub in subscriptions {
                let (Some(id), Some(ch)) = (
                    sub.id.and_then(|i| u32::try_from(i).ok()),
                    sub.channel_id.and_then(Channel::from_id),
                ) else {
                    send_text(
                        ws,
                        &status(
                            1,
                            "subscribe: expected {id, channelId} of an advertised channel",
                        ),
                    )?;
                    continue;
                };
                if sent.subscriptions.iter().any(|(i, _)| *i == id) {
                    send_text(ws, &status(1, &format!("subscription id {id} is in use")))?;
                    continue;
                }
                sent.subscriptions.push((id, ch));
                // A new subscriber gets the newest message at once.
                match ch {
                    Channel::Tiles => sent.tile = 0,
                    Channel::Patches => sent.patch = 0,
                    Channel::Preview => sent.canvas = 0,
                    Channel::Boxes => sent.boxes = 0,
                    Channel::Progress => sent.progress = 0,
                }
            }
        }
        Ok(ClientOp::Unsubscribe { subscription_ids }) => {
            sent.subscriptions
                .retain(|(i, _)| !subscription_ids.contains(&u64::from(*i)));
        }
        Err(e) => send_text(
            ws,
            &status(
                1,
                &format!(
                    "unsupported message ({e}): this server is read-only (subscribe, unsubscribe)"
                ),
            ),
        )?,
    }
    Ok(())
}

fn status(level: u8, message: &str) -> ServerOp {
    ServerOp::Status {
        level,
        message: message.to_owned(),
    }
}

/// Sends each subscribed channel's newest message when it changed since the last one sent.
fn send_updates(ws: &mut WebSocket<TcpStream>, shared: &Shared, sent: &mut Sent) -> Result<()> {
    if sent.subscriptions.is_empty() {
        return Ok(());
    }
    let subscribed = |c: Channel| {
        sent.subscriptions
            .iter()
            .find(|(_, s)| *s == c)
            .map(|s| s.0)
    };
    let mut out: Vec<(u32, Vec<u8>)> = Vec::new();
    let mut skipped = 0u64;
    {
        let s = shared.lock();
        let mut newest =
            |sub: Option<u32>, version: u64, last: &mut u64, map: Option<&Arc<HeightMap>>| {
                if let (Some(id), Some(m)) = (sub, map) {
                    if version != *last {
                        if *last > 0 {
                            skipped += version.saturating_sub(*last + 1);
                        }
                        *last = version;
                        let mut buf = Vec::new();
                        if encode_frame_json(&m.header, &m.heights, &mut buf).is_ok() {
                            out.push((id, buf));
                        }
                    }
                }
            };
        newest(
            subscribed(Channel::Tiles),
            s.tile_version,
            &mut sent.tile,
            s.newest_tile.as_ref(),
        );
        newest(
            subscribed(Channel::Patches),
            s.canvas_version,
            &mut sent.patch,
            s.newest_patch.as_ref(),
        );
        if let Some(id) = subscribed(Channel::Boxes) {
            if s.boxes_version != sent.boxes {
                sent.boxes = s.boxes_version;
                out.push((id, json_bytes(&scene_update(&s))));
            }
        }
        let progress_due = sent
            .progress_at
            .is_none_or(|t| t.elapsed() >= PROGRESS_INTERVAL);
        if let (Some(id), true) = (subscribed(Channel::Progress), progress_due) {
            if s.version != sent.progress {
                sent.progress = s.version;
                sent.progress_at = Some(Instant::now());
                out.push((id, json_bytes(&progress(&s))));
            }
        }
        let image_due = sent.image_at.is_none_or(|t| t.elapsed() >= IMAGE_INTERVAL);
        if let (Some(id), true) = (subscribed(Channel::Preview), image_due) {
            if s.canvas_version != sent.canvas && !s.canvas.is_empty() {
                sent.canvas = s.canvas_version;
                sent.image_at = Some(Instant::now());
                let c = &s.canvas;
                let (h, rows, cols) = (c.heights.clone(), c.rows, c.cols);
                drop(s);
                if let Some(m) = preview_image(&h, rows, cols) {
                    out.push((id, json_bytes(&m)));
                }
            }
        }
    }
    if skipped > 0 {
        shared.lock().drops.foxglove_messages_skipped += skipped;
    }
    for (id, payload) in out {
        ws.send(Message::Binary(message_data(id, &payload).into()))
            .map_err(|e| anyhow!("Foxglove client: {e}"))?;
    }
    Ok(())
}

/// The protocol's binary Message Data: opcode 1, subscription id, receive time (ns), payload.
pub fn message_data(subscription: u32, payload: &[u8]) -> Vec<u8> {
    let mut m = Vec::with_capacity(13 + payload.len());
    m.push(0x01);
    m.extend_from_slice(&subscription.to_le_bytes());
    m.extend_from_slice(&surfstream_core::frame::monotonic_ns().to_le_bytes());
    m.extend_from_slice(payload);
    m
}

fn stamp() -> FoxgloveTime {
    FoxgloveTime::from_ns(surfstream_core::frame::monotonic_ns())
}

fn preview_image(heights: &[f32], rows: usize, cols: usize) -> Option<CompressedImage> {
    let range = surfstream_io::preview::robust_range_um(heights)?;
    let m = surfstream_io::preview::encode_map_png(heights, rows, cols, 2048, range).ok()?;
    Some(CompressedImage {
        timestamp: stamp(),
        frame_id: SCAN_FRAME_ID,
        data: base64::engine::general_purpose::STANDARD.encode(&m.png),
        format: "png",
    })
}

/// Every tile's box (1 um thick, at its registered position) and its planned outline, in
/// metres in the scan frame.
pub fn scene_update(s: &LiveState) -> SceneUpdate {
    let mut entities = Vec::new();
    for t in s.tiles.values() {
        let (Some(w), Some(h)) = (t.width_um, t.height_um) else {
            continue;
        };
        let mut cubes = Vec::new();
        let mut lines = Vec::new();
        if let (Some(x), Some(y)) = (t.x_um, t.y_um) {
            let (r, g, b) = match t.placement {
                Some(Placement::StageFallback) => (0.86, 0.15, 0.15),
                Some(Placement::WeakLink) => (0.95, 0.65, 0.1),
                _ => (0.2, 0.7, 0.3),
            };
            cubes.push(CubePrimitive {
                pose: Pose {
                    position: Vector3 {
                        x: (x + w / 2.0) * 1e-6,
                        y: (y + h / 2.0) * 1e-6,
                        z: 0.0,
                    },
                    orientation: Quaternion::IDENTITY,
                },
                size: Vector3 {
                    x: w * 1e-6,
                    y: h * 1e-6,
                    z: 1e-6,
                },
                color: Color { r, g, b, a: 0.35 },
            });
        }
        if let (Some(x), Some(y)) = (t.stage_x_um, t.stage_y_um) {
            let p = |dx: f64, dy: f64| Vector3 {
                x: (x + dx) * 1e-6,
                y: (y + dy) * 1e-6,
                z: 0.0,
            };
            lines.push(LinePrimitive {
                line_type: 1, // LINE_LOOP
                pose: Pose {
                    position: Vector3 {
                        x: 0.0,
                        y: 0.0,
                        z: 0.0,
                    },
                    orientation: Quaternion::IDENTITY,
                },
                thickness: 2.0,
                scale_invariant: true,
                points: vec![p(0.0, 0.0), p(w, 0.0), p(w, h), p(0.0, h)],
                color: Color {
                    r: 0.5,
                    g: 0.5,
                    b: 0.5,
                    a: 1.0,
                },
                colors: [],
                indices: [],
            });
        }
        entities.push(SceneEntity {
            timestamp: stamp(),
            frame_id: SCAN_FRAME_ID,
            id: format!("tile-{}", t.index),
            lifetime: FoxgloveTime::from_ns(0),
            frame_locked: false,
            metadata: vec![
                KeyValuePair {
                    key: "placement",
                    value: format!("{:?}", t.placement),
                },
                KeyValuePair {
                    key: "ncc",
                    value: t.ncc.map_or("-".into(), |n| format!("{n:.3}")),
                },
            ],
            arrows: [],
            cubes,
            spheres: [],
            cylinders: [],
            lines,
            triangles: [],
            texts: [],
            models: [],
        });
    }
    SceneUpdate {
        deletions: [],
        entities,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::Value;

    #[test]
    fn message_data_is_opcode_subscription_time_payload() {
        let m = message_data(7, b"{}");
        assert_eq!(m[0], 1);
        assert_eq!(u32::from_le_bytes(m[1..5].try_into().unwrap()), 7);
        assert!(u64::from_le_bytes(m[5..13].try_into().unwrap()) > 0);
        assert_eq!(&m[13..], b"{}");
    }

    #[test]
    fn the_advertisement_names_every_channel_with_its_schema() {
        let a = serde_json::to_value(advertise()).unwrap();
        let ch = a["channels"].as_array().unwrap();
        assert_eq!(ch.len(), 5);
        assert_eq!(ch[0]["topic"], "/tiles");
        assert_eq!(ch[0]["schemaName"], "foxglove.Grid");
        for c in ch {
            let schema: Value = serde_json::from_str(c["schema"].as_str().unwrap()).unwrap();
            assert_eq!(schema["title"], c["schemaName"]);
        }
    }

    #[test]
    fn tile_boxes_sit_at_their_registered_position_in_metres() {
        let mut s = LiveState::new("g", vec![(0, 0)], false);
        let mut tile = HeightMap {
            header: surfstream_core::frame::FrameHeader {
                width: 10,
                height: 20,
                pitch_x_um: 1.0,
                pitch_y_um: 1.0,
                origin_x_um: 100.0,
                ..Default::default()
            },
            heights: vec![0.0; 200],
        };
        tile.header.kind = surfstream_core::frame::FrameKind::Tile as u32;
        s.on_tile(tile);
        let r = surfstream_core::frame::TileRegistration {
            x_um: 102.0,
            placed_by: surfstream_core::frame::placed_by::STAGE,
            ..Default::default()
        };
        s.on_registration(&r, Instant::now());
        let u = serde_json::to_value(scene_update(&s)).unwrap();
        let e = &u["entities"][0];
        assert_eq!(e["id"], "tile-0");
        let cube = &e["cubes"][0];
        assert!((cube["pose"]["position"]["x"].as_f64().unwrap() - 107e-6).abs() < 1e-12);
        assert!((cube["size"]["y"].as_f64().unwrap() - 20e-6).abs() < 1e-12);
        assert_eq!(cube["color"]["r"], 0.86);
        assert!((e["lines"][0]["points"][1]["x"].as_f64().unwrap() - 110e-6).abs() < 1e-12);
        let p = serde_json::to_value(progress(&s)).unwrap();
        assert_eq!(p["tiles_planned"], 1);
        assert_eq!(p["tiles_registered"], 1);
        assert_eq!(p["stage_fallbacks"], 1);
        assert_eq!(p["verdict"], Value::Null);
        // Every key the message has, the schema declares.
        let schema: Value = serde_json::from_str(PROGRESS_SCHEMA).unwrap();
        for k in p.as_object().unwrap().keys() {
            assert!(
                schema["properties"].get(k).is_some(),
                "{k} not in the schema"
            );
        }
    }
}
