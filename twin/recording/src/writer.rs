//! The writing side of a [`crate::record::Recorder`]: batches of serialised
//! messages, and the MCAP writer that frames, compresses and writes them, on
//! the recorder's thread or on one of its own.

use mcap::records::Metadata;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use serde::Serialize;

use prost_reflect::MessageDescriptor;

use crate::disk::DiskGuard;
use crate::mcap_file::McapFile;
use crate::protobuf;
use crate::write_error::WriteError;

type Result<T, E = WriteError> = std::result::Result<T, E>;

/// A message type the writer serialises itself: see
/// [`crate::record::Recorder::write_deferred`].
pub trait Deferred: Serialize + Send + 'static {
    /// Append the message's protobuf bytes ([`protobuf::Protobuf`]) to `out`
    /// for a channel of the message type named `schema`; `false` where the
    /// type has no such writer, and the writer transcodes it instead.
    fn write_protobuf(&self, schema: &str, out: &mut Vec<u8>) -> bool {
        let _ = (schema, out);
        false
    }
}

/// No message is deferred: a recorder whose caller serialises everything.
#[derive(Debug, Clone, Copy)]
pub enum NoDeferred {}

impl Serialize for NoDeferred {
    fn serialize<S: serde::Serializer>(&self, _: S) -> std::result::Result<S::Ok, S::Error> {
        match *self {}
    }
}

impl Deferred for NoDeferred {}

/// A threaded writer gets batches of this size: large enough that the
/// hand-over costs nothing per message (32 kB ran no faster, pinned).
const THREADED_BATCH_BYTES: usize = 256 * 1024;
/// An inline writer's batches stay small enough to be in cache when written.
const INLINE_BATCH_BYTES: usize = 32 * 1024;
/// Deferred messages per batch, at most: a plant sample is about 250
/// bytes encoded, so in ev-meb a batch holds about as many bytes of them
/// as of the rest and the writer thread wakes every five simulated seconds
/// or so (each wake-up on a busy core is two context switches and the
/// engine's cache to refill).
const BATCH_DEFERRED: usize = 1024;
/// Batches in flight to a writer thread: the caller waits when the writer is
/// this far behind, so a run faster than its compression cannot fill memory.
const BATCHES_IN_FLIGHT: usize = 4;

/// Messages handed to the writer at once: their bytes back to back.
#[derive(Debug)]
pub(crate) struct Batch<D> {
    pub(crate) bytes: Vec<u8>,
    /// Messages the writer serialises.
    pub(crate) deferred: Vec<D>,
    pub(crate) messages: Vec<Queued>,
    /// Hand over at this many bytes.
    limit: usize,
}

impl<D> Batch<D> {
    /// An empty batch with room for a whole one (no growing on the way).
    pub(crate) fn new(limit: usize) -> Self {
        Self {
            bytes: Vec::with_capacity(limit + 4096),
            deferred: Vec::with_capacity(BATCH_DEFERRED),
            messages: Vec::with_capacity(1024),
            limit,
        }
    }

    /// A placeholder holding nothing (replaced by a spent or new batch).
    pub(crate) fn empty() -> Self {
        Self {
            bytes: Vec::new(),
            deferred: Vec::new(),
            messages: Vec::new(),
            limit: 0,
        }
    }

    pub(crate) fn is_full(&self) -> bool {
        self.bytes.len() >= self.limit || self.deferred.len() >= BATCH_DEFERRED
    }

    fn clear(&mut self) {
        self.bytes.clear();
        self.deferred.clear();
        self.messages.clear();
    }
}

/// One message of a batch.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Queued {
    pub(crate) channel: usize,
    pub(crate) sequence: u32,
    pub(crate) time_ns: u64,
    /// Where its bytes end in [`Batch::bytes`] (they start where the
    /// previous message's end), or, for a deferred message, its index in
    /// [`Batch::deferred`].
    pub(crate) end: usize,
    pub(crate) deferred: bool,
    /// Close the open chunk before this message (a simulated second began).
    pub(crate) flush_before: bool,
}

/// What the recorder asks the writer, in order.
pub(crate) enum Job<D> {
    Channel {
        topic: String,
        schema_name: String,
        schema_encoding: &'static str,
        schema: Vec<u8>,
        message_encoding: &'static str,
        /// Its protobuf message type, for the deferred messages (`None`: JSON).
        proto: Option<MessageDescriptor>,
    },
    Messages(Batch<D>),
    Metadata(Metadata),
    /// A file carried whole (an MCAP attachment).
    Attachment {
        log_time: u64,
        name: String,
        media_type: String,
        data: Vec<u8>,
    },
    /// Close the open chunk (and, to a thread, say when it is written).
    Flush(Option<SyncSender<()>>),
}

