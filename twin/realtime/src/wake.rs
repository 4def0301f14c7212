//! How the engine wakes the task or thread that carries a connection when it
//! has made frames due there.

use std::net::{Shutdown, TcpStream};
use std::os::fd::OwnedFd;
use std::sync::Arc;

use rustix::event::{EventfdFlags, eventfd};
use tokio::sync::Notify;

/// How a connection's carrier is told the engine has something for it.
#[derive(Debug, Clone)]
pub enum Wake {
    /// A tokio task (a serial port): notified when the engine has made
    /// frames due; it sees a `Close` on its channel by itself.
    Task(Arc<Notify>),
    /// A TCP connection's own thread, blocked in a read or a poll.
    Thread(Arc<ThreadWake>),
}

/// How the engine wakes a connection's thread.
#[derive(Debug)]
pub struct ThreadWake {
    /// Signalled when the engine made frames due.
    pub(crate) frames: OwnedFd,
    /// The connection's socket (a second handle), to shut its reading side.
    socket: TcpStream,
}

impl ThreadWake {
    pub(crate) fn new(socket: &TcpStream) -> std::io::Result<Self> {
        Ok(Self {
            frames: eventfd(0, EventfdFlags::CLOEXEC | EventfdFlags::NONBLOCK)?,
            socket: socket.try_clone()?,
        })
    }

    pub fn frames_due(&self) {
        let _ = rustix::io::write(&self.frames, &1u64.to_ne_bytes());
    }

    /// A `Close` is on the thread's channel: end its `recv` (or `poll`).
    pub fn closing(&self) {
        let _ = self.socket.shutdown(Shutdown::Read);
    }

    pub(crate) fn clear(&self) {
        let mut count = [0u8; 8];
        let _ = rustix::io::read(&self.frames, &mut count);
    }
}
