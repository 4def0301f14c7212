//! The Raspberry Pi master of the Controller_network project: a state
//! handshake with the motor, then a loop reading the motor's rpm and the light
//! sensor, toggling the set point between 5000 and 10000 every 20th cycle,
//! printing what it does. Its step-response program is the other program the
//! project ran on the Pi: no handshake, and a loop that reads both nodes and
//! writes the motor's state to operational, so that its first write is the step.
//!
//! Beside either program, or in place of both, a scenario can script
//! requests ([`ScriptedRequest`]): frames sent at given times, as the
//! project's command-line `modbus` program (`./modbus 1 6 1 128`) sent the
//! single requests of its oscilloscope captures.

use std::collections::VecDeque;

use crate::node::{Node, NodeEvent};
use protocols::modbus::Exception;
use protocols::modbus8::{self, CrcOrder, FRAME_LEN, Modbus8Decoder, Modbus8Error, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};

use super::{
    BAUD, LIGHT_ID, MOTOR_ID, MotorState, REG_LIGHT_VALUE, REG_RPM, REG_SET_SPEED, REG_STATE,
    corrupt_crc,
};

/// Events kept for the engine to take; older ones are dropped beyond this.
const EVENT_QUEUE: usize = 64;

/// Which of the project's two Pi programs runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MasterProgram {
    /// `main.cpp`: the handshake, then read rpm, toggle the set point every
    /// `toggle_every` cycles, read the sensor, sleep.
    #[default]
    Loop,
    /// `main_step_response.cpp`: from the start, read rpm, read the sensor,
    /// write the state operational, again and again with no sleep. It never
    /// writes the set point, so the motor's power-up target is the step.
    StepResponse,
    /// The command-line `modbus` program: only the scripted requests, one
    /// at a time, each reply read once after the wait.
    Requests,
}

impl MasterProgram {
    /// The program in the lab's words.
    pub fn name(self) -> &'static str {
        match self {
            MasterProgram::Loop => "loop",
            MasterProgram::StepResponse => "step-response",
            MasterProgram::Requests => "requests",
        }
    }
}

/// Settings of the master; the defaults are the project's program.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MasterConfig {
    /// Which program runs.
    pub program: MasterProgram,
    /// The program starts (sends its first request) at this time: the Pi
    /// started after the Nanos had booted.
    pub start: SimDuration,
    /// CRC byte order (the project's own: high byte first).
    pub crc_order: CrcOrder,
    /// Line quiet that ends a partial reply.
    pub silence: SimDuration,
    /// `usleep(100000)` between writing a request and reading the reply.
    pub reply_wait: SimDuration,
    /// Give up on a reply this long after the request left. `None` (the
    /// original program): wait for ever, so a lost reply hangs the master.
    pub reply_timeout: Option<SimDuration>,
    /// Sleep at the end of every loop cycle.
    pub cycle_sleep: SimDuration,
    /// The set point toggles every this many cycles.
    pub toggle_every: u32,
    /// The lower set point (rpm); the first toggle writes it.
    pub set_point_low: u16,
    /// The higher set point (rpm): the motor's default, assumed before the first toggle.
    pub set_point_high: u16,
    /// Emit the program's printout as `log` events.
    pub log: bool,
    /// Injected fault: add 1 to the CRC of every request (the project's `0x55aa` test).
    pub corrupt_request_crc: bool,
}

impl Default for MasterConfig {
    fn default() -> Self {
        MasterConfig {
            program: MasterProgram::Loop,
            start: SimDuration::ZERO,
            crc_order: CrcOrder::HighFirst,
            silence: protocols::modbus::serial::silence_3_5_chars(BAUD, 10),
            reply_wait: SimDuration::from_millis(100),
            reply_timeout: None,
            cycle_sleep: SimDuration::from_millis(500),
            toggle_every: 20,
            set_point_low: 5_000,
            set_point_high: 10_000,
            log: true,
            corrupt_request_crc: false,
        }
    }
}

impl MasterConfig {
    /// The step-response program as the project built it: it reads each
    /// reply 10 ms after its request (`usleep(10000)`), where the loop waits 100 ms.
    pub fn step_response() -> Self {
        MasterConfig {
            program: MasterProgram::StepResponse,
            reply_wait: SimDuration::from_millis(10),
            cycle_sleep: SimDuration::ZERO,
            ..MasterConfig::default()
        }
    }
}

