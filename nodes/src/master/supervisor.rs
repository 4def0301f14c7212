//! The supervisor node: poll cycles, retries and one PI loop per slave.

mod forward;

use std::collections::VecDeque;

pub use forward::{ForwardError, WriteOutcome, WriteTicket};

use crate::node::{Node, NodeEvent};
use protocols::time::{SimDuration, SimTime};

use super::layout::MebLayout;
use super::pi::{SpeedPi, VEL_MAX};
use super::wire::{INPUT_WORDS, Reply, ReplyDecoder, StatusBlock, Transaction};
use super::{
    LoopMode, Protocol, SlaveLoopConfig, StartupOutputs, SupervisorConfig, SupervisorConfigError,
};

/// Events kept for the recorder; older ones are dropped (and counted) if
/// nobody drains them, so a run without a recorder does not grow without end.
const EVENT_QUEUE_LEN: usize = 1024;

/// What happened on the bus for one slave, since start.
///
/// Every request ends in exactly one of `replies`, `timeouts`, `bad_checks` or
/// `exceptions`, so between exchanges `requests` is their sum.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PollCounters {
    /// Requests sent, retries included.
    pub requests: u64,
    /// Replies that answered the request and were used.
    pub replies: u64,
    /// Requests that got no usable reply within the reply timeout.
    pub timeouts: u64,
    /// Replies that failed their check (FCS, CRC) or their form.
    pub bad_checks: u64,
    /// Error replies (MEB `ER`) and Modbus exceptions.
    pub exceptions: u64,
    /// Requests sent again after a failed attempt.
    pub retries: u64,
    /// Exchanges given up after every retry failed.
    pub lost: u64,
    /// Well-formed frames that answered something else; ignored.
    pub unexpected: u64,
}

/// The slave's status words as last read (`SupervisorConfig::status_every`);
/// `None` until read.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StatusWords {
    /// `ED 00`: hall code (bits 0-2), flag seen (bit 3).
    pub hall: Option<u16>,
    /// `FA 00` SOC (0.1 %) and `FA 01` ERRS.
    pub flags: Option<[u16; 2]>,
    /// `FD 00` STATUS.
    pub status: Option<u16>,
}

/// The state of one slave's speed loop, for recording.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LoopState {
    /// Set point at the last measurement, rpm.
    pub set_point_rpm: f64,
    /// Last measured wheel speed, rpm.
    pub measured_rpm: f64,
    /// Set point minus measurement, rpm.
    pub error_rpm: f64,
    /// Last `VEL` computed, DAC counts.
    pub output: u16,
    /// The PI's integral term after the last pass, DAC counts.
    pub integral: f64,
    /// Last `VEL` the slave acknowledged, if any yet.
    pub vel_written: Option<u16>,
    /// The six analog inputs last read (V2, I, V1, RPM_M, RPM_L, LDR).
    pub inputs: [u16; INPUT_WORDS],
    /// When the last measurement arrived.
    pub measured_at: Option<SimTime>,
    /// Whether the start-up outputs were acknowledged.
    pub started: bool,
    /// Bus counters.
    pub counters: PollCounters,
    /// Status words, if the supervisor reads them.
    pub status: StatusWords,
}

#[derive(Debug, Clone)]
struct Slave {
    config: SlaveLoopConfig,
    pi: SpeedPi,
    /// A set point written at run time (the image's `VA 10`), over the schedule.
    set_point_override: Option<f64>,
    state: LoopState,
    /// The inputs of this cycle's read so far (a mapped slave may need several).
    reading: [u16; INPUT_WORDS],
    /// The switches' words as the default map has them, as last written:
    /// what a client's write of some switches leaves the others at.
    switches: [u16; 2],
}

/// Where the supervisor is in its exchange.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// The next request goes out at `at` (gap or poll period).
    Waiting { at: SimTime },
    /// A request is out, its reply awaited. The reply timeout runs from
    /// when the request has left (`Node::transmit_done`): until then
    /// `deadline` is `None`, so a request the engine writes late (a busy
    /// machine, a stopped process) is never given up before it is out.
    Awaiting { deadline: Option<SimTime> },
}

#[derive(Debug, Clone, Copy)]
struct Pending {
    slave: usize,
    transaction: Transaction,
    /// 0 for the first try.
    attempt: u8,
}

