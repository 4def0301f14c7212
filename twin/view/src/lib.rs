//! Looking at runs in rerun: a recording turned into a rerun recording
//! (`twin view`), or a run streamed live (`twin run --view`), both with a
//! blueprint that shows the bench the way the lab looks at it.
//!
//! The matching viewer is PyPI `rerun-sdk==0.36.3` (the wheel ships `rerun`).

pub mod blueprint;
pub mod layout;
pub mod live;
pub mod logger;
pub mod recording;

use anyhow::{Context, Result};
use std::collections::BTreeMap;
use std::path::Path;

pub use layout::ViewLayout;
pub use live::{RerunObserver, ViewTarget, live_view, open_stream, viewer_available};
pub use logger::RerunLogger;
pub use recording::{ReadSummary, Session};

/// What converting a recording gave.
#[derive(Debug, Clone)]
pub struct Converted {
    pub read: ReadSummary,
    /// Samples logged per rerun entity.
    pub samples: BTreeMap<String, u64>,
}

/// Turn the MCAP recording at `path` into a rerun stream to `target`.
pub fn convert(path: &Path, target: &ViewTarget) -> Result<Converted> {
    let layout = recording::layout_of(path)?;
    let name = path
        .file_stem()
        .map_or_else(|| "twin".into(), |s| s.to_string_lossy().into_owned());
    let observer = RerunObserver::open(target, &name, layout)?;
    let mut logger = observer.logger;
    let read = recording::replay_into(path, &mut logger)
        .with_context(|| format!("cannot read {}", path.display()))?;
    let samples = std::mem::take(&mut logger.samples);
    RerunObserver { logger }.finish()?;
    Ok(Converted { read, samples })
}
