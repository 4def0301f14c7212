//! A slave EV module on the PWM-capture link: its controller board takes
//! `VEL` and run/stop from the master's frames instead of its serial port.

use std::collections::VecDeque;

use plant::{Actuators, Sensors};

use crate::firmware::{EvController, EvControllerConfig, WriteSet, sd};
use crate::master::StartupOutputs;
use crate::node::{Firmware, Node, NodeEvent};
use protocols::pwmcap::{PwmCoding, PwmData, PwmFrameKind, PwmRepr};
use protocols::time::{SimDuration, SimTime};

use super::{
    MAX_PWM_SLAVE_ID, PwmReceiver, RxOutcome, STATUS_RUN, STATUS_STOP, designated_frame,
    emit_widths, vel_of,
};

/// Events kept before the oldest is dropped.
const MAX_PENDING_EVENTS: usize = 64;

/// Which frames the master sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PwmAddressing {
    /// One frame for all; never answered.
    Broadcast,
    /// One frame per slave; the addressed slave answers.
    Designated,
}

/// A PWM slave's configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct PwmSlaveConfig {
    /// Its id in designated frames, 1–15.
    pub id: u8,
    /// What the master sends.
    pub addressing: PwmAddressing,
    /// The link's coding.
    pub coding: PwmCoding,
    /// The link's symbol period, counter ticks.
    pub period_ticks: u32,
    /// The module's controller (its loop period, motor, light sensor).
    pub controller: EvControllerConfig,
}

/// What a slave received.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PwmSlaveCounters {
    /// Frames that decoded and were for this slave.
    pub frames_taken: u64,
    /// Frames that decoded and were for another slave (or another slave's answer).
    pub frames_ignored: u64,
    /// Frames that did not decode (width out of range, bad status).
    pub bad_frames: u64,
    /// Frames that stopped short (pulses lost on the line).
    pub incomplete_frames: u64,
    /// Answers sent (designated).
    pub answers: u64,
}

/// The slave module's controller on the PWM-capture link.
#[derive(Debug)]
pub struct PwmSlave {
    config: PwmSlaveConfig,
    controller: EvController,
    rx: PwmReceiver,
    tx: [u8; 64],
    tx_len: usize,
    counters: PwmSlaveCounters,
    /// The last `VEL` taken from the master.
    vel: Option<u16>,
    events: VecDeque<NodeEvent>,
}

impl PwmSlave {
    /// A slave at power-up; `None` for an id a designated frame cannot carry.
    pub fn new(config: PwmSlaveConfig) -> Option<Self> {
        if config.id == 0 || config.id > MAX_PWM_SLAVE_ID {
            return None;
        }
        Some(PwmSlave {
            controller: EvController::new(config.controller.clone()),
            rx: PwmReceiver::new(&config.coding, config.period_ticks),
            tx: [0; 64],
            tx_len: 0,
            counters: PwmSlaveCounters::default(),
            vel: None,
            events: VecDeque::with_capacity(MAX_PENDING_EVENTS),
            config,
        })
    }

    /// What it received so far.
    pub fn counters(&self) -> &PwmSlaveCounters {
        &self.counters
    }

    /// The last `VEL` it took.
    pub fn vel(&self) -> Option<u16> {
        self.vel
    }

    /// The controller board.
    pub fn controller(&self) -> &EvController {
        &self.controller
    }

    fn push_event(&mut self, at: SimTime, kind: &'static str, detail: String) {
        if self.events.len() >= MAX_PENDING_EVENTS {
            self.events.pop_front();
        }
        self.events.push_back(NodeEvent { at, kind, detail });
    }

