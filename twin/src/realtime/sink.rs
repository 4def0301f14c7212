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
use serde::Serialize;
use serde_json::{Value, json};
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, Sender, TryRecvError, channel};
use std::thread::JoinHandle;
use std::time::Duration;

pub use super::frame_log::{Direction, FrameBatch};
use super::lateness::LatenessSummary;
use crate::observe::{McapObserver, decode_frame};
use crate::record::Recorder;
use crate::view::logger::{LatenessSample, PlantSample};
use crate::view::{RerunObserver, Session, ViewLayout, ViewTarget};

/// How often the sink drains its queue (console lines and recording may lag
/// by this much; the engine never waits for them).
const DRAIN_EVERY: Duration = Duration::from_millis(2);

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
    /// Bytes on the links: whole frames (tx), chunks as read (rx).
    Frames(FrameBatch),
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
            SinkMsg::Frames(_)
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
        .spawn(move || {
            // Recording and printing can wait (the queue holds them); the
            // links' tasks and the plant cannot. On a machine whose cores are
            // all busy, the kernel now gives them the time first.
            let _ = rustix::process::setpriority_process(None, 10);
            run(config, &rx)
        })
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
    /// Appends `bytes` and hands each complete frame, with its start, to
    /// `frame` (the buffer is reused: nothing is allocated per frame).
    fn push(
        &mut self,
        protocol: &str,
        at: SimTime,
        bytes: &[u8],
        mut frame: impl FnMut(SimTime, &[u8]),
    ) {
        if self.buf.is_empty() {
            self.started = Some(at);
        }
        self.buf.extend_from_slice(bytes);
        let mut taken = 0;
        while let Some(rest) = self.buf.get(taken..).filter(|r| !r.is_empty()) {
            let end = match protocol {
                "meb" | "modbus-ascii" => rest.iter().position(|&b| b == b'\n').map(|i| i + 1),
                "modbus-tcp" => match rest.get(4..6) {
                    Some(&[hi, lo]) => {
                        let total = 6 + usize::from(u16::from_be_bytes([hi, lo]));
                        (rest.len() >= total).then_some(total)
                    }
                    _ => None,
                },
                // Binary serial framings: a read on a pty is one frame.
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

/// Shows and records the frames of the links.
struct FrameSink {
    conns: HashMap<u64, ConnFrames>,
    /// Per link: `/link/<link>/frames`.
    topics: Vec<String>,
}

impl FrameSink {
    fn new(config: &SinkConfig) -> Self {
        Self {
            conns: HashMap::new(),
            topics: config
                .links
                .iter()
                .map(|(name, _)| format!("/link/{name}/frames"))
                .collect(),
        }
    }

    /// Every frame of `batch`: printed if the monitor is on, recorded, viewed.
    fn take(
        &mut self,
        config: &SinkConfig,
        batch: &FrameBatch,
        out: &mut impl Write,
        observer: &mut Option<McapObserver>,
        view: &mut Option<LiveView>,
    ) -> Result<()> {
        if !config.monitor && observer.is_none() && view.is_none() {
            return Ok(());
        }
        let mut result = Ok(());
        for (record, bytes) in batch.iter() {
            let Some((name, protocol)) = config.links.get(record.link) else {
                continue;
            };
            let topic = self.topics.get(record.link).map_or("", String::as_str);
            let conn = record.conn;
            let state = self.conns.entry(conn).or_insert_with(|| ConnFrames {
                client: format!("client {conn}"),
                ..ConnFrames::default()
            });
            let mut show = |at: SimTime, end: SimTime, frame: &[u8], from: &str, after: &str| {
                let arrow = if from == "twin" { "->" } else { "<-" };
                let decoded = (config.monitor || observer.is_some())
                    .then(|| link_frame_fields(protocol, frame));
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
                    v.frame(name, from, at, end, frame);
                }
                if let (Some(o), Some(decoded)) = (observer.as_mut(), decoded) {
                    let recorded = o.record_frame(topic, from, at, end, frame, &decoded);
                    result = std::mem::replace(&mut result, Ok(())).and(recorded);
                }
            };
            match record.direction {
                Direction::Rx => {
                    state.last_request = Some(record.end);
                    let client = &state.client;
                    state
                        .framer
                        .push(protocol, record.start, bytes, |at, frame| {
                            show(at, at, frame, client, "");
                        });
                }
                Direction::Tx => {
                    let after = state.last_request.map_or(String::new(), |r| {
                        let ms = record.end.saturating_since(r).as_secs_f64() * 1e3;
                        format!("  (+{ms:.3} ms)")
                    });
                    let after = if config.monitor { after } else { String::new() };
                    show(record.start, record.end, bytes, "twin", &after);
                }
            }
        }
        result
    }
}

/// Decoded fields of a frame on a link of `protocol`.
pub fn decode_link_frame(protocol: &str, bytes: &[u8]) -> Value {
    serde_json::to_value(link_frame_fields(protocol, bytes)).unwrap_or(Value::Null)
}

/// Decoded fields of a frame on a link, as recorded. A Modbus frame's are a
/// small value (the sink decodes every frame a loaded server answers, and
/// a `Value`'s map cost it more than the decoding); their keys are in the
/// order a `Value` map sorts them, so the JSON is the same either way.
#[derive(Debug, Serialize)]
#[serde(untagged)]
pub enum LinkFrameFields<'a> {
    Modbus {
        function: Option<u8>,
        protocol: &'a str,
        #[serde(skip_serializing_if = "Option::is_none")]
        transaction: Option<u16>,
        unit: u8,
    },
    Broken {
        error: String,
        protocol: &'a str,
    },
    Other(Value),
}

pub fn link_frame_fields<'a>(protocol: &'a str, bytes: &[u8]) -> LinkFrameFields<'a> {
    let modbus = |f: Result<modbus::Frame<'_>, modbus::FrameError>| match f {
        Ok(f) => LinkFrameFields::Modbus {
            function: Some(f.function()),
            protocol,
            transaction: None,
            unit: f.unit,
        },
        Err(e) => LinkFrameFields::Broken {
            error: e.to_string(),
            protocol,
        },
    };
    match protocol {
        "modbus-tcp" => match modbus::tcp::parse(bytes) {
            Ok(f) => LinkFrameFields::Modbus {
                function: f.pdu.first().copied(),
                protocol,
                transaction: Some(f.transaction_id),
                unit: f.unit,
            },
            Err(e) => LinkFrameFields::Broken {
                error: e.to_string(),
                protocol,
            },
        },
        "modbus-ascii" => modbus(modbus::ascii::parse(
            bytes,
            &mut [0; modbus::ascii::MAX_BINARY_LEN],
        )),
        "modbus-rtu" => modbus(modbus::rtu::parse(bytes)),
        _ => LinkFrameFields::Other(decode_frame(bytes)),
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
    let mut frame_sink = FrameSink::new(&config);
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
            SinkMsg::Frames(batch) => {
                let taken = frame_sink.take(&config, &batch, &mut out, &mut observer, &mut view);
                batch.recycle();
                taken
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

#[cfg(test)]
mod tests {
    use super::*;

    fn fields(protocol: &str, bytes: &[u8]) -> String {
        serde_json::to_string(&link_frame_fields(protocol, bytes)).unwrap()
    }

    #[test]
    fn link_frames_decode_to_the_json_a_value_map_gave() {
        // The keys sorted, as a `serde_json::Value` map wrote them.
        let tcp = [0, 7, 0, 0, 0, 6, 1, 4, 0, 0, 0, 10];
        assert_eq!(
            fields("modbus-tcp", &tcp),
            r#"{"function":4,"protocol":"modbus-tcp","transaction":7,"unit":1}"#
        );
        let rtu = [1, 3, 0, 0, 0, 3, 0x05, 0xcb];
        assert_eq!(
            fields("modbus-rtu", &rtu),
            r#"{"function":3,"protocol":"modbus-rtu","unit":1}"#
        );
        let broken = fields("modbus-rtu", &[1, 3, 0, 0, 0, 3, 0, 0]);
        assert!(
            broken.starts_with(r#"{"error":""#)
                && broken.ends_with(r#"","protocol":"modbus-rtu"}"#),
            "{broken}"
        );
        let meb = fields("meb", b"@01EA0006FF*\n");
        assert_eq!(meb, decode_frame(b"@01EA0006FF*\n").to_string());
        assert_eq!(
            decode_link_frame("modbus-tcp", &tcp)["transaction"],
            json!(7)
        );
    }
}
