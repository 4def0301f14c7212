//! The disk guard: a recording stops, closed with its summary, before it
//! fills the disk it is on. A full disk would cut the file anywhere and
//! starve every other program of the machine; a recording stopped in time
//! is whole up to where it stopped, and the run says why.

use std::path::{Path, PathBuf};

/// Free space below which a recording stops: room for its summary and for
/// the rest of the machine. `TWIN_MIN_FREE_DISK_MB` sets another.
pub const DEFAULT_MIN_FREE_BYTES: u64 = 256 * 1024 * 1024;

/// The variable that sets the free space to keep, in MB (MiB).
pub const MIN_FREE_VAR: &str = "TWIN_MIN_FREE_DISK_MB";

/// Look at the disk again after this many bytes handed to the writer (the
/// file grows by less: chunks are compressed).
const CHECK_EVERY_BYTES: usize = 4 * 1024 * 1024;

/// When the free space of a recording's disk was looked at, and the floor.
#[derive(Debug)]
pub(crate) struct DiskGuard {
    folder: PathBuf,
    min_free: u64,
    since_check: usize,
}

impl DiskGuard {
    /// The guard of a recording at `path`; it looks at the disk at the
    /// first batch.
    pub(crate) fn new(path: &Path) -> Self {
        let folder = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        // Named in the error as a user finds it, not as `.`.
        let folder = std::fs::canonicalize(&folder).unwrap_or(folder);
        Self {
            folder,
            min_free: min_free_bytes(),
            since_check: CHECK_EVERY_BYTES,
        }
    }

    /// After `bytes` more were handed to the writer: an error saying so if
    /// the disk now has less free space than the floor.
    pub(crate) fn wrote(&mut self, bytes: usize) -> Result<(), DiskNearlyFull> {
        self.since_check += bytes;
        if self.since_check < CHECK_EVERY_BYTES {
            return Ok(());
        }
        self.since_check = 0;
        // A disk whose free space cannot be read is not taken for full.
        let Some(free) = free_bytes(&self.folder) else {
            return Ok(());
        };
        if free < self.min_free {
            return Err(DiskNearlyFull {
                folder: self.folder.clone(),
                free,
                min_free: self.min_free,
            });
        }
        Ok(())
    }
}

/// The free space a recording leaves on its disk: [`DEFAULT_MIN_FREE_BYTES`]
/// or what `TWIN_MIN_FREE_DISK_MB` says.
pub fn min_free_bytes() -> u64 {
    std::env::var(MIN_FREE_VAR)
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .map_or(DEFAULT_MIN_FREE_BYTES, |mb| mb.saturating_mul(1024 * 1024))
}

/// The bytes free to an unprivileged writer on the disk holding `folder`
/// (`None` if that cannot be read).
pub fn free_bytes(folder: &Path) -> Option<u64> {
    let stat = rustix::fs::statvfs(folder).ok()?;
    Some(stat.f_bavail.saturating_mul(stat.f_frsize))
}

/// The error a recording stops with when its disk is nearly full.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "the disk holding {} has {} MB free, under the {} MB a recording leaves free: \
     the recording was stopped and closed, whole up to there; free some space, \
     record to another disk (--out), or set {MIN_FREE_VAR}",
    folder.display(),
    free / (1024 * 1024),
    min_free / (1024 * 1024)
)]
pub struct DiskNearlyFull {
    pub folder: PathBuf,
    pub free: u64,
    pub min_free: u64,
}
