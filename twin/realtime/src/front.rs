//! The connections' side of the real-time engine, shared between the engine
//! thread and the link tasks: the devices (their register images), every
//! connection's endpoint and reply queue, the fault in force and the
//! counters, behind one mutex.
//!
//! Why shared: handing each request to the engine thread and its reply back
//! cost two thread switches per request (two thirds of `twin serve`'s time,
//! by perf). Now the task that read a request locks the front, lets the
//! connection's endpoint answer it from the image and writes the reply
//! itself; the lock is held for the microseconds of one request. The engine
//! thread locks it for a firmware loop tick (inputs updated, stored writes
//! applied: a write is acknowledged at once and takes effect at the next
//! tick, as before) and for the timers (turnaround, pacing, RTU silence,
//! partial-frame timeout), never across a plant step.
//!
//! Nothing here allocates per request: replies go into the connection's
//! [`Outgoing`], which its task empties into its own, and the frames for
//! the recording and monitor into one [`FrameLog`] batch that the engine
//! hands the sink once per pass of its loop.

use nodes::link::{JunkSource, frame_id, other_id, set_id, split_point, spoil_check};
use nodes::node::MAX_FRAME;
use protocols::time::{SimDuration, SimTime};
use std::collections::{BTreeMap, VecDeque};
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex, MutexGuard};

use super::clock::{CATCH_UP, RtClock};
use super::config::{LinkConfig, LinkFault};
use super::device::Device;
use super::endpoint::Endpoint;
use super::frame_log::{Backlog, Direction, FrameLog, FrameRecord};
use super::frame_log::{ConnId, Outgoing};
use super::sink::SinkMsg;
use super::wake::Wake;
use tokio::sync::mpsc::UnboundedSender;

/// The engine's tick.
pub(super) const TICK: SimDuration = SimDuration::from_millis(1);

/// Counters for the status line and the summary.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct RtCounters {
    pub bytes_in: u64,
    pub bytes_out: u64,
    pub frames_out: u64,
    pub connections: u64,
    pub closed_partial_timeout: u64,
    pub closed_rate_limit: u64,
    pub closed_idle: u64,
    pub closed_for_room: u64,
    pub replies_faulted: u64,
}

/// A reply waiting for its turnaround or its wire time; its bytes are the
/// next `len` of the connection's `queued_bytes`.
pub(super) struct Queued {
    start: SimTime,
    due: SimTime,
    len: usize,
    /// The first write of a split reply: its end is not the reply's.
    part: bool,
}

/// What a connection needs of its link's configuration (copied at open, so
/// the link tasks never touch the links, whose factories stay on the engine
/// thread).
#[derive(Clone)]
pub(super) struct Rules {
    serial: crate::io::SerialSettings,
    turnaround: SimDuration,
    pace: bool,
    check: Option<nodes::link::CheckKind>,
    partial_timeout: Option<SimDuration>,
    rate_limit: Option<u64>,
    idle_timeout: Option<SimDuration>,
}

pub(super) struct Conn {
    pub(super) link: usize,
    pub(super) peer: String,
    pub(super) endpoint: Box<dyn Endpoint>,
    task: LinkTask,
    /// Frames due, for the task to write (its `ready` tells it when the
    /// engine's timers put some there).
    due: Outgoing,
    rules: Rules,
    queue: VecDeque<Queued>,
    queued_bytes: Vec<u8>,
    line_free: SimTime,
    partial_since: Option<SimTime>,
    rate_window: SimTime,
    rate_bytes: u64,
    /// Let in beyond a full listener's limit, since then: see [`Probation`].
    probation: Option<(Probation, SimTime)>,
    /// When it last sent bytes of a frame, whole or partial (or opened):
    /// noise outside any frame does not count, so a connection that sends
    /// only that ages out and makes room as a quiet one does.
    last_rx: SimTime,
    /// The frames handed to the carrier and not yet reported written, in
    /// order, when the endpoint [`reports_writes`](Endpoint::reports_writes).
    unwritten: VecDeque<Unwritten>,
}

/// A frame handed to its carrier, until the carrier says it is written.
#[derive(Debug, Clone, Copy)]
struct Unwritten {
    /// Its time on the wire (a paced link's), before the write that ends it.
    wire: SimDuration,
    /// The first write of a split reply: its end is not the reply's.
    part: bool,
}

/// The shared state. The engine keeps its fields as its own between runs
/// (console commands and set-up see them there, see [`Front::take`]).
#[derive(Default)]
pub struct Front {
    pub(super) devices: Vec<Device>,
    pub(super) conns: BTreeMap<ConnId, Conn>,
    /// The fault in force, and the link it is limited to (all if `None`).
    pub(super) fault: Option<(LinkFault, Option<usize>)>,
    pub(super) counters: RtCounters,
    /// Link names, for notes.
    names: Vec<String>,
    sink: Option<Sender<SinkMsg>>,
    frames: FrameLog,
    clock: Option<RtClock>,
    buf: Vec<u8>,
    /// Random junk for the `fault junk N` replies.
    junk: JunkSource,
    ids: Vec<ConnId>,
    /// The session time the engine has ticked the plants and the firmware
    /// up to (its next tick), and the clock's slips since it last took them.
    pub(super) ticked_to: SimTime,
    pub(super) slips: Slips,
    /// The time the clock was held at when it last slipped: a slip before
    /// the ticks have caught up to it is the same stall, seen again.
    last_slip: Option<SimTime>,
    /// How far ahead of `ticked_to` a time may be before the clock slips
    /// (see [`crate::RtEngine::set_catch_up`]).
    pub(super) catch_up: SimDuration,
    /// The engine's next tick: the plants and the firmware have run every
    /// tick before it (`ticked_to` is the tick the engine waits for, the
    /// last of a batch while it sleeps through one).
    pub(super) plant_to: SimTime,
    /// Whether the engine sleeps through a batch of ticks: then a request
    /// that finds the plant behind asks for it first ([`After::Behind`]).
    pub(super) batching: bool,
    /// When the last bytes came on any connection, and how long after the
    /// ones before: the engine ticks every millisecond while requests come
    /// faster than [`BUSY_GAP`].
    pub(super) last_request: SimTime,
    pub(super) request_gap: SimDuration,
    /// [`BUSY_GAP`], or `TWIN_RT_BUSY_GAP_US` (a knob for measuring).
    busy_gap: SimDuration,
}

