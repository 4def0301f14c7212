//! The sink thread: records a real-time session to MCAP and prints the live
//! frame monitor, off the engine's thread. Channels of the recording are
//! those of a virtual run (`/plant/<module>/sensors`, `/plant/<module>/actuators`,
//! `/events`) plus `/link/<link>/frames` (both directions) and
//! `/realtime/lateness` (each second: that second's and the total tick
//! lateness). The file is flushed every second, so a crash loses at most one.

use anyhow::Result;
use nodes::node::NodeEvent;
use nodes::proto::modbus;
use nodes::time::SimTime;
use serde_json::{Value, json};
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, Sender, TryRecvError, channel};
use std::thread::JoinHandle;
use std::time::Duration;

use super::lateness::LatenessSummary;
use crate::observe::{McapObserver, decode_frame};
use crate::record::Recorder;
use crate::view::logger::{LatenessSample, PlantSample};
use crate::view::{RerunObserver, Session, ViewLayout, ViewTarget};

/// How often the sink drains its queue (console lines and recording may lag
/// by this much; the engine never waits for them).
const DRAIN_EVERY: Duration = Duration::from_millis(2);

/// Which way a frame went.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// From the peer to the twin.
    Rx,
    /// From the twin to the peer.
    Tx,
}

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
    /// Bytes on a link: a whole frame (tx), or a chunk as read (rx).
    Frame {
        link: usize,
        conn: u64,
        direction: Direction,
        start: SimTime,
        end: SimTime,
        bytes: Vec<u8>,
    },
    Event {
        node: String,
        event: NodeEvent,
    },
    /// A node's internals (a master's loop), recorded on `/master/<node>/loop`.
    Telemetry {
        at: SimTime,
        node: String,
        value: Value,
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
    /// A line for the console (status, a command's answer).
    Say(String),
    /// Store these totals and finish the recording.
    Finish(BTreeMap<String, String>),
}

/// What the sink knows about the session.
#[derive(Debug)]
pub struct SinkConfig {
    pub modules: Vec<String>,
    /// Per link: its name and protocol.
    pub links: Vec<(String, &'static str)>,
    /// Print every frame.
    pub monitor: bool,
    pub recorder: Option<Recorder>,
    /// A live rerun view, fed what is recorded (`--view`).
    pub view: Option<LiveView>,
}

/// A live rerun view of a session, and which role's session it is (so
/// that the link frames' senders get the view's names).
#[derive(Debug)]
pub struct LiveView {
    pub observer: RerunObserver,
    pub session: Session,
}

impl LiveView {
    /// The live view of `role`'s session with `layout` at `target` (as
    /// `twin run --view` takes it), or `None` with the reason on stderr: a
    /// session goes on without its view.
    pub fn open(target: &str, role: &str, layout: ViewLayout, session: Session) -> Option<Self> {
        match crate::view::live_view(&ViewTarget::parse(target), role, layout) {
            Ok(observer) => Some(Self { observer, session }),
            Err(e) => {
                eprintln!("{role} --view: {e:#}; running without the live view");
                None
            }
        }
    }

    fn feed(&mut self, config: &SinkConfig, message: &SinkMsg) {
        let log = &mut self.observer.logger;
        match message {
            SinkMsg::Plant {
                at,
                module,
                sensors,
            } => {
                if let Some(name) = config.modules.get(*module) {
                    log.plant(name, at.as_secs_f64(), &PlantSample::from(&**sensors));
                }
            }
            SinkMsg::Event { node, event } => {
                log.event(node, event.at.as_secs_f64(), event.kind, &event.detail);
            }
            SinkMsg::Telemetry { at, node, value } => {
                log.master_loop(node, at.as_secs_f64(), value);
            }
            SinkMsg::Lateness { at, window, .. } => {
                let sample = LatenessSample {
                    p99_us: window.p99_us,
                    max_us: window.max_us,
                };
                log.lateness(at.as_secs_f64(), &sample);
            }
            SinkMsg::Note {
                at,
                link,
                peer,
                text,
            } => log.event(
                link,
                at.as_secs_f64(),
                "connection",
                &format!("{peer}: {text}"),
            ),
            // Frames come one by one once reassembled (see `run`).
            SinkMsg::Frame { .. }
            | SinkMsg::Actuators { .. }
            | SinkMsg::Say(_)
            | SinkMsg::Finish(_) => {}
        }
    }

