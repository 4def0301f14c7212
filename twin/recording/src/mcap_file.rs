//! The MCAP file a recording writes, record by record (the format is
//! <https://mcap.dev/spec>): each chunk is built uncompressed in one buffer,
//! a message's record in a handful of appends, and compressed (zstd) and
//! checksummed whole when it closes. The MCAP library's writer sent every
//! field of every message through its checksum and a zstd stream, seven
//! small writes a message, which cost the recording more than the
//! compression did. What is written is what that writer wrote: the same
//! records in the same places (schemas and channels in the chunks and
//! repeated in the summary, message indexes after each chunk, statistics,
//! chunk and metadata indexes, summary offsets, both checksums), so every
//! MCAP reader reads it; only the zstd frames differ (one per chunk, with its
//! size in its header).
//!
//! Measured against the library's writer (mcap 0.26, zstd level 1, no zstd
//! workers: its faster setting here), release builds pinned to one core,
//! `twin bench --repeat 5 --seconds 100`, the recorded runs alone: the
//! library's took 1.19x as long on ev-meb (0.172 to 0.189 s against 0.147
//! and 0.156 s) and 1.12x on ten-modules (1.26 to 1.48 s against 1.21 and
//! 1.24 s). Over the 10 % that keeps a writer of our own, so this is the
//! workspace's one MCAP writer: recordings and `twin recover`'s copies (which
//! keep a file's own schema and channel ids: [`McapFile::add_schema_with_id`],
//! [`McapFile::add_channel_with_id`]). The library's writer stays only in
//! this module's test, as the reference this one is held to.

use mcap::records::op;
use std::collections::BTreeMap;
use std::io::{self, Seek, SeekFrom, Write};

/// zstd at `level`, its match finder set for the twin's chunks: a 4 kB-entry
/// hash table (12 bits, in the core's first-level cache) and matches from
/// 5 bytes. A plant sample's doubles differ from the last sample's in their
/// low bytes, so most 4-byte matches are the high half of one, short and
/// costly to encode. Against plain level 1:
///
/// - a virtual run's chunks (a simulated second each, about 100 kB to 1 MB,
///   mostly plant samples): 1.3 times as fast and 3.1 % (ev-meb) and 1.9 %
///   (ten-modules) smaller with matches from 4 bytes; from 5, about 1.15
///   times as fast again on ev-meb's (1.02 to 1.07 on ten-modules'), for
///   3.1 % and 2.4 % more bytes;
/// - a real-time session's chunks (1 MB of a busy link's frames): 1.18
///   times as fast and 6.5 % larger. The sink compresses beside the
///   connections it records, so its time per frame is what a recorded
///   session at eight clients loses, where a file 4 % larger (the message
///   indexes are not compressed) costs a user nothing they wait for.
fn compressor(level: i32) -> io::Result<zstd::bulk::Compressor<'static>> {
    use zstd::zstd_safe::{CParameter, Strategy};
    let mut compressor = zstd::bulk::Compressor::new(level)?;
    for parameter in [
        CParameter::Strategy(Strategy::ZSTD_fast),
        CParameter::HashLog(12),
        CParameter::MinMatch(5),
        CParameter::TargetLength(1),
    ] {
        compressor.set_parameter(parameter)?;
    }
    Ok(compressor)
}

/// A message record's bytes before its data: opcode, length, channel,
/// sequence, log time, publish time.
const MESSAGE_HEAD: usize = 1 + 8 + 2 + 4 + 8 + 8;

/// The chunks' compression, as the chunk records name it.
const COMPRESSION: &str = "zstd";

/// An MCAP file being written to `W`.
pub(crate) struct McapFile<W: Write + Seek> {
    out: Out<W>,
    /// Closes a chunk once it holds more than this many uncompressed bytes.
    chunk_size: usize,
    /// The open chunk's records, uncompressed.
    chunk: Vec<u8>,
    /// The open chunk's first and last message times.
    chunk_bounds: Option<(u64, u64)>,
    /// Per channel id (`None` where no channel has it): the open chunk's
    /// messages (log time, offset in the chunk). A message's channel is
    /// checked and indexed in one lookup.
    indexes: Vec<Option<Vec<(u64, u64)>>>,
    compressor: zstd::bulk::Compressor<'static>,
    /// A record's body, built before its length is known.
    scratch: Vec<u8>,
    /// Schema records by id, for the summary and their deduplication.
    schemas: BTreeMap<u16, Schema>,
    /// Channel records' bodies by id, for the summary.
    channels: BTreeMap<u16, Vec<u8>>,
    /// The chunk index records, whole and back to back, for the summary:
    /// one allocation for a session of any length (a 10-minute session at
    /// eight clients closes about 16 000 chunks), none per chunk.
    chunk_index_records: Vec<u8>,
    /// The open chunk's message index offsets, per channel (reused).
    index_offsets: Vec<(u16, u64)>,
    /// Metadata index records' bodies, for the summary.
    metadata_indexes: Vec<Vec<u8>>,
    /// Attachment index records' bodies, for the summary.
    attachment_indexes: Vec<Vec<u8>>,
    stats: Statistics,
}

#[derive(PartialEq)]
struct Schema {
    name: String,
    encoding: String,
    data: Vec<u8>,
}

#[derive(Default)]
struct Statistics {
    messages: u64,
    metadata: u32,
    attachments: u32,
    chunks: u32,
    bounds: Option<(u64, u64)>,
    /// Per channel id: how many messages (a lookup per message, so a list).
    per_channel: Vec<u64>,
}

