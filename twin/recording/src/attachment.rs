//! Files a recording carries whole (MCAP attachments): the compiled
//! firmware a run executed, so that `twin-avr replay` runs the very bytes
//! that were recorded, not whatever file is on disk today.

use std::path::{Path, PathBuf};

/// Why a recording's attachments cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum AttachmentError {
    #[error("cannot read {}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} is not an MCAP recording", path.display())]
    NotMcap { path: PathBuf },
}

/// An attachment as stored.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Attachment {
    pub name: String,
    pub media_type: String,
    /// Simulated time it was stored at (ns).
    pub log_time_ns: u64,
    pub data: Vec<u8>,
}

/// What reading a recording's attachments found: those whole, and those
/// whose bytes no longer match their checksum, by name.
#[derive(Debug, Default)]
pub struct Attachments {
    pub whole: Vec<Attachment>,
    pub damaged: Vec<String>,
}

impl Attachments {
    /// The attachment called `name`, if it is whole.
    pub fn get(&self, name: &str) -> Option<&Attachment> {
        self.whole.iter().find(|a| a.name == name)
    }
}

/// Every attachment of the recording at `path`, read through record by
/// record (a recording cut short keeps those before the cut). An
/// attachment whose checksum fails is listed as damaged, not returned.
pub fn read(path: &Path) -> Result<Attachments, AttachmentError> {
    let bytes = std::fs::read(path).map_err(|source| AttachmentError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut found = Attachments::default();
    let Some(mut rest) = bytes.strip_prefix(mcap::MAGIC) else {
        return Err(AttachmentError::NotMcap {
            path: path.to_path_buf(),
        });
    };
    // Record by record: opcode, length, body. Chunks are skipped unopened.
    while rest.len() >= 9 {
        let opcode = rest[0];
        let len = u64::from_le_bytes(rest[1..9].try_into().unwrap_or_default());
        let Some(body) = usize::try_from(len)
            .ok()
            .and_then(|n| rest.get(9..9usize.saturating_add(n)))
        else {
            break;
        };
        if opcode == mcap::records::op::ATTACHMENT {
            match mcap::parse_record(opcode, body) {
                Ok(mcap::records::Record::Attachment { header, data, .. }) => {
                    found.whole.push(Attachment {
                        name: header.name,
                        media_type: header.media_type,
                        log_time_ns: header.log_time,
                        data: data.into_owned(),
                    });
                }
                _ => found.damaged.push(attachment_name(body)),
            }
        }
        if opcode == mcap::records::op::DATA_END {
            break;
        }
        rest = &rest[9 + body.len()..];
    }
    Ok(found)
}

/// The name field of an attachment record's body, as far as it can be read.
fn attachment_name(body: &[u8]) -> String {
    let len = body
        .get(16..20)
        .map(|b| u32::from_le_bytes(b.try_into().unwrap_or_default()) as usize)
        .unwrap_or(0);
    body.get(20..20 + len)
        .map(|n| String::from_utf8_lossy(n).into_owned())
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::record::Recorder;
    use std::collections::BTreeMap;

    #[test]
    fn a_file_attached_reads_back_whole_and_its_damage_is_seen() {
        let dir = std::env::temp_dir().join(format!("twin-attach-{}", std::process::id()));
        let path = dir.join("a.mcap");
        let firmware: Vec<u8> = (0..5000u32).map(|i| (i * 7 % 251) as u8).collect();
        let mut rec = Recorder::create(&path).unwrap();
        rec.write_metadata("twin.run", BTreeMap::new()).unwrap();
        rec.add_channel("/events", &serde_json::json!({"a": 1}))
            .unwrap();
        rec.write("/events", 0.5, &serde_json::json!({"a": 2}))
            .unwrap();
        rec.attach(
            "firmware/ev1.elf",
            "application/x-elf",
            0.0,
            firmware.clone(),
        )
        .unwrap();
        rec.finish().unwrap();

        let found = read(&path).unwrap();
        assert_eq!(found.whole.len(), 1);
        assert_eq!(found.get("firmware/ev1.elf").unwrap().data, firmware);
        // The MCAP library reads it from the summary's index too.
        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        assert_eq!(summary.attachment_indexes.len(), 1);
        assert_eq!(summary.stats.unwrap().attachment_count, 1);
        let a = mcap::read::attachment(&bytes, &summary.attachment_indexes[0]).unwrap();
        assert_eq!(a.data.as_ref(), firmware.as_slice());

        // A byte of the stored file flipped.
        let mut damaged = bytes.clone();
        let at = damaged
            .windows(firmware.len().min(64))
            .position(|w| w == &firmware[..64])
            .unwrap();
        damaged[at + 100] ^= 0x40;
        std::fs::write(&path, &damaged).unwrap();
        let found = read(&path).unwrap();
        assert!(found.whole.is_empty());
        assert_eq!(found.damaged, ["firmware/ev1.elf"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