/// Requests closer together than this keep the engine ticking every
/// millisecond rather than in batches. A request that finds the plant
/// behind ticks it on its own thread, holding the engine; clients polling
/// as fast as they can would do that every millisecond, eight at a time
/// contending for the engine: batching them too (`TWIN_RT_BUSY_GAP_US=0`,
/// a knob for measuring) served 0.93-1.06 / 1.13-1.16 times tokio-modbus's
/// rate at one / eight clients, against 1.02-1.10 / 1.20-1.30 times at
/// 2 ms (`serve-bench --requests 5000`, release builds, alternated).
pub(super) const BUSY_GAP: SimDuration = SimDuration::from_millis(2);

/// Slips of the clock: how many, and the nanoseconds lost in all.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct Slips {
    pub(super) count: u64,
    pub(super) ns: u64,
}

/// Where a connection stands once its due frames are taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum After {
    /// Nothing pending: only new bytes can bring frames, so a TCP
    /// connection's thread may block in `recv`.
    Idle,
    /// It waits for a deadline of the engine's timers (a turnaround,
    /// pacing, the RTU silence, a partial frame's timeout): the engine must
    /// be woken to look at the deadlines again, and it will wake the
    /// carrier when the frames are due.
    Timers,
    /// Frames may come without new bytes or a deadline, from an endpoint
    /// whose replies wait on something else (a supervisor's, on the bus):
    /// the engine's passes, every tick, find them and wake the carrier.
    Waiting,
    /// It owes [`OWED_MAX`] replies or more that wait for the engine's
    /// timers (a client pipelining requests on a paced link): the carrier
    /// reads nothing more until the engine's wake-ups have let some go, so
    /// every request is answered, in order, and the queue stays bounded.
    Owing,
    /// The twin closed it: a `Close` is on the carrier's channel.
    Closed,
    /// Nothing was taken: the engine sleeps through a batch of ticks and
    /// the plant is more than a tick behind the bytes' arrival. The carrier
    /// ticks it up to that arrival itself ([`FrontHandle::catch_up`]) and
    /// hands the same bytes, with the same arrival, again, so the request
    /// is answered from the plant of its arrival, never from a batch ago.
    Behind,
}

/// A newcomer let in beyond a full listener's `--max-clients` because a
/// client there could make room (quiet for `min_idle`, or holding a partial
/// frame). It earns that client's place with its first whole request (a
/// partial frame must have been held over [`ROOM_AFTER_PARTIAL`] by then);
/// one that sends none within [`PROBATION`], or holds half a frame as long
/// as that, is closed. So a client in place is displaced only by one that
/// has shown it speaks the protocol: connections that never finish a frame
/// (slowloris, reconnecting as fast as they are closed) displace nobody,
/// one another included, and a real client gets through (`serve` with 100
/// of them beside it: 17 of 17 newcomers served, `docs/measurements.md`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Probation {
    pub max: usize,
    pub min_idle: Option<SimDuration>,
}

/// Newcomers a link keeps on probation at once; the one there longest
/// makes way for the next (it has been there longest without a request).
pub const ON_PROBATION_MAX: usize = 64;

/// Replies a connection may owe before its carrier stops reading.
pub const OWED_MAX: usize = 64;

/// How long a partial frame must have been held for its connection to make
/// room for a newcomer that has sent a whole request, on a full listener. A
/// frame's pieces over TCP come milliseconds apart; a frame typed by hand
/// in a terminal takes longer, and is displaced only when the listener is
/// full and a client that speaks the protocol is waiting. Slowloris clients
/// that reconnect before a second is up used to keep every place this fresh
/// (the threshold was 1 s) and lock everyone out.
pub const ROOM_AFTER_PARTIAL: SimDuration = SimDuration::from_millis(100);

/// How long a newcomer on [`Probation`] has to send a whole request.
pub const PROBATION: SimDuration = SimDuration::from_secs(1);

impl After {
    /// Whether the carrier must listen for the engine's wake-ups.
    pub fn listens(self) -> bool {
        matches!(self, After::Timers | After::Waiting | After::Owing)
    }

    /// Whether the carrier may read the connection's bytes.
    pub fn reads(self) -> bool {
        self != After::Owing
    }
}

/// A link task's handle on the front (sent to it when its connection
/// opens), and on the engine's plant for a request that finds it behind.
#[derive(Clone)]
pub struct FrontHandle {
    front: Arc<Mutex<Front>>,
    plant: Option<Arc<dyn CatchUp>>,
}

/// The engine's plant, ticked up to a request's arrival on its carrier's
/// thread ([`After::Behind`]). The engine is locked before the front
/// whenever both are: a carrier holds neither when it asks.
pub(super) trait CatchUp: Send + Sync {
    /// Ticks the plant and the firmware up to `at` (not beyond: the reply
    /// reads the plant of its arrival), if it is behind.
    fn catch_up(&self, at: SimTime, front: &FrontHandle);
}

