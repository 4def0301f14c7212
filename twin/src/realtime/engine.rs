//! The real-time engine: one thread owns the plants, the devices (firmware
//! nodes) and every connection's endpoint, and ticks the plant every 1 ms on
//! absolute deadlines. Tokio tasks own the sockets and ports and exchange
//! bytes with it over channels ([`Inbound`], [`Outbound`]); a sink thread
//! records and prints ([`super::sink`]), so neither a slow terminal nor
//! zstd ever delays a tick.
//!
//! Waiting: the thread blocks on its channel until shortly before the next
//! deadline (the next plant tick, a node's timer, a reply's turnaround), then
//! spins to it. Lateness (actual − scheduled tick time) goes into
//! [`Lateness`] histograms: one per second for the recording, one in total.

use nodes::link::spoil_check;
use nodes::node::MAX_FRAME;
use nodes::time::{SimDuration, SimTime};
use std::collections::{BTreeMap, VecDeque};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, TryRecvError};
use std::time::Instant;
use tokio::sync::mpsc::UnboundedSender;

use super::clock::RtClock;
pub use super::config::{Device, EndpointFactory, LinkConfig, LinkFault};
use super::endpoint::Endpoint;
pub use super::forces::Forces;
use super::lateness::{Lateness, LatenessSummary};
pub use super::messages::{ConnId, Inbound, Outbound};
use super::sink::{Direction, SinkMsg};
use crate::engine::{ModuleSlot, firmware_tick};

/// How long before a deadline the thread stops sleeping and spins: covers
/// the kernel's wake-up latency and timer slack (50 µs by default).
const SPIN: SimDuration = SimDuration::from_micros(150);

struct Queued {
    start: SimTime,
    due: SimTime,
    bytes: Vec<u8>,
}

struct Conn {
    link: usize,
    peer: String,
    endpoint: Box<dyn Endpoint>,
    out: UnboundedSender<Outbound>,
    queue: VecDeque<Queued>,
    line_free: SimTime,
    partial_since: Option<SimTime>,
    rate_window: SimTime,
    rate_bytes: u64,
}

/// Counters for the status line and the summary.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct RtCounters {
    pub bytes_in: u64,
    pub bytes_out: u64,
    pub frames_out: u64,
    pub connections: u64,
    pub closed_partial_timeout: u64,
    pub closed_rate_limit: u64,
    pub replies_faulted: u64,
}

/// What a session reports at its end.
#[derive(Debug, Clone)]
pub struct RtSummary {
    pub elapsed: SimDuration,
    pub lateness: LatenessSummary,
    pub counters: RtCounters,
    pub stopped_by: String,
}

/// The engine. Build it, add modules, devices and links, then [`RtEngine::run`]
/// it on its own thread.
pub struct RtEngine {
    pub clock: RtClock,
    pub modules: Vec<ModuleSlot>,
    pub devices: Vec<Device>,
    pub links: Vec<LinkConfig>,
    conns: BTreeMap<ConnId, Conn>,
    /// The fault in force, and the link it is limited to (all if `None`).
    fault: Option<(LinkFault, Option<usize>)>,
    read_only: bool,
    plant_step: SimDuration,
    tick: SimDuration,
    record_period: SimDuration,
    next_record: SimTime,
    status_period: SimDuration,
    next_status: SimTime,
    next_second: SimTime,
    sink: Sender<SinkMsg>,
    lateness: Lateness,
    window: Lateness,
    pub counters: RtCounters,
    stop: Option<String>,
    buf: Vec<u8>,
    ids: Vec<ConnId>,
}

