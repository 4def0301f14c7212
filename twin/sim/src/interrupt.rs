//! A stop asked from outside a virtual run: Ctrl-C or SIGTERM (the binary's
//! handler calls [`request`]). The engine looks at the flag where it reports
//! progress and, when it is up, stops at the instant it has reached; the run
//! then finishes its recording up to there and returns [`Interrupted`], so
//! that no caller takes a run cut short for a whole one. No signal, no
//! effect: the flag is never up in a run that is not interrupted, so it
//! changes nothing in a deterministic one.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);

/// Ask every virtual run of this process to stop.
pub fn request() {
    REQUESTED.store(true, Ordering::Relaxed);
}

/// Whether a stop has been asked.
pub fn requested() -> bool {
    REQUESTED.load(Ordering::Relaxed)
}

/// A run stopped by [`request`], its recording (if it had one) finished
/// where it stopped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("stopped at {at_s:.3} s of simulated time{}", recording.as_ref().map_or_else(String::new, |r| format!(": the recording {} is complete up to there", r.display())))]
pub struct Interrupted {
    pub at_s: f64,
    pub recording: Option<PathBuf>,
}
