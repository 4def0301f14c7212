//! The checked program's end of the line: a TCP connection or a serial
//! port (a pseudo-terminal included), opened from a link spec as every
//! link of the twin is (`tcp://HOST:PORT`, `PATH?baud=9600`).

use std::io::{ErrorKind, Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};
use twin_realtime::io::{LinkAddr, LinkDefaults, LinkSpec, Parity};

/// Why the link cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    #[error(transparent)]
    Spec(#[from] twin_realtime::io::spec::LinkSpecError),
    #[error("cannot connect to {link}: {why} (is the program listening there?)")]
    Connect { link: String, why: String },
    #[error("cannot open {link}: {why}")]
    Open { link: String, why: String },
    #[error("{link}: {why}")]
    Io { link: String, why: std::io::Error },
    #[error("{link} closed the connection")]
    Closed { link: String },
}

enum Line {
    Tcp(TcpStream),
    Serial(Box<dyn serialport::SerialPort>),
}

/// An open link to the checked program.
pub struct Wire {
    line: Line,
    link: String,
    started: Instant,
    /// Bytes read while a write waited for room: handed out first by
    /// [`Wire::receive`].
    inbox: Vec<u8>,
}

impl std::fmt::Debug for Wire {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Wire")
            .field("link", &self.link)
            .finish_non_exhaustive()
    }
}

impl Wire {
    /// Opens `link` (`tcp://HOST:PORT`, or a serial path with its options).
    pub fn open(link: &str) -> Result<Self, WireError> {
        let spec = LinkSpec::parse(link, &LinkDefaults::default())?;
        let line = match &spec.addr {
            LinkAddr::Tcp(addr) => {
                let stream =
                    TcpStream::connect_timeout(addr, Duration::from_secs(3)).map_err(|e| {
                        WireError::Connect {
                            link: link.into(),
                            why: refused(&e),
                        }
                    })?;
                let _ = stream.set_nodelay(true);
                Line::Tcp(stream)
            }
            LinkAddr::Serial(path) => {
                let s = &spec.serial;
                let port = serialport::new(path.to_string_lossy(), s.baud)
                    .data_bits(if s.data_bits == 7 {
                        serialport::DataBits::Seven
                    } else {
                        serialport::DataBits::Eight
                    })
                    .parity(match s.parity {
                        Parity::None => serialport::Parity::None,
                        Parity::Even => serialport::Parity::Even,
                        Parity::Odd => serialport::Parity::Odd,
                    })
                    .stop_bits(if s.stop_bits == 2 {
                        serialport::StopBits::Two
                    } else {
                        serialport::StopBits::One
                    })
                    .timeout(Duration::from_millis(10))
                    .open()
                    .map_err(|e| WireError::Open {
                        link: link.into(),
                        why: e.to_string(),
                    })?;
                Line::Serial(port)
            }
        };
        Ok(Self {
            line,
            link: link.into(),
            started: Instant::now(),
            inbox: Vec::new(),
        })
    }

    /// A connection a program made to the twin (a master to its slaves).
    pub(crate) fn accepted(stream: TcpStream, link: &str) -> Self {
        let _ = stream.set_nodelay(true);
        Self {
            line: Line::Tcp(stream),
            link: link.into(),
            started: Instant::now(),
            inbox: Vec::new(),
        }
    }

    /// Seconds since the link was opened: the times of a report.
    pub fn now(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    pub fn link(&self) -> &str {
        &self.link
    }

    pub fn send(&mut self, bytes: &[u8]) -> Result<(), WireError> {
        let result = match &mut self.line {
            Line::Tcp(s) => s.write_all(bytes).and_then(|()| s.flush()),
            Line::Serial(p) => write_patiently(p.as_mut(), bytes, &mut self.inbox),
        };
        result.map_err(|why| self.io(why))
    }

    /// Whatever comes in before `deadline`, appended to `into`; returns as
    /// soon as some bytes came (0 when none came in time).
    pub fn receive(&mut self, into: &mut Vec<u8>, deadline: Instant) -> Result<usize, WireError> {
        if !self.inbox.is_empty() {
            let n = self.inbox.len();
            into.append(&mut self.inbox);
            return Ok(n);
        }
        let mut buf = [0u8; 512];
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(0);
            }
            let slice = left.min(Duration::from_millis(10));
            let read = match &mut self.line {
                Line::Tcp(s) => s
                    .set_read_timeout(Some(slice))
                    .and_then(|()| s.read(&mut buf)),
                Line::Serial(p) => p
                    .set_timeout(slice)
                    .map_err(std::io::Error::other)
                    .and_then(|()| p.read(&mut buf)),
            };
            match read {
                Ok(0) if matches!(self.line, Line::Tcp(_)) => {
                    return Err(WireError::Closed {
                        link: self.link.clone(),
                    });
                }
                Ok(0) => {}
                Ok(n) => {
                    into.extend_from_slice(buf.get(..n).unwrap_or_default());
                    return Ok(n);
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                    ) => {}
                Err(why) => return Err(self.io(why)),
            }
        }
    }

    fn io(&self, why: std::io::Error) -> WireError {
        WireError::Io {
            link: self.link.clone(),
            why,
        }
    }
}

/// How long a write may make no way before the line counts as stuck.
const STUCK: Duration = Duration::from_secs(2);

/// All of `bytes` to a serial port whose reads time out in 10 ms: a write
/// held up by a full line (a program that floods it) is not a failure
/// until it has made no way for 2 s. While it waits it reads into `inbox`:
/// a relay between the two (a `twin vsp` pair) that is itself stuck
/// handing the program's flood to a twin that does not read would
/// otherwise never make room.
fn write_patiently(
    port: &mut dyn serialport::SerialPort,
    bytes: &[u8],
    inbox: &mut Vec<u8>,
) -> std::io::Result<()> {
    let mut left = bytes;
    let mut stuck_since = Instant::now();
    let mut buf = [0u8; 512];
    while !left.is_empty() {
        match port.write(left) {
            Ok(n) if n > 0 => {
                left = left.get(n..).unwrap_or_default();
                stuck_since = Instant::now();
            }
            Ok(_) if stuck_since.elapsed() < STUCK => {}
            Ok(_) => return Err(ErrorKind::TimedOut.into()),
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                ) && stuck_since.elapsed() < STUCK => {}
            Err(e) => return Err(e),
        }
        if !left.is_empty() {
            match port.read(&mut buf) {
                Ok(n) => inbox.extend_from_slice(buf.get(..n).unwrap_or_default()),
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(e),
            }
        }
    }
    port.flush()
}

/// Why a connection failed, as a teacher reads it in a class's scores
/// (`connection refused`, not the OS's error number).
fn refused(e: &std::io::Error) -> String {
    match e.kind() {
        ErrorKind::ConnectionRefused => "connection refused".into(),
        ErrorKind::TimedOut => "no answer within 3 s".into(),
        ErrorKind::HostUnreachable | ErrorKind::NetworkUnreachable => "host unreachable".into(),
        _ => e.to_string(),
    }
}
