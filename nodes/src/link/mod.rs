//! Simulated media: bytes in, timed arrivals out.
//!
//! [`SimBus`] is the RS-485 bus of the lab, with wire time, turnaround,
//! collisions and line noise; [`FaultyNode`] wraps any [`crate::node::Node`] to
//! make it misbehave on purpose (bad checks, lost, late or no replies).

mod fault;
mod noise;
pub mod pwmline;
mod simbus;

pub use fault::{CheckKind, Fault, FaultStats, FaultWindow, FaultyNode, spoil_check};
pub use pwmline::{PwmCalibration, PwmLine, PwmLineError, PwmLineParams, PwmTestValues};
pub use simbus::{
    BusConfig, BusConfigError, BusError, BusEvent, BusStats, FrameInfo, PortConfig, PortId, SimBus,
    Wiring,
};

use crate::time::SimTime;

/// A medium that carries nodes' frames: the simulated bus today; serial
/// ports, pseudo-terminals, TCP and the PWM-capture line plug in behind the
/// same calls, so node code never changes with the medium.
pub trait Link {
    /// Attach a node; its frames start `config.turnaround` after it hands them over.
    fn add_port(&mut self, config: PortConfig) -> PortId;
    /// A frame from `from`, handed over at `now`.
    fn send(&mut self, now: SimTime, from: PortId, bytes: &[u8]) -> Result<FrameInfo, BusError>;
    /// When the next byte lands or frame ends.
    fn poll_timeout(&self) -> Option<SimTime>;
    /// The next delivery due at or before `now`.
    fn poll_event(&mut self, now: SimTime) -> Option<BusEvent>;
}

impl Link for SimBus {
    fn add_port(&mut self, config: PortConfig) -> PortId {
        SimBus::add_port(self, config)
    }
    fn send(&mut self, now: SimTime, from: PortId, bytes: &[u8]) -> Result<FrameInfo, BusError> {
        SimBus::send(self, now, from, bytes)
    }
    fn poll_timeout(&self) -> Option<SimTime> {
        SimBus::poll_timeout(self)
    }
    fn poll_event(&mut self, now: SimTime) -> Option<BusEvent> {
        SimBus::poll_event(self, now)
    }
}
