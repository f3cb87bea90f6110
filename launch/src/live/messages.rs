//! The Foxglove bridge's messages as typed records ([`super::foxglove`] builds and sends them):
//! the protocol's text operations (`foxglove.websocket.v1`: serverInfo, advertise, status
//! from the server; subscribe, unsubscribe from a client) and the channels' JSON payloads
//! (`foxglove.CompressedImage`, `foxglove.SceneUpdate`, `surfstream.Progress`). The frames'
//! `foxglove.Grid` and the parts shared with it (time, pose) are the recorder's, in
//! [`surfstream_io::recording`].

use serde::{Deserialize, Serialize};
use surfstream_io::recording::{FoxgloveTime, Pose, Vector3};

/// Server -> client text operations.
#[derive(Debug, Serialize)]
#[serde(tag = "op", rename_all = "camelCase")]
pub enum ServerOp {
    #[serde(rename_all = "camelCase")]
    ServerInfo {
        name: String,
        capabilities: [(); 0],
        supported_encodings: [(); 0],
        metadata: Empty,
        session_id: String,
    },
    Advertise {
        channels: Vec<ChannelAd>,
    },
    /// level: 0 info, 1 warning, 2 error.
    Status {
        level: u8,
        message: String,
    },
}

/// `{}`.
#[derive(Debug, Default, Serialize)]
pub struct Empty {}

/// One advertised channel.
#[derive(Debug, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct ChannelAd {
    pub id: u64,
    pub topic: &'static str,
    pub encoding: &'static str,
    pub schema_name: &'static str,
    pub schema: &'static str,
    pub schema_encoding: &'static str,
}

/// Client -> server text operations this read-only server reads.
#[derive(Debug, Deserialize)]
#[serde(tag = "op", rename_all = "camelCase")]
pub enum ClientOp {
    Subscribe {
        subscriptions: Vec<Subscription>,
    },
    #[serde(rename_all = "camelCase")]
    Unsubscribe {
        subscription_ids: Vec<u64>,
    },
}

/// A client's subscription: its id for the channel `channel_id`. Either may be missing or out
/// of range; the server answers that one with a warning and takes the others.
#[derive(Debug, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Subscription {
    #[serde(default)]
    pub id: Option<u64>,
    #[serde(default)]
    pub channel_id: Option<u64>,
}

/// `/panorama/preview`: `foxglove.CompressedImage`.
#[derive(Debug, Serialize)]
pub struct CompressedImage {
    pub timestamp: FoxgloveTime,
    pub frame_id: &'static str,
    /// base64 of the image file
    pub data: String,
    pub format: &'static str,
}

/// `/tiles/boxes`: `foxglove.SceneUpdate`.
#[derive(Debug, Serialize)]
pub struct SceneUpdate {
    pub deletions: [(); 0],
    pub entities: Vec<SceneEntity>,
}

/// `foxglove.SceneEntity`: one tile's box and outline. Foxglove reads every primitive list,
/// so the ones this bridge does not draw go as empty lists.
#[derive(Debug, Serialize)]
pub struct SceneEntity {
    pub timestamp: FoxgloveTime,
    pub frame_id: &'static str,
    pub id: String,
    pub lifetime: FoxgloveTime,
    pub frame_locked: bool,
    pub metadata: Vec<KeyValuePair>,
    pub arrows: [(); 0],
    pub cubes: Vec<CubePrimitive>,
    pub spheres: [(); 0],
    pub cylinders: [(); 0],
    pub lines: Vec<LinePrimitive>,
    pub triangles: [(); 0],
    pub texts: [(); 0],
    pub models: [(); 0],
}

/// `foxglove.KeyValuePair`.
#[derive(Debug, Serialize)]
pub struct KeyValuePair {
    pub key: &'static str,
    pub value: String,
}

/// `foxglove.Color`, each channel 0..1.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Color {
    pub r: f64,
    pub g: f64,
    pub b: f64,
    pub a: f64,
}

/// `foxglove.CubePrimitive` (m).
#[derive(Debug, Serialize)]
pub struct CubePrimitive {
    pub pose: Pose,
    pub size: Vector3,
    pub color: Color,
}

/// `foxglove.LinePrimitive` (m).
#[derive(Debug, Serialize)]
pub struct LinePrimitive {
    /// 0 line strip, 1 line loop, 2 line list.
    #[serde(rename = "type")]
    pub line_type: u8,
    pub pose: Pose,
    pub thickness: f64,
    pub scale_invariant: bool,
    pub points: Vec<Vector3>,
    pub color: Color,
    pub colors: [(); 0],
    pub indices: [(); 0],
}

/// `/progress`: `surfstream.Progress` (its schema: `PROGRESS_SCHEMA` in [`super::foxglove`]).
#[derive(Debug, Serialize)]
pub struct Progress {
    pub timestamp: FoxgloveTime,
    pub tiles_planned: Option<usize>,
    pub tiles_registered: usize,
    pub fields_per_s: Option<f64>,
    pub eta_s: Option<f64>,
    pub tile_to_panorama_ms: Option<f64>,
    pub pairs: usize,
    pub weak_links: usize,
    pub stage_fallbacks: usize,
    pub scan_ended: bool,
    pub verdict: Option<&'static str>,
}
