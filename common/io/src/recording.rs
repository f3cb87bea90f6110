//! MCAP recordings of surfstream channels: [`Recorder`] writes them, [`read_recording`] and
//! [`RecordingReader`] read them back.
//!
//! A recording is a standard MCAP file (chunked, zstd-compressed, with CRCs, indexes and a
//! summary) that describes itself: every channel's schema is a JSON Schema stored in the file
//! (schema encoding `jsonschema`) and every message is JSON (message encoding `json`), so a
//! reader that knows nothing of surfstream decodes it from the file alone, and Foxglove shows
//! the height maps. One MCAP channel per recorded surfstream port; its topic is the port name
//! (e.g. `stage/tiles`). Two channel kinds:
//!
//! - frames (tiles, panorama patches, datum, roughness, pooled maps, end-of-scan markers):
//!   schema `foxglove.Grid` ([`FRAME_JSON_SCHEMA`]), Foxglove's well-known grid, which its 3D
//!   and Image panels draw: `column_count` = width, `cell_size` = pitch in metres, `pose` at the
//!   frame's origin, one field `height_um` (FLOAT32) in `data` (base64 of the f32 little-endian
//!   heights, rows growing with scan y, NaN = not measured). One property more than Foxglove's
//!   schema, `surfstream`, holds the frame header exactly (`z_offset_um`, scan id, kind, flags,
//!   times), so absolute height = `z_offset_um` + `height_um` and a replay rebuilds every frame
//!   bit for bit.
//! - registrations: schema `surfstream.TileRegistration` ([`REGISTRATION_JSON_SCHEMA`]).
//!
//! f64 values are JSON numbers written with the shortest digits that read back to the same
//! f64 (serde_json, read with its `float_roundtrip` parser); a non-finite one is the string
//! "NaN", "inf" or "-inf". Why JSON with base64 rather than protobuf: Foxglove documents both
//! for MCAP and draws `foxglove.Grid` from either; JSON needs no code generator or descriptor
//! set, a Python reader decodes it with the standard library, and zstd takes back most of the
//! base64 overhead.
//!
//! Recordings made before this encoding (schema encoding `surfstream.bincode2`: a bincode 2
//! `FrameHeader` + raw f32 heights, or a bincode 2 `TileRegistration`) still read: the decoder
//! is kept, and only the writer moved on. The MCAP `log_time` of a message is the caller's
//! `log_time_ns`, its `publish_time` the `t_sent_ns` of the frame or registration, its
//! `sequence` a per-channel counter from 0.
//!
//! Writing goes to `<path>.partial` ([`surfstream_core::fsutil::partial_path`]) and [`Recorder::finish`]
//! renames the complete, synced file into place; a recorder dropped without `finish` removes its
//! partial file, so a crash or an error never leaves a file at `path` that looks complete.
//!
//! Reading checks everything and never panics on bad input: MCAP structure, chunk, data and
//! summary CRCs, the end magic, that every channel has one of the schemas above and every
//! message decodes exactly (every header field present and in range, the grid layout the one
//! written, data length = width * height * 4 checked before decoding, a known frame kind), and
//! that the summary's message count matches.
//! Errors name the file, the channel's topic and what was expected. A record longer than
//! max(64 MiB, 64 x the file size) after decompression is taken for a corrupt length rather than
//! allocated.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufReader, BufWriter, Read};
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use mcap::records::{MessageHeader, Record};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use serde::Serialize;

use surfstream_core::frame::{
    FrameHeader, FrameKind, HeightMap, TileRegistration, FRAME_TYPE_NAME, REGISTRATION_TYPE_NAME,
};

/// Schema encoding of recordings written before the JSON encoding (read, never written).
pub const LEGACY_SCHEMA_ENCODING: &str = "surfstream.bincode2";
/// Message encoding of legacy frame channels.
pub const LEGACY_FRAME_MESSAGE_ENCODING: &str = "surfstream.frame.v1";
/// Message encoding of legacy registration channels.
pub const LEGACY_REGISTRATION_MESSAGE_ENCODING: &str = "surfstream.registration.v1";

/// Target uncompressed chunk size of recordings, bytes (a 1024 x 1024 tile is one chunk).
const CHUNK_SIZE_BYTES: u64 = 4 * 1024 * 1024;

fn bincode_config() -> bincode::config::Configuration {
    bincode::config::standard()
}

/// Which of the two message types a channel carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ChannelKind {
    Frame,
    Registration,
}

impl ChannelKind {
    fn schema_name(self) -> &'static str {
        match self {
            Self::Frame => FRAME_SCHEMA_NAME,
            Self::Registration => REGISTRATION_SCHEMA_NAME,
        }
    }
    fn json_schema(self) -> &'static str {
        match self {
            Self::Frame => FRAME_JSON_SCHEMA,
            Self::Registration => REGISTRATION_JSON_SCHEMA,
        }
    }
    fn legacy_schema_name(self) -> &'static str {
        match self {
            Self::Frame => FRAME_TYPE_NAME,
            Self::Registration => REGISTRATION_TYPE_NAME,
        }
    }
    fn legacy_message_encoding(self) -> &'static str {
        match self {
            Self::Frame => LEGACY_FRAME_MESSAGE_ENCODING,
            Self::Registration => LEGACY_REGISTRATION_MESSAGE_ENCODING,
        }
    }
    fn name(self) -> &'static str {
        match self {
            Self::Frame => "frame",
            Self::Registration => "registration",
        }
    }
}

/// How a channel's messages are encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ChannelEncoding {
    /// JSON messages described by a JSON Schema in the file (what [`Recorder`] writes).
    Json,
    /// bincode 2 with a prose schema: recordings made before the JSON encoding (read only).
    LegacyBincode,
}

// ---------------------------------------------------------------------------------------------
// Writing

/// A channel of a [`Recorder`], returned by its `add_*_channel` methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ChannelId(u16);

struct RecorderChannel {
    topic: String,
    kind: ChannelKind,
    next_sequence: u32,
}

/// Writes an MCAP recording (see the module docs). Call [`Recorder::finish`] to keep it.
pub struct Recorder {
    path: PathBuf,
    partial: PathBuf,
    writer: Option<mcap::Writer<BufWriter<File>>>,
    channels: BTreeMap<u16, RecorderChannel>,
    schema_ids: HashMap<ChannelKind, u16>,
    buf: Vec<u8>,
    messages: u64,
    /// Set once the file is in place: the partial file is no longer ours to remove.
    finished: bool,
}

impl Recorder {
    /// Starts a recording that [`Recorder::finish`] puts at `path`; until then it is written to
    /// `<path>.partial` (an existing partial file is replaced).
    pub fn create(path: impl AsRef<Path>) -> Result<Recorder> {
        let path = path.as_ref().to_path_buf();
        let partial = surfstream_core::fsutil::partial_path(&path);
        let file = File::create(&partial)
            .with_context(|| format!("{}: cannot create", partial.display()))?;
        let options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(CHUNK_SIZE_BYTES))
            .profile("surfstream");
        let writer = match options.create(BufWriter::new(file)) {
            Ok(w) => w,
            Err(e) => {
                let _ = std::fs::remove_file(&partial);
                bail!(
                    "{}: cannot start the MCAP recording: {e}",
                    partial.display()
                );
            }
        };
        Ok(Recorder {
            path,
            partial,
            writer: Some(writer),
            channels: BTreeMap::new(),
            schema_ids: HashMap::new(),
            buf: Vec::new(),
            messages: 0,
            finished: false,
        })
    }

    /// Where the finished recording goes.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Number of messages written so far.
    pub fn message_count(&self) -> u64 {
        self.messages
    }

    /// Adds a channel of frames ([`FrameHeader`] + heights) named `topic` (the port name).
    pub fn add_frame_channel(
        &mut self,
        topic: &str,
        metadata: BTreeMap<String, String>,
    ) -> Result<ChannelId> {
        self.add_channel(topic, ChannelKind::Frame, metadata)
    }

    /// Adds a channel of [`TileRegistration`]s named `topic` (the port name).
    pub fn add_registration_channel(
        &mut self,
        topic: &str,
        metadata: BTreeMap<String, String>,
    ) -> Result<ChannelId> {
        self.add_channel(topic, ChannelKind::Registration, metadata)
    }

    fn add_channel(
        &mut self,
        topic: &str,
        kind: ChannelKind,
        metadata: BTreeMap<String, String>,
    ) -> Result<ChannelId> {
        if let Some(c) = self.channels.values().find(|c| c.topic == topic) {
            bail!(
                "{}: topic \"{topic}\" is already recorded (as a {} channel)",
                self.path.display(),
                c.kind.name()
            );
        }
        let partial = &self.partial;
        let writer = self
            .writer
            .as_mut()
            .ok_or_else(|| anyhow!("{}: recorder is closed", partial.display()))?;
        let schema_id = match self.schema_ids.get(&kind) {
            Some(&id) => id,
            None => {
                let id = writer
                    .add_schema(
                        kind.schema_name(),
                        JSON_SCHEMA_ENCODING,
                        kind.json_schema().as_bytes(),
                    )
                    .map_err(|e| {
                        anyhow!(
                            "{}: cannot add the {} schema: {e}",
                            partial.display(),
                            kind.name()
                        )
                    })?;
                self.schema_ids.insert(kind, id);
                id
            }
        };
        let id = writer
            .add_channel(schema_id, topic, JSON_MESSAGE_ENCODING, &metadata)
            .map_err(|e| anyhow!("{}: cannot add channel \"{topic}\": {e}", partial.display()))?;
        self.channels.insert(
            id,
            RecorderChannel {
                topic: topic.to_string(),
                kind,
                next_sequence: 0,
            },
        );
        Ok(ChannelId(id))
    }

    fn channel(&mut self, channel: ChannelId, kind: ChannelKind) -> Result<&mut RecorderChannel> {
        let path = &self.path;
        let c = self.channels.get_mut(&channel.0).ok_or_else(|| {
            anyhow!(
                "{}: channel {} was not added to this recorder",
                path.display(),
                channel.0
            )
        })?;
        if c.kind != kind {
            bail!(
                "{}: topic \"{}\" is a {} channel, cannot write a {} to it",
                path.display(),
                c.topic,
                c.kind.name(),
                kind.name()
            );
        }
        Ok(c)
    }

    /// Records one frame: `heights` must hold `header.width * header.height` values (none for a
    /// payload-less marker such as end of scan).
    pub fn write_frame(
        &mut self,
        channel: ChannelId,
        header: &FrameHeader,
        heights: &[f32],
        log_time_ns: u64,
    ) -> Result<()> {
        let expected = header.width as u64 * header.height as u64;
        let c = self.channel(channel, ChannelKind::Frame)?;
        if heights.len() as u64 != expected {
            bail!(
                "topic \"{}\": frame {} rows x {} cols needs {expected} heights, got {}",
                c.topic,
                header.height,
                header.width,
                heights.len()
            );
        }
        let mut buf = std::mem::take(&mut self.buf);
        if let Err(e) = encode_frame_json(header, heights, &mut buf) {
            self.buf = buf;
            return Err(e);
        }
        let result = self.write_message(channel, &buf, log_time_ns, header.t_sent_ns);
        self.buf = buf;
        result
    }

    /// Records one registration result.
    pub fn write_registration(
        &mut self,
        channel: ChannelId,
        registration: &TileRegistration,
        log_time_ns: u64,
    ) -> Result<()> {
        self.channel(channel, ChannelKind::Registration)?;
        let data = encode_registration_json(registration)?;
        self.write_message(channel, &data, log_time_ns, registration.t_sent_ns)
    }

    fn write_message(
        &mut self,
        channel: ChannelId,
        data: &[u8],
        log_time_ns: u64,
        publish_time_ns: u64,
    ) -> Result<()> {
        let partial = &self.partial;
        let writer = self
            .writer
            .as_mut()
            .ok_or_else(|| anyhow!("{}: recorder is closed", partial.display()))?;
        let c = self
            .channels
            .get_mut(&channel.0)
            .ok_or_else(|| anyhow!("unknown channel {}", channel.0))?;
        let header = MessageHeader {
            channel_id: channel.0,
            sequence: c.next_sequence,
            log_time: log_time_ns,
            publish_time: publish_time_ns,
        };
        // The mcap error's Display hides its io::Error source ("No space left on device"):
        // keep it as the source, so `{:#}` prints it.
        writer.write_to_known_channel(&header, data).map_err(|e| {
            anyhow::Error::new(e).context(format!(
                "{}: cannot record a message on \"{}\"",
                partial.display(),
                c.topic
            ))
        })?;
        c.next_sequence = c.next_sequence.wrapping_add(1);
        self.messages += 1;
        Ok(())
    }

    /// Completes the MCAP (summary, indexes, footer), syncs it to disk and renames it into place.
    /// On error the partial file is removed.
    pub fn finish(mut self) -> Result<()> {
        let partial = self.partial.clone();
        let mut writer = self
            .writer
            .take()
            .ok_or_else(|| anyhow!("{}: recorder is closed", partial.display()))?;
        let fail =
            |what: &str, e: &dyn std::fmt::Display| anyhow!("{}: {what}: {e}", partial.display());
        let finished = writer.finish();
        let buffered = writer.into_inner();
        // On any early return below, `self` drops and removes the partial file.
        finished.map_err(|e| {
            anyhow::Error::new(e).context(format!(
                "{}: cannot complete the MCAP recording",
                partial.display()
            ))
        })?;
        let file = buffered
            .into_inner()
            .map_err(|e| fail("write failed", &e.error().to_string()))?;
        file.sync_all().map_err(|e| fail("cannot sync", &e))?;
        drop(file);
        std::fs::rename(&partial, &self.path)
            .map_err(|e| anyhow!("{}: cannot rename into place: {e}", self.path.display()))?;
        self.finished = true;
        if let Some(dir) = self.path.parent().filter(|d| !d.as_os_str().is_empty()) {
            // Persist the rename; not all filesystems allow syncing a directory.
            let _ = File::open(dir).and_then(|d| d.sync_all());
        }
        Ok(())
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        if self.finished {
            return;
        }
        if let Some(writer) = self.writer.take() {
            // Release the file without writing a summary (`into_inner` skips the summary that
            // dropping an mcap writer would write).
            drop(writer.into_inner());
        }
        let _ = std::fs::remove_file(&self.partial);
    }
}

