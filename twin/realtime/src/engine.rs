//! The real-time engine: one thread owns the plants and ticks them every
//! 1 ms on absolute deadlines. The devices (firmware nodes) and every
//! connection's endpoint live in the [`Front`], shared with what carries the
//! connections (a tokio task per serial port, a thread per TCP connection):
//! each answers the requests it reads, the engine runs the firmware loops
//! and the timers; the rest goes over channels ([`Inbound`], [`Outbound`]).
//! A sink thread records and prints ([`super::sink`]), so neither a slow
//! terminal nor zstd ever delays a tick.
//!
//! Waiting: the thread blocks on its channel until the next plant tick, or
//! until shortly before a link's next deadline (a node's timer, a reply's
//! turnaround) and spins to that. Lateness (actual − scheduled tick time) goes into
//! [`Lateness`] histograms: one per second for the recording, one in total.
//!
//! Batches: while nothing reads the plant between ticks (no one connected;
//! or TCP clients answered from the image when their bytes come, with no
//! deadline pending and requests more than `front::BUSY_GAP`
//! apart), the thread sleeps through a batch of ticks (`IDLE_BATCH` with
//! no one connected, `POLLED_BATCH` with clients) and runs them in a
//! burst, the same ticks in the same order. A request that comes
//! meanwhile and finds the plant more than a tick behind its arrival has
//! the plant ticked up to that arrival first, by its carrier's thread
//! while it holds the engine ([`FrontHandle::catch_up`]), so a client
//! reads what it would have read from an engine ticking every millisecond,
//! and a polled module costs its requests rather than a thousand wake-ups
//! a second. Serial ports, supervisors and sketches keep the 1 ms ticks
//! (`Front::answers_at_once`).

use protocols::time::{SimDuration, SimTime};
use std::collections::BTreeMap;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, TryRecvError};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

use super::clock::{CATCH_UP, RtClock};
pub use super::config::{EndpointFactory, LinkConfig, LinkFault};
pub use super::device::Device;
use super::firmware_log::FirmwareLog;
pub use super::forces::Forces;
pub use super::frame_log::{ConnId, Outgoing};
pub use super::front::RtCounters;
use super::front::{CatchUp, Conn, Front, FrontHandle, Probation};
pub use super::front::{LinkTask, Outbound};
use super::lateness::{Lateness, LatenessSummary};
use super::sink::SinkMsg;
use twin_sim::engine::{ModuleSlot, firmware_tick};

/// How long before a deadline the thread stops sleeping and spins: covers
/// the kernel's wake-up latency (the thread's timer slack is set to 1 ns).
/// Measured on the 2-core machine, 8 s idle runs: 60 µs gave a tick
/// lateness p99 of 43-51 µs, 150 µs 5-347 µs, 40 µs 45-72 µs; 60 spins
/// 6 % of a core instead of 15 %, which the links get back.
const SPIN: SimDuration = SimDuration::from_micros(60);
/// The name real time lost is recorded under, as an event.
const SLIP_NODE: &str = "clock";
/// Ticks per nanosecond.
const TICKS_PER_NANO: u64 = protocols::time::TICKS_PER_SECOND / 1_000_000_000;
/// While nothing reads the plant between ticks (no one connected, or
/// clients whose requests are answered from the image when they come and
/// have no deadline pending), the plant ticks in batches this long. The
/// clock slips only when a wake comes later than the batch's last tick by
/// more than the catch-up, so a batch may be longer than that; each batch
/// is a wake-up of every module's engine, and a newcomer, a command or a
/// request that finds the plant behind wakes it at once (the plant catches
/// up before it is served). An idle class of 35 modules, debug build: 47 %
/// of a core at 10 ms, 32 % at 20, 22 % at 40; 100 ms took 0.63× the CPU of
/// 20 ms in the same run (`serve-bench class --modules 35 --hz 0`, a loaded
/// machine).
const IDLE_BATCH: SimDuration = SimDuration::from_millis(100);
/// The batch while clients are connected (and nothing is pending). Its
/// length trades the server's CPU against how late a batch's ticks run:
/// release builds in the same runs (`serve-bench class --hz 100`, the
/// knob below), 35 modules: 10 ms took 0.78× the CPU of 20 or 100 ms but
/// its tick lateness p99 was 8.8× theirs and its reply p99 1.9× (machine
/// mostly idle; 20 and 100 ms alike); 100 modules: 10 and 20 ms ran
/// 1.7-12× later than 100 ms at p99 (every module's bursts of ticks
/// contend for the two cores), so 100 ms, as for an idle module.
const POLLED_BATCH: SimDuration = SimDuration::from_millis(100);
/// How often the engine looks for connections past their idle timeout.
const IDLE_CHECK_PERIOD: SimDuration = SimDuration::from_millis(100);

