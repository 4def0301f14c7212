//! `twin-avr replay` runs the firmware a recording stored, not the file on
//! disk today: each firmware node's ELF comes out of the recording's
//! attachment, checked against the SHA-256 its metadata gives, with the
//! wiring map it ran with. A recording without them, or whose stored file
//! is damaged, is refused in words.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use twin_recording::attachment::AttachmentError;
use twin_recording::read::ReadError;
use twin_recording::{Reader, attachment, topics};
use twin_sim::replay::RunSpec;
use twin_sim::scenario::NodeSpec;

/// Why a recording's firmware cannot be run again as recorded. `recording`
/// is the file as the user gave it.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Read(#[from] ReadError),
    #[error(transparent)]
    Attachments(#[from] AttachmentError),
    #[error(
        "{recording} holds no firmware for node `{node}` (no `{record}` record): it was recorded \
         by a twin-avr that did not store the firmware it ran, or cut short before it; \
         it cannot be re-run as recorded"
    )]
    NoFirmware {
        recording: String,
        node: String,
        record: String,
    },
    /// The attachment is there, but its bytes fail the MCAP checksum.
    #[error(
        "the firmware {recording} stored for node `{node}` ({file}) is damaged: its bytes \
         no longer match the recording's checksum, so the run cannot be repeated \
         with the firmware that ran"
    )]
    Damaged {
        recording: String,
        node: String,
        file: String,
    },
    #[error(
        "{recording} names firmware `{attachment}` for node `{node}` ({file}) but does not hold \
         it: the recording is cut short or was copied without it; it cannot be re-run \
         as recorded"
    )]
    Missing {
        recording: String,
        node: String,
        attachment: String,
        file: String,
    },
    /// The bytes read whole but are not the file the metadata describes.
    #[error(
        "the firmware {recording} stored for node `{node}` ({file}) is damaged: its SHA-256 \
         is {sha256}, the recording says {recorded}"
    )]
    WrongSha256 {
        recording: String,
        node: String,
        file: String,
        sha256: String,
        recorded: String,
    },
    #[error("cannot create {}", dir.display())]
    CreateDir {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot write {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// A firmware node's file and map as its recording stored them.
#[derive(Debug, Clone)]
pub struct Stored {
    /// The stored bytes, written out for simavr (which reads a path).
    pub elf: PathBuf,
    /// The file as the recording names it.
    pub recorded_file: String,
    pub wiring_origin: String,
    pub wiring_text: String,
}

static STORED: Mutex<BTreeMap<String, Stored>> = Mutex::new(BTreeMap::new());

/// The stored firmware of node `name`, when a replay runs.
pub fn stored(name: &str) -> Option<Stored> {
    STORED.lock().ok()?.get(name).cloned()
}

/// The folder the stored files are written to; removed when dropped.
#[derive(Debug)]
pub struct Extracted {
    dir: PathBuf,
    /// One line per firmware node, for the user.
    pub lines: Vec<String>,
}

impl Drop for Extracted {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Takes every firmware node's file out of `recording`, checks it and
/// hands it to the builder, so the replay runs exactly what was recorded.
pub fn load(recording: &Path) -> Result<Extracted, ReplayError> {
    let shown = recording.display().to_string();
    let mut reader = Reader::open(recording)?.metadata_only();
    while reader.next()?.is_some() {}
    let recorded = reader.finish();
    let dir = std::env::temp_dir().join(format!("twin-avr-replay-{}", std::process::id()));
    let mut extracted = Extracted {
        dir: dir.clone(),
        lines: Vec::new(),
    };
    // Not a scenario (an open loop, a session): twin's replay says what it is.
    let Ok(RunSpec::Scenario(scenario)) = RunSpec::from_recording(&recorded) else {
        return Ok(extracted);
    };
    let nodes: Vec<&str> = scenario
        .nodes
        .iter()
        .filter(|n| matches!(n, NodeSpec::Firmware { .. }))
        .map(NodeSpec::name)
        .collect();
    if nodes.is_empty() {
        return Ok(extracted);
    }
    let attachments = attachment::read(recording)?;
    let mut stored = BTreeMap::new();
    for node in nodes {
        let record = topics::firmware_metadata(node);
        let Some(fields) = recorded.metadata.get(&record) else {
            return Err(ReplayError::NoFirmware {
                recording: shown,
                node: node.into(),
                record,
            });
        };
        let field = |k: &str| fields.get(k).cloned().unwrap_or_default();
        let name = field("attachment");
        let file = field("file");
        let Some(stored_file) = attachments.get(&name) else {
            if attachments.damaged.contains(&name) {
                return Err(ReplayError::Damaged {
                    recording: shown,
                    node: node.into(),
                    file,
                });
            }
            return Err(ReplayError::Missing {
                recording: shown,
                node: node.into(),
                attachment: name,
                file,
            });
        };
        let sha = crate::record::sha256_hex(&stored_file.data);
        if sha != field("sha256") {
            return Err(ReplayError::WrongSha256 {
                recording: shown,
                node: node.into(),
                file,
                sha256: sha,
                recorded: field("sha256"),
            });
        }
        let file_name = Path::new(&file).file_name().map_or_else(
            || "firmware.elf".into(),
            |n| n.to_string_lossy().into_owned(),
        );
        let out = dir.join(node).join(file_name);
        if let Some(parent) = out.parent() {
            std::fs::create_dir_all(parent).map_err(|source| ReplayError::CreateDir {
                dir: parent.to_path_buf(),
                source,
            })?;
        }
        std::fs::write(&out, &stored_file.data).map_err(|source| ReplayError::Write {
            path: out.clone(),
            source,
        })?;
        extracted.lines.push(format!(
            "  firmware of `{node}`: {file} as the recording stored it ({} bytes, SHA-256 {}…, \
             matching its record), {}",
            stored_file.data.len(),
            &sha[..16],
            match field("wiring") {
                w if w.starts_with("wiring map") => w,
                w => format!("wiring map {w}"),
            }
        ));
        stored.insert(
            node.to_string(),
            Stored {
                elf: out,
                recorded_file: file,
                wiring_origin: field("wiring"),
                wiring_text: field("wiring_toml"),
            },
        );
    }
    if let Ok(mut s) = STORED.lock() {
        *s = stored;
    }
    Ok(extracted)
}
