//! The sink thread: records a real-time session to MCAP and prints the live
//! frame monitor, off the engine's thread. Channels of the recording are
//! those of a virtual run (`/plant/<module>/sensors`, `/plant/<module>/actuators`,
//! `/controller/<module>/readings`, `/events`) plus `/link/<link>/frames` (both directions) and
//! `/realtime/lateness` (each second: that second's and the total tick
//! lateness). The file is flushed every second, so a crash loses at most one.

use nodes::node::NodeEvent;
use protocols::modbus::rtu;
use protocols::modbus::serial::FrameLen;
use protocols::modbus8;
use protocols::time::{SimDuration, SimTime};
use serde_json::{Value, json};
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, Sender, TryRecvError, channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub use super::firmware_log::FirmwareBatch;
pub use super::frame_log::{Direction, FrameBatch};
use super::lateness::LatenessSummary;
use super::rotate::{DiskOutcome, Pruned, Recordings};
use twin_recording::describe::{LinkFrameFields, link_frame_fields};
use twin_recording::record::WriteError;
use twin_recording::topics::{self, LoopReport, ReadingsSample};
use twin_sim::error_text::in_full;
use twin_sim::observe::{LazyChannel, McapObserver, SimRecorder};

type Result<T, E = WriteError> = std::result::Result<T, E>;

/// How often the sink drains its queue (console lines and recording may lag
/// by this much; the engine never waits for them). A busy sink used to
/// drain every 2 ms: half of a polled class's recording threads' time was
/// the kernel's, waking them (a profile of 100 modules at 100 Hz). At
/// 10 ms the queue holds five times as many messages between drains, a
/// few kilobytes per module at 100 requests a second.
const DRAIN_EVERY: Duration = Duration::from_millis(10);
/// The longest a sink that keeps finding its queue empty waits between
/// looks: an idle module's sink then wakes a few times per batch of plant
/// ticks instead of 500 times a second, and the first message after a quiet
/// spell waits at most this long.
const DRAIN_IDLE: Duration = Duration::from_millis(16);
/// A sink that found its queue empty this long parks in `recv`: the
/// engine's next message then costs one wake-up, where looking every 16 ms
/// cost an idle class of 35 modules some 2 000 wake-ups a second.
const PARK_AFTER: Duration = Duration::from_millis(100);

/// What the engine hands the sink.
#[derive(Debug)]
pub enum SinkMsg {
    Plant {
        at: SimTime,
        module: usize,
        sensors: Box<plant::Sensors>,
    },
    Actuators {
        at: SimTime,
        module: usize,
        actuators: plant::Actuators,
    },
    /// A module controller's readings, recorded on
    /// `/controller/<module>/readings` (a session names its controller after
    /// its module: `ev1`).
    Readings {
        at: SimTime,
        module: usize,
        readings: ReadingsSample,
    },
    /// Bytes on the links: whole frames (tx), chunks as read (rx).
    Frames(FrameBatch),
    /// Compiled firmware's UART bursts and I/O samples, recorded on
    /// `/firmware/<node>/uart` and `/firmware/<node>/io`.
    Firmware(FirmwareBatch),
    Event {
        node: String,
        event: NodeEvent,
    },
    /// A node's internals (a master's loop), recorded on `/master/<node>/loop`.
    Telemetry {
        at: SimTime,
        node: String,
        report: LoopReport,
    },
    Lateness {
        at: SimTime,
        window: LatenessSummary,
        total: LatenessSummary,
    },
    /// A connection came or went.
    Note {
        at: SimTime,
        link: String,
        peer: String,
        text: String,
    },
    /// A connection has closed and its frames are all sent: what the sink
    /// kept for it (a half-received request among it) can go.
    Gone(crate::frame_log::ConnId),
    /// A line for the console (status, a command's answer).
    Say(String),
    /// Finish the recording's file and go on in a new one (SIGHUP): why.
    Rotate(String),
    /// When to start new files and which to keep, from now on (a reread
    /// configuration).
    Replan(super::rotate::RecordPlan),
    /// Store these totals and finish the recording.
    Finish(BTreeMap<String, String>),
}