/// The bus master that closes each slave's speed loop (see the module docs).
#[derive(Debug, Clone)]
pub struct Supervisor {
    protocol: Protocol,
    poll_period: SimDuration,
    inter_frame_gap: SimDuration,
    reply_timeout: SimDuration,
    retries: u8,
    startup: Option<StartupOutputs>,
    slaves: Vec<Slave>,
    decoder: ReplyDecoder,
    phase: Phase,
    pending: Pending,
    /// When the current poll cycle was due to start.
    cycle_start: SimTime,
    cycles: u64,
    events: VecDeque<NodeEvent>,
    events_dropped: u64,
    /// How long the line must be quiet before a request goes out after
    /// stray bytes (the configured silence).
    line_quiet: SimDuration,
    status_every: u32,
    /// When the line is free for a request (last exchange + gap, or quiet
    /// after stray bytes): where a forwarded write may go out.
    line_free_at: SimTime,
    forwarding: forward::Forwarding,
    layout: MebLayout,
}

impl Supervisor {
    /// A supervisor about to start its first cycle at `config.first_poll_at`.
    pub fn new(config: SupervisorConfig) -> Result<Self, SupervisorConfigError> {
        let SupervisorConfig {
            protocol,
            slaves,
            poll_period,
            inter_frame_gap,
            reply_timeout,
            retries,
            first_poll_at,
            startup_outputs,
            rtu_silence,
            status_every,
            layout,
        } = config;
        if slaves.is_empty() {
            return Err(SupervisorConfigError::NoSlaves);
        }
        let (min, max) = match protocol {
            Protocol::Meb => (1, protocols::meb::MEB_MAX_ID),
            Protocol::ModbusRtu => (1, 247),
        };
        if protocol != Protocol::Meb && !layout.is_default() {
            return Err(SupervisorConfigError::MapNeedsMeb);
        }
        let mut checked: Vec<Slave> = Vec::with_capacity(slaves.len());
        for mut slave in slaves {
            let id = slave.id;
            if !(min..=max).contains(&id) {
                return Err(SupervisorConfigError::IdOutOfRange { id, min, max });
            }
            if checked.iter().any(|other| other.config.id == id) {
                return Err(SupervisorConfigError::DuplicateId(id));
            }
            let not_finite = |field| SupervisorConfigError::NotFinite { id, field };
            if !slave.kp.is_finite() {
                return Err(not_finite("kp"));
            }
            if !slave.ki.is_finite() {
                return Err(not_finite("ki"));
            }
            if slave.set_points.iter().any(|step| !step.rpm.is_finite()) {
                return Err(not_finite("set_points"));
            }
            let source = slave.speed_source;
            layout
                .check(source.input_index(), source.name())
                .map_err(SupervisorConfigError::Map)?;
            // Stable, so steps given at the same instant keep their order and
            // the last one wins.
            slave.set_points.sort_by_key(|step| step.at);
            checked.push(Slave {
                pi: SpeedPi::new(slave.kp, slave.ki),
                set_point_override: None,
                state: LoopState::default(),
                reading: [0; INPUT_WORDS],
                switches: startup_outputs.map_or([0; 2], |o| [o.sd0, o.sd1]),
                config: slave,
            });
        }
        let mut supervisor = Self {
            protocol,
            poll_period,
            inter_frame_gap,
            reply_timeout,
            retries,
            startup: startup_outputs,
            slaves: checked,
            decoder: ReplyDecoder::new(protocol, rtu_silence),
            phase: Phase::Waiting { at: first_poll_at },
            pending: Pending {
                slave: 0,
                transaction: Transaction::ReadInputs(0),
                attempt: 0,
            },
            cycle_start: first_poll_at,
            cycles: 0,
            events: VecDeque::with_capacity(EVENT_QUEUE_LEN),
            events_dropped: 0,
            line_quiet: rtu_silence,
            status_every: if protocol == Protocol::Meb {
                status_every
            } else {
                0
            },
            line_free_at: first_poll_at,
            forwarding: forward::Forwarding::default(),
            layout,
        };
        supervisor.pending.transaction = supervisor.first_transaction(0);
        Ok(supervisor)
    }

    /// The loop of slave `id`, if the supervisor polls it.
    pub fn loop_state(&self, id: u8) -> Option<LoopState> {
        self.slave(id).map(|slave| slave.state)
    }