impl RtEngine {
    /// An engine whose plants step by `plant_step` on a 1 ms tick, recording
    /// plant state every `record_period`, reporting to `sink`.
    pub fn new(
        clock: RtClock,
        plant_step: SimDuration,
        record_period: SimDuration,
        sink: Sender<SinkMsg>,
    ) -> Self {
        Self {
            clock,
            modules: Vec::new(),
            devices: Vec::new(),
            links: Vec::new(),
            conns: BTreeMap::new(),
            fault: None,
            read_only: false,
            plant_step,
            tick: SimDuration::from_millis(1),
            record_period,
            next_record: SimTime::ZERO,
            status_period: SimDuration::from_secs(1),
            next_status: SimTime::ZERO + SimDuration::from_secs(1),
            next_second: SimTime::ZERO + SimDuration::from_secs(1),
            sink,
            lateness: Lateness::new(),
            window: Lateness::new(),
            counters: RtCounters::default(),
            stop: None,
            buf: vec![0; MAX_FRAME],
            ids: Vec::new(),
        }
    }

    /// Status lines every `period` (zero: never).
    pub fn set_status_period(&mut self, period: SimDuration) {
        self.status_period = period;
        self.next_status = SimTime::ZERO + period;
    }

    /// Make every slave front end refuse writes.
    pub fn set_read_only(&mut self, read_only: bool) {
        self.read_only = read_only;
        for conn in self.conns.values_mut() {
            if let Some(f) = conn.endpoint.frontend_mut() {
                f.set_read_only(read_only);
            }
        }
    }

    /// Switch a fault on (on link `link`, or all) or off.
    pub fn set_fault(&mut self, fault: Option<LinkFault>, link: Option<usize>) {
        self.fault = fault.map(|f| (f, link));
        let refusal = match fault {
            Some(LinkFault::Exception(r)) => Some(r),
            _ => None,
        };
        for conn in self.conns.values_mut() {
            let applies = link.is_none_or(|l| l == conn.link);
            if let Some(f) = conn.endpoint.frontend_mut() {
                f.set_forced_refusal(if applies { refusal } else { None });
            }
        }
    }

    /// The fault in force.
    pub fn fault(&self) -> Option<(LinkFault, Option<usize>)> {
        self.fault
    }

    /// Open connections: (link, peer).
    pub fn connections(&self) -> impl Iterator<Item = (usize, &str)> {
        self.conns.values().map(|c| (c.link, c.peer.as_str()))
    }

    /// A sender to the sink, for lines and records from outside the engine.
    pub fn sink(&self) -> Sender<SinkMsg> {
        self.sink.clone()
    }

    /// End the session at the next pass of the loop.
    pub fn request_stop(&mut self, why: &str) {
        self.stop.get_or_insert_with(|| why.to_string());
    }

    /// Print `text` on the console (through the sink).
    pub fn say(&self, text: impl Into<String>) {
        let _ = self.sink.send(SinkMsg::Say(text.into()));
    }

    /// Tick lateness since the start.
    pub fn lateness(&self) -> LatenessSummary {
        self.lateness.summary()
    }

    /// Run until `end` (if any) or a [`Inbound::Stop`].
    pub fn run(&mut self, inbound: &Receiver<Inbound>, end: Option<SimTime>) -> RtSummary {
        let mut next_tick = SimTime::ZERO;
        loop {
            let now = self.clock.now();
            if now >= next_tick {
                let late = now.saturating_since(next_tick);
                let ns = late.0 / (nodes::time::TICKS_PER_SECOND / 1_000_000_000);
                self.lateness.record(ns);
                self.window.record(ns);
                if late > self.tick {
                    // Fell behind (the machine was busy): skip to the latest
                    // tick due rather than run a burst of stale ones.
                    let missed = late.0 / self.tick.0;
                    self.lateness.overruns += 1;
                    self.window.overruns += 1;
                    next_tick = SimTime(next_tick.0 + missed * self.tick.0);
                }
                self.plant_tick(next_tick);
                next_tick += self.tick;
                if end.is_some_and(|e| now >= e) && self.stop.is_none() {
                    self.stop = Some("duration reached".into());
                }
            }
            self.service_timers(self.clock.now());
            if self.stop.is_some() {
                break;
            }
            let deadline = self.next_deadline().map_or(next_tick, |d| d.min(next_tick));
            if let Some(message) = self.wait(inbound, deadline) {
                self.handle(message);
                // Everything already queued is handled before the next wait.
                while let Ok(message) = inbound.try_recv() {
                    self.handle(message);
                }
            }
        }
        for conn in self.conns.values() {
            let _ = conn.out.send(Outbound::Close("server stopping".into()));
        }
        // The last (partial) second's lateness, so even a short session has one.
        let _ = self.sink.send(SinkMsg::Lateness {
            at: self.clock.now(),
            window: self.window.summary(),
            total: self.lateness.summary(),
        });
        let elapsed = self.clock.now().saturating_since(SimTime::ZERO);
        RtSummary {
            elapsed,
            lateness: self.lateness.summary(),
            counters: self.counters,
            stopped_by: self.stop.take().unwrap_or_default(),
        }
    }

