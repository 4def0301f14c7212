//! A chunk's records, read whole and checked, and the MCAP reader's errors
//! in a user's words: shared by the reader and by recovery.

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};

/// The MCAP reader's error where a file stops, in a user's words: the record
/// limit is the file's length, so a record longer than it is one cut off.
pub(crate) fn in_words(e: &mcap::McapError) -> String {
    match e {
        mcap::McapError::RecordTooLarge { .. } | mcap::McapError::UnexpectedEof => {
            "its last record is cut off".into()
        }
        other => damage_in_words(other),
    }
}

/// What is wrong with a chunk that does not read, in a user's words.
pub(crate) fn chunk_damage_in_words(e: &mcap::McapError) -> String {
    match e {
        mcap::McapError::RecordTooLarge { .. } | mcap::McapError::UnexpectedEoc => {
            "a record in it claims a length the chunk does not have".into()
        }
        other => damage_in_words(other),
    }
}

/// Any error of the MCAP library in a user's words: never its own text,
/// which names record opcodes and the library's types.
fn damage_in_words(e: &mcap::McapError) -> String {
    use mcap::McapError as E;
    match e {
        E::BadMagic => "it does not begin or end as an MCAP file does".into(),
        E::BadFooter => "its footer is missing".into(),
        E::BadChunkCrc { .. } => "a chunk's checksum does not match its data".into(),
        E::BadDataCrc { .. } | E::BadSummaryCrc { .. } | E::BadAttachmentCrc { .. } => {
            "a checksum does not match its data".into()
        }
        E::BadIndex | E::BadChunkStartOffset(_) => {
            "its index points somewhere other than the records it names".into()
        }
        E::BadAttachmentLength { .. } | E::BadChunkLength { .. } | E::BadSchemaLength { .. } => {
            "a record claims more bytes than it holds".into()
        }
        E::RecordTooLarge { len, .. } => {
            format!("a record claims {len} bytes, more than there are")
        }
        E::ChunkTooLarge(len) => format!("a chunk claims {len} bytes, more than the twin reads"),
        E::Parse(_) => "a record does not read as its kind should".into(),
        E::Io(io) => format!("reading it failed: {io}"),
        E::UnexpectedEof => "it ends in the middle of a record".into(),
        E::UnexpectedEoc => "a chunk ends in the middle of a record".into(),
        E::UnknownChannel(_, channel) => {
            format!("a message is on channel {channel}, which the file never declares")
        }
        E::UnknownSchema(channel, schema) => {
            format!("channel `{channel}` uses schema {schema}, which the file never declares")
        }
        E::InvalidSchemaId => "a schema has the id 0, which MCAP reserves".into(),
        E::ConflictingChannels(name) => format!("channel `{name}` is declared twice, differently"),
        E::ConflictingSchemas(name) => format!("schema `{name}` is declared twice, differently"),
        E::UnsupportedCompression(name) => format!(
            "its chunks are compressed with `{name}`, which the twin does not read (it reads zstd)"
        ),
        E::DecompressionError(_) => "its data do not decompress".into(),
        E::BytesAfterEndMagic => "it has bytes after its end".into(),
        // The rest are the writer's: they name a mistake of ours, not of the file.
        _ => "the MCAP library refused an operation of the twin's (a bug: please report it)".into(),
    }
}

/// No record inside a chunk is taken to be longer than this, whatever a
/// damaged chunk header claims (the twin's chunks hold about 1 MiB).
const MAX_CHUNK_BYTES: u64 = 1 << 30;

/// The records of the chunk whose record body is `body`, decompressed and
/// checked (CRC) whole. No record may claim more than the chunk's
/// uncompressed size: a damaged chunk is an error, not an allocation of
/// whatever length its garbage says.
pub(crate) fn chunk_records(
    body: &[u8],
    uncompressed_size: u64,
) -> mcap::McapResult<Vec<Record<'static>>> {
    let limit = usize::try_from(uncompressed_size.min(MAX_CHUNK_BYTES))
        .unwrap_or(usize::MAX)
        .max(body.len());
    let options = LinearReaderOptions::default()
        .with_skip_start_magic(true)
        .with_skip_end_magic(true)
        .with_validate_chunk_crcs(true)
        .with_record_length_limit(limit);
    let mut reader = LinearReader::new_with_options(options);
    let mut head = [0u8; 9];
    head[0] = mcap::records::op::CHUNK;
    head[1..].copy_from_slice(&(body.len() as u64).to_le_bytes());
    let (mut head, mut body) = (&head[..], body);
    let mut records = Vec::new();
    while let Some(event) = reader.next_event() {
        match event? {
            LinearReadEvent::ReadRequest(need) => {
                let from = if head.is_empty() {
                    &mut body
                } else {
                    &mut head
                };
                let n = need.min(from.len());
                reader.insert(n).copy_from_slice(&from[..n]);
                reader.notify_read(n);
                *from = &from[n..];
            }
            LinearReadEvent::Record { opcode, data } => {
                records.push(mcap::parse_record(opcode, data)?.into_owned());
            }
        }
    }
    Ok(records)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_mcap_library_s_errors_are_told_in_words() {
        use mcap::McapError as E;
        let errors = [
            E::RecordTooLarge {
                opcode: 6,
                len: 1 << 40,
            },
            E::BadMagic,
            E::BadFooter,
            E::BadChunkCrc {
                saved: 1,
                calculated: 2,
            },
            E::BadIndex,
            E::UnexpectedEoc,
            E::UnknownChannel(3, 7),
            E::UnknownSchema("/plant/ev1".into(), 2),
            E::ChunkTooLarge(1 << 40),
            E::UnsupportedCompression("lz4".into()),
            E::DecompressionError("zstd says no".into()),
            E::BytesAfterEndMagic,
        ];
        for e in &errors {
            for words in [in_words(e), chunk_damage_in_words(e)] {
                let library = e.to_string();
                assert_ne!(words, library);
                for jargon in [
                    "opcode",
                    "CRC",
                    "Chunk",
                    "magic",
                    "zstd says",
                    "EOC",
                    "`1099511627776`",
                ] {
                    assert!(!words.contains(jargon), "{e:?}: {words}");
                }
            }
        }
    }
}