/// The output: the records not yet in the file, where they go, and the
/// checksum of what went out since the checksum was last taken.
///
/// Records are gathered in `pending` and land in the file together, each
/// time followed by a provisional end: a data end record and a footer saying
/// there is no summary (`summary_start` 0) and the closing magic. So the
/// file always ends as an MCAP file does, and a run killed (kill -9, a
/// crash) leaves one that every reader reads up to its last whole chunk: a
/// reader looking for the summary finds none and reads the file through, as
/// Python's `mcap` `make_reader` does. The next records overwrite that end,
/// and at the close the summary does.
struct Out<W> {
    inner: W,
    /// Where the records in `pending` go: the end of the records in the file,
    /// where its provisional end starts.
    landed: u64,
    /// Bytes of the provisional end after `landed` (0 before the first).
    end_len: usize,
    pending: Vec<u8>,
    /// How much of `pending` the checksum has taken in.
    summed: usize,
    crc: crc32fast::Hasher,
}

/// The provisional end: a data end record (opcode, length, checksum), a
/// footer (opcode, length, summary start, summary offsets start, checksum)
/// and the closing magic.
const PROVISIONAL_END: usize = 13 + 29 + 8;

/// The final end: footer and closing magic.
const FINAL_END: usize = 29 + 8;

/// A footer naming no summary (summary start, summary offsets start and
/// summary checksum 0), and the closing magic.
const NO_SUMMARY: [u8; FINAL_END] = {
    let mut end = [0u8; FINAL_END];
    end[0] = op::FOOTER;
    end[1] = 20;
    let mut i = 0;
    while i < 8 {
        end[29 + i] = mcap::MAGIC[i];
        i += 1;
    }
    end
};

impl<W: Write + Seek> Out<W> {
    fn position(&self) -> u64 {
        self.landed + self.pending.len() as u64
    }

    fn put(&mut self, bytes: &[u8]) {
        self.pending.extend_from_slice(bytes);
    }

    /// A record: opcode, length, body.
    fn record(&mut self, opcode: u8, body: &[u8]) {
        let mut head = [0u8; 9];
        head[0] = opcode;
        head[1..].copy_from_slice(&(body.len() as u64).to_le_bytes());
        self.put(&head);
        self.put(body);
    }

    fn sum(&mut self) {
        self.crc.update(&self.pending[self.summed..]);
        self.summed = self.pending.len();
    }

    /// The checksum so far, starting a new one.
    fn take_crc(&mut self) -> u32 {
        self.sum();
        std::mem::take(&mut self.crc).finalize()
    }

    /// The pending records into the file, ended by a provisional end.
    fn land(&mut self) -> io::Result<()> {
        // Records shorter than the end they would overwrite (an empty
        // metadata record) wait for the next: the end could not be kept
        // readable while they land.
        if self.pending.len() < self.end_len || self.pending.is_empty() {
            return Ok(());
        }
        self.sum();
        // The data section's checksum so far, so that a reader checking it
        // finds it right.
        let mut end = [0u8; PROVISIONAL_END];
        end[0] = op::DATA_END;
        end[1..9].copy_from_slice(&4u64.to_le_bytes());
        end[9..13].copy_from_slice(&self.crc.clone().finalize().to_le_bytes());
        end[13..].copy_from_slice(&NO_SUMMARY);
        let records = std::mem::take(&mut self.pending);
        let landed = self.write(&records, &end);
        self.pending = records;
        landed?;
        self.landed += self.pending.len() as u64;
        self.end_len = PROVISIONAL_END;
        self.pending.clear();
        self.summed = 0;
        Ok(())
    }

    /// The pending records, which end with the footer and the closing magic,
    /// into the file: it is complete. Returns the output.
    fn land_last(mut self) -> io::Result<W> {
        self.sum();
        let pending = std::mem::take(&mut self.pending);
        let (records, end) = pending.split_at(pending.len() - FINAL_END);
        // The file is never longer than this: the summary (its statistics
        // record alone) is longer than the provisional end it replaces.
        // A footer naming the summary goes in once the summary is whole:
        // until then, one naming none.
        self.write(records, &NO_SUMMARY)?;
        self.inner
            .seek(SeekFrom::Start(self.landed + records.len() as u64))?;
        self.inner.write_all(end)?;
        self.inner.flush()?;
        Ok(self.inner)
    }

    /// `records` then `end` written at `landed`, over the provisional end,
    /// in an order that keeps the file readable wherever a kill stops it:
    /// `end` first, past the old end; then the records after the old end's
    /// bytes; then, last, the records' first bytes over the old end. Until
    /// that last write, a reader reading through stops at the old end's
    /// footer, and one looking at the file's last bytes finds a footer
    /// there. A kill cuts a write short only between two pages, so the
    /// long middle write may stop anywhere (behind the old end, which still
    /// reads); the two short ones at worst at one page boundary.
    fn write(&mut self, records: &[u8], end: &[u8]) -> io::Result<()> {
        // Never more than the records: `land` keeps shorter ones back, and
        // the summary is longer than the provisional end.
        let old = self.end_len.min(records.len());
        let at = self.landed;
        self.inner
            .seek(SeekFrom::Start(at + records.len() as u64))?;
        self.inner.write_all(end)?;
        self.inner.seek(SeekFrom::Start(at + old as u64))?;
        self.inner.write_all(&records[old..])?;
        self.inner.seek(SeekFrom::Start(at))?;
        self.inner.write_all(&records[..old])?;
        self.inner.flush()
    }
}

/// Little-endian fields appended to a record's body, as MCAP lays them out.
trait Fields {
    fn u16(&mut self, v: u16);
    fn u32(&mut self, v: u32);
    fn u64(&mut self, v: u64);
    fn str(&mut self, s: &str);
    fn map(&mut self, map: &BTreeMap<String, String>);
}

impl Fields for Vec<u8> {
    fn u16(&mut self, v: u16) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn u32(&mut self, v: u32) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn str(&mut self, s: &str) {
        self.u32(len32(s.len()));
        self.extend_from_slice(s.as_bytes());
    }
    fn map(&mut self, map: &BTreeMap<String, String>) {
        let bytes: usize = map.iter().map(|(k, v)| 8 + k.len() + v.len()).sum();
        self.u32(len32(bytes));
        for (k, v) in map {
            self.str(k);
            self.str(v);
        }
    }
}

