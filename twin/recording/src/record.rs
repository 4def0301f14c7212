//! Recording runs to MCAP: the plant's samples and the frames as protobuf
//! (their schema a `FileDescriptorSet` in the file), the other channels as
//! JSON on JSON-schema channels (Foxglove, Lichtblick and the `mcap` CLI open
//! both), simulated time as log time, and the run's identity
//! (preset, seed, parameters, twin version) in a metadata record so that a
//! later `replay` can re-run it. No wall-clock time goes into the file: the
//! same run gives the same bytes. What the channels and metadata are is in
//! [`crate::topics`].

use prost_reflect::MessageDescriptor;
use serde::Serialize;
use serde_json::{Map, Value, json};
use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};

use crate::mcap_file::McapFile;
use crate::protobuf;
use crate::topics;
use crate::writer::{Appender, Backend, Batch, FileWriter, Job, Queued};
pub use crate::writer::{Deferred, NoDeferred};

/// How the recording is compressed: zstd level 1 with its match finder set
/// for the twin's chunks (`mcap_file::compressor`), one stream per chunk, by
/// the writer (see [`Recorder`] for which thread that is). On the twin's
/// chunks level 1 is both faster and smaller than level 3 (ev-meb 548 kB
/// against 594 kB for 10 s of JSON, ten-modules 4.07 MB against 4.65 MB).
/// zstd's own worker threads stay off: one writer compresses.
pub(crate) const ZSTD_LEVEL: i32 = 1;
/// Uncompressed bytes per chunk (the MCAP library's default, set explicitly so
/// that a library upgrade cannot change the file layout).
pub(crate) const CHUNK_SIZE: usize = 1024 * 1024;
/// The open chunk is closed and written out once per simulated second: a
/// process killed mid-run loses at most about a second (a real-time run's
/// second is a wall-clock second), and since the cadence is simulated time the
/// chunk boundaries, like every other byte, depend only on the run.
const FLUSH_EVERY_NS: u64 = 1_000_000_000;

/// An open recording. Messages are serialised into batches, which the MCAP
/// writer frames into chunks, compresses and writes, in the order they were
/// given: on the caller's thread ([`Recorder::create`], what a session's sink
/// thread uses) or on a thread of the recording's own
/// ([`Recorder::create_threaded`], what a virtual run uses, so that the
/// engine never waits for zstd). Either way the bytes are the same: the chunk
/// boundaries come from the messages' simulated times and sizes, never from
/// timing.
///
/// `D` is a message type the writer serialises itself
/// ([`Recorder::write_deferred`]): a run's plant samples, most of its bytes,
/// cost a threaded recording's caller a copy instead of their JSON.
pub struct Recorder<D: Deferred = NoDeferred> {
    path: PathBuf,
    /// Per channel, in creation order: its next sequence number.
    sequences: Vec<u32>,
    /// Per channel, in creation order: its protobuf message type (`None`: JSON).
    protos: Vec<Option<MessageDescriptor>>,
    /// Per channel: the hand-written message type found to match its
    /// schema, so that the next message of that type costs a pointer
    /// compare instead of comparing the names.
    typed_as: Vec<Option<&'static str>>,
    topics: BTreeMap<String, ChannelId>,
    /// Messages serialised since the last hand-over.
    batch: Batch<D>,
    /// `None` once finished or failed.
    backend: Option<Backend<D>>,
    /// Simulated time (ns) at or after which the next message first flushes.
    next_flush_ns: u64,
}

/// A channel of an open recording: writing through it skips the topic lookup.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChannelId(usize);

impl<D: Deferred> std::fmt::Debug for Recorder<D> {
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

pub use crate::write_error::WriteError;

type Result<T, E = WriteError> = std::result::Result<T, E>;

impl Recorder {
    /// Create `path` (and its parent folders), written on the caller's thread.
    pub fn create(path: &Path) -> Result<Self> {
        Self::create_inline(path)
    }
}

impl<D: Deferred> Recorder<D> {
    /// Create `path` (and its parent folders), written on the caller's
    /// thread: for a caller that is itself off the critical path (a
    /// session's sink), where a second thread would only add the hand-over.
    pub fn create_inline(path: &Path) -> Result<Self> {
        let writer = open(path)?;
        Ok(Self::with_backend(path, Backend::inline(writer)))
    }