/// What the master is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MasterPhase {
    /// Reading the motor's state until it is operational.
    Handshake,
    /// Reading rpm and sensor, toggling the set point.
    Running,
}

impl MasterPhase {
    /// The phase in words.
    pub fn name(self) -> &'static str {
        match self {
            MasterPhase::Handshake => "handshake",
            MasterPhase::Running => "running",
        }
    }
}

/// The transaction in flight or next to send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    ReadState,
    WriteState(u16),
    ReadRpm,
    WriteSetPoint(u16),
    ReadSensor,
}

impl Step {
    fn request(self) -> Modbus8Repr {
        let (id, function, addr, value) = match self {
            Step::ReadState => (MOTOR_ID, modbus8::READ, REG_STATE, 0),
            Step::WriteState(v) => (MOTOR_ID, modbus8::WRITE, REG_STATE, v),
            // The project's master sends 0001 in this read's value field.
            Step::ReadRpm => (MOTOR_ID, modbus8::READ, REG_RPM, 1),
            Step::WriteSetPoint(v) => (MOTOR_ID, modbus8::WRITE, REG_SET_SPEED, v),
            Step::ReadSensor => (LIGHT_ID, modbus8::READ, REG_LIGHT_VALUE, 0),
        };
        Modbus8Repr {
            id,
            function,
            addr,
            value,
        }
    }
}

/// A request a scenario scripts: sent at `at`, or as soon as the
/// transaction in flight is over; its reply is read once, `reply_wait`
/// after it, and only printed (the program's own state is left alone).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ScriptedRequest {
    pub at: SimTime,
    pub frame: Modbus8Repr,
    /// Sent with its CRC plus one, as the project's test of a wrong CRC.
    pub bad_crc: bool,
}

/// Where the current transaction stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Wait {
    /// Nothing of the program's to send (the `requests` program).
    Idle,
    /// Send `step` at or after the instant.
    Send(SimTime),
    /// The request is out since the instant; read the reply from `+ reply_wait`.
    Reply(SimTime),
}

/// The Controller_network master (the Raspberry Pi program).
#[derive(Debug, Clone)]
pub struct ControllerNetworkMaster {
    config: MasterConfig,
    decoder: Modbus8Decoder,
    phase: MasterPhase,
    step: Step,
    wait: Wait,
    /// The request in flight.
    current: Modbus8Repr,
    /// Scripted requests in time order, and the next one's index.
    script: Vec<ScriptedRequest>,
    next_script: usize,
    /// While a scripted request is in flight: the program's wait it
    /// interrupted, taken up again after it.
    paused: Option<Wait>,
    reply: Option<Result<Modbus8Repr, Modbus8Error>>,
    cycle: u32,
    set_point: u16,
    motor_state: Option<u16>,
    motor_rpm: Option<i16>,
    sensor_value: Option<u16>,
    crc_errors: u64,
    timeouts: u64,
    events: VecDeque<NodeEvent>,
}

impl ControllerNetworkMaster {
    /// A master about to start its program at `config.start`.
    pub fn new(config: MasterConfig) -> Self {
        let (phase, step) = match config.program {
            MasterProgram::Loop => (MasterPhase::Handshake, Step::ReadState),
            MasterProgram::StepResponse | MasterProgram::Requests => {
                (MasterPhase::Running, Step::ReadRpm)
            }
        };
        let wait = match config.program {
            MasterProgram::Requests => Wait::Idle,
            _ => Wait::Send(SimTime::ZERO + config.start),
        };
        ControllerNetworkMaster {
            config,
            decoder: Modbus8Decoder::new(config.crc_order, config.silence),
            phase,
            step,
            wait,
            current: step.request(),
            script: Vec::new(),
            next_script: 0,
            paused: None,
            reply: None,
            cycle: 0,
            set_point: config.set_point_high,
            motor_state: None,
            motor_rpm: None,
            sensor_value: None,
            crc_errors: 0,
            timeouts: 0,
            events: VecDeque::with_capacity(EVENT_QUEUE),
        }
    }

    /// The same master with `script` to send besides (or, in the
    /// `requests` program, instead of) its program's requests.
    pub fn with_script(mut self, mut script: Vec<ScriptedRequest>) -> Self {
        // Stable: requests of one instant go in the order written.
        script.sort_by_key(|r| r.at);
        self.script = script;
        self.next_script = 0;
        self
    }

