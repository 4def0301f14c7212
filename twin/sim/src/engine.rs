//! The virtual-time engine: modules, nodes and buses on one discrete-event
//! clock, far faster than real time and deterministic.
//!
//! One loop jumps from event to event: a byte finishing on a bus, a node's
//! timer, a firmware loop tick, a recording instant. The plants are advanced
//! lazily, in fixed steps, to each instant that needs them. At equal times the
//! order is fixed (buses, then firmware ticks, then node timers, then
//! transmissions, each in declaration order), so the same scenario and seed
//! always give the same run.

use nodes::link::{BusError, BusEvent, LineMark, Medium, PortId};
use nodes::node::{Firmware, MAX_FRAME, Node, NodeEvent};
use plant::{Actuators, EvModule};
use protocols::time::{SimDuration, SimTime};
use twin_recording::WriteError;
use twin_recording::topics::{LoopReport, ReadingsSample};

/// Why the engine stopped a run before its end.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// Nodes that keep asking to be woken at an instant already handled.
    #[error(
        "simulated time stopped at {at_s:.6} s: node(s) {nodes} ask to be woken again and again at that instant"
    )]
    Stalled { at_s: f64, nodes: String },
    /// A node that cannot go on ([`SimNode::failure`]: compiled firmware
    /// that crashed), in its own words.
    #[error("node `{node}`: {why}")]
    NodeFailed { node: String, why: String },
    /// A bus refused what a node sent on it.
    #[error("bus `{bus}`")]
    Bus {
        bus: String,
        #[source]
        source: BusError,
    },
    /// An observer could not keep what it was given.
    #[error(transparent)]
    Observer(#[from] ObserveError),
}