    /// Create `path` (and its parent folders), written by a thread of its own.
    pub fn create_threaded(path: &Path) -> Result<Self> {
        let writer = open(path)?;
        Ok(Self::with_backend(path, Backend::threaded(writer)?))
    }

    fn with_backend(path: &Path, backend: Backend<D>) -> Self {
        Self {
            path: path.to_path_buf(),
            sequences: Vec::new(),
            protos: Vec::new(),
            typed_as: Vec::new(),
            topics: BTreeMap::new(),
            batch: Batch::new(backend.batch_bytes()),
            backend: Some(backend),
            next_flush_ns: FLUSH_EVERY_NS,
        }
    }

    /// Add a channel whose messages look like `sample`: protobuf where the
    /// catalogue has a protobuf schema for it ([`topics::proto_schema`]) and
    /// `sample` fits it, JSON otherwise (its schema the catalogue's, where
    /// [`topics::described_schema`] has one, else derived from `sample`).
    pub fn add_channel<T: Serialize>(&mut self, topic: &str, sample: &T) -> Result<ChannelId> {
        let proto = topics::proto_schema(topic)
            .filter(|schema| protobuf::transcode(schema, sample, &mut Vec::new()).is_ok());
        let job = match &proto {
            Some(schema) => Job::Channel {
                topic: topic.to_string(),
                schema_name: schema.full_name().to_string(),
                schema_encoding: topics::PROTOBUF,
                schema: protobuf::descriptor_set(schema),
                message_encoding: topics::PROTOBUF,
                proto: Some(schema.clone()),
            },
            None => {
                let schema = match topics::described_schema(topic) {
                    Some(schema) => schema,
                    None => schema_of(&serde_json::to_value(sample)?),
                };
                Job::Channel {
                    topic: topic.to_string(),
                    schema_name: topics::schema_name(topic),
                    schema_encoding: topics::SCHEMA_ENCODING,
                    schema: serde_json::to_vec(&schema)?,
                    message_encoding: topics::MESSAGE_ENCODING,
                    proto: None,
                }
            }
        };
        // The channel's messages must not reach the writer before it does.
        self.hand_over()?;
        self.submit(job)?;
        let channel = ChannelId(self.sequences.len());
        self.sequences.push(0);
        self.protos.push(proto);
        self.typed_as.push(None);
        self.topics.insert(topic.to_string(), channel);
        Ok(channel)
    }

    /// Whether `channel`'s messages are protobuf (else JSON).
    pub fn is_protobuf(&self, channel: ChannelId) -> bool {
        self.protos.get(channel.0).is_some_and(Option::is_some)
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
            return Err(WriteError::NoChannel {
                channel: topic.to_string(),
            });
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
        self.check(channel)?;
        let start = self.batch.bytes.len();
        let written: Result<(), Box<dyn std::error::Error + Send + Sync>> =
            match self.protos.get(channel.0) {
                Some(Some(schema)) => {
                    protobuf::transcode(schema, message, &mut self.batch.bytes).map_err(Into::into)
                }
                _ => serde_json::to_writer(Appender(&mut self.batch.bytes), message)
                    .map_err(Into::into),
            };
        if let Err(source) = written {
            self.batch.bytes.truncate(start);
            return Err(WriteError::Encode {
                topic: self.topic_of(channel).to_string(),
                source,
            });
        }
        let end = self.batch.bytes.len();
        self.queue(channel, time_s, end, false)
    }

    /// Write `message` to `channel` at simulated time `time_s`: its
    /// protobuf written through its type ([`protobuf::Protobuf`]) where the
    /// channel has its schema, else as [`Recorder::write_to`] writes it.
    pub fn write_typed<T: Serialize + protobuf::Protobuf>(
        &mut self,
        channel: ChannelId,
        time_s: f64,
        message: &T,
    ) -> Result<()> {
        if self.write_protobuf(channel, time_s, T::SCHEMA, |m| message.write_protobuf(m))? {
            Ok(())
        } else {
            self.write_to(channel, time_s, message)
        }
    }

