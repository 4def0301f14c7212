//! Reading a recording back, streamed: [`Reader`] goes through the file front
//! to back one chunk at a time (read from disk, decompressed, handed out
//! message by message, dropped), so what a reader keeps is only what it asks
//! for. [`Recording`] is what a pass leaves: the metadata, the channels with
//! their message counts, the chunks read and, for a file cut short (the
//! process killed mid-run), where and why reading stopped. Everything up to
//! the last complete chunk is read; a damaged chunk is dropped whole.
//!
//! Every reader of recordings builds on this one: [`crate::signals`]
//! (`twin compare`), [`crate::diff`] (`twin replay`), [`crate::export`]
//! (`twin export`), the frames of `twin replay --frames-to`, and the viewer
//! (`twin view`).

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use prost_reflect::MessageDescriptor;
use serde::Deserialize;
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};

use crate::chunk::{chunk_damage_in_words, chunk_records, in_words};
use crate::protobuf;
use crate::topics::{self, Topic};

/// One channel of a recording: its topic and how many messages it holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Channel {
    pub topic: String,
    /// Messages read on it.
    pub message_count: u64,
    /// How its messages are written.
    pub encoding: Encoding,
}

/// How a channel's messages are written: the twin writes the plant's
/// samples and the frames as protobuf, the rest (and everything, in files
/// older than that) as JSON; [`Message::json`] reads both.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Encoding {
    Json,
    /// Protobuf, of the message type its file's schema gives.
    Protobuf(MessageDescriptor),
    /// Protobuf whose schema does not read: why, in words.
    BadSchema(String),
    /// Anything else (not written by this twin), by its name.
    Other(String),
}

impl Encoding {
    /// The encoding of a channel of `message_encoding` whose schema record
    /// (name, encoding, data) is `schema`.
    fn of(message_encoding: &str, schema: Option<&(String, String, Vec<u8>)>) -> Self {
        match message_encoding {
            topics::MESSAGE_ENCODING => Encoding::Json,
            topics::PROTOBUF => match schema {
                Some((name, encoding, data)) if encoding == topics::PROTOBUF => {
                    match protobuf::schema_in(data, name) {
                        Ok(schema) => Encoding::Protobuf(schema),
                        Err(e) => Encoding::BadSchema(e),
                    }
                }
                _ => Encoding::BadSchema("it has no protobuf schema".into()),
            },
            other => Encoding::Other(other.to_string()),
        }
    }
}

/// Why reading stopped before the end of the data.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Cut {
    /// The file ends early (or is damaged) after `chunks` complete chunks.
    EndsEarly { chunks: u64, error: String },
    /// Chunk `chunk` (1-based) does not decompress or decode.
    DamagedChunk { chunk: u64, error: String },
    /// Every record is whole, but the summary never came: the run did not
    /// finish (the process stopped between two chunks, leaving the
    /// provisional end the writer puts after each).
    NoSummary,
}

impl Cut {
    /// The reader's own error, when one stopped it (not for a file that
    /// simply ends between two chunks).
    pub fn error(&self) -> Option<&str> {
        match self {
            Cut::EndsEarly { error, .. } | Cut::DamagedChunk { error, .. } => Some(error),
            Cut::NoSummary => None,
        }
    }
}

impl std::fmt::Display for Cut {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Cut::EndsEarly { chunks, error } => write!(
                f,
                "the file ends early or is damaged after {chunks} complete chunk(s) ({error}); \
                 read up to there"
            ),
            Cut::DamagedChunk { chunk, error } => write!(f, "chunk {chunk} is damaged ({error})"),
            Cut::NoSummary => {
                f.write_str("the file ends without its summary (the run did not finish)")
            }
        }
    }
}

