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

/// How the engine reaches the task or thread carrying a connection.
#[derive(Debug, Clone)]
pub struct LinkTask {
    pub out: UnboundedSender<Outbound>,
    pub wake: Wake,
}

/// How a connection's carrier is told the engine has something for it.
#[derive(Debug, Clone)]
pub enum Wake {
    /// A tokio task (a serial port): notified when the engine has made
    /// frames due; it sees a `Close` on its channel by itself.
    Task(Arc<Notify>),
    /// A TCP connection's own thread, blocked in a read or a poll.
    Thread(Arc<super::tcp_thread::ThreadWake>),
}

impl LinkTask {
    /// The engine (its timers, or a reply that waited on the bus) has put
    /// frames in the connection's due frames.
    pub fn frames_due(&self) {
        match &self.wake {
            Wake::Task(ready) => ready.notify_one(),
            Wake::Thread(wake) => wake.frames_due(),
        }
    }

    /// Write `owed`, then close the connection, for reason `why`.
    pub fn close(&self, why: String, owed: Outgoing) {
        let _ = self.out.send(Outbound::Close { why, owed });
        if let Wake::Thread(wake) = &self.wake {
            wake.closing();
        }
    }
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
