//! Where the twin's slaves wait for the student's master: a serial port or
//! pseudo-terminal (opened at once; the master is on its other end), or a
//! TCP port the twin listens on until the master connects.

use crate::wire::{Wire, WireError};
use std::net::TcpListener;
use std::time::{Duration, Instant};
use twin_realtime::io::{LinkAddr, LinkDefaults, LinkSpec};

/// Why the master's link cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum LineError {
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error("cannot listen on {link}: {why}")]
    Listen { link: String, why: std::io::Error },
    #[error("no master connected to {link} within {seconds} s")]
    NoMaster { link: String, seconds: u64 },
}

/// The twin's end, open and waiting for the master.
#[derive(Debug)]
pub enum MasterLine {
    Listening(TcpListener, String),
    Open(Wire),
}

impl MasterLine {
    /// Opens `link`: listens on a `tcp://` one (port 0: any free port),
    /// opens a serial one.
    pub fn open(link: &str) -> Result<Self, LineError> {
        let spec = LinkSpec::parse(link, &LinkDefaults::default()).map_err(WireError::from)?;
        match spec.addr {
            LinkAddr::Tcp(addr) => {
                let listen = |why| LineError::Listen {
                    link: link.into(),
                    why,
                };
                let listener = TcpListener::bind(addr).map_err(listen)?;
                let bound = listener.local_addr().map_err(listen)?;
                listener.set_nonblocking(true).map_err(listen)?;
                Ok(Self::Listening(listener, format!("tcp://{bound}")))
            }
            LinkAddr::Serial(_) => Ok(Self::Open(Wire::open(link)?)),
        }
    }

    /// The link as the master is told to use it (a listener's real port).
    pub fn shown(&self) -> &str {
        match self {
            Self::Listening(_, link) => link,
            Self::Open(wire) => wire.link(),
        }
    }

    /// The wire to the master: a serial one at once, a TCP one once the
    /// master connects (`wait` at most).
    pub fn connected(self, wait: Duration) -> Result<Wire, LineError> {
        let (listener, link) = match self {
            Self::Open(wire) => return Ok(wire),
            Self::Listening(listener, link) => (listener, link),
        };
        let give_up = Instant::now() + wait;
        loop {
            match listener.accept() {
                Ok((stream, _)) => {
                    let _ = stream.set_nonblocking(false);
                    return Ok(Wire::accepted(stream, &link));
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    if Instant::now() >= give_up {
                        return Err(LineError::NoMaster {
                            link,
                            seconds: wait.as_secs(),
                        });
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
                Err(why) => return Err(LineError::Listen { link, why }),
            }
        }
    }
}
