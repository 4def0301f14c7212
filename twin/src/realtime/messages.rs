//! What the link tasks and the engine tell each other.

use std::sync::Arc;
use tokio::sync::Notify;
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
        task: LinkTask,
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

/// How the engine reaches the task carrying a connection.
#[derive(Debug, Clone)]
pub struct LinkTask {
    pub out: UnboundedSender<Outbound>,
    /// Notified when the engine's timers have made frames due on it.
    pub ready: Arc<Notify>,
}

/// What the engine sends a link task.
#[derive(Debug)]
pub enum Outbound {
    /// Answer this connection's requests on the task's own thread through
    /// the shared front (the first message, unless the connection is refused).
    Direct(FrontHandle),
    /// Write these frames, then close the connection, for this reason.
    Close { why: String, owed: Outgoing },
}

impl std::fmt::Debug for Inbound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Inbound::Opened { link, conn, .. } => write!(f, "Opened({link}, {conn})"),
            Inbound::Closed { conn, why } => write!(f, "Closed({conn}, {why})"),
            Inbound::Command(_) => write!(f, "Command"),
            Inbound::Wake => write!(f, "Wake"),
            Inbound::Stop(why) => write!(f, "Stop({why})"),
        }
    }
}

/// Frames due on a connection, in order, for its task to write (each in one
/// write). The task keeps one and the front fills it, so neither allocates
/// once it has grown to the largest burst.
pub type Outgoing = super::frame_log::PackedFrames;
