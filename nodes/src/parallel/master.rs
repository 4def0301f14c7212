//! The master EV module: it closes the speed loop on its own wheel and
//! sends the resulting `VEL` to the slave modules every update period, over
//! the PWM-capture link (broadcast or designated) or over Modbus RTU.
//!
//! One update period (1 ms by default, the paper's retransmission period
//! that keeps up with a 60 Hz plant): the PI runs on the module's hall rpm,
//! the new `VEL` is stored in the master's own controller (so the master
//! module's actuator changes at that instant: the reference is issued), and
//! a send cycle starts. A broadcast cycle is one frame. A designated or
//! Modbus cycle addresses each slave in turn and waits for its answer up to
//! the reply timeout; a missing or wrong answer is retransmitted up to
//! `retries` times, then that slave's update is lost for this cycle. A cycle
//! that outlasts the period (Modbus at 115200 baud) is followed at once by
//! the next with the latest `VEL`.

use std::collections::VecDeque;

use plant::{Actuators, Sensors};

use crate::firmware::{EvController, EvControllerConfig, WriteSet, ea};
use crate::master::wire::{Reply, ReplyDecoder, Transaction};
use crate::master::{Protocol, SetPointStep, SpeedPi, StartupOutputs};
use crate::node::{Firmware, Node, NodeEvent};
use protocols::pwmcap::{PwmCoding, PwmFrameKind, PwmRepr};
use protocols::time::{SimDuration, SimTime};

use super::{
    MAX_PWM_SLAVE_ID, PwmReceiver, RxOutcome, broadcast_frame, designated_frame, emit_widths,
    vel_of,
};

/// Events kept before the oldest is dropped.
const MAX_PENDING_EVENTS: usize = 256;

/// How the master reaches its slaves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParallelLink {
    /// PWM-capture, one broadcast frame per update, no answers.
    PwmBroadcast,
    /// PWM-capture, one designated frame per slave, each answered.
    PwmDesignated,
    /// Modbus RTU: coils written once (enable, brake released), then FC 06
    /// `VEL` to each slave every update.
    ModbusRtu,
}

/// The master module's configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct ParallelMasterConfig {
    /// The link to the slaves.
    pub link: ParallelLink,
    /// Slave ids, addressed in this order (PWM designated: 1–15; Modbus: 1–247).
    pub slaves: Vec<u8>,
    /// The PWM link's coding and symbol period (unused on Modbus).
    pub coding: PwmCoding,
    /// Counter ticks per symbol.
    pub period_ticks: u32,
    /// PI update and send period.
    pub update_period: SimDuration,
    /// From the end of a request to giving up on its answer.
    pub reply_timeout: SimDuration,
    /// Retransmissions after a missing or wrong answer.
    pub retries: u8,
    /// PI gains, `VEL` counts per rpm and per rpm·s.
    pub kp: f64,
    /// Integral gain.
    pub ki: f64,
    /// Speed set-point steps for the master's wheel.
    pub set_points: Vec<SetPointStep>,
    /// The master module's own controller board.
    pub controller: EvControllerConfig,
    /// Silence that ends a partial Modbus RTU answer.
    pub rtu_silence: SimDuration,
}

/// Per slave: what the exchanges with it came to.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SlaveCounters {
    /// The slave's id (0 for the broadcast).
    pub id: u8,
    /// Frames sent to it (retransmissions included).
    pub requests: u64,
    /// Answers that acknowledged the reference.
    pub replies: u64,
    /// Answers that did not come in time.
    pub timeouts: u64,
    /// Answers that came wrong (bad check, other value, cut short).
    pub bad_replies: u64,
    /// Retransmissions.
    pub retries: u64,
    /// Updates given up on after the last retransmission.
    pub lost: u64,
    /// Refusals (Modbus exceptions).
    pub exceptions: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stage {
    Idle,
    /// A frame is on the line; `answered` if an answer will follow.
    Sending {
        answered: bool,
    },
    Waiting {
        deadline: SimTime,
    },
}