    /// Scripted requests: how many were sent, of how many.
    pub fn scripted(&self) -> (usize, usize) {
        (self.next_script, self.script.len())
    }

    /// The program it runs.
    pub fn program(&self) -> MasterProgram {
        self.config.program
    }

    /// Handshake or running.
    pub fn phase(&self) -> MasterPhase {
        self.phase
    }
    /// The motor state last read.
    pub fn motor_state(&self) -> Option<u16> {
        self.motor_state
    }
    /// The motor rpm last read.
    pub fn motor_rpm(&self) -> Option<i16> {
        self.motor_rpm
    }
    /// The light sensor's register last read (wheel rpm × 100).
    pub fn sensor_value(&self) -> Option<u16> {
        self.sensor_value
    }
    /// The set point last written (the motor's default before the first toggle).
    pub fn set_point(&self) -> u16 {
        self.set_point
    }
    /// Loop cycles started since the handshake.
    pub fn cycles(&self) -> u32 {
        self.cycle
    }
    /// Replies rejected for a bad CRC.
    pub fn crc_errors(&self) -> u64 {
        self.crc_errors
    }
    /// Replies given up on (only with a `reply_timeout`).
    pub fn timeouts(&self) -> u64 {
        self.timeouts
    }

    /// Queues an event; the oldest goes if the engine has not taken them.
    fn push_event(&mut self, at: SimTime, kind: &'static str, detail: String) {
        if self.events.len() == EVENT_QUEUE {
            self.events.pop_front();
        }
        self.events.push_back(NodeEvent { at, kind, detail });
    }

    fn log(&mut self, at: SimTime, line: impl FnOnce() -> String) {
        if self.config.log {
            self.push_event(at, "log", line());
        }
    }

    /// Reads the reply (if the wait is over) and moves to the next step.
    fn try_finish(&mut self, now: SimTime) {
        let Wait::Reply(sent_at) = self.wait else {
            return;
        };
        if now < sent_at + self.config.reply_wait {
            return;
        }
        match self.reply.take() {
            Some(Ok(frame)) => self.use_reply(now, frame),
            Some(Err(error)) => {
                self.crc_errors += 1;
                if let Modbus8Error::BadCrc {
                    received,
                    calculated,
                } = error
                {
                    self.log(now, || {
                        format!(
                            "CRC Error, will not use message. Received: 0x{received:04x} Calculated: 0x{calculated:04x}"
                        )
                    });
                }
                self.push_event(now, "bad_check", error.to_string());
                self.advance(now, None);
            }
            // The `modbus` program reads once and closes the port.
            None if self.paused.is_some() => {
                self.timeouts += 1;
                self.log(now, || "There was no data available to read!".to_string());
                let id = self.current.id;
                self.push_event(now, "timeout", format!("no reply from {id:02x}"));
                self.advance(now, None);
            }
            None => match self.config.reply_timeout {
                Some(timeout) if now >= sent_at + timeout => {
                    self.timeouts += 1;
                    self.log(now, || "There was no data available to read!".to_string());
                    let id = self.current.id;
                    self.push_event(now, "timeout", format!("no reply from {id:02x}"));
                    self.advance(now, None);
                }
                // Blocks in read() until bytes come.
                _ => {}
            },
        }
    }

    fn use_reply(&mut self, now: SimTime, frame: Modbus8Repr) {
        let request = self.current;
        let order = self.config.crc_order;
        self.log(now, || {
            let bytes = frame.to_bytes(order);
            format!(
                "The following was read in [8]: {:02x} {:02x} {:02x}{:02x} {:02x}{:02x} {:02x}{:02x}",
                bytes[0], bytes[1], bytes[2], bytes[3], bytes[4], bytes[5], bytes[6], bytes[7]
            )
        });
        if frame.id != request.id
            || frame.addr != request.addr
            || frame.function & 0x7f != request.function
        {
            self.push_event(
                now,
                "bad_reply",
                format!("reply {} to request {}", words(&frame), words(&request)),
            );
            self.advance(now, None);
            return;
        }
        match frame.reply() {
            Ok(v) => {
                // A scripted request's value is only printed (above).
                if self.config.log && self.paused.is_none() {
                    self.log_value(now, v);
                }
                self.advance(now, Some(v));
            }
            Err(exception) => {
                self.log(now, || exception_text(exception).to_string());
                self.push_event(
                    now,
                    "exception",
                    format!("{exception} from {:02x}", frame.id),
                );
                self.advance(now, None);
            }
        }
    }

