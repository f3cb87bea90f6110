//! How many tiles a replay source will send, learnt before it runs and without reading the
//! tiles: the simulated stage's grid, a scan manifest's `[[tile]]` entries, a recording's
//! messages on the tile topic from its MCAP summary. The live view's `tiles_planned` (issue 34)
//! comes from here, so a replay shows "done / planned" and an ETA from its first tile.
//!
//! A source that cannot say (a recording without a summary, a file that does not parse) gives
//! `None`: the count is a display, and the replay node itself reports a bad source when it
//! opens it.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use mcap::records::Record;
use mcap::sans_io::{SummaryReadEvent, SummaryReader, SummaryReaderOptions};
use surfstream_core::frame::flags;

use crate::config::Config;

/// The largest chunk read to look at a recording's last tile message (the recorder writes
/// 4 MiB chunks; a larger one is not ours to decompress for a display).
const MAX_CHUNK_BYTES: u64 = 256 * 1024 * 1024;

/// Tiles the replay node with these parameters will send, when the source says before it
/// runs.
pub fn planned_tiles(config: &Config) -> Option<usize> {
    match config {
        Config::Simulated(p) => {
            let n = p.stage.rows.checked_mul(p.stage.cols)?;
            (n <= crate::stage::MAX_TILES).then_some(n)
        }
        Config::Scan(s) => manifest_tiles(&s.path),
        Config::Mcap(m) => recorded_tiles(&m.path, &m.topic).ok().flatten(),
    }
}

/// The `[[tile]]` entries of a scan manifest (`scan.toml`, or a folder holding one).
fn manifest_tiles(path: &Path) -> Option<usize> {
    #[derive(serde::Deserialize)]
    struct Manifest {
        #[serde(default)]
        tile: Vec<toml::Table>,
    }
    let manifest = if path.is_dir() {
        path.join("scan.toml")
    } else {
        path.to_path_buf()
    };
    let text = std::fs::read_to_string(manifest).ok()?;
    let m: Manifest = toml::from_str(&text).ok()?;
    (!m.tile.is_empty()).then_some(m.tile.len())
}

/// The tile frames a recording holds on `topic`, from its summary: the topic's message count,
/// less its last message when that is the end-of-scan marker (the recorder writes one per
/// channel; the replay sends tiles only). Reads the summary and the one chunk holding the
/// topic's last message. `Ok(None)`: the recording has no summary, or the topic is not in it.
pub fn recorded_tiles(path: &Path, topic: &str) -> Result<Option<usize>> {
    let p = path.display();
    if !std::fs::metadata(path).is_ok_and(|m| m.is_file()) {
        bail!("{p}: not a regular file: expected a .mcap recording");
    }
    let mut file = File::open(path).with_context(|| format!("{p}: cannot open"))?;
    let size = file
        .metadata()
        .with_context(|| format!("{p}: cannot read"))?
        .len();
    let mut reader =
        SummaryReader::new_with_options(SummaryReaderOptions::default().with_file_size(size));
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| anyhow!("{p}: MCAP summary: {e}"))? {
            SummaryReadEvent::ReadRequest(n) => {
                let read = file
                    .read(reader.insert(n))
                    .with_context(|| format!("{p}: cannot read"))?;
                reader.notify_read(read);
            }
            SummaryReadEvent::SeekRequest(to) => {
                let pos = file.seek(to).with_context(|| format!("{p}: cannot seek"))?;
                reader.notify_seeked(pos);
            }
        }
    }
    let Some(summary) = reader.finish() else {
        return Ok(None);
    };
    let Some(channel) = summary.channels.values().find(|c| c.topic == topic) else {
        return Ok(None);
    };
    let Some(&count) = summary
        .stats
        .as_ref()
        .and_then(|s| s.channel_message_counts.get(&channel.id))
    else {
        return Ok(None);
    };
    // The chunk that ends last among those holding the topic holds its last message.
    let Some(chunk) = summary
        .chunk_indexes
        .iter()
        .filter(|c| c.message_index_offsets.contains_key(&channel.id))
        .max_by_key(|c| (c.message_end_time, c.chunk_start_offset))
    else {
        return Ok(None);
    };
    if chunk.chunk_length > MAX_CHUNK_BYTES || chunk.chunk_length < 9 {
        return Ok(None);
    }
    let mut bytes = vec![0u8; chunk.chunk_length as usize];
    file.seek(SeekFrom::Start(chunk.chunk_start_offset))
        .and_then(|_| file.read_exact(&mut bytes))
        .with_context(|| format!("{p}: cannot read the chunk at {}", chunk.chunk_start_offset))?;
    let (header, data) = match mcap::parse_record(bytes[0], &bytes[9..]) {
        Ok(Record::Chunk { header, data }) => (header, data),
        Ok(_) => bail!("{p}: the summary's chunk index points at a record that is no chunk"),
        Err(e) => bail!("{p}: chunk at {}: {e}", chunk.chunk_start_offset),
    };
    let mut last: Option<(u64, Vec<u8>)> = None;
    for record in mcap::read::ChunkReader::new(header, &data)
        .map_err(|e| anyhow!("{p}: chunk at {}: {e}", chunk.chunk_start_offset))?
    {
        if let Record::Message { header, data } =
            record.map_err(|e| anyhow!("{p}: chunk at {}: {e}", chunk.chunk_start_offset))?
        {
            if header.channel_id == channel.id
                && last.as_ref().is_none_or(|(t, _)| header.log_time >= *t)
            {
                last = Some((header.log_time, data.into_owned()));
            }
        }
    }
    let Some((_, message)) = last else {
        return Ok(None);
    };
    let marker = match channel.message_encoding.as_str() {
        surfstream_io::recording::JSON_MESSAGE_ENCODING => is_end_marker_json(&message),
        _ => return Ok(None), // recordings before the JSON channels: not worth decoding here
    };
    Ok(usize::try_from(count - u64::from(marker && count > 0)).ok())
}