    /// Blocks until a message arrives or `deadline` passes: sleeps on the
    /// channel until [`SPIN`] before it, then spins.
    fn wait(&mut self, inbound: &Receiver<Inbound>, deadline: SimTime) -> Option<Inbound> {
        let wake = self.clock.instant(deadline);
        let sleep_until = self
            .clock
            .instant(SimTime(deadline.0.saturating_sub(SPIN.0)));
        let now = Instant::now();
        if sleep_until > now {
            match inbound.recv_timeout(sleep_until - now) {
                Ok(message) => return Some(message),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => {
                    self.stop.get_or_insert_with(|| "all links closed".into());
                    return None;
                }
            }
        }
        loop {
            match inbound.try_recv() {
                Ok(message) => return Some(message),
                Err(TryRecvError::Empty) => {}
                Err(TryRecvError::Disconnected) => {
                    self.stop.get_or_insert_with(|| "all links closed".into());
                    return None;
                }
            }
            if Instant::now() >= wake {
                return None;
            }
            std::hint::spin_loop();
        }
    }

    fn handle(&mut self, message: Inbound) {
        match message {
            Inbound::Opened {
                link,
                conn,
                peer,
                out,
            } => self.open(link, conn, peer, out),
            Inbound::Bytes { conn, at, bytes } => self.receive(conn, at, &bytes),
            Inbound::Closed { conn, why } => {
                if let Some(c) = self.conns.remove(&conn) {
                    self.note(c.link, &c.peer, &format!("closed: {why}"));
                }
            }
            Inbound::Command(command) => command(self),
            Inbound::Stop(why) => {
                self.stop.get_or_insert(why);
            }
        }
    }

    fn note(&self, link: usize, peer: &str, text: &str) {
        let at = self.clock.now();
        let name = self.links.get(link).map_or("?", |l| l.name.as_str());
        let _ = self.sink.send(SinkMsg::Note {
            at,
            link: name.to_string(),
            peer: peer.to_string(),
            text: text.to_string(),
        });
    }

    fn open(&mut self, link: usize, id: ConnId, peer: String, out: UnboundedSender<Outbound>) {
        let Some(config) = self.links.get_mut(link) else {
            return;
        };
        let mut endpoint = (config.factory)(&mut self.devices, &peer);
        if let Some(f) = endpoint.frontend_mut() {
            f.set_read_only(self.read_only);
            if let Some((LinkFault::Exception(r), l)) = self.fault
                && l.is_none_or(|l| l == link)
            {
                f.set_forced_refusal(Some(r));
            }
        }
        self.counters.connections += 1;
        let now = self.clock.now();
        self.conns.insert(
            id,
            Conn {
                link,
                peer: peer.clone(),
                endpoint,
                out,
                queue: VecDeque::new(),
                line_free: SimTime::ZERO,
                partial_since: None,
                rate_window: now,
                rate_bytes: 0,
            },
        );
        self.note(link, &peer, "connected");
    }

