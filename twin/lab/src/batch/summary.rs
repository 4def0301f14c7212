//! An entry's summary: one JSON line in `NAME.json` beside its recording
//! `NAME.mcap`, written whole or not at all (a temporary file renamed into
//! place), so a reader or a retried task never finds half of one. An entry
//! is done when its summary says `"status": "ok"`.

use super::BatchError;

type Result<T, E = BatchError> = std::result::Result<T, E>;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    Ok,
    Failed,
}

/// What one entry's run gave.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Its index in the manifest, from 0.
    pub entry: usize,
    pub name: String,
    pub status: Status,
    /// The scenario as the manifest names it.
    pub scenario: String,
    /// The seed it ran with (`None` when it failed before that was known).
    pub seed: Option<u64>,
    /// Its `--set` changes: path and value.
    pub set: BTreeMap<String, serde_json::Value>,
    pub simulated_s: Option<f64>,
    /// Wall time of the run itself (s).
    pub wall_s: f64,
    /// The recording's file name, in the same folder.
    pub recording: Option<String>,
    /// What users compare: speeds, voltages, step figures, bus counts, by name.
    pub figures: BTreeMap<String, Option<f64>>,
    /// Why it failed.
    pub error: Option<String>,
}

impl Summary {
    /// Where an entry named `name` keeps its summary in `dir`.
    pub fn path(dir: &Path, name: &str) -> PathBuf {
        dir.join(format!("{name}.json"))
    }

    /// Write it as one line to `NAME.json`, replacing what was there only
    /// once it is whole on disk.
    pub fn write(&self, dir: &Path) -> Result<PathBuf> {
        let path = Self::path(dir, &self.name);
        let mut line = serde_json::to_string(self)?;
        line.push('\n');
        write_atomically(&path, line.as_bytes())?;
        Ok(path)
    }

    /// The summary at `path`, `None` when there is none.
    pub fn read(path: &Path) -> Result<Option<Self>> {
        let text = match std::fs::read_to_string(path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => {
                return Err(BatchError::ReadSummary {
                    path: path.to_path_buf(),
                    source,
                });
            }
        };
        let summary =
            serde_json::from_str(text.trim_end()).map_err(|source| BatchError::NotASummary {
                path: path.to_path_buf(),
                source,
            })?;
        Ok(Some(summary))
    }
}

/// A temporary name beside `path` that no other process writing the same
/// file uses (a scheduler may run a task twice at once).
pub fn temporary(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.{}.tmp", std::process::id()))
}

/// Write `bytes` to `path` through a temporary file, synced, then renamed.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = temporary(path);
    let written = (|| -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(BatchError::Write {
            path: path.to_path_buf(),
            source: e,
        });
    }
    Ok(())
}