/// What the sink knows about the session.
#[derive(Debug)]
pub struct SinkConfig {
    pub modules: Vec<String>,
    /// Per link: its name, protocol and line silence.
    pub links: Vec<SinkLink>,
    /// Print every frame.
    pub monitor: bool,
    /// The session's recordings and the first file's recorder.
    pub recording: Option<(Recordings, SimRecorder)>,
    /// A live view, fed what is recorded (`--view`).
    pub view: Option<Box<dyn LiveView>>,
}

/// What the sink knows of one link.
#[derive(Debug, Clone)]
pub struct SinkLink {
    pub name: String,
    /// As printed: `meb`, `modbus-tcp`, `modbus-rtu`, `modbus-ascii`, `modbus8`.
    pub protocol: &'static str,
    /// The line quiet that ends a partial frame on a serial link (the
    /// nodes' own rule), so that the frames shown are those they took.
    pub silence: SimDuration,
    /// The twin is the master here: what comes in is a slave's reply.
    pub twin_is_master: bool,
}

/// One frame on a link, with both its parties: `twin`, `client N` (a
/// connection), `slave NN` (on the twin's own bus, by the id the frame
/// carries), `every slave` (a broadcast), `a slave` (a reply too garbled to
/// name its sender).
#[derive(Debug, Clone, Copy)]
pub struct LiveFrame<'a> {
    pub link: &'a str,
    pub from: &'a str,
    pub to: &'a str,
    pub start: f64,
    pub end: f64,
    pub bytes: &'a [u8],
}

/// A live view of a session, fed by the sink what it records. The viewer
/// crate's rerun view is one; the binary opens it and hands it in, so this
/// crate never links rerun.
pub trait LiveView: Send + std::fmt::Debug {
    fn plant(&mut self, module: &str, t: f64, sensors: &plant::Sensors);
    fn event(&mut self, node: &str, t: f64, kind: &str, detail: &str);
    /// A master's loop report, as recorded on `/master/<node>/loop`.
    fn master_loop(&mut self, node: &str, t: f64, report: &Value);
    /// A module controller's readings, as recorded on `/controller/<node>/readings`.
    fn readings(&mut self, node: &str, t: f64, readings: &ReadingsSample);
    /// The engine's tick lateness over the last second.
    fn lateness(&mut self, t: f64, p99_us: f64, max_us: f64);
    /// One reassembled frame.
    fn frame(&mut self, frame: &LiveFrame<'_>);
    /// Close the view: the samples it streamed, and what its viewer did
    /// not take, if anything.
    fn finish(self: Box<Self>) -> (u64, Option<String>);
}

/// Opens a session's live view once the session knows its modules (the
/// view's layout depends on them). Cloned with the options that hold it.
#[derive(Clone)]
pub struct ViewOpener(std::sync::Arc<OpenView>);

/// What a [`ViewOpener`] calls: the session's module names in, the view out.
type OpenView = dyn Fn(&[String]) -> Option<Box<dyn LiveView>> + Send + Sync;

impl ViewOpener {
    /// `open` gets the session's module names and gives the view, or
    /// `None` (having said why on stderr): a session goes on without it.
    pub fn new(
        open: impl Fn(&[String]) -> Option<Box<dyn LiveView>> + Send + Sync + 'static,
    ) -> Self {
        Self(std::sync::Arc::new(open))
    }

    pub fn open(&self, modules: &[String]) -> Option<Box<dyn LiveView>> {
        (self.0)(modules)
    }
}

impl std::fmt::Debug for ViewOpener {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ViewOpener")
    }
}

