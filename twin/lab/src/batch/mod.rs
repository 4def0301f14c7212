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

pub use manifest::{Entry, Manifest, Selection, scheduler_index};
pub use runner::{Options, Report};
pub use summary::{Status, Summary};
