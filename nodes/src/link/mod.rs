//! Simulated media: bytes in, timed arrivals out.
//!
//! [`SimBus`] is the RS-485 bus of the lab, with wire time, turnaround,
//! collisions and line noise; [`PwmBus`] the PWM-capture link; [`Medium`]
//! either, as the engine drives them; [`FaultyNode`] wraps any [`crate::node::Node`] to
//! make it misbehave on purpose (bad checks, lost, late or no replies).

mod fault;
mod medium;
mod noise;
pub mod pwmbus;
pub mod pwmline;
mod simbus;

pub use fault::{CheckKind, Fault, FaultStats, FaultWindow, FaultyNode, spoil_check};
pub use medium::Medium;
pub use pwmbus::{PwmBus, PwmBusConfig, PwmDuplex, PwmFrameRecord, PwmReception, PwmStats};
pub use pwmline::{
    CableModel, PwmCalibration, PwmCapture, PwmLine, PwmLineError, PwmLineParams, PwmTestValues,
};
pub use simbus::{
    BusConfig, BusConfigError, BusError, BusEvent, BusStats, FrameInfo, PortConfig, PortId, SimBus,
    Wiring,
};
