//! MCAP recordings of surfstream channels: [`Recorder`] writes them, [`read_recording`] and
//! [`RecordingReader`] read them back.
//!
//! A recording is a standard MCAP file (chunked, zstd-compressed, with CRCs, indexes and a
//! summary), so generic MCAP tools (the `mcap` CLI, Foxglove, the Python `mcap` package) list
//! and read it. One MCAP channel per recorded surfstream port; its topic is the port name
//! (e.g. `stage/tiles`). Two channel kinds, each with its own schema:
//!
//! - frames: schema `surfstream.FrameHeader.v1`, message encoding `surfstream.frame.v1`; message
//!   data = `[u32 LE header length][FrameHeader, bincode 2][width * height f32 LE heights]`.
//! - registrations: schema `surfstream.TileRegistration.v1`, message encoding
//!   `surfstream.registration.v1`; message data = the `TileRegistration`, bincode 2.
//!
//! Both schemas have the schema encoding `surfstream.bincode2`.
//!
//! "bincode 2" is the serde encoding of bincode 2.x with `bincode::config::standard()`
//! (little-endian, variable-length integers, floats as their 4 / 8 raw bytes). The schema data is
//! a short UTF-8 text that spells this layout out for readers in other languages
//! ([`FRAME_SCHEMA_TEXT`], [`REGISTRATION_SCHEMA_TEXT`]). The MCAP `log_time` of a message is the
//! caller's `log_time_ns`, its `publish_time` the `t_sent_ns` of the frame or registration, its
//! `sequence` a per-channel counter from 0.
//!
//! Writing goes to `<path>.partial` ([`surfstream_core::fsutil::partial_path`]) and [`Recorder::finish`]
//! renames the complete, synced file into place; a recorder dropped without `finish` removes its
//! partial file, so a crash or an error never leaves a file at `path` that looks complete.
//!
//! Reading checks everything and never panics on bad input: MCAP structure, chunk, data and
//! summary CRCs, the end magic, that every channel has one of the two schemas above and every
//! message decodes exactly (header length within the message, payload length = width * height *
//! 4, no trailing bytes, a known frame kind), and that the summary's message count matches.
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

use surfstream_core::frame::{
    FrameHeader, FrameKind, HeightMap, TileRegistration, FRAME_TYPE_NAME, REGISTRATION_TYPE_NAME,
};

/// Schema encoding of both schemas.
pub const SCHEMA_ENCODING: &str = "surfstream.bincode2";
/// Message encoding of frame channels.
pub const FRAME_MESSAGE_ENCODING: &str = "surfstream.frame.v1";
/// Message encoding of registration channels.
pub const REGISTRATION_MESSAGE_ENCODING: &str = "surfstream.registration.v1";

/// Schema data of frame channels: the message layout in words.
pub const FRAME_SCHEMA_TEXT: &str = "\
surfstream.FrameHeader.v1, message encoding surfstream.frame.v1. Message data:
  u32 little-endian: header_len, the byte length of the encoded header
  header_len bytes: the FrameHeader, serde-encoded by bincode 2.x with config::standard()
    (little-endian, unsigned integers as varints: < 251 one byte, else 251 + u16 / 252 + u32 /
    253 + u64 little-endian; f64 as 8 raw bytes), fields in this order:
    kind u32 (1 tile, 2 panorama patch, 3 panorama, 4 datum, 5 roughness, 6 pooled, 7 marker),
    flags u32 (1 final, 2 end of scan, 4 placed by stage, 8 preview), scan_id u64, sequence u64,
    tile_index u32, tile_row u32, tile_col u32, width u32, height u32, _pad u32,
    pitch_x_um f64, pitch_y_um f64, origin_x_um f64, origin_y_um f64, z_offset_um f64,
    t_acquired_ns u64, t_sent_ns u64 (CLOCK_MONOTONIC)
  width * height f32 little-endian: heights in micrometres relative to z_offset_um, row-major
    (row index grows with scan y, column index with scan x), NaN = not measured
";

