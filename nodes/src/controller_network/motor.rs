//! The motor node (id 01): a CANopen-like control-state machine, a 7-pulse
//! encoder counted in 20 ms windows, and its own PI towards the set point.

use crate::node::{Firmware, Node, NodeEvent};
use protocols::modbus::Exception;
use protocols::time::{SimDuration, SimTime};

use super::{
    Access, MOTOR_ID, PortConfig, REG_RPM, REG_SET_SPEED, REG_STATE, RegisterMap, SlavePort,
};

/// The motor node's control state, with its wire value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MotorState {
    /// `0x01`: LED on, driver enabled, PI running.
    Operational,
    /// `0x02`: driver asleep.
    Stopped,
    /// `0x80`: the state at boot; driver asleep.
    PreOperational,
    /// `0x81`: falls to pre-operational on the next loop pass.
    Init,
    /// `0x82`: the serial port closes for 3 ms, then the node goes to init.
    ResetCommunication,
}

impl MotorState {
    /// The value register `0001` reads.
    pub fn code(self) -> u16 {
        match self {
            MotorState::Operational => 0x01,
            MotorState::Stopped => 0x02,
            MotorState::PreOperational => 0x80,
            MotorState::Init => 0x81,
            MotorState::ResetCommunication => 0x82,
        }
    }

    /// The state a written value asks for; `None` for anything else (exception 03).
    pub fn from_code(code: u16) -> Option<Self> {
        match code {
            0x01 => Some(MotorState::Operational),
            0x02 => Some(MotorState::Stopped),
            0x80 => Some(MotorState::PreOperational),
            0x81 => Some(MotorState::Init),
            0x82 => Some(MotorState::ResetCommunication),
            _ => None,
        }
    }

    /// The state's name in the project's firmware, in words.
    pub fn name(self) -> &'static str {
        match self {
            MotorState::Operational => "operational",
            MotorState::Stopped => "stopped",
            MotorState::PreOperational => "pre-operational",
            MotorState::Init => "init",
            MotorState::ResetCommunication => "reset communication",
        }
    }
}

impl std::fmt::Display for MotorState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#04x} ({})", self.code(), self.name())
    }
}

/// One change of control state, waiting to be reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct StateChange {
    at: SimTime,
    from: MotorState,
    to: MotorState,
}

/// State changes not yet polled, oldest first. Two can fall between polls
/// (a state written by the master and the loop's next step in the same
/// tick), so one slot would lose the first. A fixed ring keeps the loop
/// free of allocation; the engines poll after every tick, so it never
/// fills, and if it did the oldest change would give way.
#[derive(Debug, Clone, Copy)]
struct StateChanges {
    ring: [Option<StateChange>; StateChanges::CAPACITY],
    head: usize,
    len: usize,
}

impl StateChanges {
    const CAPACITY: usize = 8;

    const fn new() -> Self {
        StateChanges {
            ring: [None; Self::CAPACITY],
            head: 0,
            len: 0,
        }
    }

    fn push(&mut self, change: StateChange) {
        if self.len == Self::CAPACITY {
            self.head = (self.head + 1) % Self::CAPACITY;
            self.len -= 1;
        }
        self.ring[(self.head + self.len) % Self::CAPACITY] = Some(change);
        self.len += 1;
    }

    fn pop(&mut self) -> Option<StateChange> {
        if self.len == 0 {
            return None;
        }
        let change = self.ring[self.head].take();
        self.head = (self.head + 1) % Self::CAPACITY;
        self.len -= 1;
        change
    }
}

/// Settings of the motor node; the defaults are the project's firmware.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotorConfig {
    /// Serial port settings and faults.
    pub port: PortConfig,
    /// Encoder pulses per motor turn.
    pub encoder_pulses: u32,
    /// Proportional gain (rpm of output per rpm of error).
    pub kp: f64,
    /// Integral time (s).
    pub ti: f64,
    /// Set point at power-up (rpm).
    pub default_set_point: u16,
}

impl Default for MotorConfig {
    fn default() -> Self {
        MotorConfig {
            port: PortConfig::default(),
            encoder_pulses: 7,
            kp: 0.27,
            ti: 0.41,
            default_set_point: 10_000,
        }
    }
}

/// The firmware's 2 ms timer interrupt drives its windows; the loop runs on it.
const LOOP_PERIOD: SimDuration = SimDuration::from_millis(2);
/// Encoder counts are latched into an rpm this often.
const LATCH_PERIOD: SimDuration = SimDuration::from_millis(20);
/// The PI runs this often.
const PI_PERIOD: SimDuration = SimDuration::from_millis(100);
/// Set points the firmware accepts: `MIN_SPEED < v < MAX_SPEED`.
const SET_POINT_RANGE: core::ops::RangeInclusive<u16> = 21..=12_499;
/// PI output limits (rpm).
const PI_OUTPUT_MIN: f64 = 1.0;
const PI_OUTPUT_MAX: f64 = 12_500.0;
/// A fault output held low this long sends the motor to stopped.
const ENCODER_FAULT_HOLD: SimDuration = SimDuration::from_millis(5);
/// `Serial.end(); delay(3); Serial.begin()`.
const RESET_COMM_PAUSE: SimDuration = SimDuration::from_millis(3);