/// A JSON frame message (`surfstream_io::recording`'s encoding) flagged end of scan.
fn is_end_marker_json(message: &[u8]) -> bool {
    #[derive(serde::Deserialize)]
    struct Surfstream {
        flags: u32,
    }
    #[derive(serde::Deserialize)]
    struct Frame {
        surfstream: Surfstream,
    }
    serde_json::from_slice::<Frame>(message)
        .is_ok_and(|f| f.surfstream.flags & flags::END_OF_SCAN != 0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;
    use surfstream_core::frame::{FrameHeader, FrameKind};
    use surfstream_io::recording::Recorder;

    fn planned(params: &toml::Table) -> Option<usize> {
        planned_tiles(&Config::from_table(params).ok()?)
    }

    fn tile(index: u32) -> (FrameHeader, Vec<f32>) {
        let h = FrameHeader {
            kind: FrameKind::Tile as u32,
            tile_index: index,
            width: 4,
            height: 3,
            pitch_x_um: 1.0,
            pitch_y_um: 1.0,
            ..FrameHeader::default()
        };
        (h, vec![index as f32; 12])
    }

    fn record(path: &Path, tiles: u32, marker: bool) {
        let mut rec = Recorder::create(path).unwrap();
        let ch = rec
            .add_frame_channel("stage/tiles", BTreeMap::new())
            .unwrap();
        let other = rec
            .add_frame_channel("fusion/preview", BTreeMap::new())
            .unwrap();
        for k in 0..tiles {
            let (h, z) = tile(k);
            rec.write_frame(ch, &h, &z, 1000 + u64::from(k)).unwrap();
            rec.write_frame(other, &h, &z, 1000 + u64::from(k)).unwrap();
        }
        if marker {
            let h = FrameHeader {
                kind: FrameKind::Marker as u32,
                flags: flags::END_OF_SCAN,
                ..FrameHeader::default()
            };
            rec.write_frame(ch, &h, &[], 5000).unwrap();
        }
        rec.finish().unwrap();
    }

    #[test]
    fn a_recording_says_its_tiles_from_its_summary_without_the_end_marker() {
        let dir = tempfile::tempdir().unwrap();
        let with = dir.path().join("with.mcap");
        record(&with, 5, true);
        assert_eq!(recorded_tiles(&with, "stage/tiles").unwrap(), Some(5));
        assert_eq!(recorded_tiles(&with, "fusion/preview").unwrap(), Some(5));
        assert_eq!(recorded_tiles(&with, "nope").unwrap(), None);
        let without = dir.path().join("without.mcap");
        record(&without, 3, false);
        assert_eq!(recorded_tiles(&without, "stage/tiles").unwrap(), Some(3));
        let mut params = toml::Table::new();
        params.insert("source".into(), "mcap".into());
        params.insert("path".into(), with.display().to_string().into());
        assert_eq!(planned(&params), Some(5));
        // Not a recording: no count (the node's own open says what is wrong).
        let junk = dir.path().join("junk.mcap");
        std::fs::write(&junk, b"not an mcap").unwrap();
        params.insert("path".into(), junk.display().to_string().into());
        assert_eq!(planned(&params), None);
        assert!(recorded_tiles(dir.path(), "stage/tiles").is_err());
    }

    #[test]
    fn a_manifest_and_the_simulated_stage_say_their_tiles() {
        let dir = tempfile::tempdir().unwrap();
        let m = dir.path().join("scan.toml");
        std::fs::write(
            &m,
            "[scan]\nrows = 1\ncols = 2\n[[tile]]\nfile = \"a.npy\"\nrow = 0\ncol = 0\n\
             [[tile]]\nfile = \"b.npy\"\nrow = 0\ncol = 1\n",
        )
        .unwrap();
        let mut params = toml::Table::new();
        params.insert("source".into(), "scan".into());
        params.insert("path".into(), dir.path().display().to_string().into());
        assert_eq!(planned(&params), Some(2));
        let mut sim = toml::Table::new();
        sim.insert("source".into(), "simulated".into());
        sim.insert("rows".into(), 3.into());
        sim.insert("cols".into(), 4.into());
        assert_eq!(planned(&sim), Some(12));
    }
}
