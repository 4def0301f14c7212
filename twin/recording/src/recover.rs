//! Turning a recording cut short (the process killed, the disk full, the
//! machine off) into a complete MCAP file that every reader opens, as the
//! `mcap recover` command of the MCAP tools does: every record that can be
//! read is copied into a new file with its summary, a damaged chunk is left
//! out and reading goes on after it, and the copy ends where the data ends.
//!
//! Schemas and channels keep their ids and metadata, messages their
//! sequence numbers and times, metadata and attachments come along, the
//! header keeps its profile and library, and each whole chunk is one chunk
//! of the copy again: the recovered file is the recording as far as it was
//! written, not a re-encoding of it. It is written by the recordings' own
//! writer ([`McapFile`]), so a complete recording of the twin's comes out
//! byte for byte the same.

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use std::collections::{BTreeMap, BTreeSet};
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};

use crate::chunk::{chunk_records, in_words};
use crate::mcap_file::McapFile;
use crate::record::{CHUNK_SIZE, ZSTD_LEVEL};
use crate::topics;

/// Why a recovery could not be made.
#[derive(Debug, thiserror::Error)]
pub enum RecoverError {
    /// The damaged file cannot be opened or read.
    #[error("cannot read {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{} is not a recording: it does not start with the MCAP magic bytes",
        path.display()
    )]
    NotMcap { path: PathBuf },
    #[error("{} holds nothing after its first bytes: there is nothing to recover", path.display())]
    Empty { path: PathBuf },
    #[error("cannot create {}", path.display())]
    Create {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot start MCAP file {}", path.display())]
    Start {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot write {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot finish {}", path.display())]
    Finish {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

type Result<T, E = RecoverError> = std::result::Result<T, E>;

/// What a recovery copied and what it could not.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Recovered {
    pub messages: u64,
    pub channels: usize,
    pub metadata: usize,
    pub attachments: usize,
    /// Complete chunks copied.
    pub chunks: u64,
    /// Chunks that did not decompress or decode (1-based), left out.
    pub damaged_chunks: Vec<u64>,
    /// Messages on a channel the file never declares (left out).
    pub strays: u64,
    /// The file had its data end record and no footer naming no summary
    /// after it (the end the writer puts after every chunk until the
    /// close): it was complete already.
    pub was_complete: bool,
    /// Why reading stopped before a data end record, if it did: the end of
    /// the file, or the reader's error where the file is damaged.
    pub stopped: Option<String>,
}

/// Copy what `damaged` holds into a complete MCAP file at `out`.
pub fn recover(damaged: &Path, out: &Path) -> Result<Recovered> {
    let cannot_read = |source| RecoverError::Read {
        path: damaged.to_path_buf(),
        source,
    };
    let mut source = File::open(damaged).map_err(cannot_read)?;
    let len = source.metadata().map_err(cannot_read)?.len();
    let mut magic = [0u8; 8];
    if source.read_exact(&mut magic).is_err() || magic != *mcap::MAGIC {
        return Err(RecoverError::NotMcap {
            path: damaged.to_path_buf(),
        });
    }
    let options = LinearReaderOptions::default()
        .with_skip_start_magic(true)
        .with_skip_end_magic(true)
        .with_emit_chunks(true)
        .with_record_length_limit(usize::try_from(len).unwrap_or(usize::MAX));
    let mut reader = LinearReader::new_with_options(options);
    let mut copy = Copy::default();
    let mut writer = None;
    'copy: loop {
        let record = match next_record(&mut reader, &mut source) {
            Ok(Some(record)) => record,
            Ok(None) => {
                copy.found.stopped = Some("the file ends without its summary".into());
                break;
            }
            Err(Stop::Io(e)) => return Err(cannot_read(e)),
            Err(Stop::Damaged(e)) => {
                copy.found.stopped = Some(format!(
                    "after {} complete chunk(s), {}",
                    copy.found.chunks,
                    in_words(&e)
                ));
                break;
            }
        };
        let writer = match (&mut writer, &record) {
            (Some(w), _) => w,
            (None, Outer::Record(Record::Header(h))) => {
                writer.insert(create(out, &h.profile, &h.library)?)
            }
            (None, _) => writer.insert(create(out, "", "")?),
        };
        let cannot_write = |source| RecoverError::Write {
            path: out.to_path_buf(),
            source,
        };
        match record {
            Outer::Record(Record::DataEnd(_)) => {
                // Followed by a footer naming no summary, it is the end the
                // twin's writer puts after every chunk until the close: the
                // run was cut.
                match next_record(&mut reader, &mut source) {
                    Ok(Some(Outer::Record(Record::Footer(f)))) if f.summary_start == 0 => {
                        copy.found.stopped = Some("the file ends without its summary".into());
                    }
                    _ => copy.found.was_complete = true,
                }
                break;
            }
            Outer::Record(other) => {
                if let Err(e) = copy.take(writer, other) {
                    copy.stop_at_fault(e).map_err(cannot_write)?;
                    break 'copy;
                }
            }
            Outer::Chunk(Ok(records)) => {
                for r in records {
                    if let Err(e) = copy.take(writer, r) {
                        copy.stop_at_fault(e).map_err(cannot_write)?;
                        break 'copy;
                    }
                }
                copy.found.chunks += 1;
                // Where the recording closed a chunk (a simulated second's
                // end, a full chunk), so does the copy.
                writer.flush().map_err(cannot_write)?;
            }
            // A damaged chunk's neighbours are whole: leave it out and go
            // on, as `mcap recover` does.
            Outer::Chunk(Err(_)) => {
                let number = copy.found.chunks + copy.found.damaged_chunks.len() as u64 + 1;
                copy.found.damaged_chunks.push(number);
            }
        }
    }
    let mut writer = match writer {
        Some(w) => w,
        None => {
            return Err(RecoverError::Empty {
                path: damaged.to_path_buf(),
            });
        }
    };
    // The copy of a run cut short says so, so that a replay or a comparison
    // reads it as the cut run it is (up to its end), not as a whole run
    // whose messages stop early.
    if let Some(why) = &copy.found.stopped {
        let fields = BTreeMap::from([("stopped".to_string(), why.clone())]);
        writer
            .write_metadata(topics::RECOVERED_METADATA, &fields)
            .map_err(|source| RecoverError::Write {
                path: out.to_path_buf(),
                source,
            })?;
    }
    writer.finish().map_err(|source| RecoverError::Finish {
        path: out.to_path_buf(),
        source,
    })?;
    copy.found.channels = copy.channels.len();
    Ok(copy.found)
}

type FileWriter = McapFile<File>;

/// The copy, compressed as the twin's recordings are.
fn create(out: &Path, profile: &str, library: &str) -> Result<FileWriter> {
    let file = File::create(out).map_err(|source| RecoverError::Create {
        path: out.to_path_buf(),
        source,
    })?;
    McapFile::new(file, profile, library, ZSTD_LEVEL, CHUNK_SIZE).map_err(|source| {
        RecoverError::Start {
            path: out.to_path_buf(),
            source,
        }
    })
}

/// Ids declared so far, and the tally.
#[derive(Default)]
struct Copy {
    schemas: BTreeSet<u16>,
    channels: BTreeSet<u16>,
    found: Recovered,
}

impl Copy {
    /// A declaration the file got wrong (a channel or schema declared twice,
    /// differently) ends the copy there, as a damaged record does: what
    /// came before it is kept. Any other error is the copy's own.
    fn stop_at_fault(&mut self, e: std::io::Error) -> std::io::Result<()> {
        if e.kind() != std::io::ErrorKind::InvalidData {
            return Err(e);
        }
        self.found.stopped = Some(format!(
            "after {} complete chunk(s), {e}",
            self.found.chunks
        ));
        Ok(())
    }

    /// Write `record` into the copy, if it is data (the summary and the
    /// indexes are the writer's to rebuild).
    fn take(&mut self, writer: &mut FileWriter, record: Record<'_>) -> std::io::Result<()> {
        match record {
            Record::Schema { header, data } => {
                writer.add_schema_with_id(header.id, &header.name, &header.encoding, &data)?;
                self.schemas.insert(header.id);
            }
            Record::Channel(c) => {
                // A channel whose schema the file lost is kept without one
                // rather than dropped with its messages.
                let schema = if self.schemas.contains(&c.schema_id) {
                    c.schema_id
                } else {
                    0
                };
                writer.add_channel_with_id(
                    c.id,
                    schema,
                    &c.topic,
                    &c.message_encoding,
                    &c.metadata,
                )?;
                self.channels.insert(c.id);
            }
            Record::Message { header, data } => {
                if self.channels.contains(&header.channel_id) {
                    writer.write_message(
                        header.channel_id,
                        header.sequence,
                        header.log_time,
                        header.publish_time,
                        &data,
                    )?;
                    self.found.messages += 1;
                } else {
                    self.found.strays += 1;
                }
            }
            Record::Metadata(m) => {
                writer.write_metadata(&m.name, &m.metadata)?;
                self.found.metadata += 1;
            }
            Record::Attachment { header, data, .. } => {
                writer.write_attachment(
                    header.log_time,
                    header.create_time,
                    &header.name,
                    &header.media_type,
                    &data,
                )?;
                self.found.attachments += 1;
            }
            _ => {}
        }
        Ok(())
    }
}

enum Stop {
    Io(std::io::Error),
    /// The MCAP reader's error: the file is damaged from here on.
    Damaged(mcap::McapError),
}

/// A record outside the chunks, or a chunk's records (all or, damaged, none).
enum Outer {
    Record(Record<'static>),
    Chunk(mcap::McapResult<Vec<Record<'static>>>),
}

/// The next record of the file outside the chunks (a chunk read whole),
/// reading `source` as the reader asks; `None` where the file ends.
fn next_record(reader: &mut LinearReader, source: &mut File) -> Result<Option<Outer>, Stop> {
    while let Some(event) = reader.next_event() {
        match event.map_err(Stop::Damaged)? {
            LinearReadEvent::ReadRequest(need) => {
                let buf = reader.insert(need);
                let n = loop {
                    match source.read(buf) {
                        Ok(n) => break n,
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                        Err(e) => return Err(Stop::Io(e)),
                    }
                };
                reader.notify_read(n);
            }
            LinearReadEvent::Record { opcode, data } => {
                return match mcap::parse_record(opcode, data).map_err(Stop::Damaged)? {
                    Record::Chunk { header, .. } => Ok(Some(Outer::Chunk(chunk_records(
                        data,
                        header.uncompressed_size,
                    )))),
                    other => Ok(Some(Outer::Record(other.into_owned()))),
                };
            }
        }
    }
    Ok(None)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::read::Recording;
    use crate::read::tests::{damage_chunk, scratch, write};
    use std::collections::BTreeMap;

    /// A file laid out as another writer may lay one out, with its own ids:
    /// schemas 7 and 3, channels 9, 0 (no schema) and 4 (with metadata), a
    /// profile, sequence numbers that skip, publish times apart from log
    /// times, metadata and an attachment between 4 kB chunks.
    fn write_with_own_ids(path: &Path) {
        let file = File::create(path).unwrap();
        let mut w = McapFile::new(file, "x-lab", "a lab's logger", ZSTD_LEVEL, 4096).unwrap();
        let none = BTreeMap::new();
        let rate = BTreeMap::from([("rate_hz".to_string(), "100".to_string())]);
        w.write_metadata("run", &rate).unwrap();
        w.add_schema_with_id(7, "a", "jsonschema", b"{}").unwrap();
        w.add_schema_with_id(3, "b", "jsonschema", b"{\"type\":\"object\"}")
            .unwrap();
        w.add_channel_with_id(9, 7, "/nine", "json", &none).unwrap();
        w.add_channel_with_id(0, 0, "/zero", "json", &none).unwrap();
        w.add_channel_with_id(4, 3, "/four", "json", &rate).unwrap();
        for i in 0..3000u32 {
            let channel = [9, 0, 4][(i % 7 % 3) as usize];
            let data = format!("{{\"i\":{i},\"x\":{}}}", f64::from(i) * 0.37);
            let time = 5_000_000_000 + u64::from(i) * 1_000_000;
            w.write_message(channel, 3 * i + 1, time, time - 250, data.as_bytes())
                .unwrap();
            if i == 900 {
                w.write_attachment(time, 5, "fw.hex", "text/plain", &[b':'; 300])
                    .unwrap();
            }
            if i == 2000 {
                w.write_metadata("checkpoint", &none).unwrap();
            }
        }
        w.finish().unwrap();
    }

    /// Every message of `bytes`: channel id and topic, sequence, log and
    /// publish time, data.
    fn messages(bytes: &[u8]) -> Vec<(u16, String, u32, u64, u64, Vec<u8>)> {
        mcap::MessageStream::new(bytes)
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                let c = &m.channel;
                let data = m.data.into_owned();
                (
                    c.id,
                    c.topic.clone(),
                    m.sequence,
                    m.log_time,
                    m.publish_time,
                    data,
                )
            })
            .collect()
    }

    #[test]
    fn a_copy_is_the_file_itself_up_to_its_last_whole_chunk() {
        let path = scratch("own-ids.mcap");
        write_with_own_ids(&path);
        let full = std::fs::read(&path).unwrap();
        let all = messages(&full);
        // Complete: the same bytes.
        let out = scratch("own-ids-copy.mcap");
        let found = recover(&path, &out).unwrap();
        assert!(found.was_complete);
        assert_eq!((found.messages, found.channels), (3000, 3));
        assert!(std::fs::read(&out).unwrap() == full, "the copy differs");
        // Cut anywhere: the file's own bytes up to its last whole chunk,
        // then the data end and a summary of what the copy holds.
        let cut = scratch("own-ids-cut.mcap");
        let mut counts = BTreeSet::new();
        for at in (full.len() / 10..full.len() * 9 / 10).step_by(full.len() / 9) {
            std::fs::write(&cut, &full[..at]).unwrap();
            let found = recover(&cut, &out).unwrap();
            assert!(!found.was_complete, "cut at {at}");
            let copied = std::fs::read(&out).unwrap();
            let footer = mcap::read::footer(&copied).unwrap();
            let data_end = usize::try_from(footer.summary_start).unwrap() - 13;
            let summary = mcap::Summary::read(&copied).unwrap().unwrap();
            // Then the copy's one record of its own, saying where the run
            // stops, right before the data end.
            let said = summary
                .metadata_indexes
                .iter()
                .find(|m| m.name == topics::RECOVERED_METADATA)
                .expect("the copy says the run was cut");
            let own = usize::try_from(said.offset).unwrap();
            assert_eq!(own + usize::try_from(said.length).unwrap(), data_end);
            assert!(copied[..own] == full[..own], "cut at {at}");
            let stopped = Recording::read(&out).unwrap();
            assert_eq!(stopped.truncated, None, "cut at {at}");
            assert_eq!(stopped.recovered_from_cut(), found.stopped.as_deref());
            assert!(stopped.ends_early(), "cut at {at}");
            let got = messages(&copied);
            assert_eq!(got[..], all[..got.len()], "cut at {at}");
            assert_eq!(got.len() as u64, found.messages);
            counts.insert(got.len());
            assert_eq!(summary.stats.unwrap().message_count, found.messages);
            let mut ids: Vec<_> = summary
                .channels
                .values()
                .map(|c| (c.id, c.schema.as_ref().map(|s| s.id), c.metadata.len()))
                .collect();
            ids.sort();
            assert_eq!(ids, [(0, None, 0), (4, Some(3), 1), (9, Some(7), 0)]);
            let header = mcap::read::LinearReader::new(&copied)
                .unwrap()
                .next()
                .unwrap()
                .unwrap();
            let Record::Header(header) = header else {
                panic!("{header:?}")
            };
            assert_eq!(
                (header.profile.as_str(), header.library.as_str()),
                ("x-lab", "a lab's logger")
            );
        }
        assert_eq!(counts.len(), 8, "each cut in another chunk: {counts:?}");
    }

    #[test]
    fn a_file_that_is_not_mcap_or_holds_nothing_is_refused_with_its_name() {
        let junk = scratch("junk-to-recover.mcap");
        std::fs::write(&junk, b"not a recording").unwrap();
        let e = recover(&junk, &scratch("junk-recovered.mcap")).unwrap_err();
        assert!(matches!(e, RecoverError::NotMcap { .. }), "{e:?}");
        assert_eq!(
            e.to_string(),
            format!(
                "{} is not a recording: it does not start with the MCAP magic bytes",
                junk.display()
            )
        );
        let bare = scratch("bare-to-recover.mcap");
        std::fs::write(&bare, mcap::MAGIC).unwrap();
        let e = recover(&bare, &scratch("bare-recovered.mcap")).unwrap_err();
        assert!(matches!(e, RecoverError::Empty { .. }), "{e:?}");
        assert!(
            e.to_string().ends_with("there is nothing to recover"),
            "{e}"
        );
    }

    #[test]
    fn recover_leaves_a_damaged_chunk_out_and_copies_the_rest() {
        let path = scratch("to-recover.mcap");
        write(&path);
        let damaged = scratch("damaged-for-recover.mcap");
        std::fs::write(&damaged, damage_chunk(&path, 2)).unwrap();
        let whole = scratch("recovered.mcap");
        let found = recover(&damaged, &whole).unwrap();
        assert_eq!(found.damaged_chunks, [2]);
        assert_eq!(found.chunks, 2);
        // Seconds 0 and 2: 200 sensor samples and the events at 0.5 and 2.5 s.
        assert_eq!(found.messages, 202);
        assert_eq!((found.channels, found.metadata, found.strays), (2, 1, 0));
        assert!(found.was_complete, "the data end record is after chunk 3");
        let r = Recording::read(&whole).unwrap();
        assert_eq!(r.truncated, None, "a complete file");
        assert_eq!(r.message_count(), 202);
        assert_eq!(r.run_field("kind"), Some("scenario"));
        // Its summary is there for the indexed readers.
        let bytes = std::fs::read(&whole).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
        assert_eq!(summary.stats.unwrap().message_count, 202);
        let events = r.events().unwrap();
        let times: Vec<f64> = events.iter().map(|e| e.time_s).collect();
        assert_eq!(times, [0.5, 2.5]);
    }

    /// A file that declares channel 1 a second time as another topic (its
    /// channel 2's record, its id overwritten): the copy stops there, says
    /// why in the file's terms, and keeps the messages before it. It was
    /// refused as "cannot write" the copy, whose fault it was not.
    #[test]
    fn a_channel_declared_twice_differently_ends_the_copy_there() {
        let mut w = mcap::WriteOptions::new()
            .use_chunks(false)
            .emit_summary_records(false)
            .create(std::io::Cursor::new(Vec::new()))
            .unwrap();
        let none = BTreeMap::new();
        w.add_channel_with_id(1, 0, "/nine", "json", &none).unwrap();
        for i in 0..5u64 {
            w.write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: 1,
                    sequence: 0,
                    log_time: i,
                    publish_time: i,
                },
                b"{}",
            )
            .unwrap();
        }
        w.add_channel_with_id(2, 0, "/ten!", "json", &none).unwrap();
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: 2,
                sequence: 0,
                log_time: 9,
                publish_time: 9,
            },
            b"{}",
        )
        .unwrap();
        w.finish().unwrap();
        let mut bytes = w.into_inner().into_inner();
        // The second channel record: its id (after the opcode and the
        // length) becomes 1.
        let topic = b"\x05\x00\x00\x00/ten!";
        let at = bytes
            .windows(topic.len())
            .position(|w| w == topic)
            .expect("the second channel");
        bytes[at - 4] = 1;
        let path = scratch("declared-twice.mcap");
        std::fs::write(&path, &bytes).unwrap();

        let out = scratch("declared-twice-copy.mcap");
        let found = recover(&path, &out).unwrap();
        let stopped = found.stopped.unwrap_or_default();
        assert!(
            stopped
                .contains("channel 1 is declared twice, differently (the second time as `/ten!`)"),
            "{stopped}"
        );
        assert_eq!((found.messages, found.channels), (5, 1));
        let copied = std::fs::read(&out).unwrap();
        assert_eq!(messages(&copied).len(), 5);
    }
}