/// Why an [`Observer`] could not keep what the engine reported.
#[derive(Debug, thiserror::Error)]
pub enum ObserveError {
    /// The recording could not be written (the disk guard's stop is
    /// [`WriteError::DiskFull`]).
    #[error(transparent)]
    Recording(#[from] WriteError),
    /// An observer of another crate failed (a live view), in its own words.
    #[error(transparent)]
    Other(Box<dyn std::error::Error + Send + Sync>),
}

type Result<T, E = ObserveError> = std::result::Result<T, E>;

/// Passes of the loop at one instant after which the engine calls it a stall
/// (a busy bus with many nodes takes a few dozen).
const STALL_PASSES: u32 = 100_000;

/// A node as the engine drives it: the sans-IO node plus what recording and
/// the plant need from it.
pub trait SimNode: Node {
    /// The firmware, for nodes that run a module.
    fn firmware(&mut self) -> Option<&mut dyn Firmware> {
        None
    }
    /// Internals worth recording now (a master's loop state), if changed
    /// since the last call.
    fn telemetry(&mut self) -> Option<serde_json::Value> {
        None
    }
    /// The master's loop report, if changed since the last call: its
    /// [`SimNode::telemetry`] unless the node gives a typed one (a
    /// supervisor's, which is recorded without building a JSON value).
    /// Asked only when an observer keeps it.
    fn loop_report(&mut self) -> Option<LoopReport> {
        self.telemetry().map(LoopReport::Other)
    }
    /// A report [`SimNode::loop_report`] gave, handed back once observed,
    /// so that the next one reuses what it holds.
    fn recycle_loop_report(&mut self, report: LoopReport) {
        drop(report);
    }
    /// Whether the firmware's actuators drive its module (a sensor-only
    /// node, like the Controller_network light sensor, only reads it).
    fn drives_plant(&self) -> bool {
        true
    }
    /// A summary of the node's state for the end-of-run report.
    fn final_state(&self) -> Option<serde_json::Value> {
        None
    }
    /// The register image, for nodes whose image other front ends serve
    /// too (the real-time server's links).
    fn image_mut(&mut self) -> Option<&mut nodes::firmware::RegisterImage> {
        None
    }
    /// The supervisor, for nodes that are one (its TCP server reads its image).
    fn supervisor_mut(&mut self) -> Option<&mut nodes::master::Supervisor> {
        None
    }
    /// What the node's own speed sensors read now (firmware nodes).
    fn speed_readings(&self) -> SpeedReadings {
        SpeedReadings::default()
    }
    /// An EV module controller's readings, recorded beside its module's
    /// plant samples on `/controller/<node>/readings`.
    fn controller_readings(&self) -> Option<ReadingsSample> {
        None
    }
    /// Why the node cannot go on (compiled firmware that crashed), in the
    /// user's words: the engine stops the run with it.
    fn failure(&self) -> Option<String> {
        None
    }
    /// Requests for the node (`asked` of them, the first at `since`) have
    /// gone unanswered until `now` (the real-time server's watchdog):
    /// compiled firmware is marked dead, its [`SimNode::failure`] saying
    /// where its program is; a node that cannot hang ignores it.
    fn not_answering(&mut self, _now: SimTime, _since: SimTime, _asked: u32) {}
    /// Whether the node can compute ahead of the engine's clock on its own
    /// (compiled firmware on a thread of its own) until its next input.
    fn can_run_ahead(&self) -> bool {
        false
    }
    /// Nothing reaches the node before `horizon` (no byte, no loop tick):
    /// it may compute up to there now, on its own thread, as long as it
    /// ends exactly as if it had waited for its next input.
    fn run_ahead(&mut self, horizon: SimTime) {
        let _ = horizon;
    }
    /// Whether the node hands the bus bytes whose wire time may have begun
    /// before the engine touched it (compiled firmware, whose bytes are
    /// found when its core is run): its bytes can arrive at that instant.
    fn streams_bytes(&self) -> bool {
        false
    }
    /// Asked once, when the node joins a serial bus: whether it will hand
    /// its bytes over one by one through [`SimNode::poll_stream`] from now
    /// on, each at its own wire time, instead of whole frames through
    /// `poll_transmit`.
    fn start_streaming(&mut self) -> bool {
        false
    }
    /// The next byte the node put on its wire, or the end of its frame.
    fn poll_stream(&mut self, now: SimTime) -> Option<Streamed> {
        let _ = now;
        None
    }
    /// The compiled firmware the node runs, to store whole in the
    /// recording (so that a replay runs the same bytes).
    fn firmware_file(&self) -> Option<FirmwareFile> {
        None
    }
    /// Hands `record` what the node keeps for its own channels since the
    /// last call (compiled firmware: UART bursts, pins, ADC inputs, cycles).
    fn firmware_records(
        &mut self,
        record: &mut dyn FnMut(FirmwareRecord<'_>) -> Result<()>,
    ) -> Result<()> {
        let _ = record;
        Ok(())
    }
}

/// A compiled firmware file as a recording stores it: its metadata fields
/// (`twin.firmware.<node>`) and its bytes (the attachment the fields name).
#[derive(Debug, Clone)]
pub struct FirmwareFile {
    pub fields: std::collections::BTreeMap<String, String>,
    /// The attachment's name.
    pub attachment: String,
    pub bytes: Vec<u8>,
}

/// A record of a firmware node's own channels, at simulated time `at`.
#[derive(Debug, Clone, Copy)]
pub enum FirmwareRecord<'a> {
    Uart(SimTime, twin_recording::topics::UartBurst<'a>),
    Io(SimTime, twin_recording::topics::FirmwareIo<'a>),
}

/// What a streaming node (compiled firmware) hands the bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Streamed {
    /// A byte, on the node's wire during `[start, end)`.
    Byte {
        byte: u8,
        start: SimTime,
        end: SimTime,
    },
    /// The node's line has gone quiet: its frame is complete.
    End,
}

/// A firmware node's speed estimates, as its registers hold them.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SpeedReadings {
    /// Wheel rpm from the hall edges (the EV controller's `RPM_M`).
    pub hall_wheel_rpm: Option<f64>,
    /// Motor-shaft rpm from an encoder (the Controller_network motor node,
    /// register 0005).
    pub motor_shaft_rpm: Option<f64>,
    /// Wheel rpm from the photoresistor's dips.
    pub light_rpm: Option<f64>,
    /// The speed the node's own loop holds, motor rpm (the Controller_network
    /// motor node: its set point while operational, 0 otherwise).
    pub set_point_motor_rpm: Option<f64>,
}

/// One bench module and the plant time it has reached.
pub struct ModuleSlot {
    pub name: String,
    pub plant: EvModule,
    pub actuators: Actuators,
    plant_time: SimTime,
}

impl ModuleSlot {
    /// A module whose plant has reached time zero.
    pub fn new(name: &str, plant: EvModule) -> Self {
        Self {
            name: name.into(),
            plant,
            actuators: Actuators::default(),
            plant_time: SimTime::ZERO,
        }
    }

