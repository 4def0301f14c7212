//! The MCAP file a recording writes, through the MCAP library's writer
//! (`mcap::Writer`, <https://mcap.dev/spec>): chunks of about 1 MiB, zstd,
//! schemas and channels in the chunks and repeated in the summary, message
//! indexes after each chunk, statistics, the summary's indexes and offsets,
//! both checksums.
//!
//! The library writes into [`Landing`], which holds what was written since
//! the last whole record and lands it in the file, followed by a provisional
//! end, each time a chunk (or a metadata record, or an attachment) is whole:
//! so a run killed (kill -9, a crash) leaves a file that every reader reads
//! up to its last whole chunk.

use mcap::records::{MessageHeader, Metadata, op};
use mcap::{Attachment, McapError, WriteOptions, Writer};
use std::collections::BTreeMap;
use std::io::{self, Cursor, Seek, SeekFrom, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// zstd level 1, on the writer's own thread (no zstd workers): the faster
/// of the library's settings here. Against the hand-written writer this
/// replaced (whole chunks compressed at once, zstd's match finder set for
/// plant samples), whole `taskset -c 0 twin bench --repeat 1` processes in
/// turn, CPU time, median of 5 pairs: ev-meb (200 s) 1.07x, ten-modules
/// (40 s) 1.05x; at the library's default level (3) 1.10x and 1.12x, for
/// files 5 % smaller. Under the 10 % that would have kept a second writer.
pub(crate) const LEVEL: u32 = 1;
const THREADS: u32 = 0;
/// Uncompressed bytes per chunk (the MCAP library's default, set explicitly so
/// that a library upgrade cannot change the file layout).
pub(crate) const CHUNK_SIZE: usize = 1024 * 1024;

/// The library's writer as every recording and recovered file is written.
pub(crate) fn write_options(profile: &str, library: &str) -> WriteOptions {
    WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .compression_level(LEVEL)
        .compression_threads(THREADS)
        .chunk_size(Some(CHUNK_SIZE as u64))
        .profile(profile)
        .library(library)
}

/// An MCAP file being written to `W`.
pub(crate) struct McapFile<W: Write + Seek> {
    writer: Writer<Landing<W>>,
    /// Set before the close, so that the library's last flush leaves the
    /// summary to [`Landing::land_last`].
    closing: Arc<AtomicBool>,
    /// A message's bytes, for a message serialised by the caller.
    scratch: Vec<u8>,
}

fn io_error(e: McapError) -> io::Error {
    match e {
        McapError::Io(e) => e,
        other => io::Error::other(other),
    }
}

impl<W: Write + Seek> McapFile<W> {
    /// Start the file: magic and header, into the file with a provisional
    /// end, so that a run killed before its first chunk leaves an MCAP file
    /// of no message.
    pub(crate) fn new(inner: W, library: &str) -> io::Result<Self> {
        let closing = Arc::new(AtomicBool::new(false));
        let landing = Landing {
            inner,
            landed: 0,
            end_len: 0,
            pending: Cursor::new(Vec::with_capacity(CHUNK_SIZE + 64 * 1024)),
            crc: crc32fast::Hasher::new(),
            closing: Arc::clone(&closing),
        };
        let mut writer = write_options("", library)
            .create(landing)
            .map_err(io_error)?;
        writer.flush().map_err(io_error)?;
        Ok(Self {
            writer,
            closing,
            scratch: Vec::new(),
        })
    }

    /// The id of a schema (the same id for the same schema).
    pub(crate) fn add_schema(
        &mut self,
        name: &str,
        encoding: &str,
        data: &[u8],
    ) -> io::Result<u16> {
        self.writer
            .add_schema(name, encoding, data)
            .map_err(io_error)
    }

    /// A new channel.
    pub(crate) fn add_channel(
        &mut self,
        schema_id: u16,
        topic: &str,
        message_encoding: &str,
    ) -> io::Result<u16> {
        self.writer
            .add_channel(schema_id, topic, message_encoding, &BTreeMap::new())
            .map_err(io_error)
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
        let header = MessageHeader {
            channel_id: channel,
            sequence,
            log_time,
            publish_time,
        };
        self.writer
            .write_to_known_channel(&header, data)
            .map_err(io_error)
    }

    /// [`McapFile::write_message`] with the message's bytes appended by
    /// `data`; if it fails, nothing of the message is written.
    pub(crate) fn write_message_with(
        &mut self,
        channel: u16,
        sequence: u32,
        log_time: u64,
        publish_time: u64,
        data: impl FnOnce(&mut Vec<u8>) -> io::Result<()>,
    ) -> io::Result<()> {
        let mut scratch = std::mem::take(&mut self.scratch);
        scratch.clear();
        let written = data(&mut scratch)
            .and_then(|()| self.write_message(channel, sequence, log_time, publish_time, &scratch));
        self.scratch = scratch;
        written
    }

    /// A metadata record, after the open chunk (which it closes).
    pub(crate) fn write_metadata(
        &mut self,
        name: &str,
        metadata: &BTreeMap<String, String>,
    ) -> io::Result<()> {
        self.writer
            .write_metadata(&Metadata {
                name: name.into(),
                metadata: metadata.clone(),
            })
            .map_err(io_error)?;
        self.flush()
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
        self.writer
            .attach(&Attachment {
                log_time,
                // Simulated too, so the bytes repeat.
                create_time: log_time,
                name: name.into(),
                media_type: media_type.into(),
                data: data.into(),
            })
            .map_err(io_error)?;
        self.flush()
    }

    /// Close the open chunk, into the file.
    pub(crate) fn flush(&mut self) -> io::Result<()> {
        self.writer.flush().map_err(io_error)
    }

    /// Close the data section and write the summary, the footer and the
    /// closing magic over the provisional end; returns the output.
    pub(crate) fn finish(mut self) -> io::Result<W> {
        self.closing.store(true, Ordering::Relaxed);
        self.writer.finish().map_err(io_error)?;
        self.writer.into_inner().land_last()
    }
}

/// The library's output: the bytes not yet in the file (the library seeks
/// back into them to put in a chunk's sizes), where they go, and the
/// checksum of the bytes in the file.
///
/// What the library wrote lands in the file at each of its flushes (a chunk,
/// a metadata record or an attachment whole), followed by a provisional end:
/// a data end record and a footer saying there is no summary (`summary_start`
/// 0) and the closing magic. So the file always ends as an MCAP file does,
/// and a run killed leaves one that every reader reads up to its last whole
/// chunk: a reader looking for the summary finds none and reads the file
/// through, as Python's `mcap` `make_reader` does. The next records
/// overwrite that end, and at the close the summary does.
pub(crate) struct Landing<W> {
    inner: W,
    /// Where the bytes in `pending` go: the end of the records in the file,
    /// where its provisional end starts.
    landed: u64,
    /// Bytes of the provisional end after `landed` (0 before the first).
    end_len: usize,
    pending: Cursor<Vec<u8>>,
    /// The data section's checksum, of the bytes landed.
    crc: crc32fast::Hasher,
    closing: Arc<AtomicBool>,
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

impl<W: Write + Seek> Write for Landing<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.pending.write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> io::Result<()> {
        self.pending.write_all(buf)
    }

    /// The library flushes once a chunk, a metadata record or an attachment
    /// is whole, and after the summary (which [`Landing::land_last`] lands).
    fn flush(&mut self) -> io::Result<()> {
        if self.closing.load(Ordering::Relaxed) {
            return Ok(());
        }
        self.land()
    }
}

impl<W: Write + Seek> Seek for Landing<W> {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        let end = self.pending.get_ref().len() as u64;
        let at = match to {
            SeekFrom::Start(p) => p.checked_sub(self.landed),
            SeekFrom::End(d) => end.checked_add_signed(d),
            SeekFrom::Current(d) => self.pending.position().checked_add_signed(d),
        };
        // The library goes back only into the chunk it is closing.
        let Some(at) = at.filter(|&at| at <= end) else {
            return Err(io::Error::other(
                "the MCAP writer went back to bytes already in the file",
            ));
        };
        self.pending.set_position(at);
        Ok(self.landed + at)
    }
}

