//! Simulated media: bytes in, timed arrivals out.
//!
//! [`SimBus`] is the RS-485 bus of the lab, with wire time, turnaround,
//! collisions and line noise; [`FaultyNode`] wraps any [`crate::node::Node`] to
//! make it misbehave on purpose (bad checks, lost, late or no replies).

mod fault;
mod noise;
mod simbus;

pub use fault::{CheckKind, Fault, FaultStats, FaultWindow, FaultyNode};
pub use simbus::{
    BusConfig, BusConfigError, BusError, BusEvent, BusStats, FrameInfo, PortConfig, PortId, SimBus,
    Wiring,
};