    /// The time the plant has reached.
    pub fn plant_time(&self) -> SimTime {
        self.plant_time
    }

    /// Step the plant up to `t` in whole steps of `step` (and a last partial
    /// one if `t` is off the grid).
    pub fn advance(&mut self, step: SimDuration, t: SimTime) {
        while self.plant_time < t {
            let dt = step.min(t.saturating_since(self.plant_time));
            self.plant.step(dt.as_secs_f64(), &self.actuators);
            self.plant_time += dt;
        }
    }
}

/// One firmware loop pass of `node` at `t`, shared by the virtual and the
/// real-time engine: the module's plant advanced to `t`, its sensors (as
/// `adjust` leaves them: the real-time server's forced inputs) handed to the
/// firmware, the actuators it answers applied. Returns the firmware's next
/// tick and whether the actuators changed; `None` if `node` has no firmware.
pub fn firmware_tick(
    node: &mut dyn SimNode,
    module: &mut ModuleSlot,
    plant_step: SimDuration,
    t: SimTime,
    adjust: impl FnOnce(&mut plant::Sensors),
) -> Option<(SimTime, bool)> {
    module.advance(plant_step, t);
    let mut sensors = *module.plant.sensors();
    adjust(&mut sensors);
    let drives_plant = node.drives_plant();
    let fw = node.firmware()?;
    let actuators = fw.loop_tick(t, &sensors);
    let next = t + fw.loop_period();
    // A sensor-only node (the Controller_network light sensor) watches the bench that
    // another node drives: its idle pins must not overwrite the driver's.
    if !drives_plant {
        return Some((next, false));
    }
    let changed = module.actuators != actuators;
    module.actuators = actuators;
    Some((next, changed))
}

/// One node, where it is attached and when its firmware ticks next.
pub struct NodeSlot {
    pub name: String,
    pub node: Box<dyn SimNode>,
    pub bus: usize,
    pub port: PortId,
    pub module: Option<usize>,
    next_tick: Option<SimTime>,
    /// Given an input (bytes, a timeout, the end of its transmission, a loop
    /// tick) since its output was last drained. A sans-IO node's output only
    /// changes on an input, and every instant it waits for is an input
    /// through its `poll_timeout`, so the others need not be asked.
    stirred: bool,
    /// Hands its bytes over one by one ([`SimNode::poll_stream`]).
    streams: bool,
    /// Could compute ahead of the engine when added ([`SimNode::can_run_ahead`],
    /// which only a failure turns off later): the others are not asked at
    /// every event.
    may_run_ahead: bool,
    /// In the middle of a streamed frame.
    stream_open: bool,
}

/// A bus and its name.
pub struct BusSlot {
    pub name: String,
    pub bus: Medium,
    /// Node index of each port.
    pub owners: Vec<usize>,
    /// Node name of each port, for the recording.
    pub port_names: Vec<String>,
    /// Per port: the last frame it sent, and the frame it is receiving.
    sent: Vec<Vec<u8>>,
    receiving: Vec<Reception>,
    pub checks: CheckTally,
}

/// A frame as one receiver gets it.
#[derive(Default)]
struct Reception {
    bytes: Vec<u8>,
    corrupted: bool,
    from: Option<PortId>,
    counted: bool,
}

/// What the receivers' checks made of the frames that crossed a bus. The twin
/// knows what was sent, so it can count the corrupted frames that a weak check
/// (MEB's 8-bit XOR) lets through.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct CheckTally {
    /// Frames received in full, one count per receiver.
    pub frames_received: u64,
    /// Of those, frames with at least one byte changed by noise or a collision.
    pub frames_corrupted: u64,
    /// Corrupted frames that still pass their protocol's check.
    pub corrupted_passed_check: u64,
}

pub use twin_recording::describe::FrameKind;