    fn take(&mut self, now: SimTime, run: bool, vel: u16) {
        let sd0 = if run {
            // EN, BRK released, boost and discharge off, clockwise.
            StartupOutputs::ENABLED_BRAKE_RELEASED.sd0
        } else {
            sd::SD0_OFF
        };
        let stored = self.controller.image().stored;
        let set = WriteSet {
            vel: Some(vel),
            // Writing SD0 only on a change keeps the trip latch's
            // release-then-enable rule meaningful.
            sd0: (stored.sd0 != sd0).then_some(sd0),
            ..WriteSet::default()
        };
        match self.controller.store(&set) {
            Ok(()) => {
                self.counters.frames_taken += 1;
                self.vel = Some(vel);
            }
            Err(refusal) => self.push_event(now, "exception", refusal.to_string()),
        }
    }

    fn on_frame(&mut self, now: SimTime, widths: &[u32]) {
        let kind = match self.config.addressing {
            PwmAddressing::Broadcast => PwmFrameKind::Broadcast,
            PwmAddressing::Designated => PwmFrameKind::Designated,
        };
        let frame = match PwmRepr::parse(kind, &self.config.coding, widths) {
            Ok(frame) => frame,
            Err(error) => {
                self.counters.bad_frames += 1;
                self.push_event(now, "bad_check", format!("widths {widths:?}: {error}"));
                return;
            }
        };
        match frame {
            PwmRepr::Broadcast { status, data } => match (status.high, vel_of(&data)) {
                (STATUS_RUN, Some(vel)) => self.take(now, true, vel),
                (STATUS_STOP, Some(vel)) => self.take(now, false, vel),
                _ => {
                    self.counters.bad_frames += 1;
                    let why = format!("broadcast frame: {}", described(status.high, &data));
                    self.push_event(now, "bad_check", why);
                }
            },
            PwmRepr::Designated { status, data } if status.high == self.config.id => {
                let Some(vel) = vel_of(&data) else {
                    self.counters.bad_frames += 1;
                    let why = format!("designated frame: {}", described(status.high, &data));
                    self.push_event(now, "bad_check", why);
                    return;
                };
                self.take(now, true, vel);
                let answer = designated_frame(self.config.id, vel);
                if let Some(len) = emit_widths(&answer, &self.config.coding, &mut self.tx) {
                    self.tx_len = len;
                    self.counters.answers += 1;
                }
            }
            _ => self.counters.frames_ignored += 1,
        }
    }

    fn on_outcome(&mut self, now: SimTime, outcome: Option<RxOutcome>) {
        match outcome {
            Some(RxOutcome::Frame(widths)) => self.on_frame(now, &widths),
            Some(RxOutcome::Incomplete { got }) => {
                self.counters.incomplete_frames += 1;
                self.push_event(
                    now,
                    "timeout",
                    format!("frame cut short: {got} of 4 pulses"),
                );
            }
            None => {}
        }
    }
}

impl Node for PwmSlave {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        for &byte in bytes {
            let outcome = self.rx.push(now, byte);
            self.on_outcome(now, outcome);
        }
    }

    fn handle_timeout(&mut self, now: SimTime) {
        let outcome = self.rx.handle_timeout(now);
        self.on_outcome(now, outcome);
    }

    fn poll_transmit(&mut self, _now: SimTime, buf: &mut [u8]) -> Option<usize> {
        let len = std::mem::take(&mut self.tx_len);
        let out = buf.get_mut(..len).filter(|_| len > 0)?;
        out.copy_from_slice(&self.tx[..len]);
        Some(len)
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        self.rx.poll_timeout()
    }

    fn poll_event(&mut self) -> Option<NodeEvent> {
        self.events
            .pop_front()
            .or_else(|| self.controller.poll_event())
    }
}

impl Firmware for PwmSlave {
    fn loop_period(&self) -> SimDuration {
        self.controller.loop_period()
    }

    fn loop_tick(&mut self, now: SimTime, sensors: &Sensors) -> Actuators {
        self.controller.loop_tick(now, sensors)
    }
}

/// A frame's status nibble and data symbols, for an event that says why it
/// was not taken.
fn described(status: u8, data: &PwmData) -> String {
    let data: Vec<String> = data
        .as_slice()
        .iter()
        .map(|d| format!("{d:#04x}"))
        .collect();
    format!("status {status:#x}, data {}", data.join(" "))
}
