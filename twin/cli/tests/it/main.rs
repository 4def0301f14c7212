//! The `twin` binary as users run it: every subcommand, real peers, the book's examples.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

#![allow(
    clippy::disallowed_methods,
    reason = "the tests drive real processes, ports and sockets in real time"
)]

mod batch;
mod book;
mod calibrate;
mod check;
mod cmd;
mod cut_recording;
mod experiment;
mod experiment_parallel;
mod first_use;
mod frames_to;
mod install;
mod panel;
mod panel_budget;
mod peers;
mod peers_hardening;
mod peers_limits;
mod peers_meb;
mod peers_modbus;
mod peers_modbus8;
mod peers_robust;
mod peers_split;
mod progress;
mod replay;
mod rotate;
mod run;
mod scope;
mod scope_png;
mod scope_session;
mod serve;
mod serve_faults;
mod service;
mod soak;
mod step;
mod supervise;
mod supervise_map;
mod support;
mod view;
mod view_sessions;