impl<W: Write + Seek> Landing<W> {
    /// The pending records into the file, ended by a provisional end.
    fn land(&mut self) -> io::Result<()> {
        let records = std::mem::take(self.pending.get_mut());
        // Records shorter than the end they would overwrite (an empty
        // metadata record) wait for the next: the end could not be kept
        // readable while they land.
        if records.len() < self.end_len || records.is_empty() {
            *self.pending.get_mut() = records;
            return Ok(());
        }
        self.crc.update(&records);
        // The data section's checksum so far, so that a reader checking it
        // finds it right.
        let mut end = [0u8; PROVISIONAL_END];
        end[0] = op::DATA_END;
        end[1..9].copy_from_slice(&4u64.to_le_bytes());
        end[9..13].copy_from_slice(&self.crc.clone().finalize().to_le_bytes());
        end[13..].copy_from_slice(&NO_SUMMARY);
        let landed = self.write_at(&records, &end);
        *self.pending.get_mut() = records;
        landed?;
        self.landed += self.pending.get_ref().len() as u64;
        self.end_len = PROVISIONAL_END;
        self.pending.get_mut().clear();
        self.pending.set_position(0);
        Ok(())
    }

    /// The pending records, which end with the footer and the closing magic,
    /// into the file: it is complete. Returns the output.
    fn land_last(mut self) -> io::Result<W> {
        let pending = std::mem::take(self.pending.get_mut());
        let Some(split) = pending.len().checked_sub(FINAL_END) else {
            return Err(io::Error::other("the MCAP writer wrote no footer"));
        };
        let (records, end) = pending.split_at(split);
        // The file is never longer than this: the summary (its statistics
        // record alone) is longer than the provisional end it replaces.
        // A footer naming the summary goes in once the summary is whole:
        // until then, one naming none.
        self.write_at(records, &NO_SUMMARY)?;
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
    fn write_at(&mut self, records: &[u8], end: &[u8]) -> io::Result<()> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::read::{Cut, Reader};
    use std::path::Path;

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
        let mut file = McapFile::new(Tape::default(), "lib").unwrap();
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
                file.write_attachment(time, "fw.hex", "text/plain", &[b':'; 3000])
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
