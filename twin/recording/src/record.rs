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
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

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

/// An open recording. Messages are serialised on the caller's thread into
/// batches; a thread of the recording's own frames them into chunks,
/// compresses and writes them, in the order they were given, so the bytes are
/// those one thread would write (the chunk boundaries come from the messages'
/// simulated times and sizes, never from timing).
pub struct Recorder {
    path: PathBuf,
    /// Per channel, in creation order: its next sequence number.
    sequences: Vec<u32>,
    topics: BTreeMap<String, ChannelId>,
    /// Messages serialised since the last hand-over.
    batch: Batch,
    writer: Option<WriterThread>,
    /// Simulated time (ns) at or after which the next message first flushes.
    next_flush_ns: u64,
}

/// A channel of an open recording: writing through it skips the topic lookup.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChannelId(usize);

/// Messages handed to the writer thread at once: their bytes back to back.
#[derive(Debug, Default)]
struct Batch {
    bytes: Vec<u8>,
    messages: Vec<Queued>,
}

/// One message of a batch.
#[derive(Debug, Clone, Copy)]
struct Queued {
    channel: usize,
    sequence: u32,
    time_ns: u64,
    /// Where its bytes end in [`Batch::bytes`] (they start where the
    /// previous message's end).
    end: usize,
    /// Close the open chunk before this message (a simulated second began).
    flush_before: bool,
}

/// A batch is handed over at this size: large enough that the hand-over
/// costs nothing per message, small enough to stay in cache.
const BATCH_BYTES: usize = 256 * 1024;
/// Batches in flight: the caller waits when the writer is this far behind,
/// so a run faster than its compression cannot fill memory.
const BATCHES_IN_FLIGHT: usize = 4;

/// What the caller asks the writer thread, in order.
enum Job {
    Channel {
        topic: String,
        schema_name: String,
        schema: Vec<u8>,
    },
    Messages(Batch),
    Metadata(mcap::records::Metadata),
    /// Close the open chunk, then say so.
    Flush(SyncSender<()>),
}

/// The writer thread and the way to it.
struct WriterThread {
    jobs: SyncSender<Job>,
    /// Batches written, handed back for reuse.
    spent: Receiver<Batch>,
    handle: JoinHandle<Result<()>>,
}

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
        let (jobs, queue) = sync_channel(BATCHES_IN_FLIGHT);
        let (give_back, spent) = sync_channel(BATCHES_IN_FLIGHT + 1);
        let shown = path.display().to_string();
        let handle = std::thread::Builder::new()
            .name("twin-recorder".into())
            .spawn(move || write_jobs(writer, &queue, &give_back, &shown))
            .context("cannot start the recording's writer thread")?;
        Ok(Self {
            path: path.to_path_buf(),
            sequences: Vec::new(),
            topics: BTreeMap::new(),
            batch: Batch::default(),
            writer: Some(WriterThread {
                jobs,
                spent,
                handle,
            }),
            next_flush_ns: FLUSH_EVERY_NS,
        })
    }

    /// Add a channel whose messages look like `sample`.
    pub fn add_channel<T: Serialize>(&mut self, topic: &str, sample: &T) -> Result<ChannelId> {
        let schema = serde_json::to_vec(&schema_of(&serde_json::to_value(sample)?))?;
        // The channel's messages must not reach the writer before it does.
        self.hand_over()?;
        self.send(Job::Channel {
            topic: topic.to_string(),
            schema_name: topics::schema_name(topic),
            schema,
        })?;
        let channel = ChannelId(self.sequences.len());
        self.sequences.push(0);
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
        let Some(sequence) = self.sequences.get_mut(channel.0) else {
            anyhow::bail!("no channel {} in the recording", channel.0);
        };
        let start = self.batch.bytes.len();
        if let Err(e) = serde_json::to_writer(&mut self.batch.bytes, message) {
            self.batch.bytes.truncate(start);
            return Err(e.into());
        }
        let time_ns = (time_s * 1e9).round() as u64;
        let flush_before = time_ns >= self.next_flush_ns;
        if flush_before {
            self.next_flush_ns = (time_ns / FLUSH_EVERY_NS + 1) * FLUSH_EVERY_NS;
        }
        self.batch.messages.push(Queued {
            channel: channel.0,
            sequence: *sequence,
            time_ns,
            end: self.batch.bytes.len(),
            flush_before,
        });
        *sequence += 1;
        if self.batch.bytes.len() >= BATCH_BYTES {
            self.hand_over()?;
        }
        Ok(())
    }

    /// Store the run's identity: key/value pairs under `name`.
    pub fn write_metadata(&mut self, name: &str, fields: BTreeMap<String, String>) -> Result<()> {
        self.hand_over()?;
        self.send(Job::Metadata(mcap::records::Metadata {
            name: name.into(),
            metadata: fields,
        }))
    }

    /// Close the open chunk and write it out, so that a crash loses at most
    /// what came after (real-time sessions call this every second or so).
    /// Returns once the writer has written it.
    pub fn flush(&mut self) -> Result<()> {
        self.hand_over()?;
        let (done, written) = sync_channel(1);
        self.send(Job::Flush(done))?;
        if written.recv().is_err() {
            return Err(self.writer_failed());
        }
        Ok(())
    }

    /// Finish the file (summary, indexes) and return its path.
    pub fn finish(mut self) -> Result<PathBuf> {
        self.hand_over()?;
        if let Some(writer) = self.writer.take() {
            drop(writer.jobs);
            join(writer.handle)?;
        }
        Ok(std::mem::take(&mut self.path))
    }

    /// Hand the messages serialised so far to the writer thread.
    fn hand_over(&mut self) -> Result<()> {
        if self.batch.messages.is_empty() {
            return Ok(());
        }
        let fresh = match &self.writer {
            Some(w) => w.spent.try_recv().unwrap_or_default(),
            None => Batch::default(),
        };
        let full = std::mem::replace(&mut self.batch, fresh);
        self.send(Job::Messages(full))
    }

    fn send(&mut self, job: Job) -> Result<()> {
        let sent = match &self.writer {
            Some(w) => w.jobs.send(job).is_ok(),
            None => false,
        };
        if sent {
            Ok(())
        } else {
            Err(self.writer_failed())
        }
    }

    /// The writer thread's error, once it has stopped on one.
    fn writer_failed(&mut self) -> anyhow::Error {
        match self.writer.take() {
            Some(w) => {
                drop(w.jobs);
                match join(w.handle) {
                    Err(e) => e,
                    Ok(()) => anyhow::anyhow!("the writer of {} stopped", self.path.display()),
                }
            }
            None => anyhow::anyhow!("the recording {} is closed", self.path.display()),
        }
    }
}