/// The MCAP file and what writing to it needs.
pub(crate) struct FileWriter {
    writer: McapFile<File>,
    /// MCAP ids of the channels, by creation order.
    ids: Vec<u16>,
    /// Protobuf message types of the channels, by creation order (`None`: JSON).
    protos: Vec<Option<MessageDescriptor>>,
    /// The file, as errors name it.
    path: PathBuf,
    disk: DiskGuard,
}

impl FileWriter {
    pub(crate) fn new(writer: McapFile<File>, path: &Path) -> Self {
        Self {
            writer,
            ids: Vec::new(),
            protos: Vec::new(),
            path: path.to_path_buf(),
            disk: DiskGuard::new(path),
        }
    }

    /// Carry out `job`; a batch comes back emptied, for reuse.
    fn apply<D: Deferred>(&mut self, job: Job<D>) -> Result<Option<Batch<D>>> {
        let path = &self.path;
        let cannot_write = |source| WriteError::Write {
            path: path.clone(),
            source,
        };
        match job {
            Job::Channel {
                topic,
                schema_name,
                schema_encoding,
                schema,
                message_encoding,
                proto,
            } => {
                let schema_id = self
                    .writer
                    .add_schema(&schema_name, schema_encoding, &schema)
                    .map_err(cannot_write)?;
                let id = self
                    .writer
                    .add_channel(schema_id, &topic, message_encoding)
                    .map_err(cannot_write)?;
                self.ids.push(id);
                self.protos.push(proto);
                Ok(None)
            }
            Job::Messages(mut batch) => {
                let mut start = 0;
                for m in &batch.messages {
                    if m.flush_before {
                        self.writer.flush().map_err(cannot_write)?;
                    }
                    let channel = self.ids.get(m.channel).copied().unwrap_or_default();
                    if m.deferred {
                        // Serialised straight into the chunk.
                        let Some(message) = batch.deferred.get(m.end) else {
                            continue;
                        };
                        let schema = self.protos.get(m.channel).and_then(Option::as_ref);
                        self.writer
                            .write_message_with(channel, m.sequence, m.time_ns, m.time_ns, |out| {
                                serialise(schema, message, out)
                            })
                            .map_err(cannot_write)?;
                    } else {
                        let data = batch.bytes.get(start..m.end).unwrap_or_default();
                        start = m.end;
                        self.writer
                            .write_message(channel, m.sequence, m.time_ns, m.time_ns, data)
                            .map_err(cannot_write)?;
                    }
                }
                // A deferred message is about 1 kB of JSON.
                self.disk
                    .wrote(batch.bytes.len() + batch.deferred.len() * 1024)?;
                batch.clear();
                Ok(Some(batch))
            }
            Job::Metadata(metadata) => {
                self.writer
                    .write_metadata(&metadata.name, &metadata.metadata)
                    .map_err(cannot_write)?;
                Ok(None)
            }
            Job::Attachment {
                log_time,
                name,
                media_type,
                data,
            } => {
                // Created at its log time: simulated too, so the bytes repeat.
                self.writer
                    .write_attachment(log_time, log_time, &name, &media_type, &data)
                    .map_err(cannot_write)?;
                Ok(None)
            }
            Job::Flush(done) => {
                self.writer.flush().map_err(cannot_write)?;
                if let Some(done) = done {
                    let _ = done.send(());
                }
                Ok(None)
            }
        }
    }

    /// Write the summary and close the file.
    fn finish(self) -> Result<()> {
        self.writer
            .finish()
            .map(drop)
            .map_err(|source| WriteError::Finish {
                path: self.path,
                source,
            })
    }
}

/// A deferred message's bytes appended to `out`: protobuf by its own
/// writer or by `schema`, else JSON.
fn serialise<D: Deferred>(
    schema: Option<&MessageDescriptor>,
    message: &D,
    out: &mut Vec<u8>,
) -> std::io::Result<()> {
    match schema {
        Some(schema) => {
            if !message.write_protobuf(schema.full_name(), out) {
                protobuf::transcode(schema, message, out).map_err(std::io::Error::other)?;
            }
            Ok(())
        }
        None => serde_json::to_writer(Appender(out), message).map_err(std::io::Error::other),
    }
}