/// The spin: `TWIN_RT_SPIN_US` (microseconds) if set, else [`SPIN`]. A
/// tuning knob for measuring, not an option: the default is what was kept.
fn spin_from_env() -> SimDuration {
    std::env::var("TWIN_RT_SPIN_US")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .map_or(SPIN, SimDuration::from_micros)
}

/// A batch: the milliseconds in the environment variable `var` (at least
/// one tick) if set, else `default`. Tuning knobs for measuring, like the
/// spin's: `TWIN_RT_BATCH_MS` ([`IDLE_BATCH`]) and `TWIN_RT_POLLED_BATCH_MS`
/// ([`POLLED_BATCH`]).
fn batch_from_env(var: &str, default: SimDuration) -> SimDuration {
    std::env::var(var)
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .map_or(default, SimDuration::from_millis)
}

/// What a session reports at its end.
#[derive(Debug, Clone)]
pub struct RtSummary {
    pub elapsed: SimDuration,
    pub lateness: LatenessSummary,
    pub counters: RtCounters,
    pub stopped_by: String,
    /// How long the connections waited, summed, for the recording to catch
    /// up (see [`crate::frame_log::Backlog`]).
    pub waited_for_recording: std::time::Duration,
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
    /// How long before a deadline the thread stops sleeping and spins.
    spin: SimDuration,
    plant_step: SimDuration,
    tick: SimDuration,
    /// The next plant tick: every one before it has run.
    next_tick: SimTime,
    record_period: SimDuration,
    next_record: SimTime,
    /// Whether anyone takes the plant samples and readings (a recording, a
    /// live view): without, the sink is not woken for them.
    samples_wanted: bool,
    status_period: SimDuration,
    next_status: SimTime,
    next_second: SimTime,
    /// When the engine next looks for connections past their idle timeout.
    next_idle_check: SimTime,
    sink: Sender<SinkMsg>,
    /// The sketches' UART bursts and I/O samples on their way to the sink.
    firmware_log: FirmwareLog,
    lateness: Lateness,
    window: Lateness,
    pub counters: RtCounters,
    stop: Option<String>,
    /// How far behind the wall the ticks catch up before the clock slips,
    /// and what the slip spares, in the user's words.
    catch_up: SimDuration,
    slip_spares: &'static str,
    /// A line said (even with the monitor off) for a device's event, when
    /// the session's role has one to say: `twin supervise`'s hint at its
    /// first timeout from each slave.
    pub event_hint: Option<EventHint>,
}