/// A length as MCAP's 32-bit fields hold it (the twin's strings, schemas and
/// maps are far below 4 GiB).
fn len32(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

fn too_many(what: &str) -> io::Error {
    io::Error::other(format!("too many {what} for one MCAP file"))
}

/// A declaration a copied file got wrong (its ids are kept): the input's
/// fault, not the writing's, told apart by its kind ([`io::ErrorKind::InvalidData`]).
fn declaration_fault(why: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, why)
}

impl<W: Write + Seek> McapFile<W> {
    /// Start the file: magic and header (and a provisional end, so that a
    /// run killed before its first chunk leaves an MCAP file of no message).
    /// The twin's recordings have no `profile` (""); a recovered file keeps
    /// its original's.
    pub(crate) fn new(
        inner: W,
        profile: &str,
        library: &str,
        level: i32,
        chunk_size: usize,
    ) -> io::Result<Self> {
        let mut file = Self {
            out: Out {
                inner,
                landed: 0,
                end_len: 0,
                pending: Vec::with_capacity(chunk_size + 64 * 1024),
                summed: 0,
                crc: crc32fast::Hasher::new(),
            },
            chunk_size,
            chunk: Vec::with_capacity(chunk_size + 64 * 1024),
            chunk_bounds: None,
            indexes: Vec::new(),
            compressor: compressor(level)?,
            scratch: Vec::new(),
            schemas: BTreeMap::new(),
            channels: BTreeMap::new(),
            chunk_index_records: Vec::new(),
            index_offsets: Vec::new(),
            metadata_indexes: Vec::new(),
            attachment_indexes: Vec::new(),
            stats: Statistics::default(),
        };
        file.out.put(mcap::MAGIC);
        let mut header = Vec::new();
        header.str(profile);
        header.str(library);
        file.out.record(op::HEADER, &header);
        file.out.land()?;
        Ok(file)
    }

    /// The id of a schema, written into the open chunk the first time it is
    /// seen (ids from 1: 0 means "no schema").
    pub(crate) fn add_schema(
        &mut self,
        name: &str,
        encoding: &str,
        data: &[u8],
    ) -> io::Result<u16> {
        let same = |s: &Schema| s.name == name && s.encoding == encoding && s.data == data;
        if let Some((&id, _)) = self.schemas.iter().find(|(_, s)| same(s)) {
            return Ok(id);
        }
        let id = first_free(&self.schemas).ok_or_else(|| too_many("schemas"))?;
        self.declare_schema(id, name, encoding, data);
        Ok(id)
    }

    /// A schema with the id `id` (a copied file's own), written into the
    /// open chunk the first time; again with the same contents, nothing.
    pub(crate) fn add_schema_with_id(
        &mut self,
        id: u16,
        name: &str,
        encoding: &str,
        data: &[u8],
    ) -> io::Result<()> {
        if id == 0 {
            return Err(declaration_fault(format!(
                "schema `{name}` has the id 0, which MCAP reserves for \"no schema\""
            )));
        }
        match self.schemas.get(&id) {
            Some(s) if s.name == name && s.encoding == encoding && s.data == data => Ok(()),
            Some(s) => Err(declaration_fault(format!(
                "schema {id} is declared twice, differently (`{}`, then `{name}`)",
                s.name
            ))),
            None => {
                self.declare_schema(id, name, encoding, data);
                Ok(())
            }
        }
    }

    fn declare_schema(&mut self, id: u16, name: &str, encoding: &str, data: &[u8]) {
        let body = schema_body(id, name, encoding, data);
        chunk_record(&mut self.chunk, op::SCHEMA, &body);
        self.schemas.insert(
            id,
            Schema {
                name: name.into(),
                encoding: encoding.into(),
                data: data.into(),
            },
        );
    }

    /// A new channel (ids from 1, as the MCAP library gave them), written
    /// into the open chunk.
    pub(crate) fn add_channel(
        &mut self,
        schema_id: u16,
        topic: &str,
        message_encoding: &str,
    ) -> io::Result<u16> {
        let id = first_free(&self.channels).ok_or_else(|| too_many("channels"))?;
        let body = channel_body(id, schema_id, topic, message_encoding, &BTreeMap::new());
        self.declare_channel(id, schema_id, topic, body)?;
        Ok(id)
    }

    /// A channel with the id `id` (a copied file's own; 0 is a channel id
    /// too) and its metadata, written into the open chunk the first time;
    /// again with the same contents, nothing.
    pub(crate) fn add_channel_with_id(
        &mut self,
        id: u16,
        schema_id: u16,
        topic: &str,
        message_encoding: &str,
        metadata: &BTreeMap<String, String>,
    ) -> io::Result<()> {
        let body = channel_body(id, schema_id, topic, message_encoding, metadata);
        match self.channels.get(&id) {
            Some(known) if *known == body => Ok(()),
            Some(_) => Err(declaration_fault(format!(
                "channel {id} is declared twice, differently (the second time as `{topic}`)"
            ))),
            None => self.declare_channel(id, schema_id, topic, body),
        }
    }

    fn declare_channel(
        &mut self,
        id: u16,
        schema_id: u16,
        topic: &str,
        body: Vec<u8>,
    ) -> io::Result<()> {
        if schema_id != 0 && !self.schemas.contains_key(&schema_id) {
            return Err(declaration_fault(format!(
                "channel `{topic}` uses schema {schema_id}, which the file never declared"
            )));
        }
        chunk_record(&mut self.chunk, op::CHANNEL, &body);
        self.channels.insert(id, body);
        let slot = usize::from(id);
        if self.indexes.len() <= slot {
            self.indexes.resize_with(slot + 1, || None);
        }
        self.indexes[slot] = Some(Vec::new());
        Ok(())
    }

    /// One message on `channel` (an id [`McapFile::add_channel`] gave).
    pub(crate) fn write_message(
        &mut self,
        channel: u16,
        sequence: u32,
        log_time: u64,
        publish_time: u64,
        data: &[u8],
    ) -> io::Result<()> {
        self.write_message_with(channel, sequence, log_time, publish_time, |chunk| {
            chunk.extend_from_slice(data);
            Ok(())
        })
    }