/// Why a recording, or a message in it, cannot be read. A file cut short
/// is not one of these: it reads up to its cut (see [`Recording::truncated`]).
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file cannot be opened, or reading it failed part way.
    #[error("cannot read {}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is not MCAP at all: `twin view` says so in its own words.
    #[error(
        "{} is not a readable recording: it does not start with the MCAP magic bytes",
        path.display()
    )]
    NotMcap { path: PathBuf },
    /// What [`Recording::scan`] met part way through `path` (a message that
    /// does not read, or one its visitor refused).
    #[error("{} is not a readable recording", path.display())]
    Unreadable {
        path: PathBuf,
        #[source]
        source: Box<ReadError>,
    },
    /// An I/O error in the system's own words, where the file is named by
    /// what wraps it or not at all.
    #[error(transparent)]
    Source(std::io::Error),
    #[error("message {sequence} on {topic} is not JSON")]
    NotJson {
        sequence: u32,
        topic: String,
        #[source]
        source: serde_json::Error,
    },
    #[error("message {sequence} on {topic} is damaged: {why}")]
    Damaged {
        sequence: u32,
        topic: String,
        why: String,
    },
    #[error("message {sequence} on {topic} lacks a field the twin reads")]
    LacksField {
        sequence: u32,
        topic: String,
        #[source]
        source: serde_json::Error,
    },
    #[error("the messages on {topic} cannot be read: {why}")]
    BadSchema { topic: String, why: String },
    #[error(
        "the messages on {topic} are `{encoding}`, which the twin does not read \
         (it reads json and protobuf)"
    )]
    OtherEncoding { topic: String, encoding: String },
    #[error("message {sequence} refers to channel {channel_id}, which was never declared")]
    Stray { sequence: u32, channel_id: u16 },
}

type Result<T, E = ReadError> = std::result::Result<T, E>;

/// What a pass through a recording found (everything but the messages).
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    pub path: PathBuf,
    /// Metadata records by name (`twin.run`: the run's identity; see
    /// [`crate::topics`]).
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// Channels in the order they first appear.
    pub channels: Vec<Channel>,
    /// Complete chunks read.
    pub chunks: u64,
    /// Why reading stopped early, when the file is cut short: everything up
    /// to its last complete chunk was read.
    pub truncated: Option<Cut>,
    /// The latest log time of any message (ns).
    pub end_ns: u64,
}

/// One message as the reader hands it out: borrowed from the chunk being read.
#[derive(Debug, Clone, Copy)]
pub struct Message<'a> {
    /// Index of its channel in [`Recording::channels`].
    pub channel: usize,
    pub topic: &'a str,
    pub sequence: u32,
    /// Log time: simulated time (ns).
    pub log_time_ns: u64,
    /// The message as recorded (JSON text or protobuf, as `encoding` says).
    pub data: &'a [u8],
    pub encoding: &'a Encoding,
}

impl Message<'_> {
    /// Log time in seconds.
    pub fn time_s(&self) -> f64 {
        self.log_time_ns as f64 * 1e-9
    }

    /// The message decoded as `T` (a [`serde_json::Value`], or one of the
    /// catalogue's sample types): a JSON message as it is, a protobuf one as
    /// the same JSON value (every field by its name).
    pub fn json<'de, T: Deserialize<'de>>(&'de self) -> Result<T> {
        let sequence = self.sequence;
        let topic = || self.topic.to_string();
        match self.encoding {
            Encoding::Json => {
                serde_json::from_slice(self.data).map_err(|source| ReadError::NotJson {
                    sequence,
                    topic: topic(),
                    source,
                })
            }
            Encoding::Protobuf(schema) => {
                let mut value =
                    protobuf::to_value(schema, self.data).map_err(|why| ReadError::Damaged {
                        sequence,
                        topic: topic(),
                        why,
                    })?;
                if schema.full_name() == topics::FRAME_SCHEMA {
                    topics::complete_frame(&mut value);
                }
                T::deserialize(value).map_err(|source| ReadError::LacksField {
                    sequence,
                    topic: topic(),
                    source,
                })
            }
            Encoding::BadSchema(why) => Err(ReadError::BadSchema {
                topic: topic(),
                why: why.clone(),
            }),
            Encoding::Other(name) => Err(ReadError::OtherEncoding {
                topic: topic(),
                encoding: name.clone(),
            }),
        }
    }

    /// The message as a JSON value, as [`Message::json`] reads it.
    pub fn value(&self) -> Result<serde_json::Value> {
        self.json()
    }

    /// Check that the message reads without keeping any of it.
    pub fn check_json(&self) -> Result<()> {
        match self.encoding {
            Encoding::Json => self.json::<serde::de::IgnoredAny>().map(|_| ()),
            _ => self.value().map(drop),
        }
    }
}