/// What a role says about a device's event, if anything.
pub type EventHint = Box<dyn FnMut(&nodes::node::NodeEvent) -> Option<String> + Send>;

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
            spin: spin_from_env(),
            plant_step,
            tick: super::front::TICK,
            next_tick: SimTime::ZERO,
            record_period,
            next_record: SimTime::ZERO,
            samples_wanted: true,
            status_period: SimDuration::from_secs(1),
            next_status: SimTime::ZERO + SimDuration::from_secs(1),
            next_second: SimTime::ZERO + SimDuration::from_secs(1),
            next_idle_check: SimTime::ZERO,
            sink,
            firmware_log: FirmwareLog::default(),
            lateness: Lateness::new(),
            window: Lateness::new(),
            counters: RtCounters::default(),
            stop: None,
            catch_up: CATCH_UP,
            slip_spares: "so that no step of the plant or the firmware was skipped",
            event_hint: None,
        }
    }

    /// How far behind the wall the engine catches up, tick by tick, before
    /// the clock slips (default [`CATCH_UP`]), and what the slip spares
    /// (said with it, "so that …"). A role with no plant to step through
    /// lost time, only timers (a master's reply timeouts), catches up
    /// little: a burst would spend a stall as time its timers waited.
    pub fn set_catch_up(&mut self, catch_up: SimDuration, spares: &'static str) {
        self.catch_up = catch_up;
        self.slip_spares = spares;
    }

    /// Whether the plant samples and the controllers' readings go to the
    /// sink: not when the session neither records nor shows them (an idle
    /// class's sinks woke a hundred times a second each for nothing).
    pub fn set_samples_wanted(&mut self, wanted: bool) {
        self.samples_wanted = wanted;
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

    /// Forces `forced` on every device, each with its module's light
    /// sensor (a forced flag sets the photoresistor's volts too): the
    /// console's `force` and the panel's alike.
    pub fn force(&mut self, forced: crate::forces::Forced) {
        let Self {
            devices, modules, ..
        } = self;
        for d in devices.iter_mut() {
            let light = d
                .module
                .and_then(|m| modules.get(m))
                .map(|m| &m.plant.params().light);
            d.forces.force(forced, light);
        }
    }

    /// Every open connection's endpoint, for a command that changes how
    /// they answer (the panel's slave id and I/O map).
    pub fn endpoints_mut(&mut self) -> impl Iterator<Item = &mut Box<dyn crate::Endpoint>> {
        self.conns.values_mut().map(|c| &mut c.endpoint)
    }

    /// Whether every slave front end refuses writes.
    pub fn read_only(&self) -> bool {
        self.read_only
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

    /// Swaps the connections' state between the engine and `front`: the
    /// engine's own fields hold it between runs and while a console command
    /// or a firmware tick runs (the front locked), the front the rest of
    /// the time. Moves a few words, never the data.
    fn swap_front(&mut self, front: &mut Front) {
        std::mem::swap(&mut self.devices, &mut front.devices);
        std::mem::swap(&mut self.conns, &mut front.conns);
        std::mem::swap(&mut self.fault, &mut front.fault);
        std::mem::swap(&mut self.counters, &mut front.counters);
    }

    /// Runs `f` on the engine with the front's state in its fields.
    fn with_front<R>(&mut self, front: &FrontHandle, f: impl FnOnce(&mut Self) -> R) -> R {
        let mut shared = front.lock();
        self.swap_front(&mut shared);
        let result = f(self);
        self.swap_front(&mut shared);
        result
    }

    /// Run until `end` (if any) or a [`Inbound::Stop`].
    pub fn run(&mut self, inbound: &Receiver<Inbound>, end: Option<SimTime>) -> RtSummary {
        // The kernel may fire a sleeping thread's timer up to its slack late
        // (50 µs by default) to merge wake-ups; this thread's deadlines are
        // worth a wake-up each, and without the slack the spin before them
        // can be short.
        let _ = rustix::thread::set_current_timer_slack(std::num::NonZeroU64::new(1));
        // While the engine sleeps through a batch, a carrier whose request
        // finds the plant behind ticks it up to the request's arrival
        // itself ([`FrontHandle::catch_up`]), holding the engine: it is shared
        // for the run, and given back whole at its end.
        let stand_in = Self::new(
            self.clock.clone(),
            self.plant_step,
            self.record_period,
            self.sink.clone(),
        );
        let shared = Arc::new(SharedEngine(Mutex::new(std::mem::replace(self, stand_in))));
        let front = {
            let engine = shared.lock();
            FrontHandle::new(
                Front::new(engine.sink.clone(), engine.clock.clone(), &engine.links),
                Some(shared.clone()),
            )
        };
        let summary = SharedEngine::run(&shared, &front, inbound, end);
        std::mem::swap(self, &mut *shared.lock());
        summary
    }

    /// The ticks a request that came `at` needs, if the plant is behind it
    /// (a carrier's catch-up, while the engine sleeps through a batch):
    /// they come late by the time since the request's arrival.
    fn catch_up(&mut self, at: SimTime, front: &FrontHandle) {
        let wall = self.clock.now();
        let to = at.min(wall);
        if to >= self.next_tick {
            self.tick_through(to, Some(wall.saturating_since(at)), front);
        }
    }

    /// The loop's plan after a pass: ticks due by now, the sketches
    /// followed, the links' timers serviced; then when to wake next, and
    /// whether to spin for it. `aimed` is the tick the last wait was for.
    fn pass(
        &mut self,
        front: &FrontHandle,
        end: Option<SimTime>,
        aimed: &mut SimTime,
        batches: (SimDuration, SimDuration),
    ) -> (SimTime, bool) {
        let now = self.clock.now();
        // Through a batch the ticks wait for its last (or a message):
        // a request caught up to its arrival is answered from there.
        if now >= self.next_tick && now >= *aimed {
            let late = now.saturating_since(*aimed);
            self.tick_through(now, Some(late), front);
            // On the session's clock, which may have slipped.
            if end.is_some_and(|e| self.clock.now() >= e) && self.stop.is_none() {
                self.stop = Some("duration reached".into());
            }
        }
        self.follow(front);
        let next_tick = self.next_tick;
        // With no one connected nothing reads the plant between ticks,
        // so they run in batches: the same ticks in the same order, on
        // a hundredth of the wake-ups (a class of idle modules paid for
        // 1000 a second each), never past the session's end. Clients
        // that are answered from the image when their bytes come, with
        // no deadline pending, read the plant only then: the engine
        // batches for them too, and a request that finds the plant
        // behind has it caught up first (`After::Behind`), so a polled
        // module costs its requests, not a thousand wake-ups a second.
        // Requests faster than `BUSY_GAP` keep it ticking every
        // millisecond, where that is cheaper than catching up for each.
        let (next, follow) = {
            let mut shared = front.lock();
            let now = self.clock.now();
            shared.service_timers(now);
            shared.ship_frames();
            let next = shared.next_deadline();
            let unread =
                shared.conns.is_empty() || (shared.answers_at_once() && !shared.requests_busy(now));
            *aimed = if unread && next.is_none() {
                let (idle_batch, polled_batch) = batches;
                let batch = if shared.conns.is_empty() {
                    idle_batch
                } else {
                    polled_batch
                };
                let last = next_tick + SimDuration(batch.0 - self.tick.0);
                end.map_or(last, |e| last.min(e.max(next_tick)))
            } else {
                next_tick
            };
            shared.batching = *aimed > next_tick;
            // The clock slips when the wake is late for the tick it
            // waited for, not for the batch's length.
            shared.ticked_to = *aimed;
            (next, shared.next_follow())
        };
        // Only a link's deadline (a reply's turnaround, a timer) is
        // worth spinning for: a plant tick a few tens of microseconds
        // late computes the same step, and spinning before each one
        // cost an idle class of 35 modules 1.6 cores.
        let (deadline, spin) = match next {
            Some(d) if d < *aimed => (d, true),
            _ => (*aimed, false),
        };
        // A sketch followed between the ticks: its loop period is
        // 100 µs or so, and a few tens of µs late it computes the same.
        match follow {
            Some(f) if f < deadline => (f, false),
            _ => (deadline, spin),
        }
    }

    /// `message`, and everything already queued behind it. The plant
    /// catches up first: a newcomer's first request, or a command, meets
    /// the plant of now, not of a batch ago.
    fn handle_all(
        &mut self,
        message: Inbound,
        inbound: &Receiver<Inbound>,
        front: &FrontHandle,
        aimed: SimTime,
    ) {
        let wall = self.clock.now();
        if wall >= self.next_tick {
            // How late the ticks come for what needed them: the wait's aim.
            let late = (wall >= aimed).then(|| wall.saturating_since(aimed));
            self.tick_through(wall, late, front);
        }
        let mut message = Some(message);
        while let Some(m) = message.take() {
            self.handle(m, front);
            message = inbound.try_recv().ok();
        }
    }

    /// The session's end: every connection closed, the last lateness
    /// sent, the summary.
    fn finish(&mut self, front: &FrontHandle) -> RtSummary {
        let waited_for_recording = {
            let mut shared = front.lock();
            shared.close_all();
            self.swap_front(&mut shared);
            shared.backlog().waited()
        };
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
            waited_for_recording,
        }
    }

    fn handle(&mut self, message: Inbound, front: &FrontHandle) {
        match message {
            Inbound::Opened {
                link,
                conn,
                peer,
                task,
                probation,
            } => self.open(link, conn, peer, task, probation, front),
            Inbound::Closed { conn, why } => front.lock().closed(conn, &why),
            Inbound::Command(command) => self.with_front(front, command),
            Inbound::Room {
                link,
                min_idle,
                answer,
            } => {
                let _ = answer.send(front.lock().room_possible(link, min_idle));
            }
            // The loop looks at the connections' deadlines again.
            Inbound::Wake => {}
            Inbound::Stop(why) => {
                self.stop.get_or_insert(why);
            }
        }
    }

    fn open(
        &mut self,
        link: usize,
        id: ConnId,
        peer: String,
        task: LinkTask,
        probation: Option<Probation>,
        front: &FrontHandle,
    ) {
        let Some(config) = self.links.get_mut(link) else {
            task.close(format!("no link {link}"), Outgoing::default());
            return;
        };
        let mut shared = front.lock();
        let mut endpoint = (config.factory)(&mut shared.devices, &peer);
        if let Some(f) = endpoint.frontend_mut() {
            f.set_read_only(self.read_only);
            if let Some((LinkFault::Exception(r), l)) = shared.fault
                && l.is_none_or(|l| l == link)
            {
                f.set_forced_refusal(Some(r));
            }
        }
        // The task answers this connection's requests itself from now on.
        let _ = task.out.send(Outbound::Direct(front.clone()));
        shared.open(config, link, id, peer, endpoint, task);
        if let Some(probation) = probation {
            shared.on_probation(id, probation);
        }
    }

    /// The firmware loops due by now that a link wants run before the next
    /// tick (a sketch that owes a reply, bytes that wait for a core to
    /// reach their arrival: [`crate::Endpoint::follow`]), so a reply the
    /// sketch writes mid-tick leaves then, not at the next tick. The plant
    /// advances to each loop tick as in a tick (lazily, in its own steps),
    /// never beyond `next_tick`, which the engine's tick runs.
    fn follow(&mut self, front: &FrontHandle) {
        let now = self.clock.now().min(self.next_tick);
        if front.lock().next_follow().is_some_and(|due| due <= now) {
            self.with_front(front, |engine| engine.firmware_loops(now));
        }
    }

    /// The ticks due at `now` from the next one on, every one in order.
    /// `late`: how late they come for what needed them (the tick the wait
    /// was for, or the request that found the plant behind), if anything
    /// did. A wake more than `CATCH_UP` behind (a stopped process, a
    /// machine too busy to keep up) slips the session's clock by the excess
    /// rather than skip ticks: the plant and every node, a sketch's pins
    /// included, step through the whole interval at their own resolution, a
    /// little late, and never compute from a jump in their inputs.
    fn tick_through(&mut self, now: SimTime, late: Option<SimDuration>, front: &FrontHandle) {
        if let Some(late) = late {
            let ns = late.0 / TICKS_PER_NANO;
            self.lateness.record(ns);
            self.window.record(ns);
            if late > self.tick {
                self.lateness.overruns += 1;
                self.window.overruns += 1;
            }
        }
        // Behind by more than `CATCH_UP`, the clock slips (here, or a
        // carrier did when bytes came after the stall).
        let now = {
            let mut shared = front.lock();
            let now = shared.hold_clock(now);
            let slips = std::mem::take(&mut shared.slips);
            self.lateness.slipped(slips.count, slips.ns);
            self.window.slipped(slips.count, slips.ns);
            now
        };
        while self.next_tick <= now {
            self.plant_tick(self.next_tick, front);
            self.next_tick += self.tick;
        }
        let mut shared = front.lock();
        shared.ticked_to = self.next_tick;
        shared.plant_to = self.next_tick;
    }

    fn plant_tick(&mut self, t: SimTime, front: &FrontHandle) {
        // The firmware loops and the status line need the devices (the
        // front locked); the plant steps do not, so requests are answered
        // while they run.
        let record = self.samples_wanted && t >= self.next_record;
        self.with_front(front, |engine| engine.firmware_ticks(t, record));
        for module in &mut self.modules {
            module.advance(self.plant_step, t);
        }
        if record {
            for (m, module) in self.modules.iter().enumerate() {
                let _ = self.sink.send(SinkMsg::Plant {
                    at: t,
                    module: m,
                    sensors: Box::new(*module.plant.sensors()),
                });
            }
            self.next_record = t + self.record_period;
        }
        if t >= self.next_idle_check {
            // Not a deadline of each connection's: that would make every
            // carrier wait on the engine's timers after each request.
            front.lock().close_idle(t);
            self.next_idle_check = t + IDLE_CHECK_PERIOD;
        }
        if t >= self.next_second {
            let window = self.window.summary();
            if window.slips > 0 {
                self.say_slip(t, window.slipped_ms);
            }
            let _ = self.sink.send(SinkMsg::Lateness {
                at: t,
                window,
                total: self.lateness.summary(),
            });
            self.window.clear();
            self.next_second += SimDuration::from_secs(1);
        }
    }

    /// Real time lost in the last second, said once for it: on the console
    /// beside the status lines (even with the monitor off; with the status
    /// lines off, only in the session's last lines), as an event of the
    /// recording and the panel's list.
    fn say_slip(&self, t: SimTime, slipped_ms: f64) {
        let detail = format!(
            "real time lost: {slipped_ms:.0} ms (the machine stopped the twin or was too busy to \
             keep up; its clock slipped {})",
            self.slip_spares
        );
        if self.status_period > SimDuration::ZERO {
            let _ = self.sink.send(SinkMsg::Say(detail.clone()));
        }
        let _ = self.sink.send(SinkMsg::Event {
            node: SLIP_NODE.into(),
            event: nodes::node::NodeEvent {
                at: t,
                kind: "slip",
                detail,
            },
        });
    }

    /// The firmware loops due at `t`, the devices' events, the status line.
    /// At a recording instant (`record`) the module controllers' readings go
    /// to the sink too, beside the plant samples.
    fn firmware_ticks(&mut self, t: SimTime, record: bool) {
        self.firmware_loops(t);
        self.firmware_reports(t, record);
    }

    /// The firmware loops due at `t`, each device's in time order.
    fn firmware_loops(&mut self, t: SimTime) {
        // Each firmware's loop at its own period, in time order across the
        // devices: a sketch's pins are fed every 100 µs or so (an encoder's
        // edges come faster than the engine's 1 ms tick), the Rust nodes'
        // loops once a tick or less. Ticks the machine delayed are caught up
        // in order (a sketch's core runs those cycles anyway, and its pins
        // must see the plant's edges when they came).
        while let Some((d, due)) = self
            .devices
            .iter()
            .enumerate()
            .filter(|(_, device)| device.module.is_some())
            .filter_map(|(d, device)| Some((d, device.next_tick?)))
            .filter(|&(_, due)| due <= t)
            .min_by_key(|&(d, due)| (due, d))
        {
            let Some(device) = self.devices.get_mut(d) else {
                break;
            };
            let Some(m) = device.module else {
                break;
            };
            let Some(module) = self.modules.get_mut(m) else {
                device.next_tick = None;
                continue;
            };
            let forces = device.forces;
            let sensing = module.plant.params().sensing.clone();
            let hall_lines = &mut device.hall_lines;
            let ticked = firmware_tick(device.node.as_mut(), module, self.plant_step, due, |s| {
                forces.apply_sensors(s, &sensing);
                hall_lines.apply(forces.hall, due.as_secs_f64(), &mut s.shaft);
            });
            let Some((next, changed)) = ticked else {
                device.next_tick = None;
                continue;
            };
            device.next_tick = Some(next.max(due + SimDuration(1)));
            if let Some(image) = device.node.image_mut() {
                forces.apply_words(image);
            }
            if changed {
                let _ = self.sink.send(SinkMsg::Actuators {
                    at: due,
                    module: m,
                    actuators: module.actuators,
                });
            }
            if !device.failed
                && let Some(why) = device.node.failure()
            {
                // Said even with the monitor off: the master's timeouts
                // from now on have this reason.
                device.failed = true;
                let _ = self
                    .sink
                    .send(SinkMsg::Say(format!("{}: {why}", device.name)));
            }
        }
    }

    /// What the loops run so far have to say: readings at a recording
    /// instant (`record`), the sketches' channels, the devices' events, the
    /// status line. Once a tick: a sketch followed between the ticks
    /// reports at the next one, so the sink is not woken ten times a tick.
    fn firmware_reports(&mut self, t: SimTime, record: bool) {
        if record {
            for device in &self.devices {
                if let (Some(module), Some(readings)) =
                    (device.module, device.node.controller_readings())
                {
                    let _ = self.sink.send(SinkMsg::Readings {
                        at: t,
                        module,
                        readings,
                    });
                }
            }
        }
        // The sketches' own channels (UART bursts, pins, ADC inputs,
        // cycles), as a virtual run records them.
        for device in &mut self.devices {
            let log = &mut self.firmware_log;
            let name = device.name.as_str();
            let _ = device.node.firmware_records(&mut |record| {
                log.push(name, record);
                Ok(())
            });
        }
        if let Some(batch) = self.firmware_log.take() {
            let _ = self.sink.send(SinkMsg::Firmware(batch));
        }
        // Devices' events (trips, a supervisor's timeouts) whatever drives them.
        for device in &mut self.devices {
            while let Some(event) = device.node.poll_event() {
                if let Some(line) = self.event_hint.as_mut().and_then(|hint| hint(&event)) {
                    let _ = self.sink.send(SinkMsg::Say(line));
                }
                let _ = self.sink.send(SinkMsg::Event {
                    node: device.name.clone(),
                    event,
                });
            }
            // A master's loop state, once per poll cycle (as in a virtual run).
            if let Some(report) = device.node.loop_report() {
                let _ = self.sink.send(SinkMsg::Telemetry {
                    at: t,
                    node: device.name.clone(),
                    report,
                });
            }
        }
        if self.status_period > SimDuration::ZERO && t >= self.next_status {
            let line = self.status_line(t);
            let _ = self.sink.send(SinkMsg::Say(line));
            self.next_status += self.status_period;
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
            line += &format!(" {} forced {};", device.name, device.forces);
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
            line += &format!("; fault {fault}");
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

/// What the link tasks (and the console) send the engine.
pub enum Inbound {
    /// A connection opened on link `link` (a TCP client, a serial port).
    Opened {
        link: usize,
        conn: ConnId,
        peer: String,
        task: LinkTask,
        /// Let in beyond a full listener's limit (see [`Probation`]).
        probation: Option<Probation>,
    },
    /// The connection is gone (peer closed, port vanished).
    Closed { conn: ConnId, why: String },
    /// A connection now waits for a timer (a turnaround, pacing, the RTU
    /// silence): the engine looks at the deadlines again.
    Wake,
    /// Run this on the engine's thread (console commands, other front ends).
    Command(Box<dyn FnOnce(&mut RtEngine) + Send>),
    /// Link `link` is full and has a newcomer: `answer` says whether a
    /// client there could make room for it (quiet for `min_idle`, never if
    /// `None`, or holding a partial frame too long); if so, the newcomer is
    /// let in on [`Probation`].
    Room {
        link: usize,
        min_idle: Option<SimDuration>,
        answer: tokio::sync::oneshot::Sender<bool>,
    },
    /// Stop the session (SIGINT, SIGTERM).
    Stop(String),
}

impl std::fmt::Debug for Inbound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Inbound::Opened { link, conn, .. } => write!(f, "Opened({link}, {conn})"),
            Inbound::Closed { conn, why } => write!(f, "Closed({conn}, {why})"),
            Inbound::Command(_) => write!(f, "Command"),
            Inbound::Room { link, .. } => write!(f, "Room({link})"),
            Inbound::Wake => write!(f, "Wake"),
            Inbound::Stop(why) => write!(f, "Stop({why})"),
        }
    }
}