// ---------------------------------------------------------------------------------------------
// Reading

/// A channel of a recording.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    pub topic: String,
    pub kind: ChannelKind,
    pub encoding: ChannelEncoding,
    pub metadata: BTreeMap<String, String>,
}

/// One recorded message, decoded.
#[derive(Debug, Clone, PartialEq)]
pub enum Recorded {
    Frame(HeightMap),
    Registration(TileRegistration),
}

/// A message with its channel's topic and log time.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedMessage {
    pub topic: String,
    pub log_time_ns: u64,
    pub message: Recorded,
}

/// A whole recording in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    /// Every channel, in the order they were added.
    pub channels: Vec<ChannelInfo>,
    /// Every message, in log-time order (file order among equal log times).
    pub messages: Vec<RecordedMessage>,
}

/// Reads and checks a whole recording. See [`RecordingReader`] to stream one instead.
pub fn read_recording(path: impl AsRef<Path>) -> Result<Recording> {
    let mut reader = RecordingReader::open(path)?;
    let mut messages = Vec::new();
    for m in &mut reader {
        messages.push(m?);
    }
    messages.sort_by_key(|m| m.log_time_ns);
    Ok(Recording {
        channels: reader.channels(),
        messages,
    })
}

/// Streams a recording's messages in file order, checking each; yields an error (and then
/// nothing) at the first problem. Structural problems at the end of the file (a truncated
/// summary, a bad summary CRC, a missing end magic) are reported after the last message, so a
/// caller that must not act on a damaged recording should read it whole first
/// ([`read_recording`]).
pub struct RecordingReader {
    path: PathBuf,
    file: BufReader<File>,
    reader: LinearReader,
    /// Schema id -> (name, encoding).
    schemas: HashMap<u16, (String, String)>,
    /// Channel id -> channel.
    channels: BTreeMap<u16, ChannelInfo>,
    past_data_end: bool,
    messages_read: u64,
    summary_message_count: Option<u64>,
    done: bool,
}

/// Messages larger than this many times the file size (after decompression) are taken for
/// corruption rather than allocated; at least [`MIN_RECORD_LIMIT_BYTES`].
const RECORD_LIMIT_FILE_FACTOR: u64 = 64;
const MIN_RECORD_LIMIT_BYTES: u64 = 64 * 1024 * 1024;

impl RecordingReader {
    /// Opens a recording for streaming.
    pub fn open(path: impl AsRef<Path>) -> Result<RecordingReader> {
        let path = path.as_ref().to_path_buf();
        // A folder read as "no such file", a FIFO blocked, /dev/zero never ended (issue 36).
        crate::input::check_regular_file(&path, "a .mcap recording")?;
        let file = File::open(&path).with_context(|| format!("{}: cannot open", path.display()))?;
        let len = file
            .metadata()
            .with_context(|| format!("{}: cannot read", path.display()))?
            .len();
        let limit = len
            .saturating_mul(RECORD_LIMIT_FILE_FACTOR)
            .max(MIN_RECORD_LIMIT_BYTES);
        let options = LinearReaderOptions::default()
            .with_prevalidate_chunk_crcs(true)
            .with_validate_chunk_crcs(true)
            .with_validate_data_section_crc(true)
            .with_validate_summary_section_crc(true)
            .with_check_finishes_after_end_magic(true)
            .with_record_length_limit(usize::try_from(limit).unwrap_or(usize::MAX));
        Ok(RecordingReader {
            path,
            file: BufReader::with_capacity(1 << 20, file),
            reader: LinearReader::new_with_options(options),
            schemas: HashMap::new(),
            channels: BTreeMap::new(),
            past_data_end: false,
            messages_read: 0,
            summary_message_count: None,
            done: false,
        })
    }

    /// The channels defined so far (all of them once the reader is exhausted), in id order.
    pub fn channels(&self) -> Vec<ChannelInfo> {
        self.channels.values().cloned().collect()
    }

    fn next_checked(&mut self) -> Option<Result<RecordedMessage>> {
        loop {
            let event = match self.reader.next_event() {
                None => return self.at_end(),
                Some(Err(e)) => return Some(Err(self.mcap_error(e))),
                Some(Ok(event)) => event,
            };
            let (opcode, data) = match event {
                LinearReadEvent::ReadRequest(n) => {
                    let buf = self.reader.insert(n);
                    let read = loop {
                        match self.file.read(buf) {
                            Ok(k) => break k,
                            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                            Err(e) => {
                                return Some(Err(anyhow!(
                                    "{}: read failed: {e}",
                                    self.path.display()
                                )))
                            }
                        }
                    };
                    self.reader.notify_read(read);
                    continue;
                }
                LinearReadEvent::Record { opcode, data } => (opcode, data),
            };
            // Only the records this reader uses are parsed: the others (attachments,
            // metadata, indexes) are skipped unread. mcap 0.26's parser panics on some
            // malformed ones (an attachment shorter than its own header: "slice index starts
            // at 32 but ends at 30", found by the fuzzer), and a recording is user input.
            use mcap::records::op;
            if !matches!(
                opcode,
                op::SCHEMA | op::CHANNEL | op::MESSAGE | op::STATISTICS | op::DATA_END
            ) {
                continue;
            }
            let record = match mcap::parse_record(opcode, data) {
                Ok(r) => r,
                Err(e) => {
                    return Some(Err(anyhow!(
                        "{}: corrupt MCAP recording: bad record (opcode {opcode:#04x}) \
                         after {} messages: {e}",
                        self.path.display(),
                        self.messages_read
                    )))
                }
            };
            if self.past_data_end {
                // The summary repeats schemas and channels; only its statistics are checked.
                if let Record::Statistics(s) = record {
                    self.summary_message_count = Some(s.message_count);
                }
                continue;
            }
            match record {
                Record::DataEnd(_) => self.past_data_end = true,
                Record::Schema { header, data: _ } => {
                    if let Err(e) = self.add_schema(header.id, header.name, header.encoding) {
                        return Some(Err(e));
                    }
                }
                Record::Channel(c) => {
                    if let Err(e) = self.add_channel(c) {
                        return Some(Err(e));
                    }
                }
                Record::Message { header, data } => {
                    let r = decode_message(
                        &self.path,
                        &self.channels,
                        self.messages_read,
                        &header,
                        &data,
                    );
                    self.messages_read += 1;
                    return Some(r);
                }
                _ => {}
            }
        }
    }

    fn at_end(&mut self) -> Option<Result<RecordedMessage>> {
        if !self.past_data_end {
            return Some(Err(anyhow!(
                "{}: truncated MCAP recording: no data end record (after {} messages)",
                self.path.display(),
                self.messages_read
            )));
        }
        if let Some(n) = self.summary_message_count {
            if n != self.messages_read {
                return Some(Err(anyhow!(
                    "{}: corrupt MCAP recording: the summary counts {n} messages, \
                     the file holds {}",
                    self.path.display(),
                    self.messages_read
                )));
            }
        }
        None
    }

