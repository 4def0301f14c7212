//! Batch runs (`twin batch`): a manifest of scenario runs (parameter sweeps,
//! seeds, cable lengths), run one entry at a time as a scheduler's array
//! task hands them out (Slurm, Kubernetes Indexed Jobs, AWS Batch, GNU
//! parallel), a shard of them, or all over the local cores; each entry's
//! recording and summary written whole or not at all; the summaries
//! gathered into a CSV and a plot.

pub mod figures;
pub mod manifest;
pub mod runner;
pub mod summarize;
pub mod summary;

use std::path::PathBuf;

pub use manifest::{Entry, Manifest, Selection, scheduler_index};

/// Why a batch, or one of its entries, could not run, or its summaries
/// be gathered.
#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    #[error("cannot read the manifest {}", path.display())]
    ReadManifest {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A line of the manifest that is not JSON, or TOML that does not parse,
    /// in the parser's words.
    #[error("{at}: {message}")]
    Syntax { at: String, message: String },
    #[error("{at}: `scenario` is empty: name an embedded scenario or a scenario file")]
    EmptyScenario { at: String },
    #[error("{at}: `set`: `{set}` is not PATH=VALUE, e.g. node.supervisor.kp=0.6")]
    SetNotPathValue { at: String, set: String },
    #[error(
        "{at}: `out` `{out}` must be a plain file name: not empty, no `/` or `\\`, \
         not starting with `.`"
    )]
    BadOut { at: String, out: String },
    #[error(
        "{at}: `out` `{name}` is also the name of the entry on line {first}: \
         each entry needs its own"
    )]
    SameOut {
        at: String,
        name: String,
        first: usize,
    },
    #[error("entry {index} is past the end: the manifest has {count} entries, 0 to {last}")]
    PastTheEnd {
        index: usize,
        count: usize,
        last: usize,
    },
    #[error("`{text}` is not a shard: write K/N with 0 <= K < N, e.g. 0/4")]
    NotAShard { text: String },
    #[error("{variable} is `{value}`, not an entry index (0, 1, 2, …)")]
    NotAnIndex {
        variable: &'static str,
        value: String,
    },
    #[error("cannot create the folder {}", dir.display())]
    CreateDir {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot start a worker thread")]
    Worker(#[source] std::io::Error),
    #[error("cannot move the recording to {}", path.display())]
    MoveRecording {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("scenario {scenario} failed")]
    ScenarioFailed {
        scenario: String,
        #[source]
        source: twin_sim::virtual_run::RunError,
    },
    #[error("cannot read the folder {}", dir.display())]
    ReadDir {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{} holds no batch summaries (NAME.json): run `twin batch MANIFEST --out {}` first",
        dir.display(),
        dir.display()
    )]
    NoSummaries { dir: PathBuf },
    #[error("no column `{name}` in these summaries; the numeric ones are {numeric}")]
    NoColumn { name: String, numeric: String },
    #[error("no run that succeeded has both `{x}` and `{y}` as numbers: nothing to plot")]
    NothingToPlot { x: String, y: String },
    #[error("cannot read {}", path.display())]
    ReadSummary {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} is not a batch summary line", path.display())]
    NotASummary {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("cannot write {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    #[error(transparent)]
    Scenario(#[from] twin_sim::scenario::ScenarioError),
    #[error(transparent)]
    Replay(#[from] twin_sim::replay::ReplayError),
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
}

impl BatchError {
    /// Whether the run was stopped as asked (Ctrl-C), not failed.
    pub fn interrupted(&self) -> bool {
        matches!(self, BatchError::ScenarioFailed { source, .. } if source.interrupted().is_some())
    }
}
pub use runner::{Options, Report};
pub use summary::{Status, Summary};