    /// Write a message to `channel` at simulated time `time_s`, its fields
    /// written by `fields`, if the channel's schema is the protobuf message
    /// type named `schema`; `false` (nothing written) if it is not.
    pub fn write_protobuf(
        &mut self,
        channel: ChannelId,
        time_s: f64,
        schema: &'static str,
        fields: impl FnOnce(&mut Vec<u8>),
    ) -> Result<bool> {
        if !self.is_typed(channel, schema) {
            return Ok(false);
        }
        fields(&mut self.batch.bytes);
        let end = self.batch.bytes.len();
        self.queue(channel, time_s, end, false)?;
        Ok(true)
    }

    /// Whether `channel`'s schema is the protobuf message type `schema`.
    fn is_typed(&mut self, channel: ChannelId, schema: &'static str) -> bool {
        let Some(known) = self.typed_as.get_mut(channel.0) else {
            return false;
        };
        if known.is_some_and(|k| std::ptr::eq(k, schema)) {
            return true;
        }
        let matches =
            matches!(self.protos.get(channel.0), Some(Some(s)) if s.full_name() == schema);
        if matches {
            *known = Some(schema);
        }
        matches
    }

    /// Write `message` to `channel` at simulated time `time_s`, serialised
    /// by the writer (the same bytes as [`Recorder::write_to`]).
    pub fn write_deferred(&mut self, channel: ChannelId, time_s: f64, message: D) -> Result<()> {
        self.check(channel)?;
        let index = self.batch.deferred.len();
        self.batch.deferred.push(message);
        self.queue(channel, time_s, index, true)
    }

    /// The topic of `channel`, as errors name it.
    fn topic_of(&self, channel: ChannelId) -> &str {
        self.topics
            .iter()
            .find(|(_, c)| **c == channel)
            .map_or("", |(t, _)| t.as_str())
    }

    fn check(&self, channel: ChannelId) -> Result<()> {
        if channel.0 < self.sequences.len() {
            Ok(())
        } else {
            Err(WriteError::NoChannel {
                channel: channel.0.to_string(),
            })
        }
    }

    /// Queue the message just added to the batch.
    fn queue(&mut self, channel: ChannelId, time_s: f64, end: usize, deferred: bool) -> Result<()> {
        // Checked by the callers before they add to the batch.
        let Some(sequence) = self.sequences.get_mut(channel.0) else {
            return Err(WriteError::NoChannel {
                channel: channel.0.to_string(),
            });
        };
        let time_ns = nanoseconds(time_s);
        let flush_before = time_ns >= self.next_flush_ns;
        if flush_before {
            self.next_flush_ns = (time_ns / FLUSH_EVERY_NS + 1) * FLUSH_EVERY_NS;
        }
        self.batch.messages.push(Queued {
            channel: channel.0,
            sequence: *sequence,
            time_ns,
            end,
            deferred,
            flush_before,
        });
        *sequence += 1;
        if self.batch.is_full() {
            self.hand_over()?;
        }
        Ok(())
    }

    /// Store the run's identity: key/value pairs under `name`.
    pub fn write_metadata(&mut self, name: &str, fields: BTreeMap<String, String>) -> Result<()> {
        self.hand_over()?;
        self.submit(Job::Metadata(mcap::records::Metadata {
            name: name.into(),
            metadata: fields,
        }))
        .map(drop)
    }

    /// Carry a file whole as an MCAP attachment named `name` (the firmware
    /// a run executed, so that a replay runs the same bytes), stamped with
    /// simulated time `time_s`.
    pub fn attach(
        &mut self,
        name: &str,
        media_type: &str,
        time_s: f64,
        data: Vec<u8>,
    ) -> Result<()> {
        self.hand_over()?;
        self.submit(Job::Attachment {
            log_time: nanoseconds(time_s),
            name: name.into(),
            media_type: media_type.into(),
            data,
        })
        .map(drop)
    }