    /// The ids polled, in polling order.
    pub fn slave_ids(&self) -> impl Iterator<Item = u8> + '_ {
        self.slaves.iter().map(|slave| slave.config.id)
    }

    /// The protocol spoken on the bus.
    pub fn protocol(&self) -> Protocol {
        self.protocol
    }

    /// The configured poll period (the achieved rate is `cycles()` over the run).
    pub fn poll_period(&self) -> SimDuration {
        self.poll_period
    }

    /// The counters of every slave added up, for a run's summary.
    pub fn total_counters(&self) -> PollCounters {
        self.slaves.iter().map(|slave| slave.state.counters).fold(
            PollCounters::default(),
            |sum, c| PollCounters {
                requests: sum.requests + c.requests,
                replies: sum.replies + c.replies,
                timeouts: sum.timeouts + c.timeouts,
                bad_checks: sum.bad_checks + c.bad_checks,
                exceptions: sum.exceptions + c.exceptions,
                retries: sum.retries + c.retries,
                lost: sum.lost + c.lost,
                unexpected: sum.unexpected + c.unexpected,
            },
        )
    }

    /// Poll cycles completed.
    pub fn cycles(&self) -> u64 {
        self.cycles
    }

    /// Events dropped because the queue was full when they happened.
    pub fn events_dropped(&self) -> u64 {
        self.events_dropped
    }

    /// The set point of slave `id` at `now`: a run-time override if one was
    /// set, else the schedule.
    pub fn set_point(&self, id: u8, now: SimTime) -> Option<f64> {
        self.slave(id).map(|slave| slave.set_point(now))
    }

    /// Overrides the schedule of slave `id` with `rpm` (`None` returns to the
    /// schedule). Returns whether the slave exists; non-finite values are refused.
    pub fn set_set_point(&mut self, id: u8, rpm: Option<f64>) -> bool {
        match (self.slave_mut(id), rpm) {
            (Some(_), Some(rpm)) if !rpm.is_finite() => false,
            (Some(slave), rpm) => {
                slave.set_point_override = rpm;
                true
            }
            (None, _) => false,
        }
    }

    /// New gains for slave `id`; the integral is kept, so the output does not jump.
    pub fn set_gains(&mut self, id: u8, kp: f64, ki: f64) -> bool {
        match self.slave_mut(id) {
            Some(slave) if kp.is_finite() && ki.is_finite() => {
                slave.pi.kp = kp;
                slave.pi.ki = ki;
                slave.config.kp = kp;
                slave.config.ki = ki;
                true
            }
            _ => false,
        }
    }

    /// Closed loop or manual `VEL` for slave `id`. Closing the loop again
    /// starts the integral from the manual value, so the output does not jump.
    pub fn set_mode(&mut self, id: u8, mode: LoopMode) -> bool {
        let Some(slave) = self.slave_mut(id) else {
            return false;
        };
        if let (LoopMode::Open { vel }, LoopMode::Closed) = (slave.config.mode, mode) {
            slave.pi.preload(f64::from(vel));
        }
        slave.config.mode = mode;
        true
    }

    /// Whether the supervisor reads its slaves' status words (`ED 00`,
    /// `FA 00`–`01`, `FD 00`) now and then.
    pub fn reads_status(&self) -> bool {
        self.status_every > 0
    }

    /// The gains `(kp, ki)` of slave `id`'s loop.
    pub fn gains(&self, id: u8) -> Option<(f64, f64)> {
        self.slave(id).map(|slave| (slave.pi.kp, slave.pi.ki))
    }

    /// Closed loop or manual `VEL`, for slave `id`.
    pub fn mode(&self, id: u8) -> Option<LoopMode> {
        self.slave(id).map(|slave| slave.config.mode)
    }

    fn slave(&self, id: u8) -> Option<&Slave> {
        self.slaves.iter().find(|slave| slave.config.id == id)
    }

    fn slave_mut(&mut self, id: u8) -> Option<&mut Slave> {
        self.slaves.iter_mut().find(|slave| slave.config.id == id)
    }

    /// The status round's first read, if this cycle has one.
    fn status_round(&self) -> Option<Transaction> {
        (self.status_every > 0 && self.cycles.is_multiple_of(u64::from(self.status_every)))
            .then_some(Transaction::ReadStatus(StatusBlock::first(&self.layout)))
    }

    fn first_transaction(&self, slave: usize) -> Transaction {
        let started = self.slaves.get(slave).is_some_and(|s| s.state.started);
        // A map that places no switch leaves nothing to start up.
        let switches = self.layout.sd_spans().get(0).is_some();
        match self.startup {
            Some(outputs) if !started && switches => Transaction::Startup(outputs, 0),
            _ => Transaction::ReadInputs(0),
        }
    }

    fn push_event(&mut self, at: SimTime, kind: &'static str, detail: String) {
        if self.events.len() >= EVENT_QUEUE_LEN {
            self.events.pop_front();
            self.events_dropped += 1;
        }
        self.events.push_back(NodeEvent { at, kind, detail });
    }

    fn counters(&mut self) -> Option<&mut PollCounters> {
        self.slaves
            .get_mut(self.pending.slave)
            .map(|slave| &mut slave.state.counters)
    }

    fn pending_id(&self) -> u8 {
        self.slaves
            .get(self.pending.slave)
            .map_or(0, |slave| slave.config.id)
    }

    /// Schedules `transaction` on the same slave after the gap, or, with `None`,
    /// moves to the next slave or the next cycle.
    fn advance(&mut self, now: SimTime, next: Option<Transaction>) {
        // The exchange done (or given up) settles what a forwarded write
        // owed the polls.
        self.forwarding.owed = false;
        let after_gap = now + self.inter_frame_gap;
        self.line_free_at = self.line_free_at.max(after_gap);
        let (slave, at) = match next {
            Some(transaction) => {
                self.pending = Pending {
                    transaction,
                    attempt: 0,
                    ..self.pending
                };
                self.phase = Phase::Waiting { at: after_gap };
                self.start_forward(now);
                return;
            }
            None if self.pending.slave + 1 < self.slaves.len() => {
                (self.pending.slave + 1, after_gap)
            }
            None => {
                // A cycle keeps its period unless it overran; then the next
                // one follows straight on (after the gap), not a period later.
                self.cycles += 1;
                self.cycle_start = (self.cycle_start + self.poll_period).max(after_gap);
                (0, self.cycle_start)
            }
        };
        self.pending = Pending {
            slave,
            transaction: self.first_transaction(slave),
            attempt: 0,
        };
        self.phase = Phase::Waiting { at };
        self.start_forward(now);
    }

    /// The attempt failed: retry it, or give it up and move on.
    fn fail(&mut self, now: SimTime) {
        let Pending {
            transaction,
            attempt,
            ..
        } = self.pending;
        let id = self.pending_id();
        if attempt < self.retries {
            if let Some(counters) = self.counters() {
                counters.retries += 1;
            }
            self.push_event(
                now,
                "retry",
                format!(
                    "slave {id}: {} retry {} of {}",
                    transaction.name(),
                    attempt + 1,
                    self.retries
                ),
            );
            self.pending.attempt = attempt + 1;
            self.phase = Phase::Waiting {
                at: now + self.inter_frame_gap,
            };
            return;
        }
        if let Some(counters) = self.counters() {
            counters.lost += 1;
        }
        self.push_event(
            now,
            "dropped",
            format!(
                "slave {id}: {} lost after {} attempts",
                transaction.name(),
                u16::from(attempt) + 1
            ),
        );
        if let Transaction::Forward { .. } = transaction {
            self.finish_forward(now, WriteOutcome::NoAnswer);
            return;
        }
        // A lost start-up write does not stop the read: the telemetry still
        // flows, and the write is tried again next cycle.
        let next = match transaction {
            Transaction::Startup(..) => Some(Transaction::ReadInputs(0)),
            // A forwarded write was handled above; a lost status read
            // ends the round, the next one comes in `status_every` cycles.
            Transaction::ReadInputs(_)
            | Transaction::WriteVel(_)
            | Transaction::Forward { .. }
            | Transaction::ReadStatus(_) => None,
        };
        self.advance(now, next);
    }

    fn on_reply(&mut self, now: SimTime, reply: Reply) {
        if !matches!(self.phase, Phase::Awaiting { .. }) {
            return;
        }
        let id = self.pending_id();
        let transaction = self.pending.transaction;
        match reply {
            Reply::Unexpected => {
                if let Some(counters) = self.counters() {
                    counters.unexpected += 1;
                }
            }
            Reply::Bad => {
                if let Some(counters) = self.counters() {
                    counters.bad_checks += 1;
                }
                self.push_event(
                    now,
                    "bad_check",
                    format!("slave {id}: {} reply failed its check", transaction.name()),
                );
                self.fail(now);
                // The bad frame may have been cut short by noise (a flipped
                // byte that reads as its end) with the rest still on the wire:
                // the retry waits for a quiet line, as a Modbus master waits
                // out its silence interval.
                if let Phase::Waiting { at } = self.phase {
                    self.phase = Phase::Waiting {
                        at: at.max(now + self.line_quiet),
                    };
                }
            }
            Reply::Exception(code) => {
                if let Some(counters) = self.counters() {
                    counters.exceptions += 1;
                }
                self.push_event(
                    now,
                    "exception",
                    format!("slave {id}: {} refused, code {code:02}", transaction.name()),
                );
                // The slave's refusal of a client's write is its answer to
                // the client, not a line fault: no retry.
                match transaction {
                    Transaction::Forward { .. } => {
                        self.finish_forward(now, WriteOutcome::Refused(code));
                    }
                    _ => self.fail(now),
                }
            }
            Reply::Ack => {
                let next = match (transaction, self.slaves.get_mut(self.pending.slave)) {
                    (_, None) => None,
                    (Transaction::Forward { .. }, Some(slave)) => {
                        slave.state.counters.replies += 1;
                        self.finish_forward(now, WriteOutcome::Acknowledged);
                        return;
                    }
                    (Transaction::Startup(outputs, part), Some(slave)) => {
                        slave.state.counters.replies += 1;
                        if self.layout.sd_spans().is_last(part) {
                            slave.state.started = true;
                            Some(Transaction::ReadInputs(0))
                        } else {
                            Some(Transaction::Startup(outputs, part + 1))
                        }
                    }
                    (Transaction::WriteVel(vel), Some(slave)) => {
                        slave.state.counters.replies += 1;
                        slave.state.vel_written = Some(vel);
                        self.status_round()
                    }
                    // Never classified as an acknowledgement.
                    (Transaction::ReadInputs(_) | Transaction::ReadStatus(_), Some(_)) => None,
                };
                self.advance(now, next);
            }
            Reply::Inputs(words, count) => {
                let part = match transaction {
                    Transaction::ReadInputs(part) => part,
                    _ => 0,
                };
                let spans = self.layout.input_spans();
                let first = spans.get(part).map_or(0, |(first, _)| first);
                let last = spans.is_last(part);
                let default_dt = self.poll_period;
                let Some(slave) = self.slaves.get_mut(self.pending.slave) else {
                    self.advance(now, None);
                    return;
                };
                let got = words.get(..usize::from(count)).unwrap_or_default();
                self.layout.place_inputs(first, got, &mut slave.reading);
                let next = if last {
                    let reading = slave.reading;
                    slave
                        .measure(now, reading, default_dt)
                        .or_else(|| self.status_round())
                } else {
                    slave.state.counters.replies += 1;
                    Some(Transaction::ReadInputs(part + 1))
                };
                self.advance(now, next);
            }
            Reply::Status(block, words) => {
                let flags = self.layout.flags_read();
                if let Some(slave) = self.slaves.get_mut(self.pending.slave) {
                    slave.state.counters.replies += 1;
                    let status = &mut slave.state.status;
                    let [soc, errs] = status.flags.unwrap_or_default();
                    match (block, flags) {
                        (StatusBlock::Hall, _) => status.hall = Some(words[0]),
                        (StatusBlock::Flags, Some((_, 2, Some(1)))) => {
                            status.flags = Some([words[1], words[0]]);
                        }
                        (StatusBlock::Flags, Some((_, 2, _))) => status.flags = Some(words),
                        (StatusBlock::Flags, _) => status.flags = Some([words[0], errs]),
                        (StatusBlock::Errs, _) => status.flags = Some([soc, words[0]]),
                        (StatusBlock::Status, _) => status.status = Some(words[0]),
                    }
                }
                let next = block.next(&self.layout).map(Transaction::ReadStatus);
                self.advance(now, next);
            }
        }
    }
}