/// Hand `message` to the live view (frames come one by one once
/// reassembled, see `run`).
fn feed(view: &mut dyn LiveView, config: &SinkConfig, message: &SinkMsg) {
    match message {
        SinkMsg::Plant {
            at,
            module,
            sensors,
        } => {
            if let Some(name) = config.modules.get(*module) {
                view.plant(name, at.as_secs_f64(), sensors);
            }
        }
        SinkMsg::Readings {
            at,
            module,
            readings,
        } => {
            if let Some(name) = config.modules.get(*module) {
                view.readings(name, at.as_secs_f64(), readings);
            }
        }
        SinkMsg::Event { node, event } => {
            view.event(node, event.at.as_secs_f64(), event.kind, &event.detail);
        }
        SinkMsg::Telemetry { at, node, report } => {
            view.master_loop(node, at.as_secs_f64(), &report.to_value());
        }
        SinkMsg::Lateness { at, window, .. } => {
            view.lateness(at.as_secs_f64(), window.p99_us, window.max_us);
        }
        SinkMsg::Note {
            at,
            link,
            peer,
            text,
        } => view.event(
            link,
            at.as_secs_f64(),
            "connection",
            &format!("{peer}: {text}"),
        ),
        SinkMsg::Frames(_)
        | SinkMsg::Firmware(_)
        | SinkMsg::Actuators { .. }
        | SinkMsg::Gone(_)
        | SinkMsg::Say(_)
        | SinkMsg::Rotate(_)
        | SinkMsg::Replan(_)
        | SinkMsg::Finish(_) => {}
    }
}

/// What the sink reports when it ends.
#[derive(Debug, Default)]
pub struct SinkOutcome {
    /// The last file of the recording.
    pub recording: Option<PathBuf>,
    /// The files finished before it (rotated), oldest first.
    pub earlier_files: Vec<PathBuf>,
    pub frames_recorded: u64,
    pub events: BTreeMap<String, u64>,
    /// Samples streamed to the live view, if there was one.
    pub view_samples: Option<u64>,
    /// What the live view's viewer did not take, if anything.
    pub view_error: Option<String>,
}

/// Starts the sink thread.
pub fn spawn(config: SinkConfig) -> (Sender<SinkMsg>, JoinHandle<Result<SinkOutcome>>) {
    let (tx, rx) = channel();
    (tx, spawn_with(config, rx))
}

/// Starts the sink thread on a channel made earlier.
pub fn spawn_with(config: SinkConfig, rx: Receiver<SinkMsg>) -> JoinHandle<Result<SinkOutcome>> {
    std::thread::Builder::new()
        .name("twin-sink".into())
        // The thread keeps the process's priority. At nice 10 it was meant
        // to give the links the cores first, but on a machine whose cores
        // were all busy it never emptied its queue, preempted at every
        // wake-up of the others, and eight recorded clients got 0.80x the
        // rate of eight unrecorded ones where at nice 0 they got 0.91x, the
        // plant's tick lateness alike (docs/measurements.md).
        .spawn(move || run(config, &rx))
        .unwrap_or_else(|e| panic!("cannot start the recording thread: {e}"))
}

/// Reassembles received chunks into frames for display and recording, by
/// the rule the twin's own end of the link frames them with: a line feed
/// (MEB, ASCII), the MBAP length (Modbus TCP), the length a request's
/// header implies (RTU, the 8-byte variant); a partial binary frame that the
/// line's silence ends is shown as it is, as the node dropped it. A chunk
/// split by the writer (a frame written as 4 + 4 bytes) is one frame.
#[derive(Default)]
struct Framer {
    buf: Vec<u8>,
    started: Option<SimTime>,
    /// When the last chunk came.
    last: Option<SimTime>,
}

/// A received frame is complete when the protocol says so; garbage longer
/// than this is shown as it is.
const MAX_SHOWN: usize = 1024;