    fn close(&mut self, id: ConnId, why: &str) {
        if let Some(conn) = self.conns.remove(&id) {
            let _ = conn.out.send(Outbound::Close(why.into()));
            self.note(conn.link, &conn.peer, &format!("closed by the twin: {why}"));
        }
    }

    fn receive(&mut self, id: ConnId, at: SimTime, bytes: &[u8]) {
        let Some(conn) = self.conns.get_mut(&id) else {
            return;
        };
        let Some(link) = self.links.get(conn.link) else {
            return;
        };
        self.counters.bytes_in += bytes.len() as u64;
        let _ = self.sink.send(SinkMsg::Frame {
            link: conn.link,
            conn: id,
            direction: Direction::Rx,
            start: at,
            end: at,
            bytes: bytes.to_vec(),
        });
        if let Some(limit) = link.rate_limit {
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
        conn.endpoint.handle_bytes(&mut self.devices, at, bytes);
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
        let Some(link) = self.links.get(conn.link) else {
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
            let frame = &mut self.buf[..len.min(MAX_FRAME)];
            let mut extra = SimDuration::ZERO;
            match fault {
                Some(LinkFault::NoReply) => {
                    self.counters.replies_faulted += 1;
                    conn.endpoint.transmit_done(&mut self.devices, base);
                    continue;
                }
                Some(LinkFault::BadCheck) => {
                    if let Some(kind) = link.check
                        && spoil_check(kind, frame)
                    {
                        self.counters.replies_faulted += 1;
                    }
                }
                Some(LinkFault::Delay(d)) => {
                    self.counters.replies_faulted += 1;
                    extra = d;
                }
                Some(LinkFault::Exception(_)) | None => {}
            }
            let start = (base + link.spec.turnaround + extra).max(conn.line_free);
            let due = if link.spec.pace {
                start + link.spec.serial.wire_time(frame.len())
            } else {
                start
            };
            conn.line_free = due;
            conn.queue.push_back(Queued {
                start,
                due,
                bytes: frame.to_vec(),
            });
        }
        self.flush(id, self.clock.now());
    }

    /// Writes the queued frames that are due at `now`.
    fn flush(&mut self, id: ConnId, now: SimTime) {
        let Some(conn) = self.conns.get_mut(&id) else {
            return;
        };
        while conn.queue.front().is_some_and(|q| q.due <= now) {
            let Some(q) = conn.queue.pop_front() else {
                break;
            };
            self.counters.frames_out += 1;
            self.counters.bytes_out += q.bytes.len() as u64;
            let _ = self.sink.send(SinkMsg::Frame {
                link: conn.link,
                conn: id,
                direction: Direction::Tx,
                start: q.start,
                end: now,
                bytes: q.bytes.clone(),
            });
            let _ = conn.out.send(Outbound::Frame(q.bytes));
            conn.endpoint.transmit_done(&mut self.devices, now);
        }
    }

    /// The earliest instant a connection needs attention at.
    fn next_deadline(&self) -> Option<SimTime> {
        self.conns
            .values()
            .flat_map(|c| {
                let partial = c.partial_since.and_then(|since| {
                    let timeout = self.links.get(c.link)?.partial_timeout?;
                    Some(since + timeout)
                });
                [
                    c.endpoint.poll_timeout(&self.devices),
                    c.queue.front().map(|q| q.due),
                    partial,
                ]
            })
            .flatten()
            .min()
    }

    fn service_timers(&mut self, now: SimTime) {
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
            let timeout = self.links.get(conn.link).and_then(|l| l.partial_timeout);
            if let (Some(since), Some(timeout)) = (conn.partial_since, timeout)
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
            while let Some((who, event)) = self
                .conns
                .get_mut(&id)
                .and_then(|c| c.endpoint.poll_event(&mut self.devices))
            {
                let _ = self.sink.send(SinkMsg::Event { node: who, event });
            }
        }
        self.ids = ids;
    }

