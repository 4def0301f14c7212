//! Replaying a recording's master frames against a live slave: every
//! request a master sent on one bus goes out on a real link (a TCP socket
//! carrying the raw bus bytes, or a serial device / pseudo-terminal), and
//! each reply that comes back is held against the reply recorded after that
//! request.
//!
//! A live slave runs its own plant on its own clock, so replies that carry
//! measurements (speeds, voltages, counters) will differ in their values; a
//! reply that is missing, fails its check, or answers something else (other
//! id, command, function or length) is a real departure. The two are counted
//! apart.

use std::io::{Read, Write};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::time::{Duration, Instant};

use crate::io::spec::LinkSpecError;
use crate::io::{LinkAddr, LinkSpec};
use twin_recording::describe::decode_frame;
use twin_recording::read::ReadError;
use twin_recording::{BusFrame, Recording};
use twin_sim::engine::FrameKind;
use twin_sim::nodes_build::is_master;
use twin_sim::replay::{ReplayError, RunSpec};

/// Why recorded frames could not be sent to a live slave (`twin replay
/// --frames-to`): the link, or the recording.
#[derive(Debug, thiserror::Error)]
pub enum FramesToError {
    #[error(transparent)]
    Spec(#[from] LinkSpecError),
    #[error("cannot connect to {addr} (is the slave serving?)")]
    Connect {
        addr: std::net::SocketAddr,
        #[source]
        source: std::io::Error,
    },
    /// The connection, made, could not be set up to be read and written.
    #[error("cannot set up the connection to {addr}")]
    Socket {
        addr: std::net::SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot open serial device {}", path.display())]
    OpenSerial {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The far end hung up between exchanges, and there is more to send.
    #[error("{link} closed ({why})")]
    ClosedBefore { link: String, why: String },
    #[error("cannot write to {link}")]
    Write {
        link: String,
        #[source]
        source: std::io::Error,
    },
    /// The far end hung up (or failed) while a reply was awaited.
    #[error("{link} closed")]
    Closed {
        link: String,
        #[source]
        source: Option<std::io::Error>,
    },
    #[error("no bus `{bus}` in the recording: it has {buses}")]
    NoSuchBus { bus: String, buses: String },
    #[error("the recording holds no bus frames to replay")]
    NoFrames,
    #[error("the recording has several buses ({buses}): pick one with --bus")]
    SeveralBuses { buses: String },
    #[error("an open-loop recording has no bus frames to replay")]
    OpenLoop,
    #[error("no master on bus `{bus}` in the recorded scenario")]
    NoMaster { bus: String },
    /// The recording's scenario could not be read back.
    #[error(transparent)]
    Replay(#[from] ReplayError),
    /// The recording's frames could not be read.
    #[error(transparent)]
    Read(#[from] ReadError),
}

type Result<T, E = FramesToError> = std::result::Result<T, E>;

/// How long the line must stay quiet after the last byte before a reply that
/// has not passed its check is taken as complete.
const QUIET: Duration = Duration::from_millis(100);

/// A live link: bytes out, and a stream of what comes back (read on a thread
/// so that a reply can be waited for with a timeout on any kind of file).
pub struct Link {
    name: String,
    out: Box<dyn Write + Send>,
    rx: Receiver<std::io::Result<Vec<u8>>>,
    /// Why the far end is gone, once it is.
    closed: Option<String>,
}

impl std::fmt::Debug for Link {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Link").field("name", &self.name).finish()
    }
}

impl Link {
    /// Open `spec`, a link spec of `twin serve`'s grammar ([`LinkSpec`])
    /// without options: `tcp://HOST:PORT`, or the path of a serial device or
    /// pseudo-terminal. A serial device is used as it is configured (set its
    /// baud rate with `stty` first); a pseudo-terminal needs nothing.
    pub fn open(spec: &str) -> Result<Self> {
        let link = LinkSpec::parse_without_options(
            spec,
            "the link is used as it is: set a serial device's baud rate with stty",
        )?;
        match &link.addr {
            LinkAddr::Tcp(addr) => {
                let addr = *addr;
                let stream = std::net::TcpStream::connect(addr)
                    .map_err(|source| FramesToError::Connect { addr, source })?;
                let socket = |source| FramesToError::Socket { addr, source };
                stream.set_nodelay(true).map_err(socket)?;
                let reader = stream.try_clone().map_err(socket)?;
                Ok(Self::from_parts(spec, Box::new(stream), reader))
            }
            LinkAddr::Serial(path) => {
                let open = |source| FramesToError::OpenSerial {
                    path: path.clone(),
                    source,
                };
                let file = std::fs::OpenOptions::new()
                    .read(true)
                    .write(true)
                    .open(path)
                    .map_err(open)?;
                let reader = file.try_clone().map_err(open)?;
                Ok(Self::from_parts(spec, Box::new(file), reader))
            }
        }
    }

    fn from_parts(
        name: &str,
        out: Box<dyn Write + Send>,
        mut reader: impl Read + Send + 'static,
    ) -> Self {
        let (tx, rx) = channel();
        std::thread::spawn(move || {
            let mut buf = [0u8; 512];
            loop {
                match reader.read(&mut buf) {
                    Ok(0) => {
                        let _ = tx.send(Err(std::io::ErrorKind::UnexpectedEof.into()));
                        return;
                    }
                    Ok(n) => {
                        if tx.send(Ok(buf[..n].to_vec())).is_err() {
                            return;
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => {
                        let _ = tx.send(Err(e));
                        return;
                    }
                }
            }
        });
        Self {
            name: name.to_string(),
            out,
            rx,
            closed: None,
        }
    }

    /// Drop whatever arrived unasked. A far end that hung up is noted, not
    /// an error yet: it is one only if there is more to send.
    fn drain(&mut self) -> usize {
        let mut n = 0;
        while let Ok(chunk) = self.rx.try_recv() {
            match chunk {
                Ok(bytes) => n += bytes.len(),
                Err(e) => {
                    self.closed.get_or_insert_with(|| e.to_string());
                    break;
                }
            }
        }
        n
    }

    /// Send `request` and collect the reply: until the bytes pass the check
    /// of `kind`, the line is quiet for a moment after some bytes, or
    /// `timeout` passes with none.
    fn exchange(
        &mut self,
        request: &[u8],
        kind: Option<FrameKind>,
        timeout: Duration,
    ) -> Result<Vec<u8>> {
        if let Some(why) = &self.closed {
            return Err(FramesToError::ClosedBefore {
                link: self.name.clone(),
                why: why.clone(),
            });
        }
        self.out
            .write_all(request)
            .and_then(|()| self.out.flush())
            .map_err(|source| FramesToError::Write {
                link: self.name.clone(),
                source,
            })?;
        let deadline = Instant::now() + timeout;
        let mut reply = Vec::new();
        loop {
            let now = Instant::now();
            let wait = if reply.is_empty() {
                deadline.saturating_duration_since(now)
            } else {
                QUIET.min(deadline.saturating_duration_since(now))
            };
            match self.rx.recv_timeout(wait) {
                Ok(chunk) => {
                    reply.extend(chunk.map_err(|source| FramesToError::Closed {
                        link: self.name.clone(),
                        source: Some(source),
                    })?);
                    if kind.is_some_and(|k| k.passes_check(&reply)) {
                        return Ok(reply);
                    }
                }
                Err(RecvTimeoutError::Timeout) => return Ok(reply),
                Err(RecvTimeoutError::Disconnected) => {
                    return Err(FramesToError::Closed {
                        link: self.name.clone(),
                        source: None,
                    });
                }
            }
        }
    }
}

/// One request and its replies, recorded and live.
#[derive(Debug, Clone, PartialEq)]
pub struct Exchange {
    pub time_s: f64,
    pub request: Vec<u8>,
    /// The first reply recorded after the request, if any.
    pub recorded: Option<Vec<u8>>,
    pub live: Vec<u8>,
    pub verdict: Verdict,
}

/// How a live reply compares with the recorded one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Byte for byte the recorded reply (or no reply, as recorded).
    Same,
    /// The same kind of reply to the same request, other values.
    ValuesDiffer,
    /// A reply was recorded and none came.
    Missing,
    /// A reply came where none was recorded.
    Unexpected,
    /// It fails its check, or answers something else.
    Different,
}

impl std::fmt::Display for Verdict {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Verdict::Same => "as recorded",
            Verdict::ValuesDiffer => "values differ",
            Verdict::Missing => "missing",
            Verdict::Unexpected => "unexpected",
            Verdict::Different => "different",
        })
    }
}

/// What a replay against a live slave found.
#[derive(Debug, Clone, Default)]
pub struct FramesReport {
    pub bus: String,
    pub masters: Vec<String>,
    pub exchanges: Vec<Exchange>,
    /// Bytes that arrived between exchanges, unasked.
    pub stray_bytes: usize,
    /// The run ended right after this many last requests, before any reply
    /// could be recorded: they are not sent, as nothing can be said of them.
    pub cut_off: usize,
}

impl FramesReport {
    pub fn count(&self, v: Verdict) -> usize {
        self.exchanges.iter().filter(|e| e.verdict == v).count()
    }
}

/// The bus to replay: `wanted`, or the recording's only bus.
fn pick_bus(frames: &[BusFrame], wanted: Option<&str>) -> Result<String> {
    let mut buses: Vec<&str> = frames.iter().map(|f| f.bus.as_str()).collect();
    buses.dedup();
    buses.sort_unstable();
    buses.dedup();
    match wanted {
        Some(b) if buses.contains(&b) => Ok(b.to_string()),
        Some(b) => Err(FramesToError::NoSuchBus {
            bus: b.to_string(),
            buses: buses.join(", "),
        }),
        None => match buses.as_slice() {
            [] => Err(FramesToError::NoFrames),
            [one] => Ok(one.to_string()),
            many => Err(FramesToError::SeveralBuses {
                buses: many.join(", "),
            }),
        },
    }
}

/// Replay the master frames of `recording` on `bus` over `link`; at most
/// `limit` requests. `progress` gets the fraction done.
pub fn replay_frames(
    recording: &Recording,
    link: &mut Link,
    bus: Option<&str>,
    timeout: Duration,
    limit: Option<usize>,
    mut progress: impl FnMut(f64),
) -> Result<FramesReport> {
    let RunSpec::Scenario(scenario) = RunSpec::from_recording(recording)? else {
        return Err(FramesToError::OpenLoop);
    };
    let frames = recording.frames()?;
    let bus = pick_bus(&frames, bus)?;
    let masters: Vec<String> = scenario
        .nodes
        .iter()
        .filter(|n| is_master(n) && n.bus() == bus)
        .map(|n| n.name().to_string())
        .collect();
    if masters.is_empty() {
        return Err(FramesToError::NoMaster { bus });
    }
    let on_bus: Vec<&BusFrame> = frames.iter().filter(|f| f.bus == bus).collect();
    let mut requests: Vec<usize> = on_bus
        .iter()
        .enumerate()
        .filter(|(_, f)| masters.contains(&f.from))
        .map(|(i, _)| i)
        .collect();
    // A request that is the last frame on the bus was cut off by the end of
    // the run: whether it got a reply is unknown.
    let cut_off = match requests.last() {
        Some(&i) if i + 1 == on_bus.len() => {
            requests.pop();
            1
        }
        _ => 0,
    };
    requests.truncate(limit.unwrap_or(usize::MAX));
    let mut report = FramesReport {
        bus,
        masters,
        cut_off,
        ..Default::default()
    };
    report.stray_bytes += link.drain();
    for (n, &i) in requests.iter().enumerate() {
        let request = &on_bus[i];
        let recorded = on_bus[i + 1..]
            .iter()
            .take_while(|f| !report.masters.contains(&f.from))
            .map(|f| f.bytes.clone())
            .next();
        let kind = recorded.as_deref().map(FrameKind::of);
        let live = link.exchange(&request.bytes, kind, timeout)?;
        let verdict = judge(recorded.as_deref(), &live);
        report.exchanges.push(Exchange {
            time_s: request.time_s,
            request: request.bytes.clone(),
            recorded,
            live,
            verdict,
        });
        report.stray_bytes += link.drain();
        progress((n + 1) as f64 / requests.len() as f64);
    }
    Ok(report)
}

fn judge(recorded: Option<&[u8]>, live: &[u8]) -> Verdict {
    match recorded {
        None if live.is_empty() => Verdict::Same,
        None => Verdict::Unexpected,
        Some(_) if live.is_empty() => Verdict::Missing,
        Some(r) if r == live => Verdict::Same,
        Some(r) => {
            let kind = FrameKind::of(r);
            if !kind.passes_check(live) || r.len() != live.len() {
                return Verdict::Different;
            }
            // The same header (id, command or function, address, count):
            // only the carried values moved.
            if decode_frame(r).header() == decode_frame(live).header() {
                Verdict::ValuesDiffer
            } else {
                Verdict::Different
            }
        }
    }
}

/// Bytes as a user reads them: text for MEB (line ends escaped), hex otherwise.
pub fn show(bytes: &[u8]) -> String {
    if !bytes.is_empty()
        && bytes
            .iter()
            .all(|b| b.is_ascii_graphic() || *b == b'\n' || *b == b'\r')
    {
        String::from_utf8_lossy(bytes)
            .replace('\n', "\\n")
            .replace('\r', "\\r")
    } else {
        bytes
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect::<Vec<_>>()
            .join(" ")
    }
}