impl BusSlot {
    /// Follow one byte into its receiver's frame and tally the frame's check
    /// when its last byte lands.
    fn tally(
        &mut self,
        to: PortId,
        from: PortId,
        byte: u8,
        corrupted: bool,
        index: usize,
        last: bool,
    ) {
        let Some(rx) = self.receiving.get_mut(to.index()) else {
            return;
        };
        if index == 0 {
            rx.bytes.clear();
            rx.corrupted = false;
            rx.from = Some(from);
            rx.counted = false;
        }
        rx.bytes.push(byte);
        rx.corrupted |= corrupted;
        if last {
            self.count(to, from);
        }
    }

    /// A streamed frame of `from` ended after every listener had all its
    /// bytes (none came marked `last`): count it where it was received.
    fn tally_stream_end(&mut self, from: PortId) {
        for to in 0..self.receiving.len() {
            let rx = &self.receiving[to];
            if rx.from == Some(from) && !rx.counted && !rx.bytes.is_empty() {
                self.count(PortId(u16::try_from(to).unwrap_or(u16::MAX)), from);
            }
        }
    }

    fn count(&mut self, to: PortId, from: PortId) {
        let Some(rx) = self.receiving.get_mut(to.index()) else {
            return;
        };
        rx.counted = true;
        self.checks.frames_received += 1;
        if rx.corrupted {
            self.checks.frames_corrupted += 1;
            let sent = self.sent.get(from.index()).map_or(&[][..], Vec::as_slice);
            // PWM-capture frames carry no check at all (Table 2: no CRC).
            let pwm = matches!(self.bus, Medium::Pwm(_));
            if pwm || FrameKind::of(sent).passes_check(&rx.bytes) {
                self.checks.corrupted_passed_check += 1;
            }
        }
    }
}

/// Everything the engine reports as it runs, for the recorder. Every
/// method keeps nothing unless an observer says otherwise, so one that
/// wants the frames alone writes only [`Observer::frame`].
pub trait Observer {
    /// A plant sample of `module`.
    fn plant(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        let _ = (now, module);
        Ok(())
    }
    /// A change of `module`'s actuators.
    fn actuators(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        let _ = (now, module);
        Ok(())
    }
    /// A frame `from` sent on `bus`, its first bit at `start`, its last at `end`.
    fn frame(
        &mut self,
        bus: &BusSlot,
        from: &NodeSlot,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<()> {
        let _ = (bus, from, start, end, bytes);
        Ok(())
    }
    /// Where `bus`'s line differed from what a node sent: a character a
    /// collision garbled, or bits noise flipped at a listener. Comes after
    /// the frame's [`Observer::frame`] or, for a frame garbled by one sent
    /// later, after that frame's.
    fn line_mark(&mut self, bus: &BusSlot, mark: &LineMark) -> Result<()> {
        let _ = (bus, mark);
        Ok(())
    }
    /// Something a node reports (a timeout, a trip, a fault).
    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<()> {
        let _ = (node, event);
        Ok(())
    }
    /// A master's loop report, once per poll cycle.
    fn telemetry(&mut self, now: SimTime, node: &NodeSlot, report: &LoopReport) -> Result<()> {
        let _ = (now, node, report);
        Ok(())
    }
    /// Whether [`Observer::telemetry`] keeps what it is given: when it does
    /// not, the masters' reports are not even made. Asked once per
    /// [`Engine::run_until`]: the answer must not change.
    fn wants_loop_reports(&self) -> bool {
        true
    }
    /// A firmware node's own records (UART bursts, pins, ADC inputs).
    fn firmware(&mut self, node: &str, record: FirmwareRecord<'_>) -> Result<()> {
        let _ = (node, record);
        Ok(())
    }
    /// A module controller's readings, at each recording instant.
    fn readings(&mut self, now: SimTime, node: &NodeSlot, readings: &ReadingsSample) -> Result<()> {
        let _ = (now, node, readings);
        Ok(())
    }
}

/// An observer that keeps nothing: the engine's own cost, without recording.
#[derive(Debug, Default, Clone, Copy)]
pub struct DiscardObserver;

impl Observer for DiscardObserver {
    fn wants_loop_reports(&self) -> bool {
        false
    }
}

/// The engine.
pub struct Engine {
    pub modules: Vec<ModuleSlot>,
    pub nodes: Vec<NodeSlot>,
    pub buses: Vec<BusSlot>,
    now: SimTime,
    plant_step: SimDuration,
    record_period: SimDuration,
    next_record: SimTime,
    tx: Vec<u8>,
    pub frames_sent: u64,
    /// Discrete events handled so far: byte arrivals and ends of frames,
    /// firmware loop ticks, node timeouts and recording instants.
    pub events: u64,
    /// A run stopped by [`crate::interrupt::request`] before its end.
    interrupted: bool,
}

impl Engine {
    pub fn new(plant_step: SimDuration, record_period: SimDuration) -> Self {
        Self {
            modules: Vec::new(),
            nodes: Vec::new(),
            buses: Vec::new(),
            now: SimTime::ZERO,
            plant_step,
            record_period,
            next_record: SimTime::ZERO,
            tx: vec![0; MAX_FRAME],
            frames_sent: 0,
            events: 0,
            interrupted: false,
        }
    }

