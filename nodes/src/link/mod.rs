//! Simulated media: bytes in, timed arrivals out.
//!
//! [`SimBus`] is the RS-485 bus of the lab, with wire time, turnaround,
//! collisions and line noise; [`PwmBus`] the PWM-capture link; [`Medium`]
//! either, as the engine drives them; [`FaultyNode`] wraps any [`crate::node::Node`] to
//! make it misbehave on purpose (bad checks, lost, late or no replies,
//! refusals, replies from the wrong id, split in two or with junk).

mod fault;
mod fault_bytes;
mod medium;
mod noise;
pub mod pwmbus;
pub mod pwmline;
mod simbus;

pub use fault::{CheckKind, Fault, FaultStats, FaultWindow, FaultyNode, spoil_check};
pub use fault_bytes::{
    Junk, JunkBytes, JunkPlace, JunkSource, MAX_JUNK, frame_id, max_id, other_id, set_id,
    split_point,
};
pub use medium::Medium;
pub use pwmbus::{PwmBus, PwmBusConfig, PwmDuplex, PwmFrameRecord, PwmReception, PwmStats};
pub use pwmline::{
    CableModel, PwmCalibration, PwmCapture, PwmLine, PwmLineError, PwmLineParams, PwmTestValues,
};
pub use simbus::{
    BusConfig, BusConfigError, BusError, BusEvent, BusStats, FrameInfo, LineMark, PortConfig,
    PortId, SimBus, Wiring,
};