/// Schema data of registration channels: the message layout in words.
pub const REGISTRATION_SCHEMA_TEXT: &str = "\
surfstream.TileRegistration.v1, message encoding surfstream.registration.v1. Message data:
  the TileRegistration, serde-encoded by bincode 2.x with config::standard() (little-endian,
  unsigned integers as varints, f64 as 8 raw bytes), fields in this order:
    scan_id u64, sequence u64, tile_index u32, placed_by u32 (1 registration, 2 stage),
    flags u32 (2 end of scan), links_accepted u32, links_tried u32, _pad u32,
    x_um f64, y_um f64 (final scan position of the tile's pixel (0, 0)), piston_um f64,
    tilt_x_um_per_px f64, tilt_y_um_per_px f64, quality f64, t_acquired_ns u64, t_sent_ns u64
";

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
            Self::Frame => FRAME_TYPE_NAME,
            Self::Registration => REGISTRATION_TYPE_NAME,
        }
    }
    fn message_encoding(self) -> &'static str {
        match self {
            Self::Frame => FRAME_MESSAGE_ENCODING,
            Self::Registration => REGISTRATION_MESSAGE_ENCODING,
        }
    }
    fn schema_text(self) -> &'static str {
        match self {
            Self::Frame => FRAME_SCHEMA_TEXT,
            Self::Registration => REGISTRATION_SCHEMA_TEXT,
        }
    }
    fn name(self) -> &'static str {
        match self {
            Self::Frame => "frame",
            Self::Registration => "registration",
        }
    }
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
                        SCHEMA_ENCODING,
                        kind.schema_text().as_bytes(),
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
            .add_channel(schema_id, topic, kind.message_encoding(), &metadata)
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
                "topic \"{}\": frame {} x {} needs {expected} heights, got {}",
                c.topic,
                header.width,
                header.height,
                heights.len()
            );
        }
        let mut buf = std::mem::take(&mut self.buf);
        buf.clear();
        buf.reserve(64 + heights.len() * 4);
        buf.extend_from_slice(&[0; 4]);
        bincode::serde::encode_into_std_write(header, &mut buf, bincode_config())
            .map_err(|e| anyhow!("cannot encode a frame header: {e}"))?;
        let header_len = (buf.len() - 4) as u32;
        buf[..4].copy_from_slice(&header_len.to_le_bytes());
        for h in heights {
            buf.extend_from_slice(&h.to_le_bytes());
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
        let data = bincode::serde::encode_to_vec(registration, bincode_config())
            .map_err(|e| anyhow!("cannot encode a registration: {e}"))?;
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
        let kind = [ChannelKind::Frame, ChannelKind::Registration]
            .into_iter()
            .find(|k| {
                k.schema_name() == name
                    && encoding == SCHEMA_ENCODING
                    && k.message_encoding() == c.message_encoding
            })
            .ok_or_else(|| {
                anyhow!(
                    "{p}: topic \"{topic}\" (channel {}) has schema \"{name}\" (encoding \
                     \"{encoding}\") and message encoding \"{}\"; expected {}",
                    c.id,
                    c.message_encoding,
                    expected_kinds()
                )
            })?;
        let info = ChannelInfo {
            topic: c.topic,
            kind,
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
    let message = match channel.kind {
        ChannelKind::Frame => decode_frame(data).map(Recorded::Frame),
        ChannelKind::Registration => decode_registration(data).map(Recorded::Registration),
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
        "schema \"{FRAME_TYPE_NAME}\" with message encoding \"{FRAME_MESSAGE_ENCODING}\" \
         or schema \"{REGISTRATION_TYPE_NAME}\" with message encoding \
         \"{REGISTRATION_MESSAGE_ENCODING}\" (schema encoding \"{SCHEMA_ENCODING}\")"
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
            "frame payload is {} bytes, expected width * height * 4 = {} x {} x 4 = {expected}",
            payload.len(),
            header.width,
            header.height
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

    #[test]
    fn bad_messages_are_reported_with_topic_and_reason() {
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
        let frame_schema = (FRAME_TYPE_NAME, SCHEMA_ENCODING);
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
        let p = write("good.mcap", frame_schema, FRAME_MESSAGE_ENCODING, &good);
        assert_eq!(read_recording(&p).expect("good").messages.len(), 1);

        let p = write(
            "schema.mcap",
            ("ros.Image", "ros2msg"),
            FRAME_MESSAGE_ENCODING,
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
            FRAME_MESSAGE_ENCODING,
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
            FRAME_MESSAGE_ENCODING,
            &good[..good.len() - 4],
        );
        let e = read_err(&p);
        assert!(
            e.contains("frame payload is 12 bytes, expected width * height * 4 = 2 x 2 x 4 = 16"),
            "{e}"
        );

        let p = write("tiny.mcap", frame_schema, FRAME_MESSAGE_ENCODING, &[1, 0]);
        assert!(read_err(&p).contains("shorter than its 4-byte header length"));

        let mut bad_kind = f.header;
        bad_kind.kind = 99;
        let mut m = vec![0u8; 4];
        bincode::serde::encode_into_std_write(bad_kind, &mut m, bincode_config()).expect("encode");
        let hl = (m.len() - 4) as u32;
        m[..4].copy_from_slice(&hl.to_le_bytes());
        let p = write("kind.mcap", frame_schema, FRAME_MESSAGE_ENCODING, &m);
        assert!(read_err(&p).contains("unknown frame kind 99"));

        let mut reg =
            bincode::serde::encode_to_vec(registration(1), bincode_config()).expect("encode");
        reg.push(0);
        let p = write(
            "reg.mcap",
            (REGISTRATION_TYPE_NAME, SCHEMA_ENCODING),
            REGISTRATION_MESSAGE_ENCODING,
            &reg,
        );
        assert!(read_err(&p).contains("1 bytes after the"));
        let p = write(
            "reg2.mcap",
            (REGISTRATION_TYPE_NAME, SCHEMA_ENCODING),
            REGISTRATION_MESSAGE_ENCODING,
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
            e.contains("missing.mcap") && e.contains("cannot open"),
            "{e}"
        );
    }
}
