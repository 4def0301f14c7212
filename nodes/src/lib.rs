//! The lab's protocols and node logic, all sans-IO: no sockets, no clock, no
//! unseeded randomness. Time comes in as [`time::SimTime`], bytes as slices.

pub mod firmware;
pub mod link;
pub mod master;
pub mod node;
pub mod parallel;
pub mod proto;
pub mod seed002;
pub mod time;