    /// Whether [`Self::run_until`] stopped early, at [`Self::now`], because
    /// a stop was asked (see [`crate::interrupt`]).
    pub fn interrupted(&self) -> bool {
        self.interrupted
    }

    pub fn add_module(&mut self, name: &str, plant: EvModule) -> usize {
        self.modules.push(ModuleSlot::new(name, plant));
        self.modules.len() - 1
    }

    /// Add a bus: a `SimBus`, a `PwmBus` or a [`Medium`].
    pub fn add_bus(&mut self, name: &str, bus: impl Into<Medium>) -> usize {
        let mut bus = bus.into();
        // The observer hears where the line differed from what was sent.
        bus.keep_line_marks();
        self.buses.push(BusSlot {
            name: name.into(),
            bus,
            owners: Vec::new(),
            port_names: Vec::new(),
            sent: Vec::new(),
            receiving: Vec::new(),
            checks: CheckTally::default(),
        });
        self.buses.len() - 1
    }

    /// Attach a node to a bus at `port` (from `SimBus::add_port`).
    pub fn add_node(
        &mut self,
        name: &str,
        mut node: Box<dyn SimNode>,
        bus: usize,
        port: PortId,
        module: Option<usize>,
    ) -> usize {
        let next_tick = node.firmware().map(|_| SimTime::ZERO);
        let streams = matches!(self.buses[bus].bus, Medium::Serial(_)) && node.start_streaming();
        let may_run_ahead = node.can_run_ahead();
        let index = self.nodes.len();
        self.nodes.push(NodeSlot {
            name: name.into(),
            node,
            bus,
            port,
            module,
            next_tick,
            stirred: true,
            streams,
            may_run_ahead,
            stream_open: false,
        });
        let owners = &mut self.buses[bus].owners;
        if owners.len() <= port.index() {
            owners.resize(port.index() + 1, usize::MAX);
        }
        owners[port.index()] = index;
        let slot = &mut self.buses[bus];
        if slot.port_names.len() <= port.index() {
            slot.port_names.resize(port.index() + 1, String::new());
        }
        slot.port_names[port.index()] = name.into();
        while slot.sent.len() < slot.owners.len() {
            slot.sent.push(Vec::with_capacity(MAX_FRAME));
            slot.receiving.push(Reception {
                bytes: Vec::with_capacity(MAX_FRAME),
                ..Reception::default()
            });
        }
        index
    }

    pub fn now(&self) -> SimTime {
        self.now
    }