    /// [`McapFile::write_message`] with the message's bytes appended by
    /// `data` straight into the chunk (no copy of them on the way); if it
    /// fails, nothing of the message stays.
    pub(crate) fn write_message_with(
        &mut self,
        channel: u16,
        sequence: u32,
        log_time: u64,
        publish_time: u64,
        data: impl FnOnce(&mut Vec<u8>) -> io::Result<()>,
    ) -> io::Result<()> {
        if !matches!(self.indexes.get(usize::from(channel)), Some(Some(_))) {
            return Err(io::Error::other(format!(
                "a message on channel {channel}, which the file never declared"
            )));
        }
        // As the MCAP library did: a chunk over its size closes before the
        // next message.
        if self.chunk.len() > self.chunk_size {
            self.close_chunk()?;
        }
        let offset = self.chunk.len();
        // The record's head in one copy of a known size (a store, not a
        // call to `memmove` per field), its length put in once the data is.
        let mut head = [0u8; MESSAGE_HEAD];
        head[0] = op::MESSAGE;
        head[9..11].copy_from_slice(&channel.to_le_bytes());
        head[11..15].copy_from_slice(&sequence.to_le_bytes());
        head[15..23].copy_from_slice(&log_time.to_le_bytes());
        head[23..31].copy_from_slice(&publish_time.to_le_bytes());
        self.chunk.extend_from_slice(&head);
        if let Err(e) = data(&mut self.chunk) {
            self.chunk.truncate(offset);
            return Err(e);
        }
        let length = (self.chunk.len() - offset - 9) as u64;
        self.chunk[offset + 1..offset + 9].copy_from_slice(&length.to_le_bytes());
        if let Some(Some(index)) = self.indexes.get_mut(usize::from(channel)) {
            index.push((log_time, offset as u64));
        }
        self.chunk_bounds = Some(match self.chunk_bounds {
            None => (log_time, log_time),
            Some((start, end)) => (start.min(log_time), end.max(log_time)),
        });
        let stats = &mut self.stats;
        stats.messages += 1;
        stats.bounds = Some(match stats.bounds {
            None => (log_time, log_time),
            Some((start, end)) => (start.min(log_time), end.max(log_time)),
        });
        let index = usize::from(channel);
        if stats.per_channel.len() <= index {
            stats.per_channel.resize(index + 1, 0);
        }
        stats.per_channel[index] += 1;
        Ok(())
    }

    /// A metadata record, after the open chunk (which it closes).
    pub(crate) fn write_metadata(
        &mut self,
        name: &str,
        metadata: &BTreeMap<String, String>,
    ) -> io::Result<()> {
        self.close_chunk()?;
        let offset = self.out.position();
        let mut body = Vec::new();
        body.str(name);
        body.map(metadata);
        self.out.record(op::METADATA, &body);
        let mut index = Vec::new();
        index.u64(offset);
        index.u64(self.out.position() - offset);
        index.str(name);
        self.metadata_indexes.push(index);
        self.stats.metadata += 1;
        self.out.land()
    }

    /// An attachment record (a file the recording carries whole: the
    /// firmware a run executed), after the open chunk (which it closes).
    pub(crate) fn write_attachment(
        &mut self,
        log_time: u64,
        create_time: u64,
        name: &str,
        media_type: &str,
        data: &[u8],
    ) -> io::Result<()> {
        self.close_chunk()?;
        let offset = self.out.position();
        let mut body = Vec::with_capacity(40 + name.len() + media_type.len() + data.len());
        body.u64(log_time);
        body.u64(create_time);
        body.str(name);
        body.str(media_type);
        body.u64(data.len() as u64);
        body.extend_from_slice(data);
        let crc = crc32fast::hash(&body);
        body.u32(crc);
        self.out.record(op::ATTACHMENT, &body);
        let mut index = Vec::new();
        index.u64(offset);
        index.u64(self.out.position() - offset);
        index.u64(log_time);
        index.u64(create_time);
        index.u64(data.len() as u64);
        index.str(name);
        index.str(media_type);
        self.attachment_indexes.push(index);
        self.stats.attachments += 1;
        self.out.land()
    }

    /// Close the open chunk, into the file.
    pub(crate) fn flush(&mut self) -> io::Result<()> {
        self.close_chunk()
    }