/// The encoding of a message whose channel is unknown.
static JSON: Encoding = Encoding::Json;

/// What [`Reader::next`] hands out, in file order.
#[derive(Debug, Clone, Copy)]
pub enum Item<'a> {
    /// A metadata record (its name and fields).
    Metadata {
        name: &'a str,
        fields: &'a BTreeMap<String, String>,
    },
    /// A channel declared for the first time: its index in
    /// [`Recording::channels`] and topic.
    Channel {
        index: usize,
        topic: &'a str,
    },
    Message(Message<'a>),
    /// A message on a channel never declared (a damaged file).
    Stray {
        channel_id: u16,
        sequence: u32,
    },
}

/// A recording read front to back, one chunk in memory at a time.
pub struct Reader<R = File> {
    source: R,
    linear: LinearReader,
    /// Records of the chunk being handed out.
    pending: std::vec::IntoIter<Record<'static>>,
    /// The record handed out last (items borrow from it).
    current: Option<Current>,
    /// Decompress chunks (off: a pass for the metadata alone).
    chunks_too: bool,
    /// MCAP channel id to index in `recording.channels`.
    by_id: HashMap<u16, usize>,
    /// Schema records by id: name, encoding, data.
    schemas: HashMap<u16, (String, String, Vec<u8>)>,
    recording: Recording,
    done: bool,
}

impl<R> std::fmt::Debug for Reader<R> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Reader")
            .field("path", &self.recording.path)
            .field("chunks", &self.recording.chunks)
            .finish_non_exhaustive()
    }
}

impl Reader<File> {
    /// Open `path`. A file that is not MCAP is an error; one cut short is not
    /// (see [`Recording::truncated`]).
    pub fn open(path: &Path) -> Result<Self> {
        let io = |source| ReadError::Io {
            path: path.to_path_buf(),
            source,
        };
        let file = File::open(path).map_err(io)?;
        let len = file.metadata().map_err(io)?.len();
        Self::new(file, len, path)
    }
}

impl<'a> Reader<&'a [u8]> {
    /// Read a recording held in memory; `path` names it.
    pub fn from_bytes(bytes: &'a [u8], path: &Path) -> Result<Self> {
        Self::new(bytes, bytes.len() as u64, path)
    }
}

impl<R: Read> Reader<R> {
    /// Read the recording `source` of `len` bytes; `path` names it. A file
    /// that is not MCAP is [`ReadError::NotMcap`].
    pub fn new(mut source: R, len: u64, path: &Path) -> Result<Self> {
        let mut magic = [0u8; 8];
        let mut got = 0;
        while got < magic.len() {
            match source.read(&mut magic[got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    return Err(ReadError::Unreadable {
                        path: path.to_path_buf(),
                        source: Box::new(ReadError::Source(e)),
                    });
                }
            }
        }
        if magic[..got] != *mcap::MAGIC {
            return Err(ReadError::NotMcap {
                path: path.to_path_buf(),
            });
        }
        // As `mcap::read::LinearReader` reads a whole file: chunks whole, no
        // record longer than the file, the end magic not required.
        let options = LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_emit_chunks(true)
            .with_record_length_limit(usize::try_from(len).unwrap_or(usize::MAX));
        Ok(Self {
            source,
            linear: LinearReader::new_with_options(options),
            pending: Vec::new().into_iter(),
            current: None,
            chunks_too: true,
            by_id: HashMap::new(),
            schemas: HashMap::new(),
            recording: Recording {
                path: path.to_path_buf(),
                metadata: BTreeMap::new(),
                channels: Vec::new(),
                chunks: 0,
                truncated: None,
                end_ns: 0,
            },
            done: false,
        })
    }

    /// Skip the chunks (counted, not decompressed): a quick pass for the
    /// metadata records, which lie between them.
    pub fn metadata_only(mut self) -> Self {
        self.chunks_too = false;
        self
    }

    /// What the reader has found so far.
    pub fn recording(&self) -> &Recording {
        &self.recording
    }