    /// Run until `end`, reporting to `observer`; `progress` gets the time reached.
    pub fn run_until(
        &mut self,
        end: SimTime,
        observer: &mut dyn Observer,
        mut progress: impl FnMut(SimTime),
    ) -> Result<(), EngineError> {
        let mut handled = 0u64;
        let mut passes_at_this_instant = 0u32;
        let mut until = end;
        // Asked once: it is the observer's nature, and the question through
        // a `Tee` of borrowed observers is a chain of calls per event.
        let wants_loop_reports = observer.wants_loop_reports();
        loop {
            self.transmit_all(observer)?;
            self.drain_node_output(observer, wants_loop_reports)?;
            self.let_firmware_run_ahead(end);
            let Some(t) = self.next_event() else { break };
            if t > end {
                break;
            }
            // A node that keeps asking to be woken at an instant it has
            // already handled would spin the clock in place: say which.
            passes_at_this_instant = if t == self.now {
                passes_at_this_instant + 1
            } else {
                0
            };
            if passes_at_this_instant > STALL_PASSES {
                let stuck: Vec<&str> = self
                    .nodes
                    .iter()
                    .filter(|n| n.node.poll_timeout().is_some_and(|due| due <= t))
                    .map(|n| n.name.as_str())
                    .collect();
                return Err(EngineError::Stalled {
                    at_s: t.as_secs_f64(),
                    nodes: stuck.join(", "),
                });
            }
            self.now = t;
            self.deliver_bus_events(t, observer)?;
            self.tick_firmware(t, observer)?;
            for slot in &mut self.nodes {
                if slot.node.poll_timeout().is_some_and(|due| due <= t) {
                    slot.node.handle_timeout(t);
                    slot.stirred = true;
                    self.events += 1;
                }
            }
            if t >= self.next_record {
                for m in 0..self.modules.len() {
                    self.advance_plant(m, t);
                    observer.plant(t, &self.modules[m])?;
                }
                for slot in &self.nodes {
                    if let Some(readings) = slot.node.controller_readings() {
                        observer.readings(t, slot, &readings)?;
                    }
                }
                self.next_record = t + self.record_period;
                self.events += 1;
            }
            handled += 1;
            if handled.is_multiple_of(4096) {
                progress(t);
                if crate::interrupt::requested() {
                    self.interrupted = true;
                    until = t;
                    break;
                }
            }
        }
        for m in 0..self.modules.len() {
            self.advance_plant(m, until);
        }
        self.now = until;
        Ok(())
    }

    /// Hands each node that can compute ahead (compiled firmware) the
    /// earliest instant anything can reach it, capped at the run's `end`:
    /// its next loop tick, the bus's next event, or the first byte another
    /// node it hears could put on the line. A firmware node hands the bus
    /// its bytes when the engine next touches it (its tick, its timer, a
    /// byte for it); any other node (a master) sends only when stirred, by
    /// its own timer or something the bus brings it, and its first byte
    /// lands a turnaround and a character later. Computed from the engine's
    /// state alone, so the split points never depend on threads.
    fn let_firmware_run_ahead(&mut self, end: SimTime) {
        let now = self.now;
        for n in 0..self.nodes.len() {
            let slot = &self.nodes[n];
            if !slot.may_run_ahead || !slot.node.can_run_ahead() {
                continue;
            }
            let Some(tick) = slot.next_tick else { continue };
            let Some(bus_slot) = self.buses.get(slot.bus) else {
                continue;
            };
            let Medium::Serial(bus) = &bus_slot.bus else {
                continue;
            };
            let wiring = bus.config().wiring;
            let bus_event = bus.poll_timeout();
            // When a firmware node on this bus is next touched (and may hand
            // the bus a byte whose wire time has begun).
            let touched = |o: &NodeSlot| {
                [o.next_tick, o.node.poll_timeout()]
                    .into_iter()
                    .flatten()
                    .min()
                    .unwrap_or(now)
            };
            let streams = |o: &NodeSlot| o.node.can_run_ahead() || o.node.streams_bytes();
            let mut horizon = tick.min(end);
            if let Some(t) = bus_event {
                horizon = horizon.min(t);
            }
            for (m, other) in self.nodes.iter().enumerate() {
                if m == n || other.bus != slot.bus || !wiring.hears(slot.port, other.port) {
                    continue;
                }
                let earliest = if streams(other) {
                    touched(other)
                } else {
                    // The first instant `other` can be stirred into sending.
                    let heard = self.nodes.iter().enumerate().filter(|&(k, f)| {
                        k != m
                            && f.bus == slot.bus
                            && streams(f)
                            && wiring.hears(other.port, f.port)
                    });
                    let stirred = [other.next_tick, other.node.poll_timeout(), bus_event]
                        .into_iter()
                        .flatten()
                        .chain(heard.map(|(_, f)| touched(f)))
                        .min();
                    // Nothing can ever stir it: it never sends.
                    let Some(stirred) = stirred else { continue };
                    let turnaround = bus
                        .port_config(other.port)
                        .map_or(SimDuration::ZERO, |p| p.turnaround);
                    stirred.max(now) + turnaround + bus.char_time()
                };
                horizon = horizon.min(earliest);
            }
            if horizon > now {
                self.nodes[n].node.run_ahead(horizon);
            }
        }
    }