impl Framer {
    /// Appends `bytes` and hands each complete frame, with its start, to
    /// `frame` (the buffer is reused: nothing is allocated per frame).
    fn push(
        &mut self,
        link: &SinkLink,
        at: SimTime,
        bytes: &[u8],
        mut frame: impl FnMut(SimTime, &[u8]),
    ) {
        let binary = matches!(link.protocol, "modbus8" | "modbus-rtu");
        if binary
            && !self.buf.is_empty()
            && self
                .last
                .is_some_and(|last| at.saturating_since(last) >= link.silence)
        {
            frame(self.started.unwrap_or(at), &self.buf);
            self.buf.clear();
        }
        self.last = Some(at);
        if self.buf.is_empty() {
            self.started = Some(at);
        }
        self.buf.extend_from_slice(bytes);
        let mut taken = 0;
        while let Some(rest) = self.buf.get(taken..).filter(|r| !r.is_empty()) {
            let end = match link.protocol {
                "meb" | "modbus-ascii" => rest.iter().position(|&b| b == b'\n').map(|i| i + 1),
                "modbus-tcp" => match rest.get(4..6) {
                    Some(&[hi, lo]) => {
                        let total = 6 + usize::from(u16::from_be_bytes([hi, lo]));
                        (rest.len() >= total).then_some(total)
                    }
                    _ => None,
                },
                "modbus8" => (rest.len() >= modbus8::FRAME_LEN).then_some(modbus8::FRAME_LEN),
                // The twin is the slave on its RTU links: what it reads are requests.
                "modbus-rtu" => match rtu::frame_len(rtu::Direction::Request, rest) {
                    FrameLen::Known(n) => (rest.len() >= n).then_some(n),
                    FrameLen::NeedAtLeast(_) => None,
                    FrameLen::UntilSilence => Some(rest.len()),
                },
                _ => Some(rest.len()),
            };
            let Some(end) = end.or((rest.len() > MAX_SHOWN).then_some(rest.len())) else {
                break;
            };
            frame(
                self.started.unwrap_or(at),
                rest.get(..end).unwrap_or_default(),
            );
            taken += end;
            self.started = Some(at);
        }
        self.buf.drain(..taken);
    }
}

/// What the sink keeps per connection.
#[derive(Default)]
struct ConnFrames {
    framer: Framer,
    /// Its frames' sender in the recording.
    client: String,
    /// When its last request ended (a reply's delay is shown from there).
    last_request: Option<SimTime>,
}

/// A connection id (a session's counter) hashed by one multiplication:
/// looked up for every frame, where the default hasher (SipHash) cost about
/// as much as the frame's fields.
#[derive(Default)]
struct ConnIdHasher(u64);

impl std::hash::Hasher for ConnIdHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ u64::from(b)).wrapping_mul(FIBONACCI);
        }
    }

    fn write_u64(&mut self, n: u64) {
        self.0 = (self.0 ^ n).wrapping_mul(FIBONACCI);
    }
}

/// 2^64 divided by the golden ratio: spreads a counter over the high bits.
const FIBONACCI: u64 = 0x9E37_79B9_7F4A_7C15;

/// Shows and records the frames of the links.
struct FrameSink {
    conns: HashMap<u64, ConnFrames, std::hash::BuildHasherDefault<ConnIdHasher>>,
    /// Per link: `/link/<link>/frames`.
    channels: Vec<LazyChannel>,
}

impl FrameSink {
    fn new(config: &SinkConfig) -> Self {
        Self {
            conns: HashMap::default(),
            channels: Self::channels(config),
        }
    }

    fn channels(config: &SinkConfig) -> Vec<LazyChannel> {
        config
            .links
            .iter()
            .map(|link| LazyChannel::new(&link.name, topics::link_frames(&link.name)))
            .collect()
    }

    /// Connection `conn` has closed: its reassembly buffer and name go, so
    /// a long session whose clients come and go holds only the connections
    /// still open.
    fn forget(&mut self, conn: u64) {
        self.conns.remove(&conn);
    }

    /// A new file has begun: its channels are made afresh on first use (a
    /// frame half received stays with its connection and goes into the new file).
    fn new_file(&mut self, config: &SinkConfig) {
        self.channels = Self::channels(config);
    }

