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

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub use layout::ViewLayout;
pub use live::{RerunObserver, ViewTarget, live_view, open_stream, viewer_available};
pub use logger::RerunLogger;
pub use recording::{ReadSummary, Session};

/// Why a recording could not be shown, or a live view opened.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error("{} is not an MCAP recording (it does not start with the MCAP magic bytes)", path.display())]
    NotMcap { path: PathBuf },
    #[error(
        "{} has no `twin.run` metadata record: it was not written by `twin run`, `twin serve` or `twin supervise`",
        path.display()
    )]
    NoRunMetadata { path: PathBuf },
    #[error("{}: the `twin.run` metadata has no `scenario_toml`", path.display())]
    NoScenarioToml { path: PathBuf },
    #[error("{}: the stored plant parameters", path.display())]
    StoredParams {
        path: PathBuf,
        #[source]
        source: toml::de::Error,
    },
    #[error("{}: unknown preset `{preset}`", path.display())]
    UnknownPreset { path: PathBuf, preset: String },
    #[error(
        "{}: the `slaves` of its `twin.run` metadata ({text}) are not slave ids",
        path.display()
    )]
    NotSlaveIds {
        path: PathBuf,
        text: String,
        #[source]
        source: std::num::ParseIntError,
    },
    #[error("{}: unknown recording kind {kind:?} in its `twin.run` metadata", path.display())]
    UnknownKind { path: PathBuf, kind: String },
    /// The recording's messages, which stopped being readable.
    #[error("cannot read {}", path.display())]
    Reading {
        path: PathBuf,
        #[source]
        source: twin_recording::ReadError,
    },
    #[error("field `hex` is not hexadecimal")]
    NotHex,
    #[error(
        "no rerun viewer to open here (`rerun` on PATH and a display). Install one with \
         `pip install rerun-sdk==0.36.3`, or stream to a file with `--view FILE.rrd` and \
         open it later with `rerun FILE.rrd`"
    )]
    NoViewer,
    #[error("cannot open the live view")]
    LiveView(#[source] Box<ViewError>),
    #[error("`{url}`: expected rerun+http://HOST:PORT/proxy")]
    NotAViewerUrl {
        url: String,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "no rerun viewer listens at {authority} (start one with `rerun`, or `rerun --port PORT`)"
    )]
    NotListening { authority: String },
    #[error("cannot create {}", dir.display())]
    CreateDir {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The rerun stream refused to open or to take a message.
    #[error(transparent)]
    Stream(#[from] rerun::RecordingStreamError),
    #[error("the rerun viewer did not take the whole stream")]
    Unflushed(#[source] rerun::sink::SinkFlushError),
    #[error("the rerun sink did not take the data")]
    SinkRefused(#[source] rerun::sink::SinkFlushError),
    #[error(transparent)]
    Scenario(#[from] twin_sim::scenario::ScenarioError),
    #[error(transparent)]
    Read(#[from] twin_recording::ReadError),
}

type Result<T, E = ViewError> = std::result::Result<T, E>;

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
    let read = recording::replay_into(path, &mut logger).map_err(|source| ViewError::Reading {
        path: path.to_path_buf(),
        source,
    })?;
    let samples = std::mem::take(&mut logger.samples);
    RerunObserver { logger }.finish()?;
    Ok(Converted { read, samples })
}
