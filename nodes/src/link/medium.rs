//! The one medium abstraction the engine drives: a closed set (the RS-485
//! bus, the PWM-capture link), so a bus slot needs no box and every call is
//! a match the compiler sees through.

use super::{
    BusError, BusEvent, BusStats, FrameInfo, LineMark, PortConfig, PortId, PwmBus, SimBus,
};
use protocols::time::SimTime;

/// What carries a bus slot's frames: the RS-485 serial bus, or the PWM-capture
/// paper's link (frames of pulse widths, captured widths delivered).
// One per bus, built once and never moved on a hot path: the size of the
// PWM link's capture buffers costs nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub enum Medium {
    Serial(SimBus),
    Pwm(PwmBus),
}

impl Medium {
    pub fn add_port(&mut self, config: PortConfig) -> PortId {
        match self {
            Medium::Serial(bus) => bus.add_port(config),
            Medium::Pwm(link) => link.add_port(config),
        }
    }
    pub fn send(
        &mut self,
        now: SimTime,
        from: PortId,
        bytes: &[u8],
    ) -> Result<FrameInfo, BusError> {
        match self {
            Medium::Serial(bus) => bus.send(now, from, bytes),
            Medium::Pwm(link) => link.send(now, from, bytes),
        }
    }
    pub fn poll_timeout(&self) -> Option<SimTime> {
        match self {
            Medium::Serial(bus) => bus.poll_timeout(),
            Medium::Pwm(link) => link.poll_timeout(),
        }
    }
    pub fn poll_event(&mut self, now: SimTime) -> Option<BusEvent> {
        match self {
            Medium::Serial(bus) => bus.poll_event(now),
            Medium::Pwm(link) => link.poll_event(now),
        }
    }
    /// The line's counters (on a PWM link, bytes are 4-byte pulse records).
    pub fn stats(&self) -> &BusStats {
        match self {
            Medium::Serial(bus) => bus.stats(),
            Medium::Pwm(link) => link.stats(),
        }
    }
    /// Keep line marks for [`Medium::poll_line_mark`] (the serial bus's;
    /// a PWM-capture link records what each listener captured already).
    pub fn keep_line_marks(&mut self) {
        if let Medium::Serial(bus) = self {
            bus.keep_line_marks();
        }
    }
    /// The oldest line mark not yet polled ([`SimBus::poll_line_mark`]).
    pub fn poll_line_mark(&mut self) -> Option<LineMark> {
        match self {
            Medium::Serial(bus) => bus.poll_line_mark(),
            Medium::Pwm(_) => None,
        }
    }
    /// The PWM-capture link, if this is one.
    pub fn as_pwm(&self) -> Option<&PwmBus> {
        match self {
            Medium::Pwm(link) => Some(link),
            Medium::Serial(_) => None,
        }
    }
}

impl From<SimBus> for Medium {
    fn from(bus: SimBus) -> Self {
        Medium::Serial(bus)
    }
}

impl From<PwmBus> for Medium {
    fn from(link: PwmBus) -> Self {
        Medium::Pwm(link)
    }
}