    fn next_event(&self) -> Option<SimTime> {
        let buses = self.buses.iter().filter_map(|b| b.bus.poll_timeout());
        let nodes = self.nodes.iter().filter_map(|n| n.node.poll_timeout());
        let ticks = self.nodes.iter().filter_map(|n| n.next_tick);
        let record = (!self.modules.is_empty()).then_some(self.next_record);
        buses.chain(nodes).chain(ticks).chain(record).min()
    }

    fn deliver_bus_events(&mut self, t: SimTime, observer: &mut dyn Observer) -> Result<()> {
        for b in 0..self.buses.len() {
            while let Some(event) = self.buses[b].bus.poll_event(t) {
                self.events += 1;
                self.report_line_marks(b, observer)?;
                match event {
                    BusEvent::Byte {
                        to,
                        at,
                        byte,
                        corrupted,
                        from,
                        index,
                        last,
                    } => {
                        self.buses[b].tally(to, from, byte, corrupted, index, last);
                        if let Some(&n) = self.buses[b].owners.get(to.index())
                            && let Some(slot) = self.nodes.get_mut(n)
                        {
                            slot.node.handle_bytes(at, &[byte]);
                            slot.stirred = true;
                        }
                    }
                    BusEvent::TransmitDone { port, at } => {
                        if let Some(&n) = self.buses[b].owners.get(port.index())
                            && let Some(slot) = self.nodes.get_mut(n)
                        {
                            slot.node.transmit_done(at);
                            slot.stirred = true;
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Hands the observer every line mark bus `b` kept.
    fn report_line_marks(&mut self, b: usize, observer: &mut dyn Observer) -> Result<()> {
        while let Some(mark) = self.buses[b].bus.poll_line_mark() {
            observer.line_mark(&self.buses[b], &mark)?;
        }
        Ok(())
    }

    /// Step a module's plant up to `t` in whole plant steps (and a last
    /// partial one if `t` is off the grid).
    fn advance_plant(&mut self, m: usize, t: SimTime) {
        self.modules[m].advance(self.plant_step, t);
    }

    fn tick_firmware(
        &mut self,
        t: SimTime,
        observer: &mut dyn Observer,
    ) -> Result<(), EngineError> {
        for n in 0..self.nodes.len() {
            if self.nodes[n].next_tick.is_none_or(|due| due > t) {
                continue;
            }
            let Some(m) = self.nodes[n].module else {
                continue;
            };
            let slot = &mut self.nodes[n];
            let module = &mut self.modules[m];
            let Some((next, changed)) =
                firmware_tick(slot.node.as_mut(), module, self.plant_step, t, |_| {})
            else {
                continue;
            };
            slot.stirred = true;
            self.events += 1;
            slot.next_tick = Some(next);
            if let Some(why) = slot.node.failure() {
                return Err(EngineError::NodeFailed {
                    node: slot.name.clone(),
                    why,
                });
            }
            if changed {
                observer.actuators(t, module)?;
            }
        }
        Ok(())
    }

    fn transmit_all(&mut self, observer: &mut dyn Observer) -> Result<(), EngineError> {
        let t = self.now;
        for n in 0..self.nodes.len() {
            if !self.nodes[n].stirred {
                continue;
            }
            if self.nodes[n].streams {
                self.stream_all(n, observer)?;
            }
            while let Some(len) = self.nodes[n].node.poll_transmit(t, &mut self.tx) {
                let len = len.min(self.tx.len());
                let slot = &self.nodes[n];
                let bus = &mut self.buses[slot.bus];
                let info = bus
                    .bus
                    .send(t, slot.port, &self.tx[..len])
                    .map_err(|source| EngineError::Bus {
                        bus: bus.name.clone(),
                        source,
                    })?;
                if let Some(sent) = bus.sent.get_mut(slot.port.index()) {
                    sent.clear();
                    sent.extend_from_slice(&self.tx[..len]);
                }
                self.frames_sent += 1;
                observer.frame(
                    &self.buses[slot.bus],
                    slot,
                    info.start,
                    info.end,
                    &self.tx[..len],
                )?;
                let b = slot.bus;
                self.report_line_marks(b, observer)?;
            }
        }
        Ok(())
    }

    /// Hands a streaming node's bytes to its bus as it found them, and
    /// records its frame when its line goes quiet.
    fn stream_all(&mut self, n: usize, observer: &mut dyn Observer) -> Result<(), EngineError> {
        let t = self.now;
        while let Some(out) = self.nodes[n].node.poll_stream(t) {
            let slot = &mut self.nodes[n];
            let bus_slot = &mut self.buses[slot.bus];
            let Medium::Serial(bus) = &mut bus_slot.bus else {
                break;
            };
            let port = slot.port;
            match out {
                Streamed::Byte { byte, start, end } => {
                    bus.stream_byte(t, port, byte, start, end)
                        .map_err(|source| EngineError::Bus {
                            bus: bus_slot.name.clone(),
                            source,
                        })?;
                    if let Some(sent) = bus_slot.sent.get_mut(port.index()) {
                        if !slot.stream_open {
                            sent.clear();
                        }
                        if sent.len() < MAX_FRAME {
                            sent.push(byte);
                        }
                    }
                    slot.stream_open = true;
                }
                Streamed::End => {
                    slot.stream_open = false;
                    let Some((info, _, delivered)) = bus.end_stream(t, port) else {
                        continue;
                    };
                    if delivered {
                        bus_slot.tally_stream_end(port);
                    }
                    self.frames_sent += 1;
                    let (slot, bus_slot) = (&self.nodes[n], &self.buses[self.nodes[n].bus]);
                    let sent = bus_slot
                        .sent
                        .get(port.index())
                        .map_or(&[][..], Vec::as_slice);
                    observer.frame(bus_slot, slot, info.start, info.end, sent)?;
                    let b = slot.bus;
                    self.report_line_marks(b, observer)?;
                }
            }
        }
        Ok(())
    }

    fn drain_node_output(
        &mut self,
        observer: &mut dyn Observer,
        wants_loop_reports: bool,
    ) -> Result<(), EngineError> {
        let t = self.now;
        for n in 0..self.nodes.len() {
            if !self.nodes[n].stirred {
                continue;
            }
            while let Some(event) = self.nodes[n].node.poll_event() {
                observer.event(&self.nodes[n], &event)?;
            }
            if wants_loop_reports && let Some(report) = self.nodes[n].node.loop_report() {
                observer.telemetry(t, &self.nodes[n], &report)?;
                self.nodes[n].node.recycle_loop_report(report);
            }
            let slot = &mut self.nodes[n];
            let name = slot.name.as_str();
            slot.node
                .firmware_records(&mut |record| observer.firmware(name, record))?;
            self.nodes[n].stirred = false;
        }
        Ok(())
    }
}

macro_rules! debug_by_name {
    ($($t:ty),*) => {$(
        impl std::fmt::Debug for $t {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.debug_struct(stringify!($t)).field("name", &self.name).finish_non_exhaustive()
            }
        }
    )*};
}
debug_by_name!(ModuleSlot, NodeSlot, BusSlot);

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Engine")
            .field("now", &self.now)
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nodes::link::{BusConfig, PortConfig, SimBus};

    /// A node that wants to be woken at time zero for ever.
    struct Stuck;

    impl Node for Stuck {
        fn handle_bytes(&mut self, _now: SimTime, _bytes: &[u8]) {}
        fn handle_timeout(&mut self, _now: SimTime) {}
        fn poll_transmit(&mut self, _now: SimTime, _buf: &mut [u8]) -> Option<usize> {
            None
        }
        fn poll_timeout(&self) -> Option<SimTime> {
            Some(SimTime::ZERO)
        }
    }

    impl SimNode for Stuck {}

    #[test]
    fn a_node_that_stops_the_clock_is_named_not_spun_on() {
        let mut engine = Engine::new(SimDuration::from_millis(1), SimDuration::from_millis(5));
        let mut bus = SimBus::new(BusConfig::default()).expect("bus");
        let port = bus.add_port(PortConfig::default());
        let b = engine.add_bus("rs485", bus);
        engine.add_node("stuck-node", Box::new(Stuck), b, port, None);
        let end = SimTime::ZERO + SimDuration::from_millis(10);
        let err = engine
            .run_until(end, &mut DiscardObserver, |_| {})
            .expect_err("the clock cannot advance");
        assert!(err.to_string().contains("stuck-node"), "{err}");
    }
}