    /// Every frame of `batch`: printed if the monitor is on, recorded, viewed.
    fn take(
        &mut self,
        config: &SinkConfig,
        batch: &FrameBatch,
        out: &mut impl Write,
        observer: &mut Option<McapObserver>,
        view: &mut Option<Box<dyn LiveView>>,
    ) -> Result<(), WriteError> {
        if !config.monitor && observer.is_none() && view.is_none() {
            return Ok(());
        }
        let mut result = Ok(());
        for (record, bytes) in batch.iter() {
            let (Some(link), Some(channel)) = (
                config.links.get(record.link),
                self.channels.get_mut(record.link),
            ) else {
                continue;
            };
            let (name, protocol) = (&link.name, link.protocol);
            let conn = record.conn;
            let state = self.conns.entry(conn).or_insert_with(|| ConnFrames {
                client: format!("client {conn}"),
                ..ConnFrames::default()
            });
            let viewing = view.is_some();
            // A frame is decoded once: to name its slave, or for the
            // monitor and the recording, whichever asks first.
            let mut show = |at: SimTime,
                            end: SimTime,
                            frame: &[u8],
                            fields: Option<LinkFrameFields<'_>>,
                            from: &str,
                            to: &str,
                            after: &str| {
                let arrow = if from == "twin" { "->" } else { "<-" };
                let decoded = (config.monitor || observer.is_some())
                    .then(|| fields.unwrap_or_else(|| link_frame_fields(protocol, frame)));
                if config.monitor {
                    let shown_decoded = decoded
                        .as_ref()
                        .and_then(|d| serde_json::to_string(d).ok())
                        .unwrap_or_default();
                    let _ = writeln!(
                        out,
                        "[{:12.6} s] {name} #{conn} {arrow} {}{after}  {shown_decoded}",
                        at.as_secs_f64(),
                        shown(frame),
                    );
                }
                if let Some(v) = view.as_mut() {
                    v.frame(&LiveFrame {
                        link: name,
                        from,
                        to,
                        start: at.as_secs_f64(),
                        end: end.as_secs_f64(),
                        bytes: frame,
                    });
                }
                if let (Some(o), Some(decoded)) = (observer.as_mut(), decoded) {
                    let recorded = o.record_frame(channel, from, at, end, frame, &decoded);
                    result = std::mem::replace(&mut result, Ok(())).and(recorded);
                }
            };
            match record.direction {
                Direction::Rx => {
                    state.last_request = Some(record.end);
                    let client = &state.client;
                    state.framer.push(link, record.start, bytes, |at, frame| {
                        if link.twin_is_master {
                            // A slave's reply on the twin's bus: the slave
                            // it names, not the port's connection.
                            let fields = link_frame_fields(protocol, frame);
                            let from = match fields.node_id() {
                                Some(id) => format!("slave {id:02}"),
                                None => "a slave".to_string(),
                            };
                            show(at, at, frame, Some(fields), &from, "twin", "");
                        } else {
                            show(at, at, frame, None, client, "twin", "");
                        }
                    });
                }
                Direction::Tx => {
                    // Only the monitor shows it: not formatted for the recording.
                    let after = match state.last_request.filter(|_| config.monitor) {
                        Some(r) => {
                            let ms = record.end.saturating_since(r).as_secs_f64() * 1e3;
                            format!("  (+{ms:.3} ms)")
                        }
                        None => String::new(),
                    };
                    // A slave's reply goes back on the connection that
                    // asked; the twin's request as a master, to the slave
                    // it addresses. Named only for a live view: the
                    // recording's frames carry their sender alone.
                    let fields = (link.twin_is_master && viewing)
                        .then(|| link_frame_fields(protocol, bytes));
                    let to = match (&fields, viewing) {
                        (_, false) => String::new(),
                        (Some(f), true) => match f.node_id() {
                            Some(0) => "every slave".to_string(),
                            Some(id) => format!("slave {id:02}"),
                            None => "a slave".to_string(),
                        },
                        (None, true) => state.client.clone(),
                    };
                    show(record.start, record.end, bytes, fields, "twin", &to, &after);
                }
            }
        }
        result
    }
}

