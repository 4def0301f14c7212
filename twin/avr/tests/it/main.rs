//! Real AVR firmware in simavr: cores, the lab's sketches, serving, recording and debugging.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

#![allow(
    clippy::disallowed_methods,
    reason = "the tests drive real firmware, processes and sockets in real time"
)]

mod boot;
mod calibrate;
mod common;
mod controller_network;
mod cores;
mod debug;
mod ev_meb;
mod firmware;
mod recording;
mod serve;
mod serve_boards;
mod stall;
mod students;