    /// The pass's findings, once [`Self::next`] has returned `None`.
    pub fn finish(self) -> Recording {
        self.recording
    }

    /// The next item, or `None` at the end of the data (the data end record,
    /// or where a file cut short stops: see [`Recording::truncated`]).
    /// Errors are the source's (I/O); a damaged file is not one.
    #[allow(clippy::should_implement_trait)]
    pub fn next(&mut self) -> Result<Option<Item<'_>>> {
        loop {
            let record = match self.pending.next() {
                Some(r) => r,
                None => {
                    if self.done {
                        return Ok(None);
                    }
                    let Some(record) = self.outer()? else {
                        return Ok(None);
                    };
                    record
                }
            };
            if let Some(current) = self.take(record) {
                let current = self.current.insert(current);
                return Ok(Some(current.item(&self.recording)));
            }
        }
    }

    /// The next record outside the chunks, or (a chunk read whole) the
    /// first of its records; `None` once the data ends.
    fn outer(&mut self) -> Result<Option<Record<'static>>> {
        loop {
            let record = match self.raw()? {
                Some(Ok(Raw::Record(r))) => r,
                Some(Ok(Raw::Chunk(Ok(records)))) => {
                    self.recording.chunks += 1;
                    self.pending = records.into_iter();
                    match self.pending.next() {
                        Some(first) => return Ok(Some(first)),
                        None => continue,
                    }
                }
                Some(Ok(Raw::Chunk(Err(e)))) => {
                    self.stop(Some(Cut::DamagedChunk {
                        chunk: self.recording.chunks + 1,
                        error: chunk_damage_in_words(&e),
                    }));
                    return Ok(None);
                }
                Some(Ok(Raw::SkippedChunk)) => {
                    self.recording.chunks += 1;
                    continue;
                }
                Some(Err(e)) => {
                    self.stop(Some(Cut::EndsEarly {
                        chunks: self.recording.chunks,
                        error: in_words(&e),
                    }));
                    return Ok(None);
                }
                None => {
                    self.stop(Some(Cut::NoSummary));
                    return Ok(None);
                }
            };
            match record {
                Record::DataEnd(_) => {
                    // The twin's writer ends the file after every chunk with
                    // a data end and a footer naming no summary, which the
                    // summary replaces at the close: a file that still ends
                    // so was cut before it.
                    let cut = match self.raw()? {
                        Some(Ok(Raw::Record(Record::Footer(f)))) if f.summary_start == 0 => {
                            Some(Cut::NoSummary)
                        }
                        _ => None,
                    };
                    self.stop(cut);
                    return Ok(None);
                }
                other => return Ok(Some(other)),
            }
        }
    }

    fn stop(&mut self, cut: Option<Cut>) {
        self.done = true;
        self.pending = Vec::new().into_iter();
        self.recording.truncated = cut;
    }

    /// The next record of the file, a chunk decoded whole (or skipped),
    /// reading the source as the MCAP reader asks.
    fn raw(&mut self) -> Result<Option<mcap::McapResult<Raw>>> {
        while let Some(event) = self.linear.next_event() {
            match event {
                Ok(LinearReadEvent::ReadRequest(need)) => {
                    let buf = self.linear.insert(need);
                    let n = loop {
                        match self.source.read(buf) {
                            Ok(n) => break n,
                            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                            Err(source) => {
                                return Err(ReadError::Io {
                                    path: self.recording.path.clone(),
                                    source,
                                });
                            }
                        }
                    };
                    self.linear.notify_read(n);
                }
                Ok(LinearReadEvent::Record { opcode, data }) => {
                    let raw = match mcap::parse_record(opcode, data) {
                        Ok(Record::Chunk { .. }) if !self.chunks_too => Ok(Raw::SkippedChunk),
                        Ok(Record::Chunk { header, .. }) => {
                            Ok(Raw::Chunk(chunk_records(data, header.uncompressed_size)))
                        }
                        Ok(record) => Ok(Raw::Record(record.into_owned())),
                        Err(e) => Err(e),
                    };
                    return Ok(Some(raw));
                }
                Err(e) => return Ok(Some(Err(e))),
            }
        }
        Ok(None)
    }

    /// Note what `record` says; the item it is, if it is one.
    fn take(&mut self, record: Record<'static>) -> Option<Current> {
        Some(match record {
            Record::Channel(c) => {
                if self.by_id.contains_key(&c.id) {
                    return None;
                }
                let index = self.recording.channels.len();
                self.by_id.insert(c.id, index);
                let encoding = Encoding::of(&c.message_encoding, self.schemas.get(&c.schema_id));
                self.recording.channels.push(Channel {
                    topic: c.topic,
                    message_count: 0,
                    encoding,
                });
                Current::Channel(index)
            }
            Record::Schema { header, data } => {
                self.schemas
                    .entry(header.id)
                    .or_insert_with(|| (header.name, header.encoding, data.into_owned()));
                return None;
            }
            Record::Message { header, data } => {
                let channel = self.by_id.get(&header.channel_id).copied();
                if let Some(i) = channel {
                    self.recording.channels[i].message_count += 1;
                    self.recording.end_ns = self.recording.end_ns.max(header.log_time);
                }
                Current::Message {
                    channel,
                    channel_id: header.channel_id,
                    sequence: header.sequence,
                    log_time_ns: header.log_time,
                    data: data.into_owned(),
                }
            }
            Record::Metadata(m) => {
                self.recording
                    .metadata
                    .insert(m.name.clone(), m.metadata.clone());
                Current::Metadata {
                    name: m.name,
                    fields: m.metadata,
                }
            }
            _ => return None,
        })
    }
}