impl std::fmt::Debug for Front {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Front")
            .field("devices", &self.devices.len())
            .field("connections", &self.conns.len())
            .finish_non_exhaustive()
    }
}

impl std::fmt::Debug for FrontHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FrontHandle")
    }
}

impl Conn {
    /// The earliest instant this connection needs the engine's timers at:
    /// its endpoint's timer, its next queued reply, its partial-frame timeout.
    fn next_deadline(&self, devices: &[Device]) -> Option<SimTime> {
        let partial = self
            .partial_since
            .and_then(|since| Some(since + self.rules.partial_timeout?));
        [
            self.endpoint.poll_timeout(devices),
            self.queue.front().map(|q| q.due),
            partial,
        ]
        .into_iter()
        .flatten()
        .min()
    }
}

impl FrontHandle {
    /// A handle on `front`, whose requests that find the plant behind
    /// catch it up through `plant`.
    pub(super) fn new(front: Front, plant: Option<Arc<dyn CatchUp>>) -> Self {
        Self {
            front: Arc::new(Mutex::new(front)),
            plant,
        }
    }

    /// The front, locked. A task that panicked holding it left whole state
    /// (every update is a few field writes), so poisoning is ignored.
    pub(super) fn lock(&self) -> MutexGuard<'_, Front> {
        self.front.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Bytes read at `at` on connection `conn`, answered on the caller's
    /// thread: the replies due now are added to `out`. A carrier that can
    /// wait for the engine (`may_wait`: a TCP connection's thread) is told
    /// [`After::Behind`] instead, taking nothing, when the engine sleeps
    /// through a batch and has not ticked the plant to `at`; the others
    /// (serial ports' tasks, on the links' runtime) never are, and their
    /// engine never batches ([`Front::answers_at_once`]).
    pub fn receive(
        &self,
        conn: ConnId,
        at: SimTime,
        bytes: &[u8],
        may_wait: bool,
        out: &mut Outgoing,
    ) -> After {
        let mut guard = self.lock();
        let front = &mut *guard;
        let at = front.hold_clock(at);
        if may_wait && front.behind(at) && front.conns.contains_key(&conn) {
            return After::Behind;
        }
        front.request_gap = at.saturating_since(front.last_request);
        front.last_request = at;
        front.receive(conn, at, bytes);
        front.take_due(conn, out)
    }

    /// Ticks the plant up to `at`, the arrival of a request that found it
    /// behind ([`After::Behind`]); the caller hands its bytes again. Must
    /// not be called holding the front.
    pub fn catch_up(&self, at: SimTime) {
        if let Some(plant) = &self.plant {
            plant.catch_up(at, self);
        }
    }

    /// Adds the frames the engine's timers made due on `conn` to `out`.
    pub fn take_due(&self, conn: ConnId, out: &mut Outgoing) -> After {
        self.lock().take_due(conn, out)
    }

    /// The carrier of `conn` wrote `frames` (which [`Outgoing::reports`])
    /// at `at`: they are recorded as written then, and the endpoint told
    /// its transmission has ended; the frames that follow are added to `out`.
    pub fn written(
        &self,
        conn: ConnId,
        at: SimTime,
        frames: &Outgoing,
        out: &mut Outgoing,
    ) -> After {
        let mut guard = self.lock();
        let front = &mut *guard;
        let at = front.hold_clock(at);
        front.written(conn, at, frames);
        front.take_due(conn, out)
    }

    /// The count of frames shipped to the sink and not yet recorded.
    pub fn backlog(&self) -> Backlog {
        self.lock().backlog()
    }
}

impl Front {
    /// The count of frames shipped to the sink and not yet recorded.
    pub(super) fn backlog(&self) -> Backlog {
        self.frames.backlog()
    }

    pub(super) fn new(sink: Sender<SinkMsg>, clock: RtClock, links: &[LinkConfig]) -> Self {
        Self {
            names: links.iter().map(|l| l.name.clone()).collect(),
            sink: Some(sink),
            clock: Some(clock),
            buf: vec![0; MAX_FRAME],
            catch_up: CATCH_UP,
            request_gap: BUSY_GAP,
            busy_gap: std::env::var("TWIN_RT_BUSY_GAP_US")
                .ok()
                .and_then(|v| v.trim().parse::<u64>().ok())
                .map_or(BUSY_GAP, SimDuration::from_micros),
            ..Self::default()
        }
    }

    /// Whether a request that came at `at` would find the plant more than
    /// a tick behind it because the engine sleeps through a batch: the
    /// tick before the one due at `at` has not run. (A tick that is merely
    /// late, the engine awake, is answered as it stands, as it always was.)
    fn behind(&self, at: SimTime) -> bool {
        self.batching && at >= self.plant_to + TICK
    }

    /// Whether the engine may sleep through a batch of ticks while these
    /// connections are open (and none has a deadline): each is carried by
    /// a thread that can wait for the plant to be caught up
    /// ([`After::Behind`]), answers from the image when its bytes come (no
    /// reply waiting on a bus or a sketch: [`Endpoint::answers_later`]),
    /// and wants no firmware loop run between the ticks. A serial port, a
    /// supervisor's clients and a sketch's UART keep the engine ticking
    /// every millisecond, as they always had it.
    pub(super) fn answers_at_once(&self) -> bool {
        self.conns.values().all(|c| {
            matches!(c.task.wake, Wake::Thread(_))
                && !c.endpoint.answers_later()
                && c.endpoint.follow(&self.devices).is_none()
        })
    }

    /// Whether requests come faster than [`BUSY_GAP`] (the last two closer
    /// than it, the last less than it before `now`).
    pub(super) fn requests_busy(&self, now: SimTime) -> bool {
        self.request_gap < self.busy_gap && now.saturating_since(self.last_request) < self.busy_gap
    }

