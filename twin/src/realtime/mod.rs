//! The real-time engine and its links: the same node and plant code as the
//! virtual engine, paced to the wall clock, on real serial ports,
//! pseudo-terminals and TCP sockets.
//!
//! Threads: the engine ([`engine::RtEngine::run`]) owns the plants and ticks
//! at 1 ms on absolute deadlines; a tokio runtime owns the sockets and ports
//! ([`links`]) and answers requests through the devices and endpoints the
//! two share ([`front`]); the sink ([`sink`]) records and prints.

pub mod clock;
pub mod config;
pub mod endpoint;
pub mod engine;
pub mod forces;
pub mod frame_log;
pub mod front;
pub mod lateness;
pub mod links;
pub mod messages;
pub mod session;
pub mod sink;

pub use clock::RtClock;
pub use endpoint::{Endpoint, NodeEndpoint, SlaveEndpoint};
pub use engine::{
    ConnId, Device, EndpointFactory, Forces, Inbound, LinkConfig, LinkFault, Outbound, RtEngine,
    RtSummary,
};
pub use lateness::{Lateness, LatenessSummary};