/// The frame as the monitor shows it: text for MEB and ASCII, hex otherwise.
fn shown(bytes: &[u8]) -> String {
    let printable = bytes
        .iter()
        .all(|b| b.is_ascii_graphic() || *b == b' ' || *b == b'\r' || *b == b'\n');
    if printable {
        String::from_utf8_lossy(bytes).trim_end().to_string()
    } else {
        bytes
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

fn run(mut config: SinkConfig, rx: &Receiver<SinkMsg>) -> Result<SinkOutcome> {
    let (mut files, first) = match config.recording.take() {
        Some((files, first)) => (Some(files), Some(first)),
        None => (None, None),
    };
    let mut observer = first.map(McapObserver::new);
    let mut past = PastFiles::default();
    // The session time of the last message that carried one.
    let mut last_at = SimTime::ZERO;
    let mut frame_sink = FrameSink::new(&config);
    let stdout = std::io::stdout();
    let mut failed: Option<WriteError> = None;
    let mut finish = None;
    let mut view = config.view.take();
    let mut drain_every = DRAIN_EVERY;
    // When the queue was first found empty, in this quiet spell.
    let mut empty_since: Option<Instant> = None;
    loop {
        // Polled on a short timer rather than parked in `recv`: a parked
        // receiver costs the engine thread a futex wake-up, and the cores a
        // context switch, for every frame it sends here (serve-bench: the
        // median Modbus TCP reply latency went from about 45 to 25 µs).
        let message = match rx.try_recv() {
            Ok(message) => {
                drain_every = DRAIN_EVERY;
                empty_since = None;
                message
            }
            Err(TryRecvError::Empty) => {
                let since = *empty_since.get_or_insert_with(Instant::now);
                if since.elapsed() < PARK_AFTER {
                    std::thread::sleep(drain_every);
                    drain_every = (drain_every * 2).min(DRAIN_IDLE);
                    continue;
                }
                match rx.recv() {
                    Ok(message) => {
                        drain_every = DRAIN_EVERY;
                        empty_since = None;
                        message
                    }
                    Err(_) => break,
                }
            }
            Err(TryRecvError::Disconnected) => break,
        };
        if let Some(v) = &mut view {
            feed(v.as_mut(), &config, &message);
        }
        let mut out = stdout.lock();
        let mut rotate = None;
        let recorded: Result<(), WriteError> = match message {
            SinkMsg::Plant {
                at,
                module,
                sensors,
            } => {
                last_at = at;
                match (&mut observer, config.modules.get(module)) {
                    (Some(o), Some(name)) => o.record(at, name, &*sensors),
                    _ => Ok(()),
                }
            }
            SinkMsg::Actuators {
                at,
                module,
                actuators,
            } => match (&mut observer, config.modules.get(module)) {
                (Some(o), Some(name)) => o.record(at, name, &actuators),
                _ => Ok(()),
            },
            SinkMsg::Readings {
                at,
                module,
                readings,
            } => match (&mut observer, config.modules.get(module)) {
                (Some(o), Some(name)) => o.record(at, name, &readings),
                _ => Ok(()),
            },
            SinkMsg::Frames(batch) => {
                let taken = frame_sink.take(&config, &batch, &mut out, &mut observer, &mut view);
                batch.recycle();
                taken
            }
            SinkMsg::Firmware(batch) => {
                let written = match &mut observer {
                    Some(o) => batch
                        .iter()
                        .try_for_each(|(node, record)| o.record_firmware(node, record)),
                    None => Ok(()),
                };
                batch.recycle();
                written
            }
            SinkMsg::Event { node, event } => {
                // A slip is said beside the status lines (see the engine).
                if config.monitor && event.kind != "log" && event.kind != "slip" {
                    let _ = writeln!(
                        out,
                        "[{:12.6} s] {node}: {} {}",
                        event.at.as_secs_f64(),
                        event.kind,
                        event.detail
                    );
                }
                match &mut observer {
                    Some(o) => o.record_event(&node, &event),
                    None => Ok(()),
                }
            }
            SinkMsg::Telemetry { at, node, report } => match &mut observer {
                Some(o) => o.record(at, &node, &report),
                None => Ok(()),
            },
            SinkMsg::Lateness { at, window, total } => {
                last_at = at;
                match &mut observer {
                    Some(o) => {
                        let written = o
                            .put(
                                topics::REALTIME_LATENESS,
                                at,
                                &json!({ "window": window, "total": total }),
                            )
                            .and_then(|()| o.recorder.flush());
                        // Once a second, with the file just flushed: its size is known.
                        rotate = files.as_ref().and_then(|f| f.due(at));
                        written
                    }
                    None => {
                        resume(
                            &mut files,
                            &mut observer,
                            &mut frame_sink,
                            &config,
                            at,
                            &mut out,
                        );
                        Ok(())
                    }
                }
            }
            SinkMsg::Gone(conn) => {
                frame_sink.forget(conn);
                Ok(())
            }
            SinkMsg::Replan(plan) => {
                if let Some(f) = &mut files {
                    f.update(plan);
                }
                Ok(())
            }
            SinkMsg::Rotate(reason) => {
                match (&files, &observer) {
                    (Some(_), Some(_)) => rotate = Some(reason),
                    (Some(f), None) => {
                        let _ = writeln!(
                            out,
                            "{reason}: no recording to rotate (stopped at {})",
                            f.current().display()
                        );
                    }
                    (None, _) => {
                        let _ = writeln!(out, "{reason}: this session does not record");
                    }
                }
                Ok(())
            }
            SinkMsg::Note {
                at,
                link,
                peer,
                text,
            } => {
                let _ = writeln!(out, "[{:12.6} s] {link} {peer}: {text}", at.as_secs_f64());
                let event = NodeEvent {
                    at,
                    kind: "connection",
                    detail: format!("{peer}: {text}"),
                };
                match &mut observer {
                    Some(o) => o.record_event(&link, &event),
                    None => Ok(()),
                }
            }
            SinkMsg::Say(line) => {
                let _ = writeln!(out, "{line}");
                Ok(())
            }
            SinkMsg::Finish(totals) => {
                finish = Some(totals);
                break;
            }
        };
        let recorded = match (recorded, rotate, &mut files) {
            (Ok(()), Some(reason), Some(f)) => rotate_file(
                &mut observer,
                f,
                &mut past,
                &mut frame_sink,
                &config,
                last_at,
                &reason,
                &mut out,
            ),
            (recorded, _, _) => recorded,
        };
        if let Err(e) = recorded {
            if let Some(o) = observer.take() {
                past.add(&o);
            }
            match &mut files {
                // A service's recording goes on in a new file, after the
                // old ones the retention rules let go.
                Some(f) if matches!(e, WriteError::DiskFull(_)) => {
                    let _ = writeln!(
                        out,
                        "warning: recording {}: {}",
                        f.current().display(),
                        in_full(&e)
                    );
                    match f.disk_full(last_at) {
                        DiskOutcome::Resumed(recorder, pruned) => {
                            say_pruned(&mut out, &pruned);
                            let _ =
                                writeln!(out, "recording: going on in {}", f.current().display());
                            observer = Some(McapObserver::new(*recorder));
                            frame_sink.new_file(&config);
                        }
                        DiskOutcome::Paused(pruned, error) => {
                            say_pruned(&mut out, &pruned);
                            let _ = writeln!(
                                out,
                                "warning: recording paused until the disk has {} MB free{}{}",
                                super::rotate::resume_free() / (1024 * 1024),
                                if f.keeps_some() {
                                    ""
                                } else {
                                    " (no --keep-files, --keep-age or --keep-size: no old recording is deleted)"
                                },
                                error
                                    .map(|e| format!(": {}", in_full(&e)))
                                    .unwrap_or_default()
                            );
                        }
                    }
                }
                _ => {
                    // Keep serving: the session matters more than its recording.
                    if failed.is_none() {
                        let _ = writeln!(out, "warning: recording stopped: {}", in_full(&e));
                    }
                    failed.get_or_insert(e);
                }
            }
        }
        let _ = out.flush();
    }
    let mut outcome = SinkOutcome::default();
    if let Some(v) = view {
        let (samples, error) = v.finish();
        outcome.view_samples = Some(samples);
        outcome.view_error = error;
    }
    if let Some(mut o) = observer {
        if let Some(totals) = finish {
            o.recorder
                .write_metadata(topics::REALTIME_METADATA, totals)?;
        }
        past.add(&o);
        outcome.recording = Some(o.recorder.finish()?);
    } else if let Some(f) = &files {
        outcome.recording = Some(f.current().to_path_buf());
    }
    outcome.frames_recorded = past.frames;
    outcome.events = past.events;
    if let Some(f) = files {
        outcome.earlier_files = f.finished;
    }
    match failed {
        Some(e) => Err(e),
        None => Ok(outcome),
    }
}

/// What the files finished so far recorded, for the session's last lines.
#[derive(Debug, Default)]
struct PastFiles {
    frames: u64,
    events: BTreeMap<String, u64>,
}

impl PastFiles {
    fn add(&mut self, o: &McapObserver) {
        self.frames += o.frames;
        for (kind, n) in &o.events {
            *self.events.entry(kind.clone()).or_default() += n;
        }
    }
}

/// Finishes the current file (its summary written, and a `twin.part` record
/// naming the next) and opens the next; says so, and what the retention
/// rules deleted. Called between two messages: each is in exactly one file.
#[allow(
    clippy::too_many_arguments,
    reason = "the sink loop's state, lent for one step"
)]
fn rotate_file(
    observer: &mut Option<McapObserver>,
    files: &mut Recordings,
    past: &mut PastFiles,
    frame_sink: &mut FrameSink,
    config: &SinkConfig,
    at: SimTime,
    reason: &str,
    out: &mut impl Write,
) -> Result<()> {
    let Some(mut o) = observer.take() else {
        return Ok(());
    };
    let next = files.next_path();
    o.recorder
        .write_metadata(topics::PART_METADATA, files.part_end(reason, &next))?;
    past.add(&o);
    o.frames = 0;
    o.events.clear();
    let done = o.recorder.finish()?;
    let (recorder, pruned) = files.rotate(at)?;
    *observer = Some(McapObserver::new(recorder));
    frame_sink.new_file(config);
    let _ = writeln!(
        out,
        "recording: {} finished ({reason}); recording to {}",
        done.display(),
        files.current().display()
    );
    say_pruned(out, &pruned);
    Ok(())
}