/// A record of the file as [`Reader::raw`] reads it.
enum Raw {
    Record(Record<'static>),
    /// A chunk's records, every one or (damaged) none.
    Chunk(mcap::McapResult<Vec<Record<'static>>>),
    /// A chunk not opened (a pass for the metadata).
    SkippedChunk,
}

/// The record handed out last, which its item borrows from.
#[derive(Debug)]
enum Current {
    Channel(usize),
    Message {
        /// Index in `Recording::channels`; `None` if never declared.
        channel: Option<usize>,
        channel_id: u16,
        sequence: u32,
        log_time_ns: u64,
        data: Vec<u8>,
    },
    Metadata {
        name: String,
        fields: BTreeMap<String, String>,
    },
}

impl Current {
    fn item<'a>(&'a self, recording: &'a Recording) -> Item<'a> {
        let topic = |i: usize| recording.channels.get(i).map_or("", |c| c.topic.as_str());
        match self {
            Current::Channel(index) => Item::Channel {
                index: *index,
                topic: topic(*index),
            },
            Current::Message {
                channel: Some(channel),
                sequence,
                log_time_ns,
                data,
                ..
            } => Item::Message(Message {
                channel: *channel,
                topic: topic(*channel),
                sequence: *sequence,
                log_time_ns: *log_time_ns,
                data,
                encoding: recording
                    .channels
                    .get(*channel)
                    .map_or(&JSON, |c| &c.encoding),
            }),
            Current::Message {
                channel: None,
                channel_id,
                sequence,
                ..
            } => Item::Stray {
                channel_id: *channel_id,
                sequence: *sequence,
            },
            Current::Metadata { name, fields } => Item::Metadata { name, fields },
        }
    }
}

impl<'a> Item<'a> {
    /// The message this item is, if it is one; an error for a message on
    /// a channel never declared.
    pub fn message(self) -> Result<Option<Message<'a>>> {
        match self {
            Item::Message(m) => Ok(Some(m)),
            Item::Stray {
                channel_id,
                sequence,
            } => Err(ReadError::Stray {
                sequence,
                channel_id,
            }),
            _ => Ok(None),
        }
    }
}

impl Recording {
    /// Read `path` through, keeping no message: its metadata, channels and
    /// extent. A file that is not MCAP, or holds a message that is not
    /// JSON, is an error; one cut short is not.
    pub fn read(path: &Path) -> Result<Self> {
        Self::scan(path, |m| m.check_json())
    }

