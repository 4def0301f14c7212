//! What the link tasks and the engine tell each other.

use nodes::time::SimTime;
use tokio::sync::mpsc::UnboundedSender;

use super::engine::RtEngine;
use super::front::FrontHandle;

/// A connection's id, unique for the session.
pub type ConnId = u64;

/// What the link tasks (and the console) send the engine.
pub enum Inbound {
    /// A connection opened on link `link` (a TCP client, a serial port).
    Opened {
        link: usize,
        conn: ConnId,
        peer: String,
        out: UnboundedSender<Outbound>,
    },
    /// Bytes read at `at`.
    Bytes {
        conn: ConnId,
        at: SimTime,
        bytes: Vec<u8>,
    },
    /// The connection is gone (peer closed, port vanished).
    Closed { conn: ConnId, why: String },
    /// A connection now waits for a timer (a turnaround, pacing, the RTU
    /// silence): the engine looks at the deadlines again.
    Wake,
    /// Run this on the engine's thread (console commands, other front ends).
    Command(Box<dyn FnOnce(&mut RtEngine) + Send>),
    /// Stop the session (SIGINT, SIGTERM).
    Stop(String),
}

/// What the engine sends a link task.
#[derive(Debug)]
pub enum Outbound {
    /// Write this frame, in one write.
    Frame(Vec<u8>),
    /// Close the connection, for this reason.
    Close(String),
    /// Answer this connection's requests on the task's own thread through
    /// the shared front (always the first message).
    Direct(FrontHandle),
}

impl std::fmt::Debug for Inbound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Inbound::Opened { link, conn, .. } => write!(f, "Opened({link}, {conn})"),
            Inbound::Bytes { conn, bytes, .. } => write!(f, "Bytes({conn}, {})", bytes.len()),
            Inbound::Closed { conn, why } => write!(f, "Closed({conn}, {why})"),
            Inbound::Command(_) => write!(f, "Command"),
            Inbound::Wake => write!(f, "Wake"),
            Inbound::Stop(why) => write!(f, "Stop({why})"),
        }
    }
}