    fn take_due(&mut self, conn: ConnId, out: &mut Outgoing) -> After {
        let devices = &self.devices;
        match self.conns.get_mut(&conn) {
            None => After::Closed,
            Some(c) => {
                c.due.move_to(out);
                if c.queue.len() >= OWED_MAX {
                    After::Owing
                } else if c.next_deadline(devices).is_some() {
                    After::Timers
                } else if c.endpoint.answers_later() {
                    After::Waiting
                } else {
                    After::Idle
                }
            }
        }
    }

    /// The time `at` (read from the clock before the lock was taken) on
    /// the clock as it stands, slipping the clock first if `at` is further
    /// ahead of the engine's ticks than it catches up in a burst: after a
    /// stall, whoever looks first (the engine, or a carrier with the bytes
    /// that came meanwhile) holds the session's time back, so no node is
    /// handed a time beyond what the plant and the firmware will step
    /// through in order.
    pub(super) fn hold_clock(&mut self, at: SimTime) -> SimTime {
        let Some(clock) = &self.clock else {
            return at;
        };
        // Stamped before an earlier slip: it came at most now.
        let at = at.min(clock.now());
        let ahead = at.saturating_since(self.ticked_to);
        if ahead <= self.catch_up {
            return at;
        }
        let slip = SimDuration(ahead.0 - self.catch_up.0);
        clock.slip(slip);
        let held = SimTime(at.0 - slip.0);
        // While the engine still runs the ticks up to the last slip, every
        // look at the clock (a carrier's bytes, a timer) finds it ahead by
        // the microseconds since: the same stall, not another (one stall
        // of 300 ms was counted as several slips).
        if self.last_slip.is_none_or(|last| self.plant_to > last) {
            self.slips.count += 1;
        }
        self.last_slip = Some(held);
        self.slips.ns += slip.0 / (protocols::time::TICKS_PER_SECOND / 1_000_000_000);
        held
    }

    fn now(&self) -> SimTime {
        self.clock.as_ref().map_or(SimTime::ZERO, |c| c.now())
    }

    /// The session's time now, the clock held first (see
    /// [`Front::hold_clock`]): what the endpoints' timers and frames are
    /// stamped with. A time read across a stall the clock has not yet
    /// slipped for would count the stall as time that passed, and lie
    /// ahead of every time stamped after the slip.
    fn held_now(&mut self) -> SimTime {
        let now = self.now();
        self.hold_clock(now)
    }

    fn send(&self, message: SinkMsg) {
        if let Some(sink) = &self.sink {
            let _ = sink.send(message);
        }
    }

    /// Hands the frames logged so far to the sink (the engine calls it on
    /// every pass of its loop, so they reach the sink within a tick).
    pub(super) fn ship_frames(&mut self) {
        if let Some(batch) = self.frames.take()
            && let Some(sink) = &self.sink
        {
            let _ = sink.send(SinkMsg::Frames(batch));
        }
    }

    /// A line about a connection, after the frames it follows.
    pub(super) fn note(&mut self, link: usize, peer: &str, text: &str) {
        self.ship_frames();
        let name = self.names.get(link).map_or("?", |l| l.as_str());
        self.send(SinkMsg::Note {
            at: self.now(),
            link: name.to_string(),
            peer: peer.to_string(),
            text: text.to_string(),
        });
    }

    /// Adds connection `id` on `link`, whose endpoint `endpoint` is.
    pub(super) fn open(
        &mut self,
        link: &LinkConfig,
        link_index: usize,
        id: ConnId,
        peer: String,
        endpoint: Box<dyn Endpoint>,
        task: LinkTask,
    ) {
        self.counters.connections += 1;
        let now = self.now();
        let rules = Rules {
            serial: link.spec.serial,
            turnaround: link.spec.turnaround,
            pace: link.spec.pace,
            check: link.check,
            partial_timeout: link.partial_timeout,
            rate_limit: link.rate_limit,
            idle_timeout: link.idle_timeout,
        };
        self.conns.insert(
            id,
            Conn {
                link: link_index,
                peer: peer.clone(),
                endpoint,
                task,
                due: Outgoing::default(),
                rules,
                queue: VecDeque::new(),
                queued_bytes: Vec::new(),
                line_free: SimTime::ZERO,
                partial_since: None,
                rate_window: now,
                rate_bytes: 0,
                probation: None,
                last_rx: now,
                unwritten: VecDeque::new(),
            },
        );
        self.note(link_index, &peer, "connected");
    }

    /// Connection `id`, just opened, came beyond its listener's limit: it
    /// is on probation (see [`Probation`]).
    pub(super) fn on_probation(&mut self, id: ConnId, probation: Probation) {
        let now = self.now();
        let Some(conn) = self.conns.get_mut(&id) else {
            return;
        };
        conn.probation = Some((probation, now));
        let link = conn.link;
        self.limit_probation(link);
    }

    pub(super) fn closed(&mut self, id: ConnId, why: &str) {
        if let Some(c) = self.conns.remove(&id) {
            self.note(c.link, &c.peer, &format!("closed: {why}"));
            // After the note, which shipped the connection's last frames.
            self.send(SinkMsg::Gone(id));
        }
    }

    pub(super) fn close(&mut self, id: ConnId, why: &str) {
        if let Some(conn) = self.conns.remove(&id) {
            conn.task.close(why.into(), conn.due);
            self.note(conn.link, &conn.peer, &format!("closed by the twin: {why}"));
            self.send(SinkMsg::Gone(id));
        }
    }

