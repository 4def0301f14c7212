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

use mcap::records::op;
use std::collections::BTreeMap;
use std::io::{self, Write};

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
pub(crate) struct McapFile<W: Write> {
    out: Out<W>,
    /// Closes a chunk once it holds more than this many uncompressed bytes.
    chunk_size: usize,
    /// The open chunk's records, uncompressed.
    chunk: Vec<u8>,
    /// The open chunk's first and last message times.
    chunk_bounds: Option<(u64, u64)>,
    /// Per channel id (0, no channel, stays empty): the open chunk's
    /// messages (log time, offset in the chunk).
    indexes: Vec<Vec<(u64, u64)>>,
    compressor: zstd::bulk::Compressor<'static>,
    compressed: Vec<u8>,
    /// A record's body, built before its length is known.
    scratch: Vec<u8>,
    /// Schema records (id order), for the summary and their deduplication.
    schemas: Vec<Schema>,
    /// Channel records' bodies (id order), for the summary.
    channels: Vec<Vec<u8>>,
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

/// The output, with its position and the checksum of what went out since
/// the checksum was last taken.
struct Out<W> {
    inner: W,
    position: u64,
    crc: crc32fast::Hasher,
}

impl<W: Write> Out<W> {
    fn put(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.inner.write_all(bytes)?;
        self.crc.update(bytes);
        self.position += bytes.len() as u64;
        Ok(())
    }

    /// A record: opcode, length, body.
    fn record(&mut self, opcode: u8, body: &[u8]) -> io::Result<()> {
        let mut head = [0u8; 9];
        head[0] = opcode;
        head[1..].copy_from_slice(&(body.len() as u64).to_le_bytes());
        self.put(&head)?;
        self.put(body)
    }