    /// One plant tick at `t`: firmware loops, the plants, recording.
    fn plant_tick(&mut self, t: SimTime) {
        for device in &mut self.devices {
            let (Some(m), Some(due)) = (device.module, device.next_tick) else {
                continue;
            };
            if due > t {
                continue;
            }
            let Some(module) = self.modules.get_mut(m) else {
                continue;
            };
            let forces = device.forces;
            let sensing = module.plant.params().sensing.clone();
            let held = module.actuators;
            let ticked = firmware_tick(device.node.as_mut(), module, self.plant_step, t, |s| {
                forces.apply_sensors(s, &sensing)
            });
            if !device.node.drives_plant() {
                // A sensor-only node (seed 002's light sensor) watches the
                // bench; the motor node drives it.
                module.actuators = held;
            }
            if let Some((next, changed)) = ticked {
                let changed = changed && device.node.drives_plant();
                device.next_tick = Some(next.max(t + self.tick));
                if let Some(image) = device.node.image_mut() {
                    forces.apply_words(image);
                }
                if changed {
                    let _ = self.sink.send(SinkMsg::Actuators {
                        at: t,
                        module: m,
                        actuators: module.actuators,
                    });
                }
            }
        }
        // Devices' events (trips, a supervisor's timeouts) whatever drives them.
        for device in &mut self.devices {
            while let Some(event) = device.node.poll_event() {
                let _ = self.sink.send(SinkMsg::Event {
                    node: device.name.clone(),
                    event,
                });
            }
        }
        for module in &mut self.modules {
            module.advance(self.plant_step, t);
        }
        if t >= self.next_record {
            for (m, module) in self.modules.iter().enumerate() {
                let _ = self.sink.send(SinkMsg::Plant {
                    at: t,
                    module: m,
                    sensors: Box::new(*module.plant.sensors()),
                });
            }
            self.next_record = t + self.record_period;
        }
        if self.status_period > SimDuration::ZERO && t >= self.next_status {
            let line = self.status_line(t);
            let _ = self.sink.send(SinkMsg::Say(line));
            self.next_status += self.status_period;
        }
        if t >= self.next_second {
            let _ = self.sink.send(SinkMsg::Lateness {
                at: t,
                window: self.window.summary(),
                total: self.lateness.summary(),
            });
            self.window.clear();
            self.next_second += SimDuration::from_secs(1);
        }
    }

    /// One line of the module's state.
    pub fn status_line(&self, t: SimTime) -> String {
        let mut line = format!("[{:10.3} s]", t.as_secs_f64());
        for module in &self.modules {
            let s = module.plant.sensors();
            let a = &module.actuators;
            line += &format!(
                " {}: wheel {:.1} rpm, V1 {:.2} V, V2 {:.2} V, I {:.2} A, VEL {:.2} V, EN {};",
                module.name,
                s.wheel_rpm,
                s.battery_volts,
                s.bus_volts,
                s.inverter_current,
                a.vel_volts,
                if a.enable { "on" } else { "off" }
            );
        }
        for device in self.devices.iter().filter(|d| d.forces.any()) {
            line += &format!(" {} forced {:?};", device.name, device.forces);
        }
        let w = self.window.summary();
        line += &format!(
            " clients {}, frames out {}; tick lateness p99 {:.0} µs, max {:.0} µs",
            self.conns.len(),
            self.counters.frames_out,
            w.p99_us,
            w.max_us
        );
        if let Some((fault, _)) = self.fault {
            line += &format!("; fault {fault:?}");
        }
        line
    }
}

impl std::fmt::Debug for RtEngine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RtEngine")
            .field("modules", &self.modules.len())
            .field("devices", &self.devices.len())
            .field("links", &self.links.len())
            .field("connections", &self.conns.len())
            .finish_non_exhaustive()
    }
}