    /// Every connection told the server is stopping, the last frames
    /// shipped, and the sink let go: the connections' threads, which may
    /// outlive the session by a moment, must not keep it waiting for more.
    pub(super) fn close_all(&mut self) {
        for conn in self.conns.values_mut() {
            let owed = std::mem::take(&mut conn.due);
            conn.task.close("server stopping".into(), owed);
        }
        self.ship_frames();
        self.sink = None;
    }

    /// Closes every connection that has sent nothing for its link's idle
    /// timeout (the engine looks a few times a second).
    pub(super) fn close_idle(&mut self, now: SimTime) {
        let mut ids = std::mem::take(&mut self.ids);
        ids.clear();
        ids.extend(self.conns.iter().filter_map(|(&id, c)| {
            if let Some((_, since)) = c.probation {
                // A newcomer's half frame held as long as would let it be
                // displaced shows it is no faster than those it would displace.
                let slow = c
                    .partial_since
                    .is_some_and(|p| now.saturating_since(p) >= ROOM_AFTER_PARTIAL);
                return (slow || now.saturating_since(since) >= PROBATION).then_some(id);
            }
            let timeout = c.rules.idle_timeout?;
            (now.saturating_since(c.last_rx) >= timeout).then_some(id)
        }));
        for &id in &ids {
            if self.conns.get(&id).is_some_and(|c| c.probation.is_some()) {
                self.counters.closed_for_room += 1;
                self.close(
                    id,
                    "arrived over --max-clients and sent no whole request in time",
                );
                continue;
            }
            self.counters.closed_idle += 1;
            let quiet = self
                .conns
                .get(&id)
                .map_or(0.0, |c| now.saturating_since(c.last_rx).as_secs_f64());
            self.close(
                id,
                &format!("idle for {quiet:.1} s, longer than --idle-timeout"),
            );
        }
        self.ids = ids;
    }

    /// The client on `link` a newcomer may displace, and why: the one quiet
    /// longest if it has been for at least `min_idle`, else the one that has
    /// held a partial frame longest if for at least `min_partial` (places
    /// held by frames that never end would otherwise lock everyone out).
    /// Newcomers still on probation are never displaced: they have no place.
    fn displaceable(
        &self,
        link: usize,
        min_idle: Option<SimDuration>,
        min_partial: SimDuration,
    ) -> Option<(ConnId, String)> {
        let now = self.now();
        let members = || {
            self.conns
                .iter()
                .filter(move |(_, c)| c.link == link && c.probation.is_none())
        };
        let quietest = members()
            .min_by_key(|(_, c)| c.last_rx)
            .map(|(&id, c)| (id, now.saturating_since(c.last_rx)));
        if let Some((id, quiet)) = quietest
            && min_idle.is_some_and(|min| quiet >= min)
        {
            return Some((id, format!("idle for {:.0} s", quiet.as_secs_f64())));
        }
        let (id, since) = members()
            .filter_map(|(&id, c)| Some((id, c.partial_since?)))
            .min_by_key(|&(_, since)| since)?;
        let held = now.saturating_since(since);
        (held >= min_partial).then(|| {
            let why = format!("held a partial frame for {:.1} s", held.as_secs_f64());
            (id, why)
        })
    }

    /// Whether a newcomer to `link`, full, could displace a client there
    /// (see [`Front::displaceable`]): then it is let in on [`Probation`].
    /// A partial frame of any age counts here: by the newcomer's first
    /// request, it may have been held long enough.
    pub(super) fn room_possible(&self, link: usize, min_idle: Option<SimDuration>) -> bool {
        self.displaceable(link, min_idle, SimDuration::ZERO)
            .is_some()
    }

    /// Closes the client a newcomer may displace on `link`, if there is
    /// one; says whether there was.
    fn make_room(&mut self, link: usize, min_idle: Option<SimDuration>, max: usize) -> bool {
        let Some((id, why)) = self.displaceable(link, min_idle, ROOM_AFTER_PARTIAL) else {
            return false;
        };
        self.counters.closed_for_room += 1;
        self.close(
            id,
            &format!("{why}, the longest of {max} (--max-clients): made room for a new client"),
        );
        true
    }

    /// Keeps at most [`ON_PROBATION_MAX`] newcomers on probation on `link`:
    /// the one there longest goes.
    fn limit_probation(&mut self, link: usize) {
        let on_probation = || {
            self.conns
                .iter()
                .filter(|(_, c)| c.link == link)
                .filter_map(|(&id, c)| Some((id, c.probation?.1)))
        };
        if on_probation().count() <= ON_PROBATION_MAX {
            return;
        }
        if let Some((oldest, _)) = on_probation().min_by_key(|&(_, since)| since) {
            self.counters.closed_for_room += 1;
            self.close(
                oldest,
                "sent no whole request while newer clients arrived over --max-clients",
            );
        }
    }

    /// A newcomer on probation has sent its first whole request: it takes
    /// the place of the client it may displace, or, if none is left (they
    /// were active again), it is refused. Says whether it stays.
    fn settle_probation(&mut self, id: ConnId) -> bool {
        let Some(conn) = self.conns.get_mut(&id) else {
            return false;
        };
        let Some((probation, _)) = conn.probation.take() else {
            return true;
        };
        let link = conn.link;
        if self.make_room(link, probation.min_idle, probation.max) {
            return true;
        }
        self.counters.closed_for_room += 1;
        let max = probation.max;
        self.close(
            id,
            &format!("refused, {max} client(s) already connected and none quiet (--max-clients)"),
        );
        false
    }