    /// Read `path` through, handing every message to `visit`. A message on
    /// a channel never declared is an error (see [`Reader`] to take it), as
    /// is any `visit` returns: both say the file is not a readable recording.
    pub fn scan(path: &Path, mut visit: impl FnMut(&Message<'_>) -> Result<()>) -> Result<Self> {
        let mut reader = Reader::open(path)?;
        let read: Result<()> = (|| {
            while let Some(item) = reader.next()? {
                if let Some(m) = item.message()? {
                    visit(&m)?;
                }
            }
            Ok(())
        })();
        read.map_err(|e| ReadError::Unreadable {
            path: path.to_path_buf(),
            source: Box::new(e),
        })?;
        Ok(reader.finish())
    }

    /// The channel on `topic`.
    pub fn channel(&self, topic: &str) -> Option<&Channel> {
        self.channels.iter().find(|c| c.topic == topic)
    }

    /// A field of the run's identity (`twin.run` metadata).
    pub fn run_field(&self, key: &str) -> Option<&str> {
        self.metadata
            .get(topics::RUN_METADATA)
            .and_then(|m| m.get(key))
            .map(String::as_str)
    }

    /// Where and why the run stopped, if this file is `twin recover`'s copy
    /// of a run cut short (complete as a file, but not as a run).
    pub fn recovered_from_cut(&self) -> Option<&str> {
        self.metadata
            .get(topics::RECOVERED_METADATA)
            .and_then(|m| m.get("stopped"))
            .map(String::as_str)
    }

    /// Whether the run ends before it would have: the file is cut short,
    /// or was recovered from one that was. Only what it holds is compared.
    pub fn ends_early(&self) -> bool {
        self.truncated.is_some() || self.recovered_from_cut().is_some()
    }

    /// Why a recording holds no message, for an error that says so: `PATH
    /// holds no messages…`, with where a file cut short stops.
    pub fn holds_no_messages(&self) -> String {
        let path = self.path.display();
        match &self.truncated {
            None => format!("{path} holds no messages"),
            Some(Cut::NoSummary) | Some(Cut::EndsEarly { chunks: 0, .. }) => {
                let why = self.truncated.as_ref().and_then(Cut::error);
                format!(
                    "{path} holds no messages: the file ends before its first complete chunk{}",
                    why.map_or_else(String::new, |e| format!(" ({e})"))
                )
            }
            Some(cut) => format!("{path} holds no messages: {cut}"),
        }
    }

    /// Messages in all channels.
    pub fn message_count(&self) -> u64 {
        self.channels.iter().map(|c| c.message_count).sum()
    }

    /// The latest log time of any message (s).
    pub fn end_s(&self) -> f64 {
        self.end_ns as f64 * 1e-9
    }

    /// Every frame on every bus, in file order (read again from the file).
    pub fn frames(&self) -> Result<Vec<BusFrame>> {
        let mut frames = Vec::new();
        Self::scan(&self.path, |m| {
            let Topic::BusFrames(bus) = Topic::parse(m.topic) else {
                return Ok(());
            };
            let v: serde_json::Value = m.json()?;
            let s = |k: &str| v[k].as_str().unwrap_or("").to_string();
            frames.push(BusFrame {
                time_s: m.time_s(),
                bus: bus.to_string(),
                from: s("from"),
                end_s: v["end_s"].as_f64().unwrap_or(f64::NAN),
                bytes: unhex(v["hex"].as_str().unwrap_or("")),
            });
            Ok(())
        })?;
        Ok(frames)
    }

    /// Every event, in file order (read again from the file).
    pub fn events(&self) -> Result<Vec<Event>> {
        let mut events = Vec::new();
        Self::scan(&self.path, |m| {
            if Topic::parse(m.topic) != Topic::Events {
                return Ok(());
            }
            let v: serde_json::Value = m.json()?;
            let s = |k: &str| v[k].as_str().unwrap_or("").to_string();
            events.push(Event {
                time_s: m.time_s(),
                node: s("node"),
                kind: s("kind"),
                detail: s("detail"),
            });
            Ok(())
        })?;
        Ok(events)
    }
}

/// A message read with the MCAP library's own reader (`mcap::MessageStream`),
/// as a JSON value: JSON as it is, protobuf by its channel's schema.
pub fn value_of(channel: &mcap::Channel<'_>, data: &[u8]) -> Result<serde_json::Value> {
    let schema = channel
        .schema
        .as_ref()
        .map(|s| (s.name.clone(), s.encoding.clone(), s.data.to_vec()));
    let encoding = Encoding::of(&channel.message_encoding, schema.as_ref());
    Message {
        channel: 0,
        topic: &channel.topic,
        sequence: 0,
        log_time_ns: 0,
        data,
        encoding: &encoding,
    }
    .value()
}

/// A frame as it went on a bus.
#[derive(Debug, Clone, PartialEq)]
pub struct BusFrame {
    /// When its first byte started (s).
    pub time_s: f64,
    pub end_s: f64,
    pub bus: String,
    pub from: String,
    pub bytes: Vec<u8>,
}

/// A node's event (timeout, bad check, log line, …).
#[derive(Debug, Clone, PartialEq)]
pub struct Event {
    pub time_s: f64,
    pub node: String,
    pub kind: String,
    pub detail: String,
}

/// The bytes a frame's `hex` field spells (none if it is not hex).
fn unhex(digits: &str) -> Vec<u8> {
    hex::decode(digits).unwrap_or_default()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::record::Recorder;
    use serde_json::json;

    pub(crate) fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("twin-recording-read-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    /// Three simulated seconds: sensors at 100 Hz, an event each second.
    pub(crate) fn write(path: &Path) {
        let mut rec = Recorder::create(path).unwrap();
        let run = BTreeMap::from([("kind".to_string(), "scenario".to_string())]);
        rec.write_metadata(topics::RUN_METADATA, run).unwrap();
        let sensors = topics::plant_sensors("ev1");
        rec.add_channel(&sensors, &json!({"wheel_rpm": 0.0, "on": false}))
            .unwrap();
        rec.add_channel(
            topics::EVENTS,
            &json!({"node": "", "kind": "", "detail": ""}),
        )
        .unwrap();
        for i in 0..300 {
            let t = f64::from(i) * 0.01;
            rec.write(
                &sensors,
                t,
                &json!({"wheel_rpm": t * 100.0, "on": i % 2 == 0}),
            )
            .unwrap();
            if i % 100 == 50 {
                let e = json!({"node": "master", "kind": "log", "detail": format!("at {t}")});
                rec.write(topics::EVENTS, t, &e).unwrap();
            }
        }
        rec.finish().unwrap();
    }

    #[test]
    fn a_pass_counts_channels_and_messages_and_keeps_the_metadata() {
        let path = scratch("whole.mcap");
        write(&path);
        let r = Recording::read(&path).unwrap();
        assert_eq!(r.truncated, None);
        assert_eq!(r.run_field("kind"), Some("scenario"));
        let topics: Vec<(&str, u64)> = r
            .channels
            .iter()
            .map(|c| (c.topic.as_str(), c.message_count))
            .collect();
        assert_eq!(topics, [("/plant/ev1/sensors", 300), ("/events", 3)]);
        assert_eq!(r.message_count(), 303);
        assert!((r.end_s() - 2.99).abs() < 1e-9);
        // One chunk per simulated second.
        assert_eq!(r.chunks, 3);
        let events = r.events().unwrap();
        assert_eq!(events.len(), 3);
        assert_eq!(
            (events[1].node.as_str(), events[1].detail.as_str()),
            ("master", "at 1.5")
        );

        let signals = crate::Signals::read(&path).unwrap();
        let wheel = &signals.by_name["/plant/ev1/sensors.wheel_rpm"];
        assert_eq!(wheel.len(), 300);
        assert!(!wheel.hold);
        assert_eq!(
            signals.by_name["/plant/ev1/sensors.on"].values[..3],
            [1.0, 0.0, 1.0]
        );
        assert!(!signals.by_name.contains_key("/events.detail"));
        assert_eq!(signals.recording, r);
    }

    #[test]
    fn a_file_cut_short_is_read_up_to_its_last_complete_chunk() {
        let path = scratch("full.mcap");
        write(&path);
        let bytes = std::fs::read(&path).unwrap();
        let cut = scratch("cut.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let r = Recording::read(&cut).unwrap();
        let Some(Cut::EndsEarly { chunks, .. }) = &r.truncated else {
            panic!("{:?}", r.truncated);
        };
        assert_eq!(*chunks, r.chunks);
        assert!(r.chunks > 0 && r.chunks < 3, "{}", r.chunks);
        // Whole chunks only: whole simulated seconds of sensors.
        let sensors = r.channel("/plant/ev1/sensors").unwrap().message_count;
        assert_eq!(sensors, 100 * r.chunks);
        assert!(
            r.truncated
                .as_ref()
                .unwrap()
                .to_string()
                .contains("ends early")
        );

        let e = Recording::read(&scratch("missing.mcap")).unwrap_err();
        assert!(matches!(e, ReadError::Io { .. }), "{e:?}");
        assert!(e.to_string().contains("cannot read"), "{e}");
        let junk = scratch("junk.mcap");
        std::fs::write(&junk, b"not a recording").unwrap();
        let e = Recording::read(&junk).unwrap_err();
        assert!(matches!(e, ReadError::NotMcap { .. }), "{e:?}");
        assert_eq!(
            e.to_string(),
            format!(
                "{} is not a readable recording: it does not start with the MCAP magic bytes",
                junk.display()
            )
        );
    }

    #[test]
    fn a_message_that_does_not_read_says_which_and_why() {
        let message = |data: &'static [u8], encoding: &'static Encoding| Message {
            channel: 0,
            topic: "/events",
            sequence: 3,
            log_time_ns: 0,
            data,
            encoding,
        };
        let e = message(b"{", &Encoding::Json).value().unwrap_err();
        assert!(matches!(e, ReadError::NotJson { sequence: 3, .. }), "{e:?}");
        assert_eq!(e.to_string(), "message 3 on /events is not JSON");
        static CBOR: std::sync::LazyLock<Encoding> =
            std::sync::LazyLock::new(|| Encoding::Other("cbor".into()));
        let e = message(b"", &CBOR).value().unwrap_err();
        assert_eq!(
            e.to_string(),
            "the messages on /events are `cbor`, which the twin does not read \
             (it reads json and protobuf)"
        );
    }

    #[test]
    fn a_damaged_chunk_is_dropped_whole_and_reading_stops_there() {
        let path = scratch("to-damage.mcap");
        write(&path);
        let damaged = scratch("damaged.mcap");
        std::fs::write(&damaged, damage_chunk(&path, 2)).unwrap();
        let r = Recording::read(&damaged).unwrap();
        assert!(
            matches!(r.truncated, Some(Cut::DamagedChunk { chunk: 2, .. })),
            "{:?}",
            r.truncated
        );
        assert_eq!(r.chunks, 1);
        assert_eq!(r.channel("/plant/ev1/sensors").unwrap().message_count, 100);
        assert!(
            r.truncated
                .unwrap()
                .to_string()
                .starts_with("chunk 2 is damaged")
        );
    }

    /// The recording at `path` with garbage in the middle of chunk `n`'s
    /// compressed records: walk the records (opcode, length, body) to it.
    pub(crate) fn damage_chunk(path: &Path, n: usize) -> Vec<u8> {
        let mut bytes = std::fs::read(path).unwrap();
        let (mut at, mut chunks) = (8, 0);
        loop {
            let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
            if bytes[at] == mcap::records::op::CHUNK {
                chunks += 1;
                if chunks == n {
                    let mid = at + 9 + len / 2;
                    for b in &mut bytes[mid..mid + 64] {
                        *b ^= 0x5a;
                    }
                    return bytes;
                }
            }
            at += 9 + len;
        }
    }

    #[test]
    fn the_metadata_pass_skips_the_chunks() {
        let path = scratch("meta.mcap");
        write(&path);
        let mut reader = Reader::open(&path).unwrap().metadata_only();
        let mut names = Vec::new();
        while let Some(item) = reader.next().unwrap() {
            match item {
                Item::Metadata { name, .. } => names.push(name.to_string()),
                Item::Message(_) | Item::Channel { .. } => panic!("{item:?}"),
                Item::Stray { .. } => {}
            }
        }
        assert_eq!(names, [topics::RUN_METADATA]);
        let r = reader.finish();
        assert_eq!(r.chunks, 3);
        assert_eq!(r.truncated, None);
    }
}