/// The registers and the control state (what requests read and write).
#[derive(Debug, Clone)]
struct MotorRegisters {
    state: MotorState,
    set_point: u16,
    latched_rpm: i16,
}

impl RegisterMap for MotorRegisters {
    fn access(&self, addr: u16) -> Option<Access> {
        match addr {
            REG_STATE => Some(Access::ReadWrite),
            REG_RPM => Some(Access::Read),
            REG_SET_SPEED => Some(Access::Write),
            _ => None,
        }
    }

    fn read(&self, addr: u16) -> u16 {
        match addr {
            REG_STATE => self.state.code(),
            // Two's complement on the wire: reverse reads negative.
            REG_RPM => self.latched_rpm as u16,
            _ => 0,
        }
    }

    fn write(&mut self, addr: u16, value: u16) -> Result<(), Exception> {
        match addr {
            REG_STATE => {
                self.state = MotorState::from_code(value).ok_or(Exception::IllegalDataValue)?;
            }
            REG_SET_SPEED if SET_POINT_RANGE.contains(&value) => self.set_point = value,
            _ => return Err(Exception::IllegalDataValue),
        }
        Ok(())
    }
}

/// The project's PI: `output = Kp (e + ∫e dt / Ti)`, clamped; the integral stops
/// while the output is clamped in the error's direction, so a long stop does
/// not wind it up.
#[derive(Debug, Clone)]
struct SpeedPi {
    kp: f64,
    ti: f64,
    integral: f64,
}

impl SpeedPi {
    fn update(&mut self, set_point: f64, measured: f64, dt: f64) -> f64 {
        let error = set_point - measured;
        let integral = self.integral + error * dt;
        let output = self.kp * (error + integral / self.ti);
        let clamped = output.clamp(PI_OUTPUT_MIN, PI_OUTPUT_MAX);
        let winding_up =
            (output > PI_OUTPUT_MAX && error > 0.0) || (output < PI_OUTPUT_MIN && error < 0.0);
        if !winding_up {
            self.integral = integral;
        }
        clamped
    }
}

/// The motor node (id 01) of the Controller_network project.
#[derive(Debug, Clone)]
pub struct MotorNode {
    config: MotorConfig,
    port: SlavePort,
    registers: MotorRegisters,
    pi: SpeedPi,
    /// PWM duty, whole percent as the firmware's `ana_out.set(int)`, 0..=1.
    duty: f64,
    /// Encoder count at the start of the current 20 ms window.
    window_start_count: Option<i64>,
    next_latch_at: SimTime,
    next_pi_at: SimTime,
    /// Set by the 100 ms timer, taken by the PI only in operational (the
    /// firmware's `bUpdateSpeed`).
    pi_due: bool,
    /// Injected encoder fault output (active low) and when it went low.
    encoder_fault_low_since: Option<SimTime>,
    last_state: MotorState,
    state_changes: StateChanges,
}

impl MotorNode {
    /// A motor node at power-up: pre-operational, set point 10000.
    pub fn new(config: MotorConfig) -> Self {
        MotorNode {
            config,
            port: SlavePort::new(MOTOR_ID, config.port),
            registers: MotorRegisters {
                state: MotorState::PreOperational,
                set_point: config.default_set_point,
                latched_rpm: 0,
            },
            pi: SpeedPi {
                kp: config.kp,
                ti: config.ti,
                integral: 0.0,
            },
            duty: 0.0,
            window_start_count: None,
            next_latch_at: SimTime::ZERO,
            next_pi_at: SimTime::ZERO,
            pi_due: false,
            encoder_fault_low_since: None,
            last_state: MotorState::PreOperational,
            state_changes: StateChanges::new(),
        }
    }

    /// The control state now.
    pub fn state(&self) -> MotorState {
        self.registers.state
    }

    /// The set point (rpm).
    pub fn set_point(&self) -> u16 {
        self.registers.set_point
    }

    /// The rpm latched at the end of the last 20 ms window (register `0005`).
    pub fn latched_rpm(&self) -> i16 {
        self.registers.latched_rpm
    }

    /// The PWM duty the firmware drives (0..=1).
    pub fn duty(&self) -> f64 {
        self.duty
    }

    /// Injected fault: the encoder's fault output is held low (`true`) or released.
    pub fn set_encoder_fault(&mut self, now: SimTime, low: bool) {
        self.encoder_fault_low_since = match (low, self.encoder_fault_low_since) {
            (true, Some(since)) => Some(since),
            (true, None) => Some(now),
            (false, _) => None,
        };
    }