    pub(super) fn receive(&mut self, id: ConnId, at: SimTime, bytes: &[u8]) {
        let Some(conn) = self.conns.get_mut(&id) else {
            return;
        };
        self.counters.bytes_in += bytes.len() as u64;
        let record = FrameRecord {
            link: conn.link,
            conn: id,
            direction: Direction::Rx,
            start: at,
            end: at,
        };
        self.frames.push(record, bytes);
        if let Some(limit) = conn.rules.rate_limit {
            if at.saturating_since(conn.rate_window) >= SimDuration::from_secs(1) {
                conn.rate_window = at;
                conn.rate_bytes = 0;
            }
            conn.rate_bytes += bytes.len() as u64;
            if conn.rate_bytes > limit {
                self.counters.closed_rate_limit += 1;
                self.close(
                    id,
                    &format!("rate limit: more than {limit} bytes in one second"),
                );
                return;
            }
        }
        let noise_before = conn.endpoint.noise_bytes();
        conn.endpoint.handle_bytes(&mut self.devices, at, bytes);
        let noise = conn.endpoint.noise_bytes().saturating_sub(noise_before);
        if noise < bytes.len() as u64 {
            conn.last_rx = at;
        }
        let earned = conn.probation.is_some()
            && conn.endpoint.requests().is_none_or(|requests| requests > 0);
        if earned && !self.settle_probation(id) {
            return;
        }
        let Some(conn) = self.conns.get_mut(&id) else {
            return;
        };
        if let Some(why) = conn.endpoint.close_request() {
            // Replies already owed go out first.
            self.drain(id, at);
            self.close(id, &why);
            return;
        }
        if conn.endpoint.pending() > 0 {
            conn.partial_since.get_or_insert(at);
        } else {
            conn.partial_since = None;
        }
        self.drain(id, at);
    }

    /// Takes the endpoint's frames, applies the fault in force and the
    /// link's turnaround and pacing, and writes those that are due.
    fn drain(&mut self, id: ConnId, base: SimTime) {
        let Some(conn) = self.conns.get_mut(&id) else {
            return;
        };
        let fault = self
            .fault
            .filter(|(_, only)| only.is_none_or(|l| l == conn.link))
            .map(|(f, _)| f);
        while let Some(len) = conn
            .endpoint
            .poll_transmit(&mut self.devices, base, &mut self.buf)
        {
            let mut len = len.min(MAX_FRAME);
            let frame = &mut self.buf[..len];
            let mut extra = SimDuration::ZERO;
            let mut split = None;
            match fault {
                Some(LinkFault::NoReply) => {
                    self.counters.replies_faulted += 1;
                    conn.endpoint.transmit_done(&mut self.devices, base);
                    continue;
                }
                Some(LinkFault::BadCheck) => {
                    if let Some(kind) = conn.rules.check
                        && spoil_check(kind, frame)
                    {
                        self.counters.replies_faulted += 1;
                    }
                }
                Some(LinkFault::Delay(d)) => {
                    self.counters.replies_faulted += 1;
                    extra = d;
                }
                Some(LinkFault::WrongId(id)) => {
                    if let Some(kind) = conn.rules.check
                        && let Some(id) =
                            id.or_else(|| frame_id(kind, frame).map(|own| other_id(kind, own)))
                        && set_id(kind, frame, id)
                    {
                        self.counters.replies_faulted += 1;
                    }
                }
                Some(LinkFault::Split(gap)) => {
                    split = split_point(len, None).map(|at| (at, gap));
                    if split.is_some() {
                        self.counters.replies_faulted += 1;
                    }
                }
                Some(LinkFault::Junk(junk)) => {
                    len = self.junk.apply(&junk, &mut self.buf, len);
                    self.counters.replies_faulted += 1;
                }
                Some(LinkFault::Exception(_)) | None => {}
            }
            let frame = &self.buf[..len];
            let rules = &conn.rules;
            let mut start = (base + rules.turnaround + extra).max(conn.line_free);
            // A split reply is two writes: the second `gap` after the first
            // has gone (its wire time, on a paced link), on the engine's
            // timers like any reply's turnaround, never a sleep.
            let (first, rest) = match split {
                Some((at, _)) => frame.split_at(at),
                None => (frame, &[][..]),
            };
            for (piece, part) in [(first, !rest.is_empty()), (rest, false)] {
                if piece.is_empty() {
                    continue;
                }
                let due = if rules.pace {
                    start + rules.serial.wire_time(piece.len())
                } else {
                    start
                };
                conn.line_free = due;
                conn.queued_bytes.extend_from_slice(piece);
                conn.queue.push_back(Queued {
                    start,
                    due,
                    len: piece.len(),
                    part,
                });
                start = due + split.map_or(SimDuration::ZERO, |(_, gap)| gap);
            }
        }
        let now = self.held_now();
        self.flush(id, now);
    }

    /// Moves the queued frames that are due at `now` to the connection's
    /// due frames, for its task to write.
    fn flush(&mut self, id: ConnId, now: SimTime) {
        let Some(conn) = self.conns.get_mut(&id) else {
            return;
        };
        while let Some(q) = conn.queue.front()
            && q.due <= now
        {
            let len = q.len.min(conn.queued_bytes.len());
            let frame = conn.queued_bytes.get(..len).unwrap_or_default();
            self.counters.frames_out += 1;
            self.counters.bytes_out += len as u64;
            let part = q.part;
            if conn.endpoint.reports_writes() {
                // Recorded and reported when its carrier has written it.
                conn.unwritten.push_back(Unwritten {
                    wire: q.due.saturating_since(q.start),
                    part,
                });
                conn.due.push(frame);
                conn.due.report_when_written();
                conn.queued_bytes.drain(..len);
                conn.queue.pop_front();
                continue;
            }
            let record = FrameRecord {
                link: conn.link,
                conn: id,
                direction: Direction::Tx,
                start: q.start,
                end: now,
            };
            self.frames.push(record, frame);
            conn.due.push(frame);
            conn.queued_bytes.drain(..len);
            conn.queue.pop_front();
            if !part {
                conn.endpoint.transmit_done(&mut self.devices, now);
            }
        }
    }

