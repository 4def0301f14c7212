//! Real links: TCP sockets, serial ports and pseudo-terminals, as tokio byte
//! streams. A link is named by a spec (`tcp://127.0.0.1:5020`,
//! `/tmp/ttyV1?baud=9600&parity=E&stop=2`), parsed by [`LinkSpec::parse`].

pub mod serial;
pub mod tcp;

use std::net::SocketAddr;
use std::path::PathBuf;

/// The link grammar, from `protocols` (serve-bench reads it too).
pub use protocols::link as spec;

pub use spec::{LinkAddr, LinkDefaults, LinkSpec, Parity, SerialSettings};

/// Why a link could not be opened: a serial port or pseudo-terminal, or a
/// TCP listener. Each says what to do about it where there is something.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error(
        "serial port {} does not exist; if it is a pseudo-terminal that another program \
         creates (twin vsp, socat), start that program first, or pass --wait-for-ports",
        path.display()
    )]
    NoSuchPort { path: PathBuf },
    #[error("serial port path {} is not valid UTF-8", path.display())]
    NotUtf8 { path: PathBuf },
    #[error("cannot open serial port {} at {settings}", path.display())]
    Serial {
        path: PathBuf,
        settings: SerialSettings,
        #[source]
        source: tokio_serial::Error,
    },
    /// A stop (SIGTERM, SIGINT) came while `--wait-for-ports` waited.
    #[error("stopped ({signal}) while waiting for {} to appear", path.display())]
    StoppedWaiting { signal: &'static str, path: PathBuf },
    #[error(
        "cannot listen on tcp://{addr}: the port is in use (choose another, or port 0 for any free one)"
    )]
    PortInUse { addr: SocketAddr },
    #[error("cannot listen on tcp://{addr}: no such local address (127.0.0.1 is the default)")]
    NoSuchAddress { addr: SocketAddr },
    #[error("cannot listen on tcp://{addr}")]
    Listen {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
}