    fn mcap_error(&self, e: mcap::McapError) -> anyhow::Error {
        let p = self.path.display();
        let n = self.messages_read;
        match e {
            mcap::McapError::UnexpectedEof => {
                anyhow!(
                    "{p}: truncated or corrupt MCAP recording: the file ends in the middle \
                     of a record (after {n} messages)"
                )
            }
            mcap::McapError::BadMagic => anyhow!(
                "{p}: not a complete MCAP file: bad magic bytes (expected \\x89MCAP0\\r\\n \
                 at the start and the end; after {n} messages)"
            ),
            e => anyhow!("{p}: corrupt MCAP recording (after {n} messages): {e}"),
        }
    }

    fn add_schema(&mut self, id: u16, name: String, encoding: String) -> Result<()> {
        if id == 0 {
            bail!(
                "{}: corrupt MCAP recording: schema \"{name}\" has the reserved id 0",
                self.path.display()
            );
        }
        if let Some(prev) = self.schemas.get(&id) {
            if prev.0 != name || prev.1 != encoding {
                bail!(
                    "{}: schema id {id} is defined twice, as \"{}\" and as \"{name}\"",
                    self.path.display(),
                    prev.0
                );
            }
            return Ok(());
        }
        self.schemas.insert(id, (name, encoding));
        Ok(())
    }

    fn add_channel(&mut self, c: mcap::records::Channel) -> Result<()> {
        let p = self.path.display();
        let topic = &c.topic;
        if c.schema_id == 0 {
            bail!(
                "{p}: topic \"{topic}\" (channel {}) has no schema; expected {}",
                c.id,
                expected_kinds()
            );
        }
        let (name, encoding) = self.schemas.get(&c.schema_id).ok_or_else(|| {
            anyhow!(
                "{p}: topic \"{topic}\" (channel {}) refers to schema {}, which is not defined",
                c.id,
                c.schema_id
            )
        })?;
        let kinds = [ChannelKind::Frame, ChannelKind::Registration];
        let json = kinds.into_iter().find(|k| {
            k.schema_name() == name
                && encoding == JSON_SCHEMA_ENCODING
                && c.message_encoding == JSON_MESSAGE_ENCODING
        });
        let legacy = kinds.into_iter().find(|k| {
            k.legacy_schema_name() == name
                && encoding == LEGACY_SCHEMA_ENCODING
                && k.legacy_message_encoding() == c.message_encoding
        });
        let (kind, channel_encoding) = match (json, legacy) {
            (Some(k), _) => (k, ChannelEncoding::Json),
            (None, Some(k)) => (k, ChannelEncoding::LegacyBincode),
            (None, None) => bail!(
                "{p}: topic \"{topic}\" (channel {}) has schema \"{name}\" (encoding \
                 \"{encoding}\") and message encoding \"{}\"; expected {}",
                c.id,
                c.message_encoding,
                expected_kinds()
            ),
        };
        let info = ChannelInfo {
            topic: c.topic,
            kind,
            encoding: channel_encoding,
            metadata: c.metadata,
        };
        if let Some(prev) = self.channels.get(&c.id) {
            if *prev != info {
                bail!(
                    "{p}: channel id {} is defined twice, as \"{}\" and as \"{}\"",
                    c.id,
                    prev.topic,
                    info.topic
                );
            }
            return Ok(());
        }
        self.channels.insert(c.id, info);
        Ok(())
    }
}

/// Decodes message number `index` of the file (for error messages).
fn decode_message(
    path: &Path,
    channels: &BTreeMap<u16, ChannelInfo>,
    index: u64,
    header: &MessageHeader,
    data: &[u8],
) -> Result<RecordedMessage> {
    let channel = channels.get(&header.channel_id).ok_or_else(|| {
        anyhow!(
            "{}: message {} (log time {} ns) is on channel {}, which is not defined before it",
            path.display(),
            index,
            header.log_time,
            header.channel_id
        )
    })?;
    let message = match (channel.kind, channel.encoding) {
        (ChannelKind::Frame, ChannelEncoding::Json) => decode_frame_json(data).map(Recorded::Frame),
        (ChannelKind::Registration, ChannelEncoding::Json) => {
            decode_registration_json(data).map(Recorded::Registration)
        }
        (ChannelKind::Frame, ChannelEncoding::LegacyBincode) => {
            decode_frame(data).map(Recorded::Frame)
        }
        (ChannelKind::Registration, ChannelEncoding::LegacyBincode) => {
            decode_registration(data).map(Recorded::Registration)
        }
    }
    .map_err(|what| {
        anyhow!(
            "{}: topic \"{}\", message {} (log time {} ns): {what}",
            path.display(),
            channel.topic,
            index,
            header.log_time
        )
    })?;
    Ok(RecordedMessage {
        topic: channel.topic.clone(),
        log_time_ns: header.log_time,
        message,
    })
}

fn expected_kinds() -> String {
    format!(
        "schema \"{FRAME_SCHEMA_NAME}\" or \"{REGISTRATION_SCHEMA_NAME}\" (encoding \
         \"{JSON_SCHEMA_ENCODING}\", message encoding \"{JSON_MESSAGE_ENCODING}\"), or from an \
         older recording schema \"{FRAME_TYPE_NAME}\" with message encoding \
         \"{LEGACY_FRAME_MESSAGE_ENCODING}\" or \"{REGISTRATION_TYPE_NAME}\" with message encoding \
         \"{LEGACY_REGISTRATION_MESSAGE_ENCODING}\" (encoding \"{LEGACY_SCHEMA_ENCODING}\")"
    )
}

impl Iterator for RecordingReader {
    type Item = Result<RecordedMessage>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        // The mcap crate checks its input, but a reader of untrusted files must not take the
        // process down if some corner of it does not: a panic becomes an error.
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.next_checked()));
        let item = match result {
            Ok(item) => item,
            Err(panic) => {
                let what = panic
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| panic.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into());
                Some(Err(anyhow!(
                    "{}: corrupt MCAP recording: the MCAP reader failed \
                     (after {} messages): {what}",
                    self.path.display(),
                    self.messages_read
                )))
            }
        };
        if !matches!(item, Some(Ok(_))) {
            self.done = true;
        }
        item
    }
}

/// Decodes the message data of a frame channel; the error says what was wrong.
fn decode_frame(data: &[u8]) -> std::result::Result<HeightMap, String> {
    let Some((len_bytes, rest)) = data.split_first_chunk::<4>() else {
        return Err(format!(
            "frame message is {} bytes, shorter than its 4-byte header length",
            data.len()
        ));
    };
    let header_len = u32::from_le_bytes(*len_bytes) as usize;
    if header_len > rest.len() {
        return Err(format!(
            "frame header length {header_len} bytes is larger than the message \
             ({} bytes after the length)",
            rest.len()
        ));
    }
    let (header_bytes, payload) = rest.split_at(header_len);
    let (header, used): (FrameHeader, usize) =
        bincode::serde::decode_from_slice(header_bytes, bincode_config()).map_err(|e| {
            format!("cannot decode the {FRAME_TYPE_NAME} header ({header_len} bytes): {e}")
        })?;
    if used != header_len {
        return Err(format!(
            "the frame header is {used} bytes but its length field says {header_len}"
        ));
    }
    if FrameKind::from_u32(header.kind).is_none() {
        return Err(format!(
            "unknown frame kind {} (expected 1..=7)",
            header.kind
        ));
    }
    let expected = header.width as u64 * header.height as u64 * 4;
    if payload.len() as u64 != expected {
        return Err(format!(
            "frame payload is {} bytes, expected rows * cols * 4 = {} x {} x 4 = {expected}",
            payload.len(),
            header.height,
            header.width
        ));
    }
    let heights = payload
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Ok(HeightMap { header, heights })
}

/// Decodes the message data of a registration channel.
fn decode_registration(data: &[u8]) -> std::result::Result<TileRegistration, String> {
    let (reg, used): (TileRegistration, usize) =
        bincode::serde::decode_from_slice(data, bincode_config()).map_err(|e| {
            format!(
                "cannot decode the {REGISTRATION_TYPE_NAME} message ({} bytes): {e}",
                data.len()
            )
        })?;
    if used != data.len() {
        return Err(format!(
            "{} bytes after the {REGISTRATION_TYPE_NAME} message ({used} bytes)",
            data.len() - used
        ));
    }
    Ok(reg)
}

// ---------------------------------------------------------------------------------------------
// The self-describing encoding (JSON messages, JSON Schema schemas)

/// Schema encoding of the schemas written now.
pub const JSON_SCHEMA_ENCODING: &str = "jsonschema";
/// Message encoding of the channels written now.
pub const JSON_MESSAGE_ENCODING: &str = "json";
/// Schema name of frame channels: Foxglove's well-known grid, which its 3D and Image panels show.
pub const FRAME_SCHEMA_NAME: &str = "foxglove.Grid";
/// Schema name of registration channels.
pub const REGISTRATION_SCHEMA_NAME: &str = "surfstream.TileRegistration";
/// `frame_id` of every grid: the scan coordinates (x along columns, y along rows).
pub const SCAN_FRAME_ID: &str = "surfstream_scan";
/// The one field of a grid's `data`: f32 heights in micrometres relative to `z_offset_um`.
pub const HEIGHT_FIELD: &str = "height_um";
/// Foxglove's NumericType of an f32.
const NUMERIC_TYPE_FLOAT32: u64 = 7;

/// JSON Schema of a number that may also be a non-finite float spelled as a string.
macro_rules! float_schema {
    ($desc:literal) => {
        concat!(
            r#"{"type": ["number", "string"], "description": ""#,
            $desc,
            r#" (f64; written with enough digits to read back bit for bit; a non-finite value is the string \"NaN\", \"inf\" or \"-inf\")"}"#
        )
    };
}