    /// The project's printout of a good reply: one line with the value, then one
    /// in hex (its "Motor RMP is" prints the high byte).
    fn log_value(&mut self, now: SimTime, v: u16) {
        let (first, second) = match self.step {
            Step::ReadState => (
                format!("Response Motor: {v}"),
                format!("Motor State: {v:04x}"),
            ),
            Step::ReadRpm => (
                format!("Response Motor: {}", v as i16),
                format!("Motor RMP is: {:04x}", v >> 8),
            ),
            Step::WriteState(_) | Step::WriteSetPoint(_) => (
                format!("Response Motor Value: {v}"),
                format!("Motor data is set:{v:04x}"),
            ),
            Step::ReadSensor => (
                format!("Response Sensor Value: {v}"),
                format!("Sensor RPM: {:02x} {:02x}", v >> 8, v & 0xff),
            ),
        };
        self.push_event(now, "log", first);
        self.push_event(now, "log", second);
    }

    /// The next step after the current one, given the value it got (if usable).
    fn advance(&mut self, now: SimTime, value: Option<u16>) {
        if let Some(wait) = self.paused.take() {
            // A scripted request is over: the program goes on where it was.
            self.wait = wait;
            return;
        }
        if self.config.program != MasterProgram::Loop {
            self.advance_step_response(now, value);
            return;
        }
        let next = match (self.step, value) {
            (Step::ReadState, Some(state)) => {
                self.motor_state = Some(state);
                match MotorState::from_code(state) {
                    Some(MotorState::Operational) => {
                        self.phase = MasterPhase::Running;
                        self.push_event(now, "state", "motor operational".to_string());
                        self.start_cycle()
                    }
                    Some(MotorState::PreOperational) => {
                        Step::WriteState(MotorState::Operational.code())
                    }
                    Some(MotorState::Stopped) => Step::WriteState(MotorState::Init.code()),
                    _ => Step::ReadState,
                }
            }
            (Step::ReadState | Step::WriteState(_), _) => Step::ReadState,
            (Step::ReadRpm, v) => {
                if let Some(v) = v {
                    self.motor_rpm = Some(v as i16);
                }
                if self.cycle.is_multiple_of(self.config.toggle_every.max(1)) {
                    let next = if self.set_point == self.config.set_point_low {
                        self.config.set_point_high
                    } else {
                        self.config.set_point_low
                    };
                    Step::WriteSetPoint(next)
                } else {
                    Step::ReadSensor
                }
            }
            (Step::WriteSetPoint(sp), v) => {
                if v == Some(sp) {
                    self.set_point = sp;
                }
                Step::ReadSensor
            }
            (Step::ReadSensor, v) => {
                if let Some(v) = v {
                    self.sensor_value = Some(v);
                }
                self.step = self.start_cycle();
                self.wait = Wait::Send(now + self.config.cycle_sleep);
                return;
            }
        };
        self.step = next;
        self.wait = Wait::Send(now);
    }

    fn start_cycle(&mut self) -> Step {
        self.cycle += 1;
        Step::ReadRpm
    }

    /// The step-response program: rpm, sensor, state operational, at once
    /// one after the other (its only pause is the wait for each reply).
    fn advance_step_response(&mut self, now: SimTime, value: Option<u16>) {
        if self.config.program == MasterProgram::Requests {
            self.wait = Wait::Idle;
            return;
        }
        self.step = match (self.step, value) {
            (Step::ReadRpm, v) => {
                if let Some(v) = v {
                    self.motor_rpm = Some(v as i16);
                }
                Step::ReadSensor
            }
            (Step::ReadSensor, v) => {
                if let Some(v) = v {
                    self.sensor_value = Some(v);
                }
                Step::WriteState(MotorState::Operational.code())
            }
            (_, v) => {
                if let Some(v) = v {
                    self.motor_state = Some(v);
                }
                self.start_cycle()
            }
        };
        self.wait = Wait::Send(now);
    }
}

