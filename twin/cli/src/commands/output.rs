//! Where commands write. A run replaces a file of the same name, as `cargo
//! build` its target and `cp` its destination do, so that running a command
//! again just works; but it says so, with what the file held, so that nobody
//! loses a long run to a short one unawares. Real-time sessions, which a
//! service may restart at any moment, are named by their start time unless
//! given a name, so a restart never writes over the last session.

use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};
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

/// A real-time session's recording when none is named: `serve-2026-12-03T07-35-44.mcap`
/// (the start time, UTC), with `-2`, `-3`, … should that name be taken.
pub fn session_recording(command: &str) -> PathBuf {
    let secs = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let stem = format!("{command}-{}", utc_stamp(secs));
    let mut path = PathBuf::from(format!("{stem}.mcap"));
    let mut n = 2;
    while path.exists() {
        path = PathBuf::from(format!("{stem}-{n}.mcap"));
        n += 1;
    }
    path
}

/// `2026-12-03T07-35-44` for a time in seconds since 1970 (UTC), with
/// hyphens for colons, which some file systems refuse.
fn utc_stamp(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rest = secs % 86_400;
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}-{:02}-{:02}",
        rest / 3600,
        rest / 60 % 60,
        rest % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_are_utc_dates() {
        assert_eq!(utc_stamp(0), "1970-01-01T00-00-00");
        assert_eq!(utc_stamp(951_782_400), "2000-02-29T00-00-00");
        assert_eq!(utc_stamp(1_796_283_344), "2026-12-03T07-35-44");
    }
}