/// The master module.
#[derive(Debug)]
pub struct ParallelMaster {
    config: ParallelMasterConfig,
    controller: EvController,
    pi: SpeedPi,
    own_enabled: bool,
    next_update: SimTime,
    /// The reference now in force.
    vel: u16,
    set_point_rpm: f64,
    measured_rpm: f64,
    updates: u64,
    cycles: u64,
    cycle_due: bool,
    in_cycle: bool,
    /// Index into the slaves of the current exchange, its attempt, and the
    /// `VEL` it carries.
    cursor: usize,
    attempt: u8,
    sent_vel: u16,
    sent_startup: bool,
    started: Vec<bool>,
    stage: Stage,
    /// Modbus RTU: no request before the line has been quiet for the
    /// inter-frame silence (t3.5), or slaves that heard a neighbour's
    /// answer cannot tell where the next request starts.
    quiet_until: Option<SimTime>,
    pwm_rx: PwmReceiver,
    rtu_rx: ReplyDecoder,
    tx: [u8; 64],
    /// Unused on Modbus RTU, which has one register map; the wire asks for one.
    layout: crate::master::MebLayout,
    counters: Vec<SlaveCounters>,
    events: VecDeque<NodeEvent>,
}

/// Why a master configuration cannot run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParallelConfigError {
    /// No slave to address.
    #[error("the master has no slaves")]
    NoSlaves,
    /// An id the link cannot carry.
    #[error("slave id {0} is outside 1..={1} for this link")]
    IdOutOfRange(u8, u8),
    /// A gain that is not a finite number, or a zero period.
    #[error("{0} must be a positive, finite number")]
    Invalid(&'static str),
}