/// The engine while it runs: its thread holds it except while it waits,
/// and a carrier whose request finds the plant behind a batch holds it to
/// tick the plant up to the request's arrival ([`CatchUp`]). Before, the
/// carrier asked the engine over its channel and waited for its signal:
/// two thread switches more per request, about 45 µs of CPU a request (35
/// modules polled at 100 Hz took 22-28 % of a core, now 14-20 %).
struct SharedEngine(Mutex<RtEngine>);

impl SharedEngine {
    /// The engine. A carrier that panicked holding it left whole ticks
    /// behind (a tick is run whole or not begun), so poisoning is ignored.
    fn lock(&self) -> MutexGuard<'_, RtEngine> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn run(
        shared: &Arc<Self>,
        front: &FrontHandle,
        inbound: &Receiver<Inbound>,
        end: Option<SimTime>,
    ) -> RtSummary {
        let (clock, spin, batches) = {
            let mut engine = shared.lock();
            engine.swap_front(&mut front.lock());
            front.lock().catch_up = engine.catch_up;
            engine.next_tick = SimTime::ZERO;
            let idle_batch = batch_from_env("TWIN_RT_BATCH_MS", IDLE_BATCH).max(engine.tick);
            let polled_batch =
                batch_from_env("TWIN_RT_POLLED_BATCH_MS", POLLED_BATCH).max(engine.tick);
            (
                engine.clock.clone(),
                engine.spin,
                (idle_batch, polled_batch),
            )
        };
        // The tick the last wait was for: the next one, or the last of a
        // batch while nothing reads the plant between ticks.
        let mut aimed = SimTime::ZERO;
        loop {
            let (deadline, spin_to) = {
                let mut engine = shared.lock();
                let plan = engine.pass(front, end, &mut aimed, batches);
                if engine.stop.is_some() {
                    break;
                }
                plan
            };
            match wait(&clock, spin, inbound, deadline, spin_to) {
                Waited::Deadline => {}
                Waited::Message(message) => {
                    shared.lock().handle_all(message, inbound, front, aimed);
                }
                Waited::Closed => {
                    shared
                        .lock()
                        .stop
                        .get_or_insert_with(|| "all links closed".into());
                }
            }
        }
        shared.lock().finish(front)
    }
}

