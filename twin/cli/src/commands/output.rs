//! Where commands write. A run replaces a file of the same name, as `cargo
//! build` its target and `cp` its destination do, so that running a command
//! again just works; but it says so, with what the file held, so that nobody
//! loses a long run to a short one unawares. Real-time sessions, which a
//! service may restart at any moment, are named by their start time unless
//! given a name, so a restart never writes over the last session.

use std::path::Path;
use twin_recording::Reader;
use twin_recording::identity::Identity;

/// What was at a path before a command wrote there.
#[derive(Debug, Clone)]
pub struct Earlier {
    /// What the file held, for a recording: `a scenario run of ev-meb, seed 1, 10.0 s`.
    held: Option<String>,
}

impl Earlier {
    /// What is at `path` now, before writing there; `None` when nothing is.
    /// Call it before the command writes.
    pub fn at(path: &Path) -> Option<Self> {
        if !path.is_file() {
            return None;
        }
        let is_recording = path.extension().is_some_and(|e| e == "mcap");
        Some(Self {
            held: is_recording.then(|| recording_held(path)),
        })
    }

    /// ` (replaced the one there before: …)`, to follow the path written.
    pub fn note(earlier: Option<&Self>) -> String {
        match earlier {
            None => String::new(),
            Some(Self { held: None }) => " (replaced the one there before)".into(),
            Some(Self { held: Some(held) }) => {
                format!(" (replaced the one there before: {held})")
            }
        }
    }
}

/// What the recording at `path` held, read from its metadata alone.
fn recording_held(path: &Path) -> String {
    // Reading through a long session's file would hold the command up.
    const READ_UP_TO: u64 = 256 << 20;
    let size = std::fs::metadata(path).map_or(0, |m| m.len());
    if size > READ_UP_TO {
        return format!("a recording of {} MB", size >> 20);
    }
    let Ok(mut reader) = Reader::open(path).map(Reader::metadata_only) else {
        return "not a readable recording".into();
    };
    while let Ok(Some(_)) = reader.next() {}
    Identity::of(reader.recording()).describe()
}