    /// The carrier of `id` wrote `frames` at `at`: each is recorded as
    /// written then (its wire time before, on a paced link), and the
    /// endpoint told each transmission has ended, so a master's reply
    /// timeout runs from when its request left, not from when the engine
    /// handed it over. Then what the endpoint has to send goes out.
    fn written(&mut self, id: ConnId, at: SimTime, frames: &Outgoing) {
        let Some(conn) = self.conns.get_mut(&id) else {
            return;
        };
        for frame in frames.iter() {
            let Some(Unwritten { wire, part }) = conn.unwritten.pop_front() else {
                break;
            };
            let record = FrameRecord {
                link: conn.link,
                conn: id,
                direction: Direction::Tx,
                start: SimTime(at.0.saturating_sub(wire.0)),
                end: at,
            };
            self.frames.push(record, frame);
            if !part {
                conn.endpoint.transmit_done(&mut self.devices, at);
            }
        }
        self.drain(id, at);
    }

    /// The earliest firmware loop tick a connection wants run before the
    /// engine's next tick (see [`crate::Endpoint::follow`]).
    pub(super) fn next_follow(&self) -> Option<SimTime> {
        self.conns
            .values()
            .filter_map(|c| c.endpoint.follow(&self.devices))
            .min()
    }

    /// The earliest instant a connection needs attention at.
    pub(super) fn next_deadline(&self) -> Option<SimTime> {
        self.conns
            .values()
            .filter_map(|c| c.next_deadline(&self.devices))
            .min()
    }

    pub(super) fn service_timers(&mut self, now: SimTime) {
        // Read before a stall, `now` would count it as time the timers
        // waited (a reply timeout fired, a request stamped ahead of every
        // time after the slip, so the next ones queued behind it).
        let now = self.hold_clock(now);
        // The ids are copied into a kept buffer: handling a connection may
        // close it, and this runs at every wake-up (no allocation here).
        let mut ids = std::mem::take(&mut self.ids);
        ids.clear();
        ids.extend(self.conns.keys().copied());
        for &id in &ids {
            let Some(conn) = self.conns.get_mut(&id) else {
                continue;
            };
            if conn
                .endpoint
                .poll_timeout(&self.devices)
                .is_some_and(|t| t <= now)
            {
                conn.endpoint.handle_timeout(&mut self.devices, now);
                conn.partial_since =
                    (conn.endpoint.pending() > 0).then_some(conn.partial_since.unwrap_or(now));
            }
            if let (Some(since), Some(timeout)) = (conn.partial_since, conn.rules.partial_timeout)
                && now >= since + timeout
            {
                self.counters.closed_partial_timeout += 1;
                let secs = timeout.as_secs_f64();
                self.close(
                    id,
                    &format!("a partial frame was held longer than {secs} s"),
                );
                continue;
            }
            self.drain(id, now);
            if let Some(conn) = self.conns.get(&id)
                && !conn.due.is_empty()
            {
                // The frames of a timer: the task is not reading them.
                conn.task.frames_due();
            }
            while let Some((who, event)) = self
                .conns
                .get_mut(&id)
                .and_then(|c| c.endpoint.poll_event(&mut self.devices))
            {
                self.ship_frames();
                self.send(SinkMsg::Event { node: who, event });
            }
        }
        self.ids = ids;
    }
}

/// How the engine reaches the task or thread carrying a connection.
#[derive(Debug, Clone)]
pub struct LinkTask {
    pub out: UnboundedSender<Outbound>,
    pub wake: Wake,
}

impl LinkTask {
    /// The engine (its timers, or a reply that waited on the bus) has put
    /// frames in the connection's due frames.
    pub fn frames_due(&self) {
        match &self.wake {
            Wake::Task(ready) => ready.notify_one(),
            Wake::Thread(wake) => wake.frames_due(),
        }
    }

    /// Write `owed`, then close the connection, for reason `why`.
    pub fn close(&self, why: String, owed: Outgoing) {
        let _ = self.out.send(Outbound::Close { why, owed });
        if let Wake::Thread(wake) = &self.wake {
            wake.closing();
        }
    }
}

/// What the engine sends a link task.
#[derive(Debug)]
pub enum Outbound {
    /// Answer this connection's requests on the task's own thread through
    /// the shared front (the first message, unless the connection is refused).
    Direct(FrontHandle),
    /// Write these frames, then close the connection, for this reason.
    Close { why: String, owed: Outgoing },
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::endpoint::NodeEndpoint;
    use crate::io::{LinkDefaults, LinkSpec};
    use crate::wake::Wake;
    use nodes::master::{Protocol, SlaveLoopConfig, Supervisor, SupervisorConfig};
    use nodes::node::Node;
    use twin_sim::nodes_build::SupervisorNode;

    fn ms(n: u64) -> SimDuration {
        SimDuration::from_millis(n)
    }

    fn supervisor_timeout(front: &FrontHandle) -> Option<SimTime> {
        front
            .lock()
            .devices
            .get_mut(0)
            .and_then(|d| d.node.supervisor_mut())
            .and_then(|s| s.poll_timeout())
    }