    /// Close the open chunk, if it holds anything: compressed whole, then its
    /// message indexes, into the file.
    fn close_chunk(&mut self) -> io::Result<()> {
        if self.chunk.is_empty() {
            return Ok(());
        }
        let uncompressed_crc = crc32fast::hash(&self.chunk);
        let (start, end) = self.chunk_bounds.take().unwrap_or((0, 0));
        let chunk_start = self.out.position();
        let at = self.out.pending.len();
        let mut head = std::mem::take(&mut self.scratch);
        head.clear();
        head.push(op::CHUNK);
        head.u64(0); // the record's length, once the compressed size is known
        head.u64(start);
        head.u64(end);
        head.u64(self.chunk.len() as u64);
        head.u32(uncompressed_crc);
        head.str(COMPRESSION);
        head.u64(0); // the compressed size
        self.out.put(&head);
        // Compressed straight after its head, no copy on the way.
        let pending = &mut self.out.pending;
        let head_end = pending.len();
        pending.reserve(zstd::zstd_safe::compress_bound(self.chunk.len()));
        let mut cursor = io::Cursor::new(&mut *pending);
        cursor.set_position(head_end as u64);
        let compressed = match self.compressor.compress_to_buffer(&self.chunk, &mut cursor) {
            Ok(n) => n as u64,
            Err(e) => {
                pending.truncate(at);
                self.scratch = head;
                return Err(e);
            }
        };
        pending[head_end - 8..head_end].copy_from_slice(&compressed.to_le_bytes());
        let record_length = (head_end - at - 9) as u64 + compressed;
        pending[at + 1..at + 9].copy_from_slice(&record_length.to_le_bytes());
        let chunk_length = self.out.position() - chunk_start;

        let indexes_start = self.out.position();
        self.index_offsets.clear();
        for (channel, entries) in self.indexes.iter_mut().enumerate() {
            let Some(entries) = entries.as_mut().filter(|e| !e.is_empty()) else {
                continue;
            };
            let channel = channel as u16;
            // In channel order, as the chunk index lists them.
            self.index_offsets.push((channel, self.out.position()));
            head.clear();
            head.u16(channel);
            head.u32(len32(entries.len() * 16));
            for &(time, offset) in entries.iter() {
                head.u64(time);
                head.u64(offset);
            }
            self.out.record(op::MESSAGE_INDEX, &head);
            entries.clear();
        }
        let indexes_length = self.out.position() - indexes_start;

        let index = &mut head;
        index.clear();
        index.u64(start);
        index.u64(end);
        index.u64(chunk_start);
        index.u64(chunk_length);
        index.u32(len32(self.index_offsets.len() * 10));
        for &(channel, offset) in &self.index_offsets {
            index.u16(channel);
            index.u64(offset);
        }
        index.u64(indexes_length);
        index.str(COMPRESSION);
        index.u64(compressed);
        index.u64(self.chunk.len() as u64);
        self.chunk_index_records.push(op::CHUNK_INDEX);
        self.chunk_index_records.u64(index.len() as u64);
        self.chunk_index_records.extend_from_slice(index);
        self.stats.chunks += 1;
        self.chunk.clear();
        self.scratch = head;
        self.out.land()
    }

    /// Close the data section and write the summary, the footer and the
    /// closing magic over the provisional end; returns the output.
    pub(crate) fn finish(mut self) -> io::Result<W> {
        self.close_chunk()?;
        let data_crc = self.out.take_crc();
        let mut body = Vec::new();
        body.u32(data_crc);
        self.out.record(op::DATA_END, &body);
        let _ = self.out.take_crc();

        let summary_start = self.out.position();
        let mut groups = Vec::new();
        let schemas: Vec<Vec<u8>> = self
            .schemas
            .iter()
            .map(|(&id, s)| schema_body(id, &s.name, &s.encoding, &s.data))
            .collect();
        let out = &mut self.out;
        group(out, &mut groups, op::SCHEMA, records(op::SCHEMA, &schemas));
        let channels: Vec<&[u8]> = self.channels.values().map(Vec::as_slice).collect();
        group(
            out,
            &mut groups,
            op::CHANNEL,
            records(op::CHANNEL, &channels),
        );
        let statistics = [statistics(&self.stats, self.schemas.len(), channels.len())];
        let statistics = records(op::STATISTICS, &statistics);
        group(out, &mut groups, op::STATISTICS, statistics);
        // Whole records already, back to back.
        let chunk_indexes = &self.chunk_index_records;
        group(out, &mut groups, op::CHUNK_INDEX, |out| {
            out.put(chunk_indexes)
        });
        let attachments = records(op::ATTACHMENT_INDEX, &self.attachment_indexes);
        group(out, &mut groups, op::ATTACHMENT_INDEX, attachments);
        let metadata = records(op::METADATA_INDEX, &self.metadata_indexes);
        group(out, &mut groups, op::METADATA_INDEX, metadata);

        let summary_offset_start = self.out.position();
        for (opcode, start, length) in groups {
            let mut body = Vec::with_capacity(17);
            body.push(opcode);
            body.u64(start);
            body.u64(length);
            self.out.record(op::SUMMARY_OFFSET, &body);
        }
        // The summary's checksum covers the footer up to itself.
        let mut footer = Vec::with_capacity(29);
        footer.push(op::FOOTER);
        footer.u64(20);
        footer.u64(summary_start);
        footer.u64(summary_offset_start);
        self.out.put(&footer);
        let summary_crc = self.out.take_crc();
        self.out.put(&summary_crc.to_le_bytes());
        self.out.put(mcap::MAGIC);
        self.out.land_last()
    }
}

/// The summary's records of one kind, `write`, and their group for the
/// summary offsets (none where there are no such records).
fn group<W: Write + Seek>(
    out: &mut Out<W>,
    groups: &mut Vec<(u8, u64, u64)>,
    opcode: u8,
    write: impl FnOnce(&mut Out<W>),
) {
    let start = out.position();
    write(out);
    if out.position() > start {
        groups.push((opcode, start, out.position() - start));
    }
}

/// Writes records of `opcode` with `bodies`.
fn records<W: Write + Seek, B: AsRef<[u8]>>(
    opcode: u8,
    bodies: &[B],
) -> impl FnOnce(&mut Out<W>) + '_ {
    move |out| bodies.iter().for_each(|b| out.record(opcode, b.as_ref()))
}

fn statistics(stats: &Statistics, schema_count: usize, channel_count: usize) -> Vec<u8> {
    let (start, end) = stats.bounds.unwrap_or((0, 0));
    let mut body = Vec::new();
    body.u64(stats.messages);
    body.u16(schema_count as u16);
    body.u32(len32(channel_count));
    body.u32(stats.attachments);
    body.u32(stats.metadata);
    body.u32(stats.chunks);
    body.u64(start);
    body.u64(end);
    // Only the channels with messages, in id order.
    let counted = || {
        (0u16..)
            .zip(stats.per_channel.iter().copied())
            .filter(|(_, count)| *count > 0)
    };
    body.u32(len32(counted().count() * 10));
    for (channel, count) in counted() {
        body.u16(channel);
        body.u64(count);
    }
    body
}

/// The lowest id from 1 that `taken` does not hold (`None`: all are taken).
fn first_free<T>(taken: &BTreeMap<u16, T>) -> Option<u16> {
    (1..=u16::MAX).find(|id| !taken.contains_key(id))
}

