//! The lab's protocols and node logic, all sans-IO: no sockets, no clock, no
//! unseeded randomness. Time comes in as [`time::SimTime`], bytes as slices.

pub mod proto;
pub mod time;