/// JSON Schema of frame messages: Foxglove's `foxglove.Grid` (same properties, same meaning, so
/// Foxglove shows the heights as a grid in its 3D and Image panels) plus one property,
/// `surfstream`, that holds the frame header exactly.
pub const FRAME_JSON_SCHEMA: &str = concat!(
    r#"{
  "title": "foxglove.Grid",
  "description": "A 2D grid of data: one surfstream height map (a tile, a panorama patch, a datum, roughness or pooled map, or an end-of-scan marker without cells). Foxglove's foxglove.Grid plus the property surfstream, the exact frame header.",
  "$comment": "Properties as in https://docs.foxglove.dev/docs/sdk/schemas/grid; surfstream is an addition that Foxglove ignores.",
  "type": "object",
  "properties": {
    "timestamp": {"type": "object", "title": "time", "description": "Timestamp of grid: the frame's t_sent_ns (CLOCK_MONOTONIC of the sending host)",
      "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}},
    "frame_id": {"type": "string", "description": "Frame of reference: surfstream_scan, the scan coordinates in metres (x along columns, y along rows)"},
    "pose": {"title": "foxglove.Pose", "type": "object", "description": "Origin of grid's corner relative to frame of reference; grid is positioned in the x-y plane relative to this origin. Position = (origin_x_um, origin_y_um, z_offset_um) in metres for display (0 where not finite); the exact values are in surfstream",
      "properties": {
        "position": {"title": "foxglove.Vector3", "type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}, "required": ["x", "y", "z"]},
        "orientation": {"title": "foxglove.Quaternion", "type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}, "w": {"type": "number"}}, "required": ["x", "y", "z", "w"]}},
      "required": ["position", "orientation"]},
    "column_count": {"type": "integer", "minimum": 0, "description": "Number of grid columns (the frame's width)"},
    "cell_size": {"title": "foxglove.Vector2", "type": "object", "description": "Size of single grid cell along x and y axes, relative to pose: the pitch in metres",
      "properties": {"x": {"type": "number"}, "y": {"type": "number"}}, "required": ["x", "y"]},
    "row_stride": {"type": "integer", "minimum": 0, "description": "Number of bytes between rows in data"},
    "cell_stride": {"type": "integer", "minimum": 0, "description": "Number of bytes between cells within a row in data"},
    "fields": {"type": "array", "description": "Fields in data: one, height_um, FLOAT32 at offset 0",
      "items": {"title": "foxglove.PackedElementField", "type": "object",
        "properties": {
          "name": {"type": "string", "description": "Name of the field"},
          "offset": {"type": "integer", "minimum": 0, "description": "Byte offset from start of data buffer"},
          "type": {"title": "foxglove.NumericType", "description": "Type of data in the field. Integers are stored using little-endian byte order.",
            "oneOf": [{"title": "UNKNOWN", "const": 0}, {"title": "UINT8", "const": 1}, {"title": "INT8", "const": 2}, {"title": "UINT16", "const": 3}, {"title": "INT16", "const": 4}, {"title": "UINT32", "const": 5}, {"title": "INT32", "const": 6}, {"title": "FLOAT32", "const": 7}, {"title": "FLOAT64", "const": 8}]}},
        "required": ["name", "offset", "type"]}},
    "data": {"type": "string", "contentEncoding": "base64", "description": "Grid cell data, interpreted using fields, in row-major (y-major) order: height_um, float32 little-endian, micrometres relative to surfstream.z_offset_um, NaN = not measured; row index grows with scan y, column index with scan x"},
    "surfstream": {"title": "surfstream.FrameHeader", "type": "object", "description": "The frame header, exactly (DESIGN section 2); absolute height = z_offset_um + height_um",
      "properties": {
        "kind": {"description": "What the frame holds", "oneOf": [{"title": "tile", "const": 1}, {"title": "panorama_patch", "const": 2}, {"title": "panorama", "const": 3}, {"title": "datum", "const": 4}, {"title": "roughness", "const": 5}, {"title": "pooled", "const": 6}, {"title": "marker", "const": 7}]},
        "flags": {"type": "integer", "minimum": 0, "description": "Bit set: 1 final, 2 end of scan, 4 placed by stage, 8 preview"},
        "scan_id": {"type": "integer", "minimum": 0, "description": "u64, identifies one scan"},
        "sequence": {"type": "integer", "minimum": 0, "description": "u64, per-channel sequence number"},
        "tile_index": {"type": "integer", "minimum": 0, "description": "Acquisition index of the tile that caused this frame"},
        "tile_row": {"type": "integer", "minimum": 0, "description": "Grid row of that tile (tiles only)"},
        "tile_col": {"type": "integer", "minimum": 0, "description": "Grid column of that tile (tiles only)"},
        "width": {"type": "integer", "minimum": 0, "description": "Columns (= column_count)"},
        "height": {"type": "integer", "minimum": 0, "description": "Rows"},
        "pitch_x_um": "#,
    float_schema!("Column spacing, micrometres"),
    r#",
        "pitch_y_um": "#,
    float_schema!("Row spacing, micrometres"),
    r#",
        "origin_x_um": "#,
    float_schema!("Scan x of cell (0, 0), micrometres"),
    r#",
        "origin_y_um": "#,
    float_schema!("Scan y of cell (0, 0), micrometres"),
    r#",
        "z_offset_um": "#,
    float_schema!("Heights in data are relative to this, micrometres"),
    r#",
        "t_acquired_ns": {"type": "integer", "minimum": 0, "description": "u64, CLOCK_MONOTONIC when the causing tile was acquired"},
        "t_sent_ns": {"type": "integer", "minimum": 0, "description": "u64, CLOCK_MONOTONIC when this frame was sent"}},
      "required": ["kind", "flags", "scan_id", "sequence", "tile_index", "tile_row", "tile_col", "width", "height", "pitch_x_um", "pitch_y_um", "origin_x_um", "origin_y_um", "z_offset_um", "t_acquired_ns", "t_sent_ns"]}
  },
  "required": ["timestamp", "frame_id", "pose", "column_count", "cell_size", "row_stride", "cell_stride", "fields", "data", "surfstream"]
}
"#
);

/// JSON Schema of registration messages.
pub const REGISTRATION_JSON_SCHEMA: &str = concat!(
    r#"{
  "title": "surfstream.TileRegistration",
  "description": "Where one tile goes in the panorama and how its heights are levelled into it; sent once per tile, and once more (flag final) after the global solve at the end of the scan",
  "type": "object",
  "properties": {
    "scan_id": {"type": "integer", "minimum": 0, "description": "u64, identifies one scan"},
    "sequence": {"type": "integer", "minimum": 0, "description": "u64, per-channel sequence number"},
    "tile_index": {"type": "integer", "minimum": 0, "description": "Acquisition index of the tile"},
    "placed_by": {"description": "How the position was found", "oneOf": [{"title": "registration", "const": 1}, {"title": "stage", "const": 2}]},
    "flags": {"type": "integer", "minimum": 0, "description": "Bit set: 1 final, 2 end of scan (no tile)"},
    "links_accepted": {"type": "integer", "minimum": 0, "description": "Neighbour links accepted"},
    "links_tried": {"type": "integer", "minimum": 0, "description": "Neighbour links tried"},
    "x_um": "#,
    float_schema!("Final scan x of the tile's pixel (0, 0), micrometres"),
    r#",
    "y_um": "#,
    float_schema!("Final scan y of the tile's pixel (0, 0), micrometres"),
    r#",
    "piston_um": "#,
    float_schema!("Height correction piston, micrometres"),
    r#",
    "tilt_x_um_per_px": "#,
    float_schema!(
        "Height correction tilt along columns, micrometres per pixel from the tile centre"
    ),
    r#",
    "tilt_y_um_per_px": "#,
    float_schema!("Height correction tilt along rows, micrometres per pixel from the tile centre"),
    r#",
    "quality": "#,
    float_schema!("Best link quality (normalized cross-correlation), 0 if none"),
    r#",
    "t_acquired_ns": {"type": "integer", "minimum": 0, "description": "u64, CLOCK_MONOTONIC when the tile was acquired"},
    "t_sent_ns": {"type": "integer", "minimum": 0, "description": "u64, CLOCK_MONOTONIC when this message was sent"}
  },
  "required": ["scan_id", "sequence", "tile_index", "placed_by", "flags", "links_accepted", "links_tried", "x_um", "y_um", "piston_um", "tilt_x_um_per_px", "tilt_y_um_per_px", "quality", "t_acquired_ns", "t_sent_ns"]
}
"#
);

/// For display fields Foxglove needs as numbers.
fn finite_or_zero(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// A JSON number, or the text "NaN" / "inf" / "-inf" where JSON has no number (the schemas
/// declare these fields `["number", "string"]`).
#[derive(Debug, Clone, Copy)]
pub struct JsonF64(pub f64);

impl Serialize for JsonF64 {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        let v = self.0;
        if v.is_finite() {
            s.serialize_f64(v)
        } else if v.is_nan() {
            s.serialize_str("NaN")
        } else if v > 0.0 {
            s.serialize_str("inf")
        } else {
            s.serialize_str("-inf")
        }
    }
}

// Foxglove's well-known message parts (also the live bridge's). Fields in key order: the
// messages have always listed their keys sorted.

/// `foxglove.Time`.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FoxgloveTime {
    pub nsec: u64,
    pub sec: u64,
}

impl FoxgloveTime {
    pub fn from_ns(ns: u64) -> Self {
        FoxgloveTime {
            nsec: ns % 1_000_000_000,
            sec: ns / 1_000_000_000,
        }
    }
}

/// `foxglove.Vector3` (m).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `foxglove.Quaternion`.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Quaternion {
    pub w: f64,
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Quaternion {
    pub const IDENTITY: Quaternion = Quaternion {
        w: 1.0,
        x: 0.0,
        y: 0.0,
        z: 0.0,
    };
}

/// `foxglove.Pose`.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Pose {
    pub orientation: Quaternion,
    pub position: Vector3,
}

/// `foxglove.Vector2` (m).
#[derive(Debug, Clone, Copy, Serialize)]
struct Vector2 {
    x: f64,
    y: f64,
}

/// `foxglove.PackedElementField`.
#[derive(Debug, Clone, Copy, Serialize)]
struct PackedElementField {
    name: &'static str,
    offset: u32,
    #[serde(rename = "type")]
    numeric_type: u64,
}

/// A frame's `foxglove.Grid` without its `data` (appended after, see [`encode_frame_json`]).
#[derive(Serialize)]
struct GridMessage {
    cell_size: Vector2,
    cell_stride: u32,
    column_count: u32,
    fields: [PackedElementField; 1],
    frame_id: &'static str,
    pose: Pose,
    row_stride: u64,
    surfstream: FrameFields,
    timestamp: FoxgloveTime,
}

/// The frame header as the `surfstream` member of a frame message (in key order).
#[derive(Serialize)]
struct FrameFields {
    flags: u32,
    height: u32,
    kind: u32,
    origin_x_um: JsonF64,
    origin_y_um: JsonF64,
    pitch_x_um: JsonF64,
    pitch_y_um: JsonF64,
    scan_id: u64,
    sequence: u64,
    t_acquired_ns: u64,
    t_sent_ns: u64,
    tile_col: u32,
    tile_index: u32,
    tile_row: u32,
    width: u32,
    z_offset_um: JsonF64,
}