    /// One stall is one slip, however many look at the clock before the
    /// engine has caught up to it; the next stall is another.
    #[test]
    fn a_stall_is_one_slip_until_the_ticks_catch_up() {
        let clock = RtClock::started_ago(std::time::Duration::from_secs(1));
        let (sink, _sink) = std::sync::mpsc::channel();
        let mut front = Front::new(sink, clock.clone(), &[]);
        front.catch_up = ms(5);
        // The engine ticked up to 0.7 s, then stood still until now (1 s).
        front.ticked_to = SimTime::ZERO + ms(700);
        front.plant_to = front.ticked_to;
        let held = front.hold_clock(clock.now());
        assert_eq!(held, SimTime::ZERO + ms(705));
        assert_eq!(front.slips.count, 1);
        let lost = front.slips.ns;
        assert!(lost >= 295_000_000, "{lost} ns lost");
        // A carrier's bytes while the engine runs its burst of ticks.
        std::thread::sleep(std::time::Duration::from_millis(1));
        front.hold_clock(clock.now());
        assert_eq!(front.slips.count, 1, "the same stall counted twice");
        assert!(front.slips.ns > lost, "the clock was held again");
        // The engine caught up; then it stands still again for 20 ms.
        front.ticked_to = clock.now();
        front.plant_to = front.ticked_to + ms(1);
        std::thread::sleep(std::time::Duration::from_millis(20));
        front.hold_clock(clock.now());
        assert_eq!(front.slips.count, 2);
    }

    /// A supervisor's bus when the engine's thread was stopped for 300 ms
    /// just after its tick and reads the time before the clock slipped for
    /// the stall: its timers are held at the catch-up, its request goes
    /// out at the held time, and is recorded and starts its reply timeout
    /// only when its carrier has written it. Before, the request was stamped
    /// 300 ms ahead of the slipped clock, so the next ones queued behind it
    /// for 300 ms, and their timeouts, counted from their hand-off, fired
    /// before their first copies were written.
    #[test]
    fn a_stall_before_the_slip_is_not_time_a_request_waited() {
        let clock = RtClock::started_ago(std::time::Duration::from_secs(1));
        let (sink, _sink) = std::sync::mpsc::channel();
        let defaults = LinkDefaults {
            serial_turnaround: SimDuration::ZERO,
            pace: false,
            ..LinkDefaults::default()
        };
        let link = LinkConfig {
            name: "bus".into(),
            protocol: "meb",
            address: "/tmp/bus".into(),
            twin_is_master: true,
            spec: LinkSpec::parse("/tmp/bus", &defaults).expect("a serial path"),
            check: None,
            partial_timeout: None,
            rate_limit: None,
            idle_timeout: None,
            factory: Box::new(|_, _| Box::new(NodeEndpoint::masters(vec![0]))),
        };
        let mut front = Front::new(sink, clock.clone(), std::slice::from_ref(&link));
        front.catch_up = ms(5);
        let mut config = SupervisorConfig::new(Protocol::Meb, vec![SlaveLoopConfig::new(1)]);
        config.startup_outputs = None;
        config.reply_timeout = ms(30);
        config.first_poll_at = SimTime::ZERO + ms(700);
        let supervisor = Supervisor::new(config).expect("a supervisor");
        front.devices.push(Device::new(
            "supervisor",
            Box::new(SupervisorNode::new(supervisor)),
            None,
        ));
        let (out, _outbox) = tokio::sync::mpsc::unbounded_channel();
        let task = LinkTask {
            out,
            wake: Wake::Task(Arc::new(tokio::sync::Notify::new())),
        };
        let endpoint = Box::new(NodeEndpoint::masters(vec![0]));
        front.open(&link, 0, 1, "/tmp/bus".into(), endpoint, task);
        // The engine ticked up to 0.7 s, then stood still until now (1 s).
        let ticked_to = SimTime::ZERO + ms(700);
        front.ticked_to = ticked_to;
        let front = FrontHandle::new(front, None);

        let read_before_the_slip = clock.now();
        front.lock().service_timers(read_before_the_slip);
        let held = ticked_to + ms(5);
        assert!(
            clock.now() < held + ms(100),
            "the clock slipped for the stall"
        );
        assert!(front.lock().slips.count >= 1);
        // Handed to the carrier, not yet written: no timeout runs.
        let mut due = Outgoing::default();
        front.take_due(1, &mut due);
        assert!(due.reports());
        assert_eq!(due.iter().collect::<Vec<_>>(), [&b"@01EA000643*\n"[..]]);
        assert_eq!(supervisor_timeout(&front), None);

        // The carrier writes it a little later (on the held clock).
        let mut more = Outgoing::default();
        front.written(1, clock.now(), &due, &mut more);
        assert!(more.is_empty());
        let batch = front.lock().frames.take().expect("the request recorded");
        let records: Vec<_> = batch.iter().map(|(r, bytes)| (*r, bytes.len())).collect();
        let [(request, 13)] = records[..] else {
            panic!("one request recorded: {records:?}");
        };
        assert_eq!(request.direction, Direction::Tx);
        assert_eq!(request.start, request.end);
        assert!(
            request.start >= ticked_to && request.start <= held,
            "written at {:?}, the engine's tick {ticked_to:?}",
            request.start
        );
        assert_eq!(supervisor_timeout(&front), Some(request.end + ms(30)));

        // Its reply, read at once, is used: nothing timed out.
        let reply = b"@01EA00060BB80000000003E8000003E84B*\n";
        let mut replies = Outgoing::default();
        front.receive(1, clock.now(), reply, false, &mut replies);
        let mut shared = front.lock();
        let supervisor = shared.devices[0]
            .node
            .supervisor_mut()
            .expect("the supervisor");
        let counters = supervisor.loop_state(1).expect("slave 1").counters;
        assert_eq!(
            (counters.replies, counters.timeouts),
            (1, 0),
            "{counters:?}"
        );
    }
}
