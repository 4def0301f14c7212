//! The EV lab bench in real time: the same node and plant code as the
//! virtual engine, paced to the wall clock, on real serial ports,
//! pseudo-terminals and TCP sockets; the sessions built on it (`twin serve`,
//! `twin supervise`), the virtual serial port pair (`twin vsp`), the MEB
//! client (`twin client`) and recorded frames sent to a live slave
//! (`twin replay --frames-to`).
//!
//! The fence: no rerun here. A live view enters through [`sink::LiveView`],
//! which the viewer crate implements and the binary hands in.
//!
//! Threads: the engine ([`engine::RtEngine::run`]) owns the plants and ticks
//! at 1 ms on absolute deadlines; a tokio runtime owns the listeners and the
//! serial ports ([`links`]), and each TCP connection has a thread of its own
//! ([`tcp_thread`]); both answer requests through the devices and endpoints
//! they share with the engine ([`front`]); the sink ([`sink`]) records and
//! prints.

#![allow(
    clippy::disallowed_methods,
    reason = "the real-time engine paces the plant to the wall clock and links wait on real ports"
)]

pub mod allow;
pub mod client;
pub mod clock;
pub mod config;
pub mod device;
pub mod endpoint;
pub mod engine;
pub mod fd_limit;
pub mod firmware_endpoint;
pub mod firmware_log;
pub mod forces;
pub mod frame_log;
pub mod frames_to;
pub mod front;
pub mod io;
pub mod lateness;
pub mod links;
pub mod notify;
pub mod rotate;
pub mod serve;
pub mod session;
pub mod sink;
pub mod slots;
pub mod supervise;
pub mod tcp_thread;
pub mod typed_line;
pub mod vsp;
pub mod wake;

pub use clock::RtClock;
pub use endpoint::{Endpoint, NodeEndpoint, SlaveEndpoint};
pub use engine::{
    ConnId, Device, EndpointFactory, Forces, Inbound, LinkConfig, LinkFault, Outbound, RtEngine,
    RtSummary,
};
pub use lateness::{Lateness, LatenessSummary};