/// The JSON message of a frame (see [`FRAME_JSON_SCHEMA`]) into `out` (also the live
/// Foxglove bridge's `foxglove.Grid` messages).
pub fn encode_frame_json(h: &FrameHeader, heights: &[f32], out: &mut Vec<u8>) -> Result<()> {
    use base64::Engine as _;
    let message = GridMessage {
        cell_size: Vector2 {
            x: finite_or_zero(h.pitch_x_um * 1e-6),
            y: finite_or_zero(h.pitch_y_um * 1e-6),
        },
        cell_stride: 4,
        column_count: h.width,
        fields: [PackedElementField {
            name: HEIGHT_FIELD,
            offset: 0,
            numeric_type: NUMERIC_TYPE_FLOAT32,
        }],
        frame_id: SCAN_FRAME_ID,
        pose: Pose {
            orientation: Quaternion::IDENTITY,
            position: Vector3 {
                x: finite_or_zero(h.origin_x_um * 1e-6),
                y: finite_or_zero(h.origin_y_um * 1e-6),
                z: finite_or_zero(h.z_offset_um * 1e-6),
            },
        },
        row_stride: h.width as u64 * 4,
        surfstream: FrameFields {
            flags: h.flags,
            height: h.height,
            kind: h.kind,
            origin_x_um: JsonF64(h.origin_x_um),
            origin_y_um: JsonF64(h.origin_y_um),
            pitch_x_um: JsonF64(h.pitch_x_um),
            pitch_y_um: JsonF64(h.pitch_y_um),
            scan_id: h.scan_id,
            sequence: h.sequence,
            t_acquired_ns: h.t_acquired_ns,
            t_sent_ns: h.t_sent_ns,
            tile_col: h.tile_col,
            tile_index: h.tile_index,
            tile_row: h.tile_row,
            width: h.width,
            z_offset_um: JsonF64(h.z_offset_um),
        },
        timestamp: FoxgloveTime::from_ns(h.t_sent_ns),
    };
    out.clear();
    serde_json::to_writer(&mut *out, &message)
        .map_err(|e| anyhow!("cannot encode a frame message: {e}"))?;
    // The cells go in last, base64 straight into the buffer (no escaping is ever needed), not
    // through a multi-megabyte JSON string value.
    if out.pop() != Some(b'}') {
        bail!("cannot encode a frame message: JSON object expected");
    }
    let raw: Vec<u8> = heights.iter().flat_map(|h| h.to_le_bytes()).collect();
    out.extend_from_slice(b",\"data\":\"");
    let start = out.len();
    out.resize(start + base64::encoded_len(raw.len(), true).unwrap_or(0), 0);
    let written = base64::engine::general_purpose::STANDARD
        .encode_slice(&raw, &mut out[start..])
        .map_err(|e| anyhow!("cannot encode a frame message: {e}"))?;
    out.truncate(start + written);
    out.extend_from_slice(b"\"}");
    Ok(())
}

/// A registration's JSON message (see [`REGISTRATION_JSON_SCHEMA`]), in key order.
#[derive(Serialize)]
struct RegistrationMessage {
    flags: u32,
    links_accepted: u32,
    links_tried: u32,
    piston_um: JsonF64,
    placed_by: u32,
    quality: JsonF64,
    scan_id: u64,
    sequence: u64,
    t_acquired_ns: u64,
    t_sent_ns: u64,
    tile_index: u32,
    tilt_x_um_per_px: JsonF64,
    tilt_y_um_per_px: JsonF64,
    x_um: JsonF64,
    y_um: JsonF64,
}

/// The JSON message of a registration (see [`REGISTRATION_JSON_SCHEMA`]).
fn encode_registration_json(r: &TileRegistration) -> Result<Vec<u8>> {
    let message = RegistrationMessage {
        flags: r.flags,
        links_accepted: r.links_accepted,
        links_tried: r.links_tried,
        piston_um: JsonF64(r.piston_um),
        placed_by: r.placed_by,
        quality: JsonF64(r.quality),
        scan_id: r.scan_id,
        sequence: r.sequence,
        t_acquired_ns: r.t_acquired_ns,
        t_sent_ns: r.t_sent_ns,
        tile_index: r.tile_index,
        tilt_x_um_per_px: JsonF64(r.tilt_x_um_per_px),
        tilt_y_um_per_px: JsonF64(r.tilt_y_um_per_px),
        x_um: JsonF64(r.x_um),
        y_um: JsonF64(r.y_um),
    };
    serde_json::to_vec(&message).map_err(|e| anyhow!("cannot encode a registration: {e}"))
}

/// Reads the members of one JSON object, naming the object (`what`) in every error.
struct JsonFields<'a> {
    what: &'static str,
    object: &'a serde_json::Map<String, serde_json::Value>,
}

impl<'a> JsonFields<'a> {
    fn of(value: &'a serde_json::Value, what: &'static str) -> std::result::Result<Self, String> {
        let object = value
            .as_object()
            .ok_or_else(|| format!("{what} is not a JSON object"))?;
        Ok(Self { what, object })
    }
    fn get(&self, key: &str) -> std::result::Result<&'a serde_json::Value, String> {
        self.object
            .get(key)
            .ok_or_else(|| format!("{}.{key} is missing", self.what))
    }
    fn u64(&self, key: &str) -> std::result::Result<u64, String> {
        let v = self.get(key)?;
        v.as_u64()
            .ok_or_else(|| format!("{}.{key} is {v}, expected an unsigned integer", self.what))
    }
    fn u32(&self, key: &str) -> std::result::Result<u32, String> {
        let v = self.u64(key)?;
        u32::try_from(v).map_err(|_| {
            format!(
                "{}.{key} is {v}, expected an unsigned 32-bit integer",
                self.what
            )
        })
    }
    fn f64(&self, key: &str) -> std::result::Result<f64, String> {
        let v = self.get(key)?;
        match v {
            serde_json::Value::Number(n) => n.as_f64(),
            serde_json::Value::String(s) => match s.as_str() {
                "NaN" => Some(f64::NAN),
                "inf" => Some(f64::INFINITY),
                "-inf" => Some(f64::NEG_INFINITY),
                _ => None,
            },
            _ => None,
        }
        .ok_or_else(|| {
            format!(
                "{}.{key} is {v}, expected a number or \"NaN\", \"inf\", \"-inf\"",
                self.what
            )
        })
    }
}

/// Decodes a JSON frame message; the error says what was wrong.
fn decode_frame_json(data: &[u8]) -> std::result::Result<HeightMap, String> {
    use base64::Engine as _;
    let value: serde_json::Value = serde_json::from_slice(data)
        .map_err(|e| format!("frame message is not JSON ({} bytes): {e}", data.len()))?;
    let grid = JsonFields::of(&value, "grid")?;
    let s = JsonFields::of(grid.get("surfstream")?, "surfstream")?;
    let header = FrameHeader {
        kind: s.u32("kind")?,
        flags: s.u32("flags")?,
        scan_id: s.u64("scan_id")?,
        sequence: s.u64("sequence")?,
        tile_index: s.u32("tile_index")?,
        tile_row: s.u32("tile_row")?,
        tile_col: s.u32("tile_col")?,
        width: s.u32("width")?,
        height: s.u32("height")?,
        _pad: 0,
        pitch_x_um: s.f64("pitch_x_um")?,
        pitch_y_um: s.f64("pitch_y_um")?,
        origin_x_um: s.f64("origin_x_um")?,
        origin_y_um: s.f64("origin_y_um")?,
        z_offset_um: s.f64("z_offset_um")?,
        t_acquired_ns: s.u64("t_acquired_ns")?,
        t_sent_ns: s.u64("t_sent_ns")?,
    };
    if FrameKind::from_u32(header.kind).is_none() {
        return Err(format!(
            "unknown frame kind {} (expected 1..=7)",
            header.kind
        ));
    }
    // The grid's own layout must be the one the header implies: one f32 field, packed.
    let columns = grid.u64("column_count")?;
    let row_stride = grid.u64("row_stride")?;
    let cell_stride = grid.u64("cell_stride")?;
    if columns != header.width as u64 || cell_stride != 4 || row_stride != header.width as u64 * 4 {
        return Err(format!(
            "grid layout column_count {columns}, row_stride {row_stride}, cell_stride \
             {cell_stride}; expected {w}, {} and 4 for a {h} rows x {w} cols frame of f32",
            header.width as u64 * 4,
            w = header.width,
            h = header.height
        ));
    }
    let fields = grid.get("fields")?;
    let one_f32 = fields.as_array().is_some_and(|f| {
        f.len() == 1
            && f[0]["name"] == HEIGHT_FIELD
            && f[0]["offset"] == 0
            && f[0]["type"] == NUMERIC_TYPE_FLOAT32
    });
    if !one_f32 {
        return Err(format!(
            "grid fields are {fields}, expected one field {HEIGHT_FIELD} of type FLOAT32 (7) at offset 0"
        ));
    }
    let b64 = grid
        .get("data")?
        .as_str()
        .ok_or_else(|| "grid.data is not a base64 string".to_string())?;
    let expected = header.width as u64 * header.height as u64 * 4;
    // Checked before decoding, so a lying header allocates nothing.
    let decoded_len = (b64.len() as u64 / 4) * 3;
    if decoded_len < expected || decoded_len > expected + 2 {
        return Err(format!(
            "grid.data holds about {decoded_len} bytes, expected width * height * 4 = {} x {} x 4 = {expected}",
            header.width, header.height
        ));
    }
    let raw = base64::engine::general_purpose::STANDARD
        .decode(b64)
        .map_err(|e| format!("grid.data is not valid base64: {e}"))?;
    if raw.len() as u64 != expected {
        return Err(format!(
            "grid.data holds {} bytes, expected rows * cols * 4 = {} x {} x 4 = {expected}",
            raw.len(),
            header.height,
            header.width
        ));
    }
    let heights = raw
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Ok(HeightMap { header, heights })
}

