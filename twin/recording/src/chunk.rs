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
        other => other.to_string(),
    }
}

/// What is wrong with a chunk that does not read, in a user's words.
pub(crate) fn chunk_damage_in_words(e: &mcap::McapError) -> String {
    match e {
        mcap::McapError::DecompressionError(_) => "its data do not decompress".into(),
        mcap::McapError::BadChunkCrc { .. } => "its checksum does not match its data".into(),
        mcap::McapError::RecordTooLarge { .. } | mcap::McapError::UnexpectedEoc => {
            "a record in it claims a length the chunk does not have".into()
        }
        other => other.to_string(),
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