/// What the project's `handleError` prints for an exception code.
/// A frame's id, function, register and value, as the project prints them.
fn words(frame: &Modbus8Repr) -> String {
    format!(
        "{:02x} {:02x} {:04x} {:04x}",
        frame.id, frame.function, frame.addr, frame.value
    )
}

fn exception_text(exception: Exception) -> &'static str {
    match exception {
        Exception::IllegalFunction => "Illegal Function",
        Exception::IllegalDataAddress => "Illegal Data Address",
        Exception::IllegalDataValue => "Illegal Data Value",
        Exception::ServerDeviceFailure => "Server Device Failure",
        _ => "Unknown error value.",
    }
}

impl Default for ControllerNetworkMaster {
    fn default() -> Self {
        Self::new(MasterConfig::default())
    }
}

impl Node for ControllerNetworkMaster {
    fn handle_bytes(&mut self, now: SimTime, mut bytes: &[u8]) {
        while !bytes.is_empty() {
            let Some(decoded) = self.decoder.decode(now, &mut bytes) else {
                break;
            };
            let decoded = decoded.map(|frame| Modbus8Repr::from_frame(&frame));
            // Only the first frame after a request is read; later bytes sit
            // in the port until it is flushed for the next request.
            if matches!(self.wait, Wait::Reply(_)) && self.reply.is_none() {
                self.reply = Some(decoded);
            }
        }
        self.try_finish(now);
    }

    fn handle_timeout(&mut self, now: SimTime) {
        if self.decoder.poll_timeout().is_some_and(|at| at <= now) {
            self.decoder.handle_timeout(now);
        }
        self.try_finish(now);
    }

    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        let scripted = self
            .script
            .get(self.next_script)
            .filter(|r| r.at <= now)
            .copied();
        let program_due = matches!(self.wait, Wait::Send(at) if at <= now);
        let ready = matches!(self.wait, Wait::Idle | Wait::Send(_));
        if !ready || (scripted.is_none() && !program_due) {
            return None;
        }
        let slot = buf.get_mut(..FRAME_LEN)?;
        let (request, bad_crc) = match scripted {
            // A scripted request goes first, between the program's.
            Some(r) => {
                self.next_script += 1;
                self.paused = Some(self.wait);
                (r.frame, r.bad_crc)
            }
            None => (self.step.request(), false),
        };
        self.current = request;
        let mut bytes = request.to_bytes(self.config.crc_order);
        if self.config.corrupt_request_crc || bad_crc {
            corrupt_crc(&mut bytes, self.config.crc_order);
        }
        slot.copy_from_slice(&bytes);
        // tcflush(TCIFLUSH) on every open: stale input is gone.
        self.decoder = Modbus8Decoder::new(self.config.crc_order, self.config.silence);
        self.reply = None;
        // The wait starts now; `transmit_done` moves it to the last stop bit.
        self.wait = Wait::Reply(now);
        let order = self.config.crc_order;
        self.log(now, || {
            let crc = u16::from_be_bytes([bytes[6], bytes[7]]);
            let crc = match order {
                CrcOrder::HighFirst => crc,
                CrcOrder::LowFirst => crc.swap_bytes(),
            };
            format!(
                "Sent request: {:02x} {:02x} {:04x} {:04x} {crc:04x}",
                request.id, request.function, request.addr, request.value
            )
        });
        Some(FRAME_LEN)
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        let next_script = self.script.get(self.next_script).map(|r| r.at);
        let own = match self.wait {
            Wait::Idle => next_script,
            Wait::Send(at) => Some(next_script.map_or(at, |s| s.min(at))),
            Wait::Reply(sent_at) => {
                let read_at = sent_at + self.config.reply_wait;
                if self.reply.is_some() || self.paused.is_some() {
                    // A reply to read, or a scripted request's one read.
                    Some(read_at)
                } else {
                    // Nothing to read yet: wake for the timeout, if there is one.
                    self.config
                        .reply_timeout
                        .map(|t| (sent_at + t).max(read_at))
                }
            }
        };
        match (own, self.decoder.poll_timeout()) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    fn transmit_done(&mut self, now: SimTime) {
        if let Wait::Reply(_) = self.wait {
            self.wait = Wait::Reply(now);
        }
    }

    fn poll_event(&mut self) -> Option<NodeEvent> {
        self.events.pop_front()
    }
}