    /// One reassembled frame on link `name`, recorded as sent by `from`.
    fn frame(&mut self, name: &str, from: &str, start: SimTime, end: SimTime, bytes: &[u8]) {
        let from = self.session.sender(name, from, bytes);
        self.observer
            .logger
            .frame(name, &from, start.as_secs_f64(), end.as_secs_f64(), bytes);
    }
}

/// What the sink reports when it ends.
#[derive(Debug, Default)]
pub struct SinkOutcome {
    pub recording: Option<PathBuf>,
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
        .spawn(move || run(config, &rx))
        .unwrap_or_else(|e| panic!("cannot start the recording thread: {e}"))
}

/// Reassembles received chunks into frames for display and recording.
#[derive(Default)]
struct Framer {
    buf: Vec<u8>,
    started: Option<SimTime>,
}

/// A received frame is complete when the protocol says so; garbage longer
/// than this is shown as it is.
const MAX_SHOWN: usize = 1024;

impl Framer {
    /// Appends `bytes` and returns the complete frames, with their start.
    fn push(&mut self, protocol: &str, at: SimTime, bytes: &[u8]) -> Vec<(SimTime, Vec<u8>)> {
        if self.buf.is_empty() {
            self.started = Some(at);
        }
        self.buf.extend_from_slice(bytes);
        let mut frames = Vec::new();
        loop {
            let end = match protocol {
                "meb" | "modbus-ascii" => self.buf.iter().position(|&b| b == b'\n').map(|i| i + 1),
                "modbus-tcp" => match self.buf.get(4..6) {
                    Some(&[hi, lo]) => {
                        let total = 6 + usize::from(u16::from_be_bytes([hi, lo]));
                        (self.buf.len() >= total).then_some(total)
                    }
                    _ => None,
                },
                // Binary serial framings: a read on a pty is one frame.
                _ => (!self.buf.is_empty()).then_some(self.buf.len()),
            };
            let end = end.or((self.buf.len() > MAX_SHOWN).then_some(self.buf.len()));
            let Some(end) = end else { break };
            let frame: Vec<u8> = self.buf.drain(..end).collect();
            frames.push((self.started.unwrap_or(at), frame));
            self.started = Some(at);
        }
        frames
    }
}

/// Decoded fields of a frame on a link of `protocol`.
pub fn decode_link_frame(protocol: &str, bytes: &[u8]) -> Value {
    let modbus = |f: Result<modbus::Frame<'_>, modbus::FrameError>| match f {
        Ok(f) => json!({ "protocol": protocol, "unit": f.unit, "function": f.function() }),
        Err(e) => json!({ "protocol": protocol, "error": e.to_string() }),
    };
    match protocol {
        "modbus-tcp" => match modbus::tcp::parse(bytes) {
            Ok(f) => json!({
                "protocol": protocol, "transaction": f.transaction_id, "unit": f.unit,
                "function": f.pdu.first(),
            }),
            Err(e) => json!({ "protocol": protocol, "error": e.to_string() }),
        },
        "modbus-ascii" => modbus(modbus::ascii::parse(
            bytes,
            &mut [0; modbus::ascii::MAX_BINARY_LEN],
        )),
        "modbus-rtu" => modbus(modbus::rtu::parse(bytes)),
        _ => decode_frame(bytes),
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
    let mut observer = config.recorder.take().map(McapObserver::new);
    let mut framers: HashMap<u64, Framer> = HashMap::new();
    let mut last_request: HashMap<u64, SimTime> = HashMap::new();
    let stdout = std::io::stdout();
    let mut failed: Option<anyhow::Error> = None;
    let mut finish = None;
    let mut view = config.view.take();
    loop {
        // Polled on a short timer rather than parked in `recv`: a parked
        // receiver costs the engine thread a futex wake-up, and the cores a
        // context switch, for every frame it sends here (serve-bench: the
        // median Modbus TCP reply latency went from about 45 to 25 µs).
        let message = match rx.try_recv() {
            Ok(message) => message,
            Err(TryRecvError::Empty) => {
                std::thread::sleep(DRAIN_EVERY);
                continue;
            }
            Err(TryRecvError::Disconnected) => break,
        };
        if let Some(v) = &mut view {
            v.feed(&config, &message);
        }
        let mut out = stdout.lock();
        let recorded: Result<()> = match message {
            SinkMsg::Plant {
                at,
                module,
                sensors,
            } => match (&mut observer, config.modules.get(module)) {
                (Some(o), Some(name)) => o.put(&format!("/plant/{name}/sensors"), at, &*sensors),
                _ => Ok(()),
            },
            SinkMsg::Actuators {
                at,
                module,
                actuators,
            } => match (&mut observer, config.modules.get(module)) {
                (Some(o), Some(name)) => o.put(&format!("/plant/{name}/actuators"), at, &actuators),
                _ => Ok(()),
            },
            SinkMsg::Frame {
                link,
                conn,
                direction,
                start,
                end,
                bytes,
            } => {
                let (name, protocol) = config.links.get(link).cloned().unwrap_or_default();
                let frames = match direction {
                    Direction::Rx => framers
                        .entry(conn)
                        .or_default()
                        .push(protocol, start, &bytes),
                    Direction::Tx => vec![(start, bytes)],
                };
                let topic = format!("/link/{name}/frames");
                let mut result = Ok(());
                for (at, frame) in frames {
                    let decoded = decode_link_frame(protocol, &frame);
                    let (arrow, from, after) = match direction {
                        Direction::Rx => {
                            last_request.insert(conn, end);
                            ("<-", format!("client {conn}"), String::new())
                        }
                        Direction::Tx => {
                            let after = last_request.get(&conn).map_or(String::new(), |r| {
                                format!(
                                    "  (+{:.3} ms)",
                                    end.saturating_since(*r).as_secs_f64() * 1e3
                                )
                            });
                            ("->", "twin".to_string(), after)
                        }
                    };
                    if config.monitor {
                        let _ = writeln!(
                            out,
                            "[{:12.6} s] {name} #{conn} {arrow} {}{after}  {decoded}",
                            at.as_secs_f64(),
                            shown(&frame),
                        );
                    }
                    let end = if direction == Direction::Rx { at } else { end };
                    if let Some(v) = &mut view {
                        v.frame(&name, &from, at, end, &frame);
                    }
                    if let Some(o) = &mut observer {
                        result =
                            result.and(o.record_frame(&topic, &from, at, end, &frame, decoded));
                    }
                }
                result
            }
            SinkMsg::Event { node, event } => {
                if config.monitor && event.kind != "log" {
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
            SinkMsg::Telemetry { at, node, value } => match &mut observer {
                Some(o) => o.put(&format!("/master/{node}/loop"), at, &value),
                None => Ok(()),
            },
            SinkMsg::Lateness { at, window, total } => match &mut observer {
                Some(o) => o
                    .put(
                        "/realtime/lateness",
                        at,
                        &json!({ "window": window, "total": total }),
                    )
                    .and_then(|()| o.recorder.flush()),
                None => Ok(()),
            },
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
        let _ = out.flush();
        if let Err(e) = recorded {
            // Keep serving: the session matters more than its recording.
            if failed.is_none() {
                let _ = writeln!(out, "warning: recording stopped: {e:#}");
            }
            failed.get_or_insert(e);
            observer = None;
        }
    }
    let mut outcome = SinkOutcome::default();
    if let Some(v) = view {
        outcome.view_samples = Some(v.observer.logger.samples.values().sum());
        if let Err(e) = v.observer.finish() {
            outcome.view_error = Some(format!("{e:#}"));
        }
    }
    if let Some(mut o) = observer {
        if let Some(totals) = finish {
            o.recorder.write_metadata("twin.realtime", totals)?;
        }
        outcome.frames_recorded = o.frames;
        outcome.events = o.events.clone();
        outcome.recording = Some(o.recorder.finish()?);
    }
    match failed {
        Some(e) => Err(e),
        None => Ok(outcome),
    }
}