    /// Injected fault: corrupt the CRC of every reply from now on (or stop).
    pub fn set_corrupt_reply_crc(&mut self, corrupt: bool) {
        self.config.port.corrupt_reply_crc = corrupt;
        self.port.config.corrupt_reply_crc = corrupt;
    }

    fn latch_encoder(&mut self, now: SimTime, encoder_count: i64) {
        let Some(start) = self.window_start_count else {
            // The timers start with the first loop pass.
            self.window_start_count = Some(encoder_count);
            self.next_latch_at = now + LATCH_PERIOD;
            self.next_pi_at = now + PI_PERIOD;
            return;
        };
        if now < self.next_latch_at {
            return;
        }
        let count = encoder_count - start;
        // rpm = count / pulses per 20 ms × 60 s, in float and truncated to
        // i16 as the firmware does: steps of 428.57 rpm for 7 pulses.
        let windows_per_second = 1.0 / LATCH_PERIOD.as_secs_f64();
        let rpm = count as f64 * windows_per_second / f64::from(self.config.encoder_pulses) * 60.0;
        self.registers.latched_rpm = rpm as i16;
        self.window_start_count = Some(encoder_count);
        while self.next_latch_at <= now {
            self.next_latch_at += LATCH_PERIOD;
        }
    }

    fn run_state_machine(&mut self, now: SimTime) {
        let fault = self
            .encoder_fault_low_since
            .is_some_and(|since| now.saturating_since(since) > ENCODER_FAULT_HOLD);
        let state = &mut self.registers.state;
        match *state {
            MotorState::Init => *state = MotorState::PreOperational,
            MotorState::ResetCommunication => {
                self.port.close_for(now, RESET_COMM_PAUSE);
                *state = MotorState::Init;
            }
            MotorState::PreOperational if fault => *state = MotorState::Stopped,
            MotorState::Operational if fault => *state = MotorState::Stopped,
            MotorState::Operational => {
                if self.pi_due {
                    self.pi_due = false;
                    let set_point = f64::from(self.registers.set_point);
                    let output = self.pi.update(
                        set_point,
                        f64::from(self.registers.latched_rpm),
                        PI_PERIOD.as_secs_f64(),
                    );
                    // `(int)(constrain(out / target, 0.01, 0.99) * 100)`.
                    self.duty = ((output / set_point).clamp(0.01, 0.99) * 100.0).trunc() / 100.0;
                }
            }
            MotorState::PreOperational | MotorState::Stopped => {}
        }
    }

    fn note_state_change(&mut self, now: SimTime) {
        let state = self.registers.state;
        if state != self.last_state {
            self.state_changes.push(StateChange {
                at: now,
                from: self.last_state,
                to: state,
            });
            self.last_state = state;
        }
    }
}

impl Default for MotorNode {
    fn default() -> Self {
        Self::new(MotorConfig::default())
    }
}

impl Node for MotorNode {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        self.port.receive(&mut self.registers, now, bytes);
        self.note_state_change(now);
    }

    fn handle_timeout(&mut self, now: SimTime) {
        self.port.handle_timeout(now);
    }

    fn poll_transmit(&mut self, _now: SimTime, buf: &mut [u8]) -> Option<usize> {
        self.port.poll_transmit(buf)
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        self.port.poll_timeout()
    }

    fn poll_event(&mut self) -> Option<NodeEvent> {
        let change = self.state_changes.pop()?;
        Some(NodeEvent {
            at: change.at,
            kind: "state",
            detail: format!("motor state {} -> {}", change.from, change.to),
        })
    }

    fn force_refusal(&mut self, refusal: Option<crate::firmware::Refusal>) -> bool {
        self.port.forced = refusal.map(crate::firmware::Refusal::modbus);
        true
    }
}

impl Firmware for MotorNode {
    fn loop_period(&self) -> SimDuration {
        LOOP_PERIOD
    }

    fn loop_tick(&mut self, now: SimTime, sensors: &plant::Sensors) -> plant::Actuators {
        self.latch_encoder(now, sensors.shaft.encoder_count);
        if self.window_start_count.is_some() && now >= self.next_pi_at {
            self.pi_due = true;
            while self.next_pi_at <= now {
                self.next_pi_at += PI_PERIOD;
            }
        }
        self.run_state_machine(now);
        self.note_state_change(now);
        let operational = self.registers.state == MotorState::Operational;
        plant::Actuators {
            // The 10 ms software PWM on the driver's input, averaged: the
            // plant's throttle map turns 0–5 V into 0–100 % duty.
            vel_volts: self.duty * 5.0,
            // The driver's sleep pin: awake only in operational.
            enable: operational,
            ..plant::Actuators::default()
        }
    }
}