impl Slave {
    fn set_point(&self, now: SimTime) -> f64 {
        self.set_point_override
            .unwrap_or_else(|| self.config.set_point_at(now))
    }

    /// One fresh measurement: runs the PI once and returns the `VEL` write to
    /// make, if the output changed since the last acknowledged write.
    fn measure(
        &mut self,
        now: SimTime,
        words: [u16; INPUT_WORDS],
        default_dt: SimDuration,
    ) -> Option<Transaction> {
        let measured = words
            .get(self.config.speed_source.input_index())
            .copied()
            .map_or(0.0, f64::from);
        let set_point = self.set_point(now);
        // The integral advances by the time the measurements are apart, so a
        // lost cycle does not slow the loop down.
        let dt = self
            .state
            .measured_at
            .map_or(default_dt, |last| now - last)
            .as_secs_f64();
        let output = match self.config.mode {
            LoopMode::Closed => self.pi.update(set_point, measured, dt).round() as u16,
            LoopMode::Open { vel } => vel.min(VEL_MAX as u16),
        };
        let state = &mut self.state;
        state.counters.replies += 1;
        state.inputs = words;
        state.measured_at = Some(now);
        state.set_point_rpm = set_point;
        state.measured_rpm = measured;
        state.error_rpm = set_point - measured;
        state.output = output;
        state.integral = self.pi.integral();
        (state.vel_written != Some(output)).then_some(Transaction::WriteVel(output))
    }
}