/// Where a recorder's jobs are carried out.
pub(crate) enum Backend<D> {
    /// Boxed: the MCAP writer is large beside a thread's handle.
    Inline(Box<FileWriter>),
    Thread(WriterThread<D>),
}

/// A writer thread and the way to it.
pub(crate) struct WriterThread<D> {
    jobs: SyncSender<Job<D>>,
    /// Batches written, handed back for reuse.
    spent: Receiver<Batch<D>>,
    handle: JoinHandle<Result<()>>,
}

impl<D: Deferred> Backend<D> {
    pub(crate) fn inline(writer: FileWriter) -> Self {
        Backend::Inline(Box::new(writer))
    }

    pub(crate) fn threaded(writer: FileWriter) -> Result<Self> {
        let (jobs, queue) = sync_channel::<Job<D>>(BATCHES_IN_FLIGHT);
        let (give_back, spent) = sync_channel(BATCHES_IN_FLIGHT + 1);
        let handle = std::thread::Builder::new()
            .name("twin-recorder".into())
            .spawn(move || {
                let mut writer = writer;
                while let Ok(job) = queue.recv() {
                    match writer.apply(job) {
                        // Kept for reuse if the recorder has room for it.
                        Ok(Some(batch)) => drop(give_back.try_send(batch)),
                        Ok(None) => {}
                        // Closed whole up to here (the disk guard's stop;
                        // on an I/O error, as far as the disk takes it).
                        Err(e) => {
                            let _ = writer.finish();
                            return Err(e);
                        }
                    }
                }
                writer.finish()
            })
            .map_err(WriteError::Thread)?;
        Ok(Backend::Thread(WriterThread {
            jobs,
            spent,
            handle,
        }))
    }

    /// The size at which the recorder hands a batch over.
    pub(crate) fn batch_bytes(&self) -> usize {
        match self {
            Backend::Inline(_) => INLINE_BATCH_BYTES,
            Backend::Thread(_) => THREADED_BATCH_BYTES,
        }
    }

    /// Carry out `job` (or send it to the thread); an emptied batch comes
    /// back when one is ready for reuse.
    pub(crate) fn submit(&mut self, job: Job<D>) -> Result<Option<Batch<D>>> {
        match self {
            Backend::Inline(writer) => writer.apply(job),
            Backend::Thread(thread) => {
                if thread.jobs.send(job).is_err() {
                    return Err(stopped());
                }
                Ok(thread.spent.try_recv().ok())
            }
        }
    }

    /// Close the open chunk and return once it is written.
    pub(crate) fn flush(&mut self) -> Result<()> {
        match self {
            Backend::Inline(writer) => writer.apply::<D>(Job::Flush(None)).map(drop),
            Backend::Thread(thread) => {
                let (done, written) = sync_channel(1);
                if thread.jobs.send(Job::Flush(Some(done))).is_err() || written.recv().is_err() {
                    return Err(stopped());
                }
                Ok(())
            }
        }
    }

    /// Write the summary and close the file (after every job sent).
    pub(crate) fn finish(self) -> Result<()> {
        match self {
            Backend::Inline(writer) => writer.finish(),
            Backend::Thread(thread) => {
                drop(thread.jobs);
                join(thread.handle)
            }
        }
    }
}

/// A writer thread that stopped: its own error comes from [`Backend::finish`].
fn stopped() -> WriteError {
    WriteError::WriterStopped
}

fn join(handle: JoinHandle<Result<()>>) -> Result<()> {
    handle
        .join()
        .unwrap_or_else(|_| Err(WriteError::WriterPanicked))
}

/// The batch's bytes as serde_json writes them. Most of its writes are a
/// comma, a quote or a short key, which `Vec`'s own `write_all` hands to
/// `memcpy` one call each (perf: `memmove` was 6 % of a recorded run's
/// engine thread, most of it from these writes).
pub(crate) struct Appender<'a>(pub(crate) &'a mut Vec<u8>);

impl std::io::Write for Appender<'_> {
    #[inline]
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.write_all(buf)?;
        Ok(buf.len())
    }

    #[inline]
    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        if buf.len() <= 16 {
            self.0.reserve(buf.len());
            for &b in buf {
                self.0.push(b);
            }
        } else {
            self.0.extend_from_slice(buf);
        }
        Ok(())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}