    /// Close the open chunk and write it out, so that a crash loses at most
    /// what came after (real-time sessions call this every second or so).
    /// Returns once the writer has written it.
    pub fn flush(&mut self) -> Result<()> {
        self.hand_over()?;
        let flushed = match &mut self.backend {
            Some(backend) => backend.flush(),
            None => return Err(self.closed()),
        };
        flushed.map_err(|e| self.fail(e))
    }

    /// Finish the file (summary, indexes) and return its path.
    pub fn finish(mut self) -> Result<PathBuf> {
        self.hand_over()?;
        match self.backend.take() {
            Some(backend) => backend.finish()?,
            None => return Err(self.closed()),
        }
        Ok(std::mem::take(&mut self.path))
    }

    /// Hand the messages serialised so far to the writer.
    fn hand_over(&mut self) -> Result<()> {
        if self.batch.messages.is_empty() {
            return Ok(());
        }
        let full = std::mem::replace(&mut self.batch, Batch::empty());
        let spent = self.submit(Job::Messages(full))?;
        let limit = self.backend.as_ref().map_or(0, Backend::batch_bytes);
        self.batch = spent.unwrap_or_else(|| Batch::new(limit));
        Ok(())
    }

    /// Give `job` to the writer; an emptied batch may come back for reuse.
    fn submit(&mut self, job: Job<D>) -> Result<Option<Batch<D>>> {
        let Some(backend) = &mut self.backend else {
            return Err(self.closed());
        };
        backend.submit(job).map_err(|e| self.fail(e))
    }

    /// Close the writer after `e`: a writer thread's own error, if it
    /// stopped on one, says more than the hand-over's.
    fn fail(&mut self, e: WriteError) -> WriteError {
        match self.backend.take().map(Backend::finish) {
            Some(Err(cause)) => cause,
            _ => e,
        }
    }

    fn closed(&self) -> WriteError {
        WriteError::Closed {
            path: self.path.clone(),
        }
    }
}

/// A recording dropped unfinished is finished as the MCAP library does on
/// drop (summary and all), and is complete on disk when the drop returns.
impl<D: Deferred> Drop for Recorder<D> {
    fn drop(&mut self) {
        let _ = self.hand_over();
        if let Some(backend) = self.backend.take() {
            let _ = backend.finish();
        }
    }
}

/// Simulated seconds as MCAP's nanoseconds, the nearest (halves away from
/// zero, as `f64::round`, whose call into libm a profile found on every
/// message: the twin's target has no rounding instruction); 0 before 0.
#[inline]
fn nanoseconds(time_s: f64) -> u64 {
    let ns = time_s * 1e9;
    if ns.is_nan() || ns <= 0.0 {
        return 0;
    }
    // Below 2^53 the fraction is exact; above it, `ns` is a whole number.
    let whole = ns as u64;
    whole.saturating_add(u64::from(ns - whole as f64 >= 0.5))
}

/// The MCAP writer of a new file at `path`.
fn open(path: &Path) -> Result<FileWriter> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| WriteError::CreateFolder {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    let file = File::create(path).map_err(|source| WriteError::Create {
        path: path.to_path_buf(),
        source,
    })?;
    let library = concat!("ev-lab-twin ", env!("CARGO_PKG_VERSION"));
    let writer = McapFile::new(file, "", library, ZSTD_LEVEL, CHUNK_SIZE).map_err(|source| {
        WriteError::Start {
            path: path.to_path_buf(),
            source,
        }
    })?;
    Ok(FileWriter::new(writer, path))
}

#[cfg(test)]
mod tests {
    use super::nanoseconds;

    #[test]
    fn simulated_seconds_round_to_nanoseconds_as_f64_round_does() {
        let mut times = vec![
            0.0,
            -1.0,
            f64::NAN,
            1e-9,
            0.5e-9,
            1.5e-9,
            2.5e-9,
            1e12,
            3600.0,
        ];
        // Every 10 µs of a 100 s run, and odd steps across it.
        times.extend((0..10_000_000).step_by(997).map(|i| f64::from(i) * 1e-5));
        times.extend((0..100_000).map(|i| f64::from(i) * 0.001_234_567_891));
        for t in times {
            assert_eq!(nanoseconds(t), (t * 1e9).round() as u64, "{t}");
        }
    }
}
