//! Why a recording could not be written: the one error of the recorder and
//! of its writer thread, in a module of its own so that neither imports the
//! other for it.

use crate::disk::DiskNearlyFull;
use std::path::PathBuf;

/// Why a recording could not be written. After any of these but a message
/// refused ([`WriteError::Encode`], [`WriteError::NoChannel`]) the recorder
/// is closed: what it was given before is on disk, whole.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    #[error("cannot create folder {}", path.display())]
    CreateFolder {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot create {}", path.display())]
    Create {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot start MCAP file {}", path.display())]
    Start {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot write {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot finish {}", path.display())]
    Finish {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The disk guard stopped the recording: a session rotating its files
    /// goes on in a new one once space is freed.
    #[error(transparent)]
    DiskFull(#[from] DiskNearlyFull),
    /// `channel` is a topic, or a channel's number where a caller named it
    /// by its id.
    #[error("no channel {channel} in the recording")]
    NoChannel { channel: String },
    /// A message that does not fit its channel (its protobuf schema, or
    /// JSON); the recording goes on without it.
    #[error("cannot record a message on {topic}")]
    Encode {
        topic: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A channel's sample that serde_json cannot write, or its schema.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    #[error("cannot start the recording's writer thread")]
    Thread(#[source] std::io::Error),
    /// The writer thread stopped; its own error comes from finishing it.
    #[error("the recording's writer stopped")]
    WriterStopped,
    #[error("the recording's writer thread failed")]
    WriterPanicked,
    #[error("the recording {} stopped after an earlier error", path.display())]
    Closed { path: PathBuf },
}