fn channel_body(
    id: u16,
    schema_id: u16,
    topic: &str,
    message_encoding: &str,
    metadata: &BTreeMap<String, String>,
) -> Vec<u8> {
    let mut body = Vec::new();
    body.u16(id);
    body.u16(schema_id);
    body.str(topic);
    body.str(message_encoding);
    body.map(metadata);
    body
}

fn schema_body(id: u16, name: &str, encoding: &str, data: &[u8]) -> Vec<u8> {
    let mut body = Vec::with_capacity(16 + name.len() + encoding.len() + data.len());
    body.u16(id);
    body.str(name);
    body.str(encoding);
    body.u32(len32(data.len()));
    body.extend_from_slice(data);
    body
}

/// A record appended to a chunk's buffer.
fn chunk_record(chunk: &mut Vec<u8>, opcode: u8, body: &[u8]) {
    chunk.push(opcode);
    chunk.u64(body.len() as u64);
    chunk.extend_from_slice(body);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::read::{Cut, Reader};
    use mcap::records::MessageHeader;
    use std::io::Cursor;
    use std::path::Path;

    /// The same recording through the MCAP library's writer and through
    /// [`McapFile`]: two schemas (one shared), three channels, messages
    /// across size-closed and flushed chunks, metadata in the middle.
    fn both(chunk_size: usize) -> (Vec<u8>, Vec<u8>) {
        let mut ours = McapFile::new(Cursor::new(Vec::new()), "", "lib", 1, chunk_size).unwrap();
        let mut theirs = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(1)
            .compression_threads(0)
            .chunk_size(Some(chunk_size as u64))
            .profile("")
            .library("lib")
            .create(Cursor::new(Vec::new()))
            .unwrap();
        let schemas = [
            ("a", b"{\"type\":\"object\"}".as_slice()),
            ("b", b"{}"),
            ("a", b"{\"type\":\"object\"}"),
        ];
        for (i, (name, data)) in schemas.iter().enumerate() {
            let s1 = ours.add_schema(name, "jsonschema", data).unwrap();
            let s2 = theirs.add_schema(name, "jsonschema", data).unwrap();
            assert_eq!(s1, s2);
            let topic = format!("/topic/{i}");
            let c1 = ours.add_channel(s1, &topic, "json").unwrap();
            let c2 = theirs
                .add_channel(s2, &topic, "json", &BTreeMap::new())
                .unwrap();
            assert_eq!(c1, c2);
        }
        for i in 0..3000u32 {
            let channel = (i % 7 % 3) as u16 + 1;
            let data = format!("{{\"i\":{i},\"x\":{}}}", f64::from(i) * 0.37);
            let time = u64::from(i) * 1_000_000 + u64::from(i % 5);
            ours.write_message(channel, i, time, time, data.as_bytes())
                .unwrap();
            let header = MessageHeader {
                channel_id: channel,
                sequence: i,
                log_time: time,
                publish_time: time,
            };
            theirs
                .write_to_known_channel(&header, data.as_bytes())
                .unwrap();
            if i % 1000 == 999 {
                ours.flush().unwrap();
                theirs.flush().unwrap();
            }
            if i == 1500 {
                let fields = BTreeMap::from([("seed".to_string(), "7".to_string())]);
                ours.write_metadata("run", &fields).unwrap();
                theirs
                    .write_metadata(&mcap::records::Metadata {
                        name: "run".into(),
                        metadata: fields,
                    })
                    .unwrap();
            }
        }
        let ours = ours.finish().unwrap().into_inner();
        theirs.finish().unwrap();
        (ours, theirs.into_inner().into_inner())
    }

    /// Every record of a file, chunks opened, CRCs checked; offsets and
    /// sizes (which depend on the compressed bytes) left out.
    fn records(file: &[u8]) -> Vec<String> {
        use mcap::records::Record;
        use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
        let options = LinearReaderOptions::default()
            .with_emit_chunks(false)
            .with_validate_chunk_crcs(true)
            .with_validate_data_section_crc(true)
            .with_validate_summary_section_crc(true);
        let mut reader = LinearReader::new_with_options(options);
        let mut rest = file;
        let mut out = Vec::new();
        while let Some(event) = reader.next_event() {
            match event.unwrap() {
                LinearReadEvent::ReadRequest(need) => {
                    let n = need.min(rest.len());
                    reader.insert(n).copy_from_slice(&rest[..n]);
                    reader.notify_read(n);
                    rest = &rest[n..];
                }
                LinearReadEvent::Record { opcode, data } => {
                    let shown = match mcap::parse_record(opcode, data).unwrap() {
                        Record::ChunkIndex(c) => format!(
                            "chunk index {}..{} channels {:?} {}",
                            c.message_start_time,
                            c.message_end_time,
                            c.message_index_offsets.keys().collect::<Vec<_>>(),
                            c.uncompressed_size
                        ),
                        Record::MessageIndex(m) => format!("{m:?}"),
                        Record::MetadataIndex(m) => format!("metadata index {}", m.name),
                        Record::AttachmentIndex(a) => format!(
                            "attachment index {} {} {} {} {}",
                            a.name, a.media_type, a.log_time, a.create_time, a.data_size
                        ),
                        Record::SummaryOffset(s) => format!("summary offset {}", s.group_opcode),
                        Record::DataEnd(_) => "data end".into(),
                        Record::Footer(_) => "footer".into(),
                        other => format!("{other:?}"),
                    };
                    out.push(shown);
                }
            }
        }
        out
    }

    #[test]
    fn the_file_holds_the_records_the_mcap_library_writes() {
        for chunk_size in [4096, 1 << 20] {
            let (ours, theirs) = both(chunk_size);
            let (a, b) = (records(&ours), records(&theirs));
            assert!(a.len() > 3000, "{}", a.len());
            assert_eq!(a, b, "chunk size {chunk_size}");
            // The summary, read as an indexed reader does.
            let summary = mcap::Summary::read(&ours).unwrap().unwrap();
            let theirs_summary = mcap::Summary::read(&theirs).unwrap().unwrap();
            assert_eq!(summary.stats, theirs_summary.stats);
            assert_eq!(
                summary.chunk_indexes.len(),
                theirs_summary.chunk_indexes.len()
            );
            let mut seen = 0;
            for index in &summary.chunk_indexes {
                let messages: Vec<_> = summary
                    .stream_chunk(&ours, index)
                    .unwrap()
                    .map(|m| m.unwrap().sequence)
                    .collect();
                for (_, entries) in summary.read_message_indexes(&ours, index).unwrap() {
                    for entry in entries {
                        let m = summary.seek_message(&ours, index, &entry).unwrap();
                        assert_eq!(m.log_time, entry.log_time);
                    }
                }
                seen += messages.len();
            }
            assert_eq!(seen, 3000);
        }
    }

    /// A file copied with its own ids, as `twin recover` writes one, through
    /// both writers: schemas 7 then 3, channels 9, 0 (no schema) and 4 (with
    /// metadata), one of each declared again alike, a profile, and an
    /// attachment created before its log time.
    fn both_with_ids() -> (Vec<u8>, Vec<u8>) {
        let mut ours = McapFile::new(Cursor::new(Vec::new()), "ros2", "lib", 1, 4096).unwrap();
        let mut theirs = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(1)
            .compression_threads(0)
            .chunk_size(Some(4096))
            .profile("ros2")
            .library("lib")
            .create(Cursor::new(Vec::new()))
            .unwrap();
        let none = BTreeMap::new();
        let qos = BTreeMap::from([(
            "offered_qos_profiles".to_string(),
            "- depth: 10".to_string(),
        )]);
        for (id, name, data) in [
            (7, "a", b"{}".as_slice()),
            (3, "b", b"{\"type\":\"object\"}"),
        ] {
            ours.add_schema_with_id(id, name, "jsonschema", data)
                .unwrap();
            theirs
                .add_schema_with_id(id, name, "jsonschema", data)
                .unwrap();
        }
        let channels = [
            (9, 7, "/nine", &none),
            (0, 0, "/zero", &none),
            (4, 3, "/four", &qos),
        ];
        for &(id, schema, topic, metadata) in channels.iter().chain(&channels[..1]) {
            ours.add_channel_with_id(id, schema, topic, "json", metadata)
                .unwrap();
            theirs
                .add_channel_with_id(id, schema, topic, "json", metadata)
                .unwrap();
        }
        ours.add_schema_with_id(7, "a", "jsonschema", b"{}")
            .unwrap();
        theirs
            .add_schema_with_id(7, "a", "jsonschema", b"{}")
            .unwrap();
        for i in 0..1000u32 {
            let channel = [9, 0, 4][(i % 3) as usize];
            let data = format!("{{\"i\":{i}}}");
            let time = u64::from(i) * 1_000_000;
            ours.write_message(channel, i * 2, time, time + 7, data.as_bytes())
                .unwrap();
            let header = MessageHeader {
                channel_id: channel,
                sequence: i * 2,
                log_time: time,
                publish_time: time + 7,
            };
            theirs
                .write_to_known_channel(&header, data.as_bytes())
                .unwrap();
            if i == 500 {
                ours.write_attachment(time, 12, "fw.hex", "text/plain", b":00000001FF")
                    .unwrap();
                theirs
                    .attach(&mcap::Attachment {
                        log_time: time,
                        create_time: 12,
                        name: "fw.hex".into(),
                        media_type: "text/plain".into(),
                        data: b":00000001FF".as_slice().into(),
                    })
                    .unwrap();
            }
        }
        let ours = ours.finish().unwrap().into_inner();
        theirs.finish().unwrap();
        (ours, theirs.into_inner().into_inner())
    }

    #[test]
    fn a_file_s_own_ids_are_written_as_the_mcap_library_writes_them() {
        let (ours, theirs) = both_with_ids();
        let (a, b) = (records(&ours), records(&theirs));
        assert!(a.len() > 1000, "{}", a.len());
        // Record by record, so that a difference shows as one.
        for (i, (a, b)) in a.iter().zip(&b).enumerate() {
            assert_eq!(a, b, "record {i}");
        }
        assert_eq!(a.len(), b.len());
        let summary = mcap::Summary::read(&ours).unwrap().unwrap();
        let theirs_summary = mcap::Summary::read(&theirs).unwrap().unwrap();
        assert_eq!(summary.stats, theirs_summary.stats);
        let ids = |s: &mcap::Summary| -> Vec<(u16, Option<u16>)> {
            let schema = |c: &mcap::Channel| c.schema.as_ref().map(|s| s.id);
            let mut ids: Vec<_> = s.channels.iter().map(|(&id, c)| (id, schema(c))).collect();
            ids.sort();
            ids
        };
        assert_eq!(ids(&summary), [(0, None), (4, Some(3)), (9, Some(7))]);
        assert_eq!(ids(&summary), ids(&theirs_summary));
        assert_eq!(
            summary.channels[&4].metadata["offered_qos_profiles"],
            "- depth: 10"
        );
        let header = mcap::read::LinearReader::new(&ours)
            .unwrap()
            .next()
            .unwrap()
            .unwrap();
        assert!(
            matches!(&header, mcap::records::Record::Header(h) if h.profile == "ros2"),
            "{header:?}"
        );
    }

    #[test]
    fn a_declaration_that_contradicts_an_earlier_one_is_refused_in_words() {
        let mut file = McapFile::new(Cursor::new(Vec::new()), "", "lib", 1, 4096).unwrap();
        file.add_schema_with_id(2, "a", "jsonschema", b"{}")
            .unwrap();
        let e = file
            .add_schema_with_id(2, "b", "jsonschema", b"{}")
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "schema 2 is declared twice, differently (`a`, then `b`)"
        );
        let e = file
            .add_schema_with_id(0, "c", "jsonschema", b"{}")
            .unwrap_err();
        assert!(
            e.to_string().contains("the id 0, which MCAP reserves"),
            "{e}"
        );
        let none = BTreeMap::new();
        file.add_channel_with_id(5, 2, "/a", "json", &none).unwrap();
        let e = file
            .add_channel_with_id(5, 2, "/b", "json", &none)
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "channel 5 is declared twice, differently (the second time as `/b`)"
        );
        let e = file
            .add_channel_with_id(6, 3, "/c", "json", &none)
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "channel `/c` uses schema 3, which the file never declared"
        );
        // A channel the file never declared, next to and far from declared ones.
        for channel in [0, 4, 6, 700] {
            let e = file.write_message(channel, 0, 0, 0, b"{}").unwrap_err();
            assert!(e.to_string().contains("never declared"), "{e}");
        }
        // The automatic ids go around the given ones.
        assert_eq!(file.add_schema("d", "jsonschema", b"[]").unwrap(), 1);
        assert_eq!(file.add_schema("d", "jsonschema", b"[]").unwrap(), 1);
        assert_eq!(file.add_schema("e", "jsonschema", b"[]").unwrap(), 3);
        assert_eq!(file.add_schema("a", "jsonschema", b"{}").unwrap(), 2);
        for expected in [1, 2, 3, 4, 6] {
            assert_eq!(file.add_channel(1, "/x", "json").unwrap(), expected);
        }
    }

    /// An output that keeps every write and where it went, so that the file
    /// can be seen as a kill would leave it after any of them.
    #[derive(Default)]
    struct Tape {
        position: u64,
        writes: Vec<(u64, Vec<u8>)>,
    }

    impl Write for Tape {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            self.writes.push((self.position, buf.to_vec()));
            self.position += buf.len() as u64;
            Ok(buf.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    impl Seek for Tape {
        fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
            match to {
                SeekFrom::Start(p) => self.position = p,
                other => panic!("the writer seeks only from the start: {other:?}"),
            }
            Ok(self.position)
        }
    }

    /// The file after `writes`, the last of them cut to its first `cut` bytes.
    fn file_after(writes: &[(u64, Vec<u8>)], cut: usize) -> Vec<u8> {
        let mut file = Vec::new();
        for (i, (at, bytes)) in writes.iter().enumerate() {
            let bytes = match i + 1 == writes.len() {
                true => &bytes[..cut.min(bytes.len())],
                false => &bytes[..],
            };
            let at = *at as usize;
            if file.len() < at + bytes.len() {
                file.resize(at + bytes.len(), 0);
            }
            file[at..at + bytes.len()].copy_from_slice(bytes);
        }
        file
    }

    /// Messages a reader reading `file` through finds, checking every CRC,
    /// the end magic and the footer at the file's end (where an indexed
    /// reader looks first); and whether that footer names a summary.
    fn read_through(file: &[u8]) -> (usize, bool) {
        let footer = mcap::read::footer(file).expect("a footer at the file's end");
        let count = records(file)
            .iter()
            .filter(|r| r.starts_with("Message {"))
            .count();
        (count, footer.summary_start != 0)
    }

    #[test]
    fn a_file_cut_after_any_write_reads_to_its_last_whole_chunk() {
        let mut file = McapFile::new(Tape::default(), "", "lib", 1, 4096).unwrap();
        let schema = file.add_schema("a", "jsonschema", b"{}").unwrap();
        let channel = file.add_channel(schema, "/a", "json").unwrap();
        for i in 0..2000u32 {
            let data = format!("{{\"i\":{i},\"x\":{}}}", f64::from(i) * 0.37);
            let time = u64::from(i) * 1_000_000;
            file.write_message(channel, i, time, time, data.as_bytes())
                .unwrap();
            if i % 300 == 299 {
                file.flush().unwrap();
            }
            if i == 700 {
                file.write_metadata("run", &BTreeMap::new()).unwrap();
            }
            if i == 1200 {
                file.write_attachment(time, time, "fw.hex", "text/plain", &[b':'; 3000])
                    .unwrap();
            }
        }
        let tape = file.finish().unwrap();
        let writes = &tape.writes;
        let mut last = 0;
        for k in 1..=writes.len() {
            let whole = file_after(&writes[..k], usize::MAX);
            if !whole.starts_with(mcap::MAGIC) {
                // Before the header landed: nothing was recorded yet.
                assert!(k < 3, "write {k}");
                continue;
            }
            let (count, summary) = read_through(&whole);
            assert!(count >= last, "write {k}: {count} messages after {last}");
            last = count;
            assert_eq!(summary, k == writes.len(), "write {k}");
            // Before the footer naming it, the summary landed whole after
            // the data end: the twin reads that as a complete file.
            let closed = k + 1 >= writes.len();
            let mut r = Reader::from_bytes(&whole, Path::new("cut.mcap")).unwrap();
            while r.next().unwrap().is_some() {}
            let r = r.finish();
            assert_eq!(r.message_count(), count as u64, "write {k}");
            match closed {
                true => assert_eq!(r.truncated, None),
                false => assert_eq!(r.truncated, Some(Cut::NoSummary), "write {k}"),
            }
            // A kill stops a long write between two pages of the file: cut
            // there, it reads as before it.
            let (at, bytes) = &writes[k - 1];
            if bytes.len() > PROVISIONAL_END {
                let before = file_after(&writes[..k], 0);
                let (before, _) = read_through(&before);
                let pages = (at / 4096 + 1) * 4096..at + bytes.len() as u64;
                for page in pages.step_by(4096) {
                    let cut = file_after(&writes[..k], (page - at) as usize);
                    assert_eq!(
                        read_through(&cut),
                        (before, false),
                        "write {k} cut at {page}"
                    );
                }
            }
        }
        assert_eq!(last, 2000);
        // Closed, the file is what it would be written at once.
        let closed = file_after(writes, usize::MAX);
        let summary = mcap::Summary::read(&closed).unwrap().expect("a summary");
        assert_eq!(summary.stats.unwrap().message_count, 2000);
    }
}