/// Decodes a JSON registration message.
fn decode_registration_json(data: &[u8]) -> std::result::Result<TileRegistration, String> {
    let value: serde_json::Value = serde_json::from_slice(data).map_err(|e| {
        format!(
            "registration message is not JSON ({} bytes): {e}",
            data.len()
        )
    })?;
    let r = JsonFields::of(&value, "registration")?;
    Ok(TileRegistration {
        scan_id: r.u64("scan_id")?,
        sequence: r.u64("sequence")?,
        tile_index: r.u32("tile_index")?,
        placed_by: r.u32("placed_by")?,
        flags: r.u32("flags")?,
        links_accepted: r.u32("links_accepted")?,
        links_tried: r.u32("links_tried")?,
        _pad: 0,
        x_um: r.f64("x_um")?,
        y_um: r.f64("y_um")?,
        piston_um: r.f64("piston_um")?,
        tilt_x_um_per_px: r.f64("tilt_x_um_per_px")?,
        tilt_y_um_per_px: r.f64("tilt_y_um_per_px")?,
        quality: r.f64("quality")?,
        t_acquired_ns: r.u64("t_acquired_ns")?,
        t_sent_ns: r.u64("t_sent_ns")?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::frame::flags;

    fn frame(seq: u64, w: u32, h: u32, with_nan: bool) -> HeightMap {
        let header = FrameHeader {
            kind: FrameKind::Tile as u32,
            flags: flags::PLACED_BY_STAGE,
            scan_id: 0xDEAD_BEEF_1234,
            sequence: seq,
            tile_index: seq as u32,
            tile_row: 1,
            tile_col: 2,
            width: w,
            height: h,
            _pad: 0,
            pitch_x_um: 0.8148,
            pitch_y_um: 0.8149,
            origin_x_um: 114.21 + seq as f64,
            origin_y_um: -26.36,
            z_offset_um: 25_000.123_456_789,
            t_acquired_ns: 1_000_000 + seq,
            t_sent_ns: 2_000_000 + seq,
        };
        let heights = (0..w * h)
            .map(|i| match i % 7 {
                3 if with_nan => f32::NAN,
                5 => -0.0,
                _ => (i as f32 * 0.37).sin() * 1.3 + seq as f32,
            })
            .collect();
        HeightMap { header, heights }
    }

    fn registration(i: u32) -> TileRegistration {
        TileRegistration {
            scan_id: 0xDEAD_BEEF_1234,
            sequence: i as u64,
            tile_index: i,
            placed_by: surfstream_core::frame::placed_by::REGISTRATION,
            flags: 0,
            links_accepted: 2,
            links_tried: 3,
            _pad: 0,
            x_um: 117.5 + i as f64,
            y_um: 25.9,
            piston_um: -0.125,
            tilt_x_um_per_px: 1e-5,
            tilt_y_um_per_px: -2e-6,
            quality: 0.97,
            t_acquired_ns: 10,
            t_sent_ns: 20 + i as u64,
        }
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// Records 3 frames (the last, of size `big`, with NaN), an end-of-scan marker and 2
    /// registrations, with log times out of file order.
    fn sample(path: &Path, big: (u32, u32)) -> (Vec<HeightMap>, Vec<TileRegistration>) {
        let mut rec = Recorder::create(path).expect("create");
        let mut meta = BTreeMap::new();
        meta.insert("node".to_string(), "stage".to_string());
        let tiles = rec
            .add_frame_channel("stage/tiles", meta)
            .expect("frame channel");
        let regs = rec
            .add_registration_channel("matcher/registrations", BTreeMap::new())
            .expect("reg channel");
        let frames = vec![
            frame(0, 5, 3, false),
            frame(1, 5, 3, false),
            frame(2, big.0, big.1, true),
        ];
        let regs_written = vec![registration(0), registration(1)];
        rec.write_frame(tiles, &frames[0].header, &frames[0].heights, 100)
            .expect("f0");
        rec.write_registration(regs, &regs_written[0], 150)
            .expect("r0");
        rec.write_frame(tiles, &frames[1].header, &frames[1].heights, 200)
            .expect("f1");
        rec.write_frame(tiles, &frames[2].header, &frames[2].heights, 300)
            .expect("f2");
        rec.write_registration(regs, &regs_written[1], 250)
            .expect("r1");
        let eos = FrameHeader::end_of_scan(0xDEAD_BEEF_1234, 3, 2, 77);
        rec.write_frame(tiles, &eos, &[], 400).expect("eos");
        assert_eq!(rec.message_count(), 6);
        assert!(surfstream_core::fsutil::partial_path(path).exists());
        assert!(!path.exists());
        rec.finish().expect("finish");
        let mut all = frames;
        all.push(HeightMap {
            header: eos,
            heights: vec![],
        });
        (all, regs_written)
    }

    #[test]
    fn round_trip_is_bit_identical_and_in_log_time_order() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("rec.mcap");
        let (frames, regs) = sample(&path, (64, 48));
        assert!(path.exists());
        assert!(!surfstream_core::fsutil::partial_path(&path).exists());

        let r = read_recording(&path).expect("read");
        assert_eq!(r.channels.len(), 2);
        assert_eq!(r.channels[0].topic, "stage/tiles");
        assert_eq!(r.channels[0].kind, ChannelKind::Frame);
        assert_eq!(
            r.channels[0].metadata.get("node").map(String::as_str),
            Some("stage")
        );
        assert_eq!(r.channels[1].topic, "matcher/registrations");
        assert_eq!(r.channels[1].kind, ChannelKind::Registration);

        let times: Vec<u64> = r.messages.iter().map(|m| m.log_time_ns).collect();
        assert_eq!(times, [100, 150, 200, 250, 300, 400]);
        let got_frames: Vec<&HeightMap> = r
            .messages
            .iter()
            .filter_map(|m| match &m.message {
                Recorded::Frame(f) => {
                    assert_eq!(m.topic, "stage/tiles");
                    Some(f)
                }
                _ => None,
            })
            .collect();
        assert_eq!(got_frames.len(), frames.len());
        for (got, want) in got_frames.iter().zip(&frames) {
            assert_eq!(got.header, want.header);
            assert_eq!(bits(&got.heights), bits(&want.heights));
        }
        assert!(got_frames[2].heights.iter().any(|h| h.is_nan()));
        assert!(got_frames[3].header.has(flags::END_OF_SCAN) && got_frames[3].heights.is_empty());
        let got_regs: Vec<TileRegistration> = r
            .messages
            .iter()
            .filter_map(|m| match m.message {
                Recorded::Registration(g) => Some(g),
                _ => None,
            })
            .collect();
        assert_eq!(got_regs, regs);
        // Order of log times puts registration 1 (250) before frame 2 (300).
        assert!(matches!(r.messages[3].message, Recorded::Registration(g) if g.tile_index == 1));
    }

    #[test]
    fn streaming_reader_yields_file_order() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("rec.mcap");
        sample(&path, (64, 48));
        let times: Vec<u64> = RecordingReader::open(&path)
            .expect("open")
            .map(|m| m.expect("message").log_time_ns)
            .collect();
        assert_eq!(times, [100, 150, 200, 300, 250, 400]);
    }

    #[test]
    fn writer_rejects_misuse() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("m.mcap");
        let mut rec = Recorder::create(&path).expect("create");
        let tiles = rec
            .add_frame_channel("stage/tiles", BTreeMap::new())
            .expect("channel");
        let regs = rec
            .add_registration_channel("matcher/registrations", BTreeMap::new())
            .expect("channel");
        assert!(rec
            .add_registration_channel("stage/tiles", BTreeMap::new())
            .is_err());
        let f = frame(0, 4, 4, false);
        let e = rec
            .write_frame(tiles, &f.header, &f.heights[..15], 1)
            .expect_err("short payload");
        assert!(e.to_string().contains("needs 16 heights, got 15"), "{e}");
        assert!(rec.write_frame(regs, &f.header, &f.heights, 1).is_err());
        assert!(rec.write_registration(tiles, &registration(0), 1).is_err());
        rec.finish().expect("finish");
        assert!(read_recording(&path).expect("read").messages.is_empty());
    }

    #[test]
    fn dropped_recorder_leaves_no_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("dropped.mcap");
        {
            let mut rec = Recorder::create(&path).expect("create");
            let tiles = rec
                .add_frame_channel("stage/tiles", BTreeMap::new())
                .expect("channel");
            let f = frame(0, 8, 8, true);
            rec.write_frame(tiles, &f.header, &f.heights, 5)
                .expect("write");
        }
        assert!(!path.exists());
        assert!(!surfstream_core::fsutil::partial_path(&path).exists());
        assert_eq!(std::fs::read_dir(dir.path()).expect("ls").count(), 0);
    }

    fn read_err(path: &Path) -> String {
        match read_recording(path) {
            Ok(r) => panic!("expected an error, read {} messages", r.messages.len()),
            Err(e) => format!("{e:#}"),
        }
    }

    #[test]
    fn truncated_copies_are_errors_not_panics() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("rec.mcap");
        sample(&path, (64, 48));
        let bytes = std::fs::read(&path).expect("read");
        let cut_path = dir.path().join("cut.mcap");
        let n = bytes.len();
        let mut cuts: Vec<usize> = vec![
            0,
            1,
            7,
            8,
            9,
            20,
            100,
            n / 3,
            n / 2,
            n - 100,
            n - 30,
            n - 9,
            n - 8,
            n - 1,
        ];
        cuts.extend((0..n).step_by(97));
        for cut in cuts {
            std::fs::write(&cut_path, &bytes[..cut]).expect("write");
            let e = read_err(&cut_path);
            assert!(e.contains("cut.mcap"), "cut at {cut}: {e}");
        }
        // Bytes after the end magic are refused too.
        let mut longer = bytes.clone();
        longer.extend_from_slice(b"junk");
        std::fs::write(&cut_path, &longer).expect("write");
        read_err(&cut_path);
    }

    #[test]
    fn flipped_bytes_are_errors_not_panics() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("rec.mcap");
        sample(&path, (16, 12));
        let bytes = std::fs::read(&path).expect("read");
        let bad = dir.path().join("flipped.mcap");
        // Every byte, with a bit pattern that varies along the file: an error naming the file,
        // never a panic and never a silently different recording.
        let mut undetected = Vec::new();
        for pos in 0..bytes.len() {
            let mut b = bytes.clone();
            b[pos] ^= [0x01u8, 0x80, 0xff, 0x10][pos % 4];
            std::fs::write(&bad, &b).expect("write");
            match read_recording(&bad) {
                Ok(_) => undetected.push(pos),
                Err(e) => assert!(format!("{e:#}").contains("flipped.mcap"), "{e:#}"),
            }
        }
        // Chunk, data-section and summary CRCs plus the structure checks leave no byte uncovered.
        assert!(
            undetected.is_empty(),
            "flips at {undetected:?} read without error"
        );
    }

    /// An MCAP file of one channel "stage/tiles" with `schema` (name, encoding), message
    /// encoding `enc` and the messages `data`, written with the mcap crate directly.
    fn write_raw(path: &Path, schema: (&str, &str), enc: &str, data: &[&[u8]]) {
        let mut w =
            mcap::Writer::new(BufWriter::new(File::create(path).expect("create"))).expect("writer");
        let s = w.add_schema(schema.0, schema.1, b"x").expect("schema");
        let c = w
            .add_channel(s, "stage/tiles", enc, &BTreeMap::new())
            .expect("channel");
        for (i, d) in data.iter().enumerate() {
            w.write_to_known_channel(
                &MessageHeader {
                    channel_id: c,
                    sequence: i as u32,
                    log_time: 5 + i as u64,
                    publish_time: 5,
                },
                d,
            )
            .expect("message");
        }
        w.finish().expect("finish");
    }

    /// A legacy (bincode 2) frame message, as recordings were written before the JSON encoding.
    fn legacy_frame_message(f: &HeightMap) -> Vec<u8> {
        let mut m = vec![0u8; 4];
        bincode::serde::encode_into_std_write(f.header, &mut m, bincode_config()).expect("encode");
        let hl = (m.len() - 4) as u32;
        m[..4].copy_from_slice(&hl.to_le_bytes());
        for h in &f.heights {
            m.extend_from_slice(&h.to_le_bytes());
        }
        m
    }

    #[test]
    fn legacy_bincode_recordings_still_read_bit_for_bit() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("old.mcap");
        let mut w = mcap::Writer::new(BufWriter::new(File::create(&path).expect("create")))
            .expect("writer");
        let fs = w
            .add_schema(FRAME_TYPE_NAME, LEGACY_SCHEMA_ENCODING, b"prose")
            .expect("schema");
        let rs = w
            .add_schema(REGISTRATION_TYPE_NAME, LEGACY_SCHEMA_ENCODING, b"prose")
            .expect("schema");
        let tiles = w
            .add_channel(
                fs,
                "stage/tiles",
                LEGACY_FRAME_MESSAGE_ENCODING,
                &BTreeMap::new(),
            )
            .expect("channel");
        let regs = w
            .add_channel(
                rs,
                "matcher/registrations",
                LEGACY_REGISTRATION_MESSAGE_ENCODING,
                &BTreeMap::new(),
            )
            .expect("channel");
        let f = frame(0, 7, 5, true);
        let r = registration(3);
        let header = |channel_id, log_time| MessageHeader {
            channel_id,
            sequence: 0,
            log_time,
            publish_time: log_time,
        };
        w.write_to_known_channel(&header(tiles, 10), &legacy_frame_message(&f))
            .expect("frame");
        let reg = bincode::serde::encode_to_vec(r, bincode_config()).expect("encode");
        w.write_to_known_channel(&header(regs, 20), &reg)
            .expect("registration");
        w.finish().expect("finish");

        let got = read_recording(&path).expect("legacy recording reads");
        assert!(got
            .channels
            .iter()
            .all(|c| c.encoding == ChannelEncoding::LegacyBincode));
        match &got.messages[0].message {
            Recorded::Frame(g) => {
                assert_eq!(g.header, f.header);
                assert_eq!(bits(&g.heights), bits(&f.heights));
            }
            other => panic!("expected a frame, got {other:?}"),
        }
        assert_eq!(got.messages[1].message, Recorded::Registration(r));
    }

    /// Issue 35: recordings are written with zstd chunks, and a recording whose chunks are
    /// not compressed (another writer's) reads to the same messages.
    #[test]
    fn zstd_chunks_are_written_and_uncompressed_ones_read_the_same() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("rec.mcap");
        sample(&path, (300, 200));
        let bytes = std::fs::read(&path).expect("read");
        let summary = mcap::Summary::read(&bytes)
            .expect("summary")
            .expect("has a summary");
        assert!(!summary.chunk_indexes.is_empty());
        for c in &summary.chunk_indexes {
            assert_eq!(c.compression, "zstd");
            assert!(c.compressed_size < c.uncompressed_size, "{c:?}");
        }
        // The same messages through the mcap crate's writer without compression.
        let plain = dir.path().join("plain.mcap");
        let mut w = mcap::WriteOptions::new()
            .compression(None)
            .create(BufWriter::new(File::create(&plain).expect("create")))
            .expect("writer");
        for m in mcap::MessageStream::new(&bytes).expect("messages") {
            w.write(&m.expect("message")).expect("write");
        }
        w.finish().expect("finish");
        drop(w);
        let plain_bytes = std::fs::read(&plain).expect("read");
        let plain_summary = mcap::Summary::read(&plain_bytes)
            .expect("summary")
            .expect("has a summary");
        assert!(plain_summary
            .chunk_indexes
            .iter()
            .all(|c| c.compression.is_empty()));
        let (a, b) = (
            read_recording(&path).expect("zstd recording"),
            read_recording(&plain).expect("uncompressed recording"),
        );
        // NaN heights: compared by their printed form (NaN != NaN).
        assert_eq!(format!("{:?}", a.messages), format!("{:?}", b.messages));
        assert_eq!(
            a.messages.len(),
            6,
            "3 frames, 2 registrations, the end marker"
        );
    }

    #[test]
    fn new_recordings_are_json_with_json_schemas() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("rec.mcap");
        sample(&path, (6, 4));
        let bytes = std::fs::read(&path).expect("read");
        let summary = mcap::Summary::read(&bytes)
            .expect("summary")
            .expect("has a summary");
        let mut names = Vec::new();
        for s in summary.schemas.values() {
            assert_eq!(s.encoding, JSON_SCHEMA_ENCODING);
            let schema: serde_json::Value = serde_json::from_slice(&s.data).expect("schema JSON");
            assert_eq!(schema["title"], s.name.as_str());
            names.push(s.name.clone());
        }
        names.sort();
        assert_eq!(names, [FRAME_SCHEMA_NAME, REGISTRATION_SCHEMA_NAME]);
        for c in summary.channels.values() {
            assert_eq!(c.message_encoding, JSON_MESSAGE_ENCODING);
        }
        // Every property a message carries is described by the schema, and every required one
        // is there.
        let frame_schema: serde_json::Value =
            serde_json::from_str(FRAME_JSON_SCHEMA).expect("frame schema");
        let reg_schema: serde_json::Value =
            serde_json::from_str(REGISTRATION_JSON_SCHEMA).expect("registration schema");
        let f = frame(1, 3, 2, true);
        let mut m = Vec::new();
        encode_frame_json(&f.header, &f.heights, &mut m).expect("encode");
        let m: serde_json::Value = serde_json::from_slice(&m).expect("message JSON");
        let check = |schema: &serde_json::Value, message: &serde_json::Value| {
            let props = schema["properties"].as_object().expect("properties");
            let keys: Vec<&String> = message.as_object().expect("object").keys().collect();
            for k in &keys {
                assert!(props.contains_key(*k), "{k} not in the schema");
            }
            for r in schema["required"].as_array().expect("required") {
                assert!(keys.iter().any(|k| *k == r), "{r} missing");
            }
        };
        check(&frame_schema, &m);
        check(&frame_schema["properties"]["surfstream"], &m["surfstream"]);
        assert_eq!(
            frame_schema["properties"]["data"]["contentEncoding"],
            "base64"
        );
        let r: serde_json::Value =
            serde_json::from_slice(&encode_registration_json(&registration(2)).expect("encode"))
                .expect("registration JSON");
        check(&reg_schema, &r);
    }

    /// An f64 as the messages wrote it before they were typed (`json!`).
    fn old_f64(v: f64) -> serde_json::Value {
        match serde_json::Number::from_f64(v) {
            Some(n) => serde_json::Value::Number(n),
            None if v.is_nan() => "NaN".into(),
            None if v > 0.0 => "inf".into(),
            None => "-inf".into(),
        }
    }

    #[test]
    fn typed_messages_are_byte_identical_to_the_json_values_they_replace() {
        use serde_json::json;
        let mut f = frame(3, 3, 2, true);
        f.header.origin_x_um = f64::NAN;
        f.header.origin_y_um = f64::NEG_INFINITY;
        f.header.z_offset_um = 0.1 + 0.2;
        f.header.pitch_y_um = -0.0;
        let h = &f.header;
        let fz = finite_or_zero;
        let old = json!({
            "timestamp": {"sec": h.t_sent_ns / 1_000_000_000, "nsec": h.t_sent_ns % 1_000_000_000},
            "frame_id": SCAN_FRAME_ID,
            "pose": {
                "position": {"x": fz(h.origin_x_um * 1e-6), "y": fz(h.origin_y_um * 1e-6),
                             "z": fz(h.z_offset_um * 1e-6)},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            },
            "column_count": h.width,
            "cell_size": {"x": fz(h.pitch_x_um * 1e-6), "y": fz(h.pitch_y_um * 1e-6)},
            "row_stride": h.width as u64 * 4,
            "cell_stride": 4,
            "fields": [{"name": HEIGHT_FIELD, "offset": 0, "type": NUMERIC_TYPE_FLOAT32}],
            "surfstream": {
                "kind": h.kind, "flags": h.flags, "scan_id": h.scan_id, "sequence": h.sequence,
                "tile_index": h.tile_index, "tile_row": h.tile_row, "tile_col": h.tile_col,
                "width": h.width, "height": h.height,
                "pitch_x_um": old_f64(h.pitch_x_um), "pitch_y_um": old_f64(h.pitch_y_um),
                "origin_x_um": old_f64(h.origin_x_um), "origin_y_um": old_f64(h.origin_y_um),
                "z_offset_um": old_f64(h.z_offset_um),
                "t_acquired_ns": h.t_acquired_ns, "t_sent_ns": h.t_sent_ns,
            },
        });
        let mut buf = Vec::new();
        encode_frame_json(h, &f.heights, &mut buf).unwrap();
        let text = String::from_utf8(buf).unwrap();
        let old = old.to_string();
        assert_eq!(text[..old.len() - 1], old[..old.len() - 1]);
        assert!(text[old.len() - 1..].starts_with(",\"data\":\""), "{text}");

        let mut r = registration(4);
        r.quality = f64::NAN;
        r.x_um = f64::INFINITY;
        r.y_um = 1e300;
        let old = json!({
            "scan_id": r.scan_id, "sequence": r.sequence, "tile_index": r.tile_index,
            "placed_by": r.placed_by, "flags": r.flags, "links_accepted": r.links_accepted,
            "links_tried": r.links_tried, "x_um": old_f64(r.x_um), "y_um": old_f64(r.y_um),
            "piston_um": old_f64(r.piston_um), "tilt_x_um_per_px": old_f64(r.tilt_x_um_per_px),
            "tilt_y_um_per_px": old_f64(r.tilt_y_um_per_px), "quality": old_f64(r.quality),
            "t_acquired_ns": r.t_acquired_ns, "t_sent_ns": r.t_sent_ns,
        });
        let typed = encode_registration_json(&r).unwrap();
        assert_eq!(String::from_utf8(typed).unwrap(), old.to_string());
    }

    #[test]
    fn non_finite_and_extreme_header_values_read_back_exactly() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("odd.mcap");
        let mut f = frame(0, 3, 2, true);
        f.header.origin_x_um = f64::NAN;
        f.header.origin_y_um = f64::NEG_INFINITY;
        f.header.z_offset_um = 0.1 + 0.2; // 0.30000000000000004: needs all 17 digits
        f.header.pitch_x_um = f64::MIN_POSITIVE;
        f.header.pitch_y_um = -0.0;
        f.header.scan_id = u64::MAX;
        f.header.t_sent_ns = u64::MAX - 1;
        let mut r = registration(0);
        r.quality = f64::NAN;
        r.x_um = f64::INFINITY;
        r.y_um = 1e300;
        let mut rec = Recorder::create(&path).expect("create");
        let t = rec
            .add_frame_channel("stage/tiles", BTreeMap::new())
            .expect("channel");
        let g = rec
            .add_registration_channel("matcher/registrations", BTreeMap::new())
            .expect("channel");
        rec.write_frame(t, &f.header, &f.heights, 1).expect("frame");
        rec.write_registration(g, &r, 2).expect("registration");
        rec.finish().expect("finish");
        let got = read_recording(&path).expect("read");
        let Recorded::Frame(gf) = &got.messages[0].message else {
            panic!("frame expected")
        };
        let hb = |h: &FrameHeader| {
            [
                h.pitch_x_um,
                h.pitch_y_um,
                h.origin_x_um,
                h.origin_y_um,
                h.z_offset_um,
            ]
            .map(f64::to_bits)
        };
        assert_eq!(hb(&gf.header), hb(&f.header));
        assert_eq!(
            (gf.header.scan_id, gf.header.t_sent_ns),
            (u64::MAX, u64::MAX - 1)
        );
        assert_eq!(bits(&gf.heights), bits(&f.heights));
        let Recorded::Registration(gr) = got.messages[1].message else {
            panic!("registration expected")
        };
        assert!(gr.quality.is_nan() && gr.x_um == f64::INFINITY && gr.y_um == 1e300);
    }

    #[test]
    fn bad_json_messages_are_reported_with_topic_and_reason() {
        let dir = tempfile::tempdir().expect("tempdir");
        let f = frame(0, 2, 2, false);
        let mut good = Vec::new();
        encode_frame_json(&f.header, &f.heights, &mut good).expect("encode");
        let good: serde_json::Value = serde_json::from_slice(&good).expect("json");
        let err = |name: &str, m: &serde_json::Value| -> String {
            let path = dir.path().join(name);
            let data = serde_json::to_vec(m).expect("json");
            write_raw(
                &path,
                (FRAME_SCHEMA_NAME, JSON_SCHEMA_ENCODING),
                JSON_MESSAGE_ENCODING,
                &[&data],
            );
            let e = read_err(&path);
            assert!(e.contains(name) && e.contains("\"stage/tiles\""), "{e}");
            e
        };
        // Sanity: the unmodified message reads.
        let path = dir.path().join("good.mcap");
        let data = serde_json::to_vec(&good).expect("json");
        write_raw(
            &path,
            (FRAME_SCHEMA_NAME, JSON_SCHEMA_ENCODING),
            JSON_MESSAGE_ENCODING,
            &[&data],
        );
        assert_eq!(read_recording(&path).expect("good").messages.len(), 1);

        let mut m = good.clone();
        m["surfstream"]
            .as_object_mut()
            .expect("object")
            .remove("z_offset_um");
        assert!(err("nozoff.mcap", &m).contains("surfstream.z_offset_um is missing"));
        let mut m = good.clone();
        m["surfstream"]["width"] = 3.into();
        assert!(err("width.mcap", &m).contains("grid layout column_count 2"));
        let mut m = good.clone();
        m["surfstream"]["height"] = 4_000_000_000u32.into();
        assert!(err("lying.mcap", &m).contains("expected width * height * 4 = 2 x 4000000000 x 4"));
        let mut m = good.clone();
        m["fields"][0]["type"] = 8.into();
        assert!(err("type.mcap", &m).contains("expected one field height_um of type FLOAT32"));
        let mut m = good.clone();
        m["data"] = "!!!!!!!!!!!!!!!!!!!!!!!!".into();
        assert!(err("b64.mcap", &m).contains("not valid base64"));
        let mut m = good.clone();
        m["surfstream"]["kind"] = 99.into();
        assert!(err("kind.mcap", &m).contains("unknown frame kind 99"));
        let mut m = good.clone();
        m["surfstream"]["pitch_x_um"] = "wide".into();
        assert!(err("pitch.mcap", &m).contains("surfstream.pitch_x_um is \"wide\""));
        let mut m = good.clone();
        m["surfstream"]["tile_row"] = (-1).into();
        assert!(err("row.mcap", &m).contains("expected an unsigned integer"));
        let path = dir.path().join("text.mcap");
        write_raw(
            &path,
            (FRAME_SCHEMA_NAME, JSON_SCHEMA_ENCODING),
            JSON_MESSAGE_ENCODING,
            &[b"{\"column_count\": 2,"],
        );
        assert!(read_err(&path).contains("frame message is not JSON"));
        // A foxglove.Grid channel in protobuf is someone else's recording: named, not guessed.
        let path = dir.path().join("proto.mcap");
        write_raw(
            &path,
            (FRAME_SCHEMA_NAME, "protobuf"),
            "protobuf",
            &[b"\x08\x01"],
        );
        let e = read_err(&path);
        assert!(
            e.contains("proto.mcap") && e.contains("encoding \"protobuf\""),
            "{e}"
        );
    }

    #[test]
    fn bad_legacy_messages_are_reported_with_topic_and_reason() {
        // Messages that pass MCAP's checks but not ours, written with the mcap crate directly.
        let dir = tempfile::tempdir().expect("tempdir");
        let write = |name: &str, schema: (&str, &str), enc: &str, data: &[u8]| -> PathBuf {
            let path = dir.path().join(name);
            let mut w = mcap::Writer::new(BufWriter::new(File::create(&path).expect("create")))
                .expect("writer");
            let s = w.add_schema(schema.0, schema.1, b"x").expect("schema");
            let c = w
                .add_channel(s, "stage/tiles", enc, &BTreeMap::new())
                .expect("channel");
            w.write_to_known_channel(
                &MessageHeader {
                    channel_id: c,
                    sequence: 0,
                    log_time: 5,
                    publish_time: 5,
                },
                data,
            )
            .expect("message");
            w.finish().expect("finish");
            path
        };
        let frame_schema = (FRAME_TYPE_NAME, LEGACY_SCHEMA_ENCODING);
        let f = frame(0, 2, 2, false);
        let mut good = vec![0u8; 4];
        bincode::serde::encode_into_std_write(f.header, &mut good, bincode_config())
            .expect("encode");
        let hl = (good.len() - 4) as u32;
        good[..4].copy_from_slice(&hl.to_le_bytes());
        for h in &f.heights {
            good.extend_from_slice(&h.to_le_bytes());
        }
        // Sanity: the hand-made message reads.
        let p = write(
            "good.mcap",
            frame_schema,
            LEGACY_FRAME_MESSAGE_ENCODING,
            &good,
        );
        assert_eq!(read_recording(&p).expect("good").messages.len(), 1);

        let p = write(
            "schema.mcap",
            ("ros.Image", "ros2msg"),
            LEGACY_FRAME_MESSAGE_ENCODING,
            &good,
        );
        let e = read_err(&p);
        assert!(
            e.contains("schema.mcap")
                && e.contains("\"stage/tiles\"")
                && e.contains("ros.Image")
                && e.contains("expected schema"),
            "{e}"
        );
        let p = write("enc.mcap", frame_schema, "json", &good);
        assert!(read_err(&p).contains("message encoding \"json\""));

        let mut long_header = good.clone();
        long_header[..4].copy_from_slice(&10_000u32.to_le_bytes());
        let p = write(
            "hlen.mcap",
            frame_schema,
            LEGACY_FRAME_MESSAGE_ENCODING,
            &long_header,
        );
        let e = read_err(&p);
        assert!(
            e.contains("hlen.mcap")
                && e.contains("stage/tiles")
                && e.contains("header length 10000 bytes is larger than the message"),
            "{e}"
        );

        let p = write(
            "short.mcap",
            frame_schema,
            LEGACY_FRAME_MESSAGE_ENCODING,
            &good[..good.len() - 4],
        );
        let e = read_err(&p);
        assert!(
            e.contains("frame payload is 12 bytes, expected rows * cols * 4 = 2 x 2 x 4 = 16"),
            "{e}"
        );

        let p = write(
            "tiny.mcap",
            frame_schema,
            LEGACY_FRAME_MESSAGE_ENCODING,
            &[1, 0],
        );
        assert!(read_err(&p).contains("shorter than its 4-byte header length"));

        let mut bad_kind = f.header;
        bad_kind.kind = 99;
        let mut m = vec![0u8; 4];
        bincode::serde::encode_into_std_write(bad_kind, &mut m, bincode_config()).expect("encode");
        let hl = (m.len() - 4) as u32;
        m[..4].copy_from_slice(&hl.to_le_bytes());
        let p = write("kind.mcap", frame_schema, LEGACY_FRAME_MESSAGE_ENCODING, &m);
        assert!(read_err(&p).contains("unknown frame kind 99"));

        let mut reg =
            bincode::serde::encode_to_vec(registration(1), bincode_config()).expect("encode");
        reg.push(0);
        let p = write(
            "reg.mcap",
            (REGISTRATION_TYPE_NAME, LEGACY_SCHEMA_ENCODING),
            LEGACY_REGISTRATION_MESSAGE_ENCODING,
            &reg,
        );
        assert!(read_err(&p).contains("1 bytes after the"));
        let p = write(
            "reg2.mcap",
            (REGISTRATION_TYPE_NAME, LEGACY_SCHEMA_ENCODING),
            LEGACY_REGISTRATION_MESSAGE_ENCODING,
            &reg[..10],
        );
        assert!(read_err(&p).contains("cannot decode the surfstream.TileRegistration.v1 message"));
    }

    #[test]
    fn not_an_mcap_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("x.mcap");
        std::fs::write(&p, b"\x93NUMPY\x01\x00 certainly not an MCAP file").expect("write");
        let e = read_err(&p);
        assert!(e.contains("x.mcap") && e.contains("bad magic"), "{e}");
        let e = read_err(&dir.path().join("missing.mcap"));
        assert!(
            e.contains("missing.mcap") && e.contains("no such file (expected a .mcap recording)"),
            "{e}"
        );
    }
}