impl CatchUp for SharedEngine {
    fn catch_up(&self, at: SimTime, front: &FrontHandle) {
        self.lock().catch_up(at, front);
    }
}

/// What a wait ended with.
enum Waited {
    Deadline,
    Message(Inbound),
    /// Every sender is gone.
    Closed,
}

/// Blocks until a message arrives or `deadline` passes: sleeps on the
/// channel until `spin` before it, then spins (with `spin_to`), or sleeps
/// to the deadline itself.
fn wait(
    clock: &RtClock,
    spin: SimDuration,
    inbound: &Receiver<Inbound>,
    deadline: SimTime,
    spin_to: bool,
) -> Waited {
    let wake = clock.instant(deadline);
    let ahead = if spin_to { spin.0 } else { 0 };
    let sleep_until = clock.instant(SimTime(deadline.0.saturating_sub(ahead)));
    let now = Instant::now();
    if sleep_until > now {
        match inbound.recv_timeout(sleep_until - now) {
            Ok(message) => return Waited::Message(message),
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => return Waited::Closed,
        }
    }
    loop {
        match inbound.try_recv() {
            Ok(message) => return Waited::Message(message),
            Err(TryRecvError::Empty) => {}
            Err(TryRecvError::Disconnected) => return Waited::Closed,
        }
        if Instant::now() >= wake {
            return Waited::Deadline;
        }
        std::hint::spin_loop();
    }
}