    /// The checksum so far, starting a new one.
    fn take_crc(&mut self) -> u32 {
        std::mem::take(&mut self.crc).finalize()
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

impl<W: Write> McapFile<W> {
    /// Start the file: magic and header.
    pub(crate) fn new(inner: W, library: &str, level: i32, chunk_size: usize) -> io::Result<Self> {
        let mut file = Self {
            out: Out {
                inner,
                position: 0,
                crc: crc32fast::Hasher::new(),
            },
            chunk_size,
            chunk: Vec::with_capacity(chunk_size + 64 * 1024),
            chunk_bounds: None,
            indexes: vec![Vec::new()],
            compressor: compressor(level)?,
            compressed: Vec::new(),
            scratch: Vec::new(),
            schemas: Vec::new(),
            channels: Vec::new(),
            chunk_index_records: Vec::new(),
            index_offsets: Vec::new(),
            metadata_indexes: Vec::new(),
            attachment_indexes: Vec::new(),
            stats: Statistics::default(),
        };
        file.out.put(mcap::MAGIC)?;
        let mut header = Vec::new();
        header.str(""); // profile
        header.str(library);
        file.out.record(op::HEADER, &header)?;
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
        if let Some(i) = self
            .schemas
            .iter()
            .position(|s| s.name == name && s.encoding == encoding && s.data == data)
        {
            return Ok(i as u16 + 1);
        }
        let id = u16::try_from(self.schemas.len() + 1).map_err(|_| too_many("schemas"))?;
        self.schemas.push(Schema {
            name: name.into(),
            encoding: encoding.into(),
            data: data.into(),
        });
        let body = schema_body(id, name, encoding, data);
        chunk_record(&mut self.chunk, op::SCHEMA, &body);
        Ok(id)
    }

    /// A new channel (ids from 1, as the MCAP library gave them), written
    /// into the open chunk.
    pub(crate) fn add_channel(
        &mut self,
        schema_id: u16,
        topic: &str,
        message_encoding: &str,
    ) -> io::Result<u16> {
        let id = u16::try_from(self.channels.len() + 1).map_err(|_| too_many("channels"))?;
        let mut body = Vec::new();
        body.u16(id);
        body.u16(schema_id);
        body.str(topic);
        body.str(message_encoding);
        body.map(&BTreeMap::new());
        chunk_record(&mut self.chunk, op::CHANNEL, &body);
        self.channels.push(body);
        self.indexes.push(Vec::new());
        Ok(id)
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
        if channel == 0 || usize::from(channel) >= self.indexes.len() {
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
        if let Some(index) = self.indexes.get_mut(usize::from(channel)) {
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
        let offset = self.out.position;
        let mut body = Vec::new();
        body.str(name);
        body.map(metadata);
        self.out.record(op::METADATA, &body)?;
        let mut index = Vec::new();
        index.u64(offset);
        index.u64(self.out.position - offset);
        index.str(name);
        self.metadata_indexes.push(index);
        self.stats.metadata += 1;
        Ok(())
    }

    /// An attachment record (a file the recording carries whole: the
    /// firmware a run executed), after the open chunk (which it closes).
    pub(crate) fn write_attachment(
        &mut self,
        log_time: u64,
        name: &str,
        media_type: &str,
        data: &[u8],
    ) -> io::Result<()> {
        self.close_chunk()?;
        let offset = self.out.position;
        let mut body = Vec::with_capacity(40 + name.len() + media_type.len() + data.len());
        body.u64(log_time);
        body.u64(log_time); // create time: simulated too, so the bytes repeat
        body.str(name);
        body.str(media_type);
        body.u64(data.len() as u64);
        body.extend_from_slice(data);
        let crc = crc32fast::hash(&body);
        body.u32(crc);
        self.out.record(op::ATTACHMENT, &body)?;
        let mut index = Vec::new();
        index.u64(offset);
        index.u64(self.out.position - offset);
        index.u64(log_time);
        index.u64(log_time);
        index.u64(data.len() as u64);
        index.str(name);
        index.str(media_type);
        self.attachment_indexes.push(index);
        self.stats.attachments += 1;
        Ok(())
    }

    /// Close the open chunk and push what is written to the file.
    pub(crate) fn flush(&mut self) -> io::Result<()> {
        self.close_chunk()?;
        self.out.inner.flush()
    }

    /// Close the open chunk, if it holds anything: compressed whole, then its
    /// message indexes.
    fn close_chunk(&mut self) -> io::Result<()> {
        if self.chunk.is_empty() {
            return Ok(());
        }
        let uncompressed_crc = crc32fast::hash(&self.chunk);
        self.compressed.clear();
        self.compressed
            .reserve(zstd::zstd_safe::compress_bound(self.chunk.len()));
        self.compressor
            .compress_to_buffer(&self.chunk, &mut self.compressed)?;
        let (start, end) = self.chunk_bounds.take().unwrap_or((0, 0));
        let chunk_start = self.out.position;
        let mut head = std::mem::take(&mut self.scratch);
        head.clear();
        head.u64(start);
        head.u64(end);
        head.u64(self.chunk.len() as u64);
        head.u32(uncompressed_crc);
        head.str(COMPRESSION);
        head.u64(self.compressed.len() as u64);
        let mut record = [0u8; 9];
        record[0] = op::CHUNK;
        record[1..].copy_from_slice(&((head.len() + self.compressed.len()) as u64).to_le_bytes());
        self.out.put(&record)?;
        self.out.put(&head)?;
        self.out.put(&self.compressed)?;
        let chunk_length = self.out.position - chunk_start;

        let indexes_start = self.out.position;
        self.index_offsets.clear();
        for (channel, entries) in self.indexes.iter_mut().enumerate() {
            if entries.is_empty() {
                continue;
            }
            let channel = channel as u16;
            // In channel order, as the chunk index lists them.
            self.index_offsets.push((channel, self.out.position));
            head.clear();
            head.u16(channel);
            head.u32(len32(entries.len() * 16));
            for &(time, offset) in entries.iter() {
                head.u64(time);
                head.u64(offset);
            }
            self.out.record(op::MESSAGE_INDEX, &head)?;
            entries.clear();
        }
        let indexes_length = self.out.position - indexes_start;

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
        index.u64(self.compressed.len() as u64);
        index.u64(self.chunk.len() as u64);
        self.chunk_index_records.push(op::CHUNK_INDEX);
        self.chunk_index_records.u64(index.len() as u64);
        self.chunk_index_records.extend_from_slice(index);
        self.stats.chunks += 1;
        self.chunk.clear();
        self.scratch = head;
        Ok(())
    }

    /// Close the data section and write the summary, the footer and the
    /// closing magic; returns the output.
    pub(crate) fn finish(mut self) -> io::Result<W> {
        self.close_chunk()?;
        let data_crc = self.out.take_crc();
        let mut body = Vec::new();
        body.u32(data_crc);
        self.out.record(op::DATA_END, &body)?;
        let _ = self.out.take_crc();

        let summary_start = self.out.position;
        let mut groups: Vec<(u8, u64, u64)> = Vec::new();
        let mut group =
            |out: &mut Out<W>, opcode: u8, write: &mut dyn FnMut(&mut Out<W>) -> io::Result<()>| {
                let start = out.position;
                write(out)?;
                if out.position > start {
                    groups.push((opcode, start, out.position - start));
                }
                io::Result::Ok(())
            };
        let records = |opcode: u8, bodies: Vec<Vec<u8>>| {
            move |out: &mut Out<W>| bodies.iter().try_for_each(|b| out.record(opcode, b))
        };
        let schemas: Vec<Vec<u8>> = self
            .schemas
            .iter()
            .enumerate()
            .map(|(i, s)| schema_body(i as u16 + 1, &s.name, &s.encoding, &s.data))
            .collect();
        group(&mut self.out, op::SCHEMA, &mut records(op::SCHEMA, schemas))?;
        let channels = std::mem::take(&mut self.channels);
        let channel_count = channels.len();
        group(
            &mut self.out,
            op::CHANNEL,
            &mut records(op::CHANNEL, channels),
        )?;
        let statistics = vec![self.statistics(channel_count)];
        group(
            &mut self.out,
            op::STATISTICS,
            &mut records(op::STATISTICS, statistics),
        )?;
        let chunk_index_records = std::mem::take(&mut self.chunk_index_records);
        group(&mut self.out, op::CHUNK_INDEX, &mut |out| {
            out.put(&chunk_index_records)
        })?;
        let attachment_indexes = std::mem::take(&mut self.attachment_indexes);
        group(
            &mut self.out,
            op::ATTACHMENT_INDEX,
            &mut records(op::ATTACHMENT_INDEX, attachment_indexes),
        )?;
        let metadata_indexes = std::mem::take(&mut self.metadata_indexes);
        group(
            &mut self.out,
            op::METADATA_INDEX,
            &mut records(op::METADATA_INDEX, metadata_indexes),
        )?;

        let summary_offset_start = self.out.position;
        for (opcode, start, length) in groups {
            let mut body = Vec::with_capacity(17);
            body.push(opcode);
            body.u64(start);
            body.u64(length);
            self.out.record(op::SUMMARY_OFFSET, &body)?;
        }
        // The summary's checksum covers the footer up to itself.
        let mut footer = Vec::with_capacity(29);
        footer.push(op::FOOTER);
        footer.u64(20);
        footer.u64(summary_start);
        footer.u64(summary_offset_start);
        self.out.put(&footer)?;
        let summary_crc = self.out.take_crc();
        self.out.put(&summary_crc.to_le_bytes())?;
        self.out.put(mcap::MAGIC)?;
        self.out.inner.flush()?;
        Ok(self.out.inner)
    }

    fn statistics(&self, channel_count: usize) -> Vec<u8> {
        let stats = &self.stats;
        let (start, end) = stats.bounds.unwrap_or((0, 0));
        let mut body = Vec::new();
        body.u64(stats.messages);
        body.u16(self.schemas.len() as u16);
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
    use mcap::records::MessageHeader;
    use std::io::Cursor;

    /// The same recording through the MCAP library's writer and through
    /// [`McapFile`]: two schemas (one shared), three channels, messages
    /// across size-closed and flushed chunks, metadata in the middle.
    fn both(chunk_size: usize) -> (Vec<u8>, Vec<u8>) {
        let mut ours = McapFile::new(Vec::new(), "lib", 1, chunk_size).unwrap();
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
        let ours = ours.finish().unwrap();
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
}
