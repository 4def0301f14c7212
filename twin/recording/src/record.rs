//! Recording runs to MCAP: JSON messages on JSON-schema channels (Foxglove and
//! `mcap` CLI open them), simulated time as log time, and the run's identity
//! (preset, seed, parameters, twin version) in a metadata record so that a
//! later `replay` can re-run it. No wall-clock time goes into the file: the
//! same run gives the same bytes. What the channels and metadata are is in
//! [`crate::topics`].

use anyhow::{Context, Result};
use mcap::{Compression, WriteOptions, Writer, records::MessageHeader};
use serde::Serialize;
use serde_json::{Map, Value, json};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use crate::topics;

/// How the recording is compressed: zstd at a fixed level, on the calling
/// thread. A worker pool would make the bytes depend on the machine's core
/// count and would hide the compression's cost from `twin bench`.
const ZSTD_LEVEL: u32 = 3;
/// The level of real-time sessions' recordings, which nobody compares byte
/// for byte: level 1 costs the sink thread about half of level 3's time
/// while a server is under load, for files a little larger.
pub const REALTIME_ZSTD_LEVEL: u32 = 1;
/// Uncompressed bytes per chunk (the MCAP library's default, set explicitly so
/// that a library upgrade cannot change the file layout).
const CHUNK_SIZE: u64 = 1024 * 1024;
/// The open chunk is closed and written out once per simulated second: a
/// process killed mid-run loses at most about a second (a real-time run's
/// second is a wall-clock second), and since the cadence is simulated time the
/// chunk boundaries, like every other byte, depend only on the run.
const FLUSH_EVERY_NS: u64 = 1_000_000_000;

/// An open recording.
pub struct Recorder {
    writer: Writer<BufWriter<File>>,
    path: PathBuf,
    /// Per channel, in creation order: its MCAP id and next sequence number.
    channels: Vec<(u16, u32)>,
    topics: BTreeMap<String, ChannelId>,
    buffer: Vec<u8>,
    /// Simulated time (ns) at or after which the next message first flushes.
    next_flush_ns: u64,
}

/// A channel of an open recording: writing through it skips the topic lookup.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChannelId(usize);

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

/// A JSON schema derived from a sample value's shape (types of every field).
pub fn schema_of(sample: &Value) -> Value {
    match sample {
        Value::Null => json!({ "type": ["null", "string"] }),
        Value::Bool(_) => json!({ "type": "boolean" }),
        Value::Number(n) if n.is_f64() => json!({ "type": "number" }),
        Value::Number(_) => json!({ "type": "integer" }),
        Value::String(_) => json!({ "type": "string" }),
        Value::Array(items) => {
            json!({ "type": "array", "items": items.first().map_or(json!({}), schema_of) })
        }
        Value::Object(fields) => {
            let props: Map<String, Value> = fields
                .iter()
                .map(|(k, v)| (k.clone(), schema_of(v)))
                .collect();
            json!({ "type": "object", "properties": props })
        }
    }
}

impl Recorder {
    /// Create `path` (and its parent folders).
    pub fn create(path: &Path) -> Result<Self> {
        Self::create_with_level(path, ZSTD_LEVEL)
    }

    /// Create `path` (and its parent folders), compressed at zstd `level`.
    pub fn create_with_level(path: &Path, level: u32) -> Result<Self> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("cannot create folder {}", dir.display()))?;
        }
        let file =
            File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
        let options = WriteOptions::new()
            .compression(Some(Compression::Zstd))
            .compression_level(level)
            .compression_threads(0)
            .chunk_size(Some(CHUNK_SIZE))
            .profile("")
            .library(concat!("ev-lab-twin ", env!("CARGO_PKG_VERSION")));
        let writer = options
            .create(BufWriter::new(file))
            .with_context(|| format!("cannot start MCAP file {}", path.display()))?;
        Ok(Self {
            writer,
            path: path.to_path_buf(),
            channels: Vec::new(),
            topics: BTreeMap::new(),
            buffer: Vec::new(),
            next_flush_ns: FLUSH_EVERY_NS,
        })
    }

    /// Add a channel whose messages look like `sample`.
    pub fn add_channel<T: Serialize>(&mut self, topic: &str, sample: &T) -> Result<ChannelId> {
        let schema = schema_of(&serde_json::to_value(sample)?);
        let name = topics::schema_name(topic);
        let schema_id = self.writer.add_schema(
            &name,
            topics::SCHEMA_ENCODING,
            &serde_json::to_vec(&schema)?,
        )?;
        let id = self.writer.add_channel(
            schema_id,
            topic,
            topics::MESSAGE_ENCODING,
            &BTreeMap::new(),
        )?;
        let channel = ChannelId(self.channels.len());
        self.channels.push((id, 0));
        self.topics.insert(topic.to_string(), channel);
        Ok(channel)
    }

    /// Whether `topic` has a channel yet.
    pub fn has_channel(&self, topic: &str) -> bool {
        self.topics.contains_key(topic)
    }

    /// The channel of `topic`, if it has one yet.
    pub fn channel(&self, topic: &str) -> Option<ChannelId> {
        self.topics.get(topic).copied()
    }

    /// Write one message at simulated time `time_s`.
    pub fn write<T: Serialize>(&mut self, topic: &str, time_s: f64, message: &T) -> Result<()> {
        let Some(channel) = self.channel(topic) else {
            anyhow::bail!("no channel {topic} in the recording");
        };
        self.write_to(channel, time_s, message)
    }

    /// Write one message to `channel` at simulated time `time_s`.
    pub fn write_to<T: Serialize>(
        &mut self,
        channel: ChannelId,
        time_s: f64,
        message: &T,
    ) -> Result<()> {
        let Some((channel_id, sequence)) = self.channels.get_mut(channel.0) else {
            anyhow::bail!("no channel {} in the recording", channel.0);
        };
        self.buffer.clear();
        serde_json::to_writer(&mut self.buffer, message)?;
        let time_ns = (time_s * 1e9).round() as u64;
        if time_ns >= self.next_flush_ns {
            self.writer
                .flush()
                .with_context(|| format!("cannot write {}", self.path.display()))?;
            self.next_flush_ns = (time_ns / FLUSH_EVERY_NS + 1) * FLUSH_EVERY_NS;
        }
        let header = MessageHeader {
            channel_id: *channel_id,
            sequence: *sequence,
            log_time: time_ns,
            publish_time: time_ns,
        };
        *sequence += 1;
        self.writer.write_to_known_channel(&header, &self.buffer)?;
        Ok(())
    }

    /// Store the run's identity: key/value pairs under `name`.
    pub fn write_metadata(&mut self, name: &str, fields: BTreeMap<String, String>) -> Result<()> {
        self.writer.write_metadata(&mcap::records::Metadata {
            name: name.into(),
            metadata: fields,
        })?;
        Ok(())
    }

    /// Close the open chunk and write it out, so that a crash loses at most
    /// what came after (real-time sessions call this every second or so).
    pub fn flush(&mut self) -> Result<()> {
        self.writer
            .flush()
            .with_context(|| format!("cannot write {}", self.path.display()))
    }

    /// Finish the file (summary, indexes) and return its path.
    pub fn finish(mut self) -> Result<PathBuf> {
        self.writer
            .finish()
            .with_context(|| format!("cannot finish {}", self.path.display()))?;
        Ok(self.path)
    }
}