/// A recording dropped unfinished is finished as the MCAP library does on
/// drop (summary and all), and is complete on disk when the drop returns.
impl Drop for Recorder {
    fn drop(&mut self) {
        let _ = self.hand_over();
        if let Some(writer) = self.writer.take() {
            drop(writer.jobs);
            let _ = writer.handle.join();
        }
    }
}

fn join(handle: JoinHandle<Result<()>>) -> Result<()> {
    handle
        .join()
        .unwrap_or_else(|_| Err(anyhow::anyhow!("the recording's writer thread failed")))
}

/// The writer thread: every job in order, then the file's summary.
fn write_jobs(
    mut writer: Writer<BufWriter<File>>,
    jobs: &Receiver<Job>,
    give_back: &SyncSender<Batch>,
    shown: &str,
) -> Result<()> {
    let cannot_write = || format!("cannot write {shown}");
    // MCAP ids of the channels, by creation order.
    let mut ids: Vec<u16> = Vec::new();
    while let Ok(job) = jobs.recv() {
        match job {
            Job::Channel {
                topic,
                schema_name,
                schema,
            } => {
                let schema_id = writer
                    .add_schema(&schema_name, topics::SCHEMA_ENCODING, &schema)
                    .with_context(cannot_write)?;
                let id = writer
                    .add_channel(
                        schema_id,
                        &topic,
                        topics::MESSAGE_ENCODING,
                        &BTreeMap::new(),
                    )
                    .with_context(cannot_write)?;
                ids.push(id);
            }
            Job::Messages(mut batch) => {
                let mut start = 0;
                for m in &batch.messages {
                    if m.flush_before {
                        writer.flush().with_context(cannot_write)?;
                    }
                    let header = MessageHeader {
                        channel_id: ids.get(m.channel).copied().unwrap_or_default(),
                        sequence: m.sequence,
                        log_time: m.time_ns,
                        publish_time: m.time_ns,
                    };
                    let data = batch.bytes.get(start..m.end).unwrap_or_default();
                    writer
                        .write_to_known_channel(&header, data)
                        .with_context(cannot_write)?;
                    start = m.end;
                }
                batch.bytes.clear();
                batch.messages.clear();
                // Kept for reuse if the caller has room for it.
                let _ = give_back.try_send(batch);
            }
            Job::Metadata(metadata) => {
                writer.write_metadata(&metadata).with_context(cannot_write)?;
            }
            Job::Flush(done) => {
                writer.flush().with_context(cannot_write)?;
                let _ = done.send(());
            }
        }
    }
    writer
        .finish()
        .with_context(|| format!("cannot finish {shown}"))?;
    Ok(())
}