impl ParallelMaster {
    /// A master at power-up.
    pub fn new(mut config: ParallelMasterConfig) -> Result<Self, ParallelConfigError> {
        if config.slaves.is_empty() {
            return Err(ParallelConfigError::NoSlaves);
        }
        let max = match config.link {
            ParallelLink::ModbusRtu => 247,
            _ => MAX_PWM_SLAVE_ID,
        };
        if let Some(&id) = config.slaves.iter().find(|&&id| id == 0 || id > max) {
            return Err(ParallelConfigError::IdOutOfRange(id, max));
        }
        if !(config.kp.is_finite() && config.ki.is_finite()) {
            return Err(ParallelConfigError::Invalid("kp and ki"));
        }
        if config.update_period == SimDuration::ZERO {
            return Err(ParallelConfigError::Invalid("update_period"));
        }
        config.set_points.sort_by_key(|s| s.at);
        let counters = match config.link {
            ParallelLink::PwmBroadcast => vec![SlaveCounters::default()],
            _ => config
                .slaves
                .iter()
                .map(|&id| SlaveCounters {
                    id,
                    ..SlaveCounters::default()
                })
                .collect(),
        };
        Ok(ParallelMaster {
            controller: EvController::new(config.controller.clone()),
            pi: SpeedPi::new(config.kp, config.ki),
            own_enabled: false,
            next_update: SimTime::ZERO,
            vel: 0,
            set_point_rpm: 0.0,
            measured_rpm: 0.0,
            updates: 0,
            cycles: 0,
            cycle_due: false,
            in_cycle: false,
            cursor: 0,
            attempt: 0,
            sent_vel: 0,
            sent_startup: false,
            started: vec![false; config.slaves.len()],
            stage: Stage::Idle,
            quiet_until: None,
            pwm_rx: PwmReceiver::new(&config.coding, config.period_ticks),
            rtu_rx: ReplyDecoder::new(Protocol::ModbusRtu, config.rtu_silence),
            tx: [0; 64],
            layout: crate::master::MebLayout::default(),
            counters,
            events: VecDeque::with_capacity(MAX_PENDING_EVENTS),
            config,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ParallelMasterConfig {
        &self.config
    }

    /// The reference now in force, `VEL` counts.
    pub fn vel(&self) -> u16 {
        self.vel
    }

    /// The set point and the hall rpm of the last update.
    pub fn loop_state(&self) -> (f64, f64) {
        (self.set_point_rpm, self.measured_rpm)
    }

    /// PI updates so far (references issued).
    pub fn updates(&self) -> u64 {
        self.updates
    }

    /// Send cycles started so far.
    pub fn cycles(&self) -> u64 {
        self.cycles
    }

    /// Per slave (one entry for the broadcast).
    pub fn counters(&self) -> &[SlaveCounters] {
        &self.counters
    }

    fn push_event(&mut self, at: SimTime, kind: &'static str, detail: String) {
        if self.events.len() >= MAX_PENDING_EVENTS {
            self.events.pop_front();
        }
        self.events.push_back(NodeEvent { at, kind, detail });
    }

    fn set_point_at(&self, now: SimTime) -> f64 {
        let after = self.config.set_points.partition_point(|s| s.at <= now);
        after
            .checked_sub(1)
            .and_then(|i| self.config.set_points.get(i))
            .map_or(0.0, |s| s.rpm)
    }

    fn counter(&mut self) -> &mut SlaveCounters {
        let i = self.cursor.min(self.counters.len() - 1);
        &mut self.counters[i]
    }

    /// The exchange with the current slave is over: on to the next.
    fn advance(&mut self) {
        self.stage = Stage::Idle;
        self.attempt = 0;
        self.cursor += 1;
        let targets = match self.config.link {
            ParallelLink::PwmBroadcast => 1,
            _ => self.config.slaves.len(),
        };
        if self.cursor >= targets {
            self.in_cycle = false;
            self.cursor = 0;
        }
    }

    fn acknowledged(&mut self) {
        self.counter().replies += 1;
        if self.sent_startup {
            // Enabled: the same slave gets its `VEL` next, in this cycle.
            self.started[self.cursor] = true;
            self.stage = Stage::Idle;
            self.attempt = 0;
        } else {
            self.advance();
        }
    }

    fn failed(&mut self, now: SimTime, kind: &'static str, why: String) {
        let id = self.config.slaves[self.cursor.min(self.config.slaves.len() - 1)];
        match kind {
            "timeout" => self.counter().timeouts += 1,
            _ => self.counter().bad_replies += 1,
        }
        self.push_event(now, kind, format!("slave {id}: {why}"));
        if self.attempt < self.config.retries {
            self.attempt += 1;
            self.counter().retries += 1;
            let attempt = self.attempt;
            self.push_event(now, "retry", format!("slave {id}: attempt {}", attempt + 1));
            self.stage = Stage::Idle;
        } else {
            self.counter().lost += 1;
            self.push_event(
                now,
                "dropped",
                format!(
                    "slave {id}: update lost after {} attempts",
                    self.attempt + 1
                ),
            );
            self.advance();
        }
    }

    fn on_pwm_answer(&mut self, now: SimTime, outcome: RxOutcome) {
        let id = self.config.slaves[self.cursor.min(self.config.slaves.len() - 1)];
        let widths = match outcome {
            RxOutcome::Frame(widths) => widths,
            RxOutcome::Incomplete { got } => {
                return self.failed(now, "bad_check", format!("answer cut short: {got} of 4"));
            }
        };
        match PwmRepr::parse(PwmFrameKind::Designated, &self.config.coding, &widths) {
            Ok(PwmRepr::Designated { status, data }) if status.high == id => {
                if vel_of(&data) == Some(self.sent_vel) {
                    self.acknowledged();
                } else {
                    let answer =
                        vel_of(&data).map_or_else(|| "no VEL".to_string(), |v| format!("VEL {v}"));
                    let why = format!("answer {answer}, sent VEL {}", self.sent_vel);
                    self.failed(now, "bad_check", why);
                }
            }
            // Another slave's answer on a half-duplex line: not ours.
            Ok(_) => {}
            Err(error) => self.failed(now, "bad_check", format!("widths {widths:?}: {error}")),
        }
    }

    fn on_rtu_answer(&mut self, now: SimTime, reply: Reply) {
        match reply {
            Reply::Ack => self.acknowledged(),
            Reply::Bad => self.failed(now, "bad_check", "crc".into()),
            Reply::Exception(code) => {
                let id = self.config.slaves[self.cursor];
                self.counter().exceptions += 1;
                self.push_event(now, "exception", format!("slave {id}: exception {code}"));
                self.advance();
            }
            // The parallel master never asks for inputs or status words.
            Reply::Unexpected | Reply::Inputs(..) | Reply::Status(..) => {}
        }
    }
}

impl Node for ParallelMaster {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        if !matches!(self.stage, Stage::Waiting { .. }) {
            return;
        }
        match self.config.link {
            ParallelLink::PwmBroadcast => {}
            ParallelLink::PwmDesignated => {
                for &byte in bytes {
                    if !matches!(self.stage, Stage::Waiting { .. }) {
                        break;
                    }
                    if let Some(outcome) = self.pwm_rx.push(now, byte) {
                        self.on_pwm_answer(now, outcome);
                    }
                }
            }
            ParallelLink::ModbusRtu => {
                self.quiet_until = Some(now + self.config.rtu_silence);
                let mut input = bytes;
                let transaction = if self.sent_startup {
                    Transaction::Startup(StartupOutputs::ENABLED_BRAKE_RELEASED, 0)
                } else {
                    Transaction::WriteVel(self.sent_vel)
                };
                while matches!(self.stage, Stage::Waiting { .. }) {
                    let id = self.config.slaves[self.cursor];
                    let Some(reply) =
                        self.rtu_rx
                            .next_reply(now, &mut input, (id, transaction), &self.layout)
                    else {
                        break;
                    };
                    self.on_rtu_answer(now, reply);
                }
            }
        }
    }

    fn handle_timeout(&mut self, now: SimTime) {
        if let Stage::Waiting { deadline } = self.stage
            && deadline <= now
        {
            self.failed(now, "timeout", "no answer".into());
        }
    }

    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        if self.stage != Stage::Idle || self.quiet_until.is_some_and(|t| now < t) {
            return None;
        }
        if !self.in_cycle {
            if !self.cycle_due {
                return None;
            }
            self.cycle_due = false;
            self.in_cycle = true;
            self.cursor = 0;
            self.attempt = 0;
            self.cycles += 1;
        }
        let vel = self.vel;
        let coding = self.config.coding;
        let (len, answered) = match self.config.link {
            ParallelLink::PwmBroadcast => (
                emit_widths(&broadcast_frame(true, vel), &coding, &mut self.tx)?,
                false,
            ),
            ParallelLink::PwmDesignated => {
                let id = self.config.slaves[self.cursor];
                self.pwm_rx.reset();
                (
                    emit_widths(&designated_frame(id, vel), &coding, &mut self.tx)?,
                    true,
                )
            }
            ParallelLink::ModbusRtu => {
                let id = self.config.slaves[self.cursor];
                self.sent_startup = !self.started[self.cursor];
                let transaction = if self.sent_startup {
                    Transaction::Startup(StartupOutputs::ENABLED_BRAKE_RELEASED, 0)
                } else {
                    Transaction::WriteVel(vel)
                };
                self.rtu_rx.reset();
                (
                    transaction.emit(Protocol::ModbusRtu, id, &self.layout, &[], &mut self.tx)?,
                    true,
                )
            }
        };
        let out = buf.get_mut(..len)?;
        out.copy_from_slice(&self.tx[..len]);
        self.sent_vel = vel;
        self.quiet_until = None;
        self.counter().requests += 1;
        self.stage = Stage::Sending { answered };
        Some(len)
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        match self.stage {
            Stage::Waiting { deadline } => Some(deadline),
            // Work waits for the quiet line (it has passed once a request went out).
            Stage::Idle if self.in_cycle || self.cycle_due => self.quiet_until,
            _ => None,
        }
    }

    fn transmit_done(&mut self, now: SimTime) {
        match self.stage {
            Stage::Sending { answered: true } => {
                self.stage = Stage::Waiting {
                    deadline: now + self.config.reply_timeout,
                };
                if self.config.link == ParallelLink::ModbusRtu {
                    self.quiet_until = Some(now + self.config.rtu_silence);
                }
            }
            Stage::Sending { answered: false } => self.advance(),
            _ => {}
        }
    }

    fn poll_event(&mut self) -> Option<NodeEvent> {
        self.events
            .pop_front()
            .or_else(|| self.controller.poll_event())
    }
}

impl Firmware for ParallelMaster {
    fn loop_period(&self) -> SimDuration {
        self.controller.loop_period()
    }

    fn loop_tick(&mut self, now: SimTime, sensors: &Sensors) -> Actuators {
        if !self.own_enabled {
            let set = WriteSet {
                sd0: Some(StartupOutputs::ENABLED_BRAKE_RELEASED.sd0),
                vel: Some(0),
                ..WriteSet::default()
            };
            self.own_enabled = self.controller.store(&set).is_ok();
        }
        if now >= self.next_update {
            self.next_update = now + self.config.update_period;
            self.set_point_rpm = self.set_point_at(now);
            // The hall rpm the controller computed at its previous tick.
            self.measured_rpm = f64::from(self.controller.image().inputs[ea::RPM_M]);
            let dt = self.config.update_period.as_secs_f64();
            let output = self.pi.update(self.set_point_rpm, self.measured_rpm, dt);
            self.vel = output.round().clamp(0.0, 4095.0) as u16;
            let set = WriteSet {
                vel: Some(self.vel),
                ..WriteSet::default()
            };
            // A trip refuses nothing here: VEL is always accepted.
            let _ = self.controller.store(&set);
            self.updates += 1;
            self.cycle_due = true;
        }
        // The new VEL reaches the master's own pins at this very tick.
        self.controller.loop_tick(now, sensors)
    }
}
