//! The lab's protocols and node logic, all sans-IO: no sockets, no clock, no
//! unseeded randomness. Time comes in as [`time::SimTime`], bytes as slices.

pub mod controller_network;
pub mod firmware;
pub mod link;
pub mod master;
pub mod node;
pub mod parallel;

/// The wire formats, from the `protocols` crate (kept here so that
/// `nodes::proto::…` paths still resolve).
pub mod proto {
    pub use protocols::{crc, meb, modbus, modbus8, pwmcap, words};
}
/// Simulated time, from the `protocols` crate.
pub use protocols::time;