impl Node for Supervisor {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        // Bytes while the request is still going out answer an earlier
        // copy (a reply late for the timeout that retried it), or are
        // noise: not this request's reply, which can only follow it. A
        // master flushes its input when it sends; taken as the reply, they
        // would move on to the next request right behind this one.
        if let Phase::Awaiting { deadline: None } = self.phase {
            return;
        }
        // Bytes while a request waits to go out: the rest of a reply already
        // given up on (a bad check mid-frame), or another talker. Sending now
        // would collide with it, so the request waits for the line to be
        // quiet for the silence interval.
        if let Phase::Waiting { at } = self.phase
            && !bytes.is_empty()
        {
            self.phase = Phase::Waiting {
                at: at.max(now + self.line_quiet),
            };
            self.line_free_at = self.line_free_at.max(now + self.line_quiet);
        }
        let mut input = bytes;
        loop {
            let pending = (self.pending_id(), self.pending.transaction);
            let Some(reply) = self
                .decoder
                .next_reply(now, &mut input, pending, &self.layout)
            else {
                break;
            };
            // Bytes after the awaited reply (noise, a late duplicate) are still
            // decoded so the decoder stays in step, but ignored.
            self.on_reply(now, reply);
        }
    }

    fn handle_timeout(&mut self, now: SimTime) {
        if let Phase::Awaiting {
            deadline: Some(deadline),
        } = self.phase
            && now >= deadline
        {
            let id = self.pending_id();
            let name = self.pending.transaction.name();
            if let Some(counters) = self.counters() {
                counters.timeouts += 1;
            }
            self.push_event(now, "timeout", format!("slave {id}: {name} not answered"));
            self.fail(now);
        }
    }

    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        let Phase::Waiting { at } = self.phase else {
            return None;
        };
        if now < at {
            return None;
        }
        let id = self.pending_id();
        let forwarded = self
            .forwarding
            .current
            .as_ref()
            .map_or(&[][..], |forward| forward.data.as_slice());
        let Some(len) =
            self.pending
                .transaction
                .emit(self.protocol, id, &self.layout, forwarded, buf)
        else {
            // Only an engine with a buffer below `MAX_FRAME` gets here: give
            // the exchange up rather than ask for the same instant forever.
            self.push_event(now, "log", format!("slave {id}: transmit buffer too small"));
            if let Some(counters) = self.counters() {
                counters.lost += 1;
            }
            match self.pending.transaction {
                Transaction::Forward { .. } => self.finish_forward(now, WriteOutcome::NoAnswer),
                _ => self.advance(now, None),
            }
            return None;
        };
        self.decoder.reset();
        if let Some(counters) = self.counters() {
            counters.requests += 1;
        }
        // The timeout starts at `transmit_done`, from the last stop bit, as
        // the spec counts it: a request still waiting to be written has not
        // begun to wait for its reply.
        self.phase = Phase::Awaiting { deadline: None };
        Some(len)
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        match self.phase {
            Phase::Waiting { at } => Some(at),
            Phase::Awaiting { deadline } => deadline,
        }
    }

    /// The request has left: its reply timeout starts. Every engine reports
    /// it (the simulated bus after the last byte's stop bit, the real-time
    /// links once the bytes are written); until then the supervisor waits.
    fn transmit_done(&mut self, now: SimTime) {
        if let Phase::Awaiting { deadline: None } = self.phase {
            self.phase = Phase::Awaiting {
                deadline: Some(now + self.reply_timeout),
            };
        }
    }

    fn poll_event(&mut self) -> Option<NodeEvent> {
        self.events.pop_front()
    }
}