/// While the recording waits for disk space: a new file once there is some.
fn resume(
    files: &mut Option<Recordings>,
    observer: &mut Option<McapObserver>,
    frame_sink: &mut FrameSink,
    config: &SinkConfig,
    at: SimTime,
    out: &mut impl Write,
) {
    let Some(f) = files.as_mut() else { return };
    match f.retry(at) {
        Some(Ok(recorder)) => {
            *observer = Some(McapObserver::new(recorder));
            frame_sink.new_file(config);
            let _ = writeln!(
                out,
                "recording: the disk has room again; recording to {}",
                f.current().display()
            );
        }
        Some(Err(e)) => {
            let _ = writeln!(out, "warning: recording still paused: {}", in_full(&e));
        }
        None => {}
    }
}

fn say_pruned(out: &mut impl Write, pruned: &[Pruned]) {
    for p in pruned {
        let _ = writeln!(
            out,
            "recording: deleted {} ({:.1} MB; {})",
            p.path.display(),
            p.bytes as f64 / 1e6,
            p.reason
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame_log::{Direction, FrameBatch, FrameRecord};

    fn received(conn: u64, bytes: &[u8], batch: &mut FrameBatch) {
        let at = SimTime::ZERO;
        let record = FrameRecord {
            link: 0,
            conn,
            direction: Direction::Rx,
            start: at,
            end: at,
        };
        batch.push(record, bytes);
    }

    #[test]
    fn a_closed_connection_is_forgotten_and_the_others_kept() {
        let config = SinkConfig {
            modules: Vec::new(),
            links: vec![SinkLink {
                name: "modbus".into(),
                protocol: "modbus-tcp",
                silence: SimDuration::ZERO,
                twin_is_master: false,
            }],
            monitor: true,
            recording: None,
            view: None,
        };
        let mut sink = FrameSink::new(&config);
        let request = [0, 7, 0, 0, 0, 6, 1, 4, 0, 0, 0, 10];
        let mut batch = FrameBatch::default();
        for conn in 1..=100 {
            received(conn, &request, &mut batch);
        }
        // The last one hangs up halfway through a request.
        received(101, &request[..5], &mut batch);
        let mut shown = Vec::new();
        sink.take(&config, &batch, &mut shown, &mut None, &mut None)
            .unwrap();
        let shown = String::from_utf8(shown).unwrap();
        assert_eq!(shown.lines().count(), 100, "{shown}");
        assert_eq!(sink.conns.len(), 101);
        for conn in 2..=101 {
            sink.forget(conn);
        }
        assert_eq!(sink.conns.keys().collect::<Vec<_>>(), [&1]);
        // A connection still open goes on being reassembled.
        let mut batch = FrameBatch::default();
        received(1, &request[..3], &mut batch);
        received(1, &request[3..], &mut batch);
        let mut shown = Vec::new();
        sink.take(&config, &batch, &mut shown, &mut None, &mut None)
            .unwrap();
        assert!(String::from_utf8(shown).unwrap().contains("modbus #1 <-"));
    }
}
