//! A TCP connection carried by its own thread, in blocking reads.
//!
//! Why not a tokio task like the serial ports: on this 2-core machine, eight
//! clients got 71-87 k requests/s from tokio-modbus, from `twin serve` on
//! tokio tasks and from a bare echo on tokio alike, and 106-113 k/s from a
//! bare echo with a thread per connection (`serve-bench load`, minutes
//! apart). A readiness loop costs an `epoll_wait` and the runtime's wake-ups
//! on top of each request's `recv` and `send`; a thread blocked in `recv` is
//! woken by the kernel with the bytes. With this carrier `twin serve` got
//! 109-113 k/s where tokio-modbus got 87-95 k/s (`serve-bench`'s rounds:
//! 1.17-1.26x tokio-modbus's rate, recording off).
//!
//! The thread reads, answers through the front and writes, like the tokio
//! task in [`super::links`]. It blocks in `recv` while only new bytes can
//! bring frames, and polls the socket together with an eventfd while frames
//! may come from the engine (its timers: a turnaround, pacing, a delay
//! fault, a partial frame's timeout; or a supervisor's reply that waited on
//! the bus), which signals that eventfd when it makes frames due.
//! When the twin closes the connection, the engine sends the `Close` and
//! shuts the socket's reading side, which wakes a blocked `recv`.
//!
//! While the engine sleeps through a batch of plant ticks (no deadline
//! pending, requests further apart than a couple of ticks), a request that
//! finds the plant behind its arrival waits on the same eventfd for the
//! engine to catch up ([`After::Behind`]): two thread switches for that
//! request, where the engine used to wake for every tick between requests.

use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, TcpStream};
use std::sync::mpsc::Sender;
use std::time::Duration;

use rustix::event::{PollFd, PollFlags, poll};
use tokio::sync::mpsc::{UnboundedReceiver, unbounded_channel};

use super::clock::RtClock;
use super::engine::Inbound;
use super::frame_log::{ConnId, Outgoing};
use super::front::{After, FrontHandle, LinkTask, Outbound, Probation};
use super::wake::{ThreadWake, Wake};

/// Bytes read at once, here and by the serial ports' tasks: larger than
/// any frame, so a frame rarely splits.
pub(super) const READ_CHUNK: usize = 4096;

/// A client that has not taken a reply for this long is dropped, so that
/// the thread does not wait on it forever.
pub const WRITE_STALL: Duration = Duration::from_secs(10);

/// Carries `stream` until either side closes it; returns why it ended.
pub fn serve_tcp(
    stream: TcpStream,
    link: usize,
    conn: ConnId,
    peer: String,
    probation: Option<Probation>,
    clock: RtClock,
    engine: Sender<Inbound>,
) -> String {
    let wake = match ThreadWake::new(&stream) {
        Ok(w) => std::sync::Arc::new(w),
        Err(e) => return format!("cannot carry the connection: {e}"),
    };
    let _ = stream.set_write_timeout(Some(WRITE_STALL));
    let (out, mut outbox) = unbounded_channel();
    let task = LinkTask {
        out,
        wake: Wake::Thread(wake.clone()),
    };
    if engine
        .send(Inbound::Opened {
            link,
            conn,
            peer,
            task,
            probation,
        })
        .is_err()
    {
        return "server stopping".into();
    }
    let mut carrier = Carrier {
        stream,
        conn,
        wake,
        due: Outgoing::default(),
    };
    // Nothing is read before the front is here, so every request is
    // answered in the order it came.
    let front = match outbox.blocking_recv() {
        Some(Outbound::Direct(front)) => front,
        Some(Outbound::Close { why, owed }) => return carrier.close(why, owed),
        None => return "server stopping".into(),
    };
    let why = match carrier.run(&front, &clock, &engine, &mut outbox) {
        Ending::Peer(why) => why,
        // The engine has dropped the connection already.
        Ending::Twin { why, owed } => return carrier.close(why, owed),
    };
    let _ = engine.send(Inbound::Closed {
        conn,
        why: why.clone(),
    });
    why
}

enum Ending {
    /// The peer closed it, or the socket failed: the engine is told.
    Peer(String),
    /// The twin closed it, for this reason, owing these frames.
    Twin { why: String, owed: Outgoing },
}

/// The twin's `Close`, which it sent before it dropped the connection.
fn twin_close(outbox: &mut UnboundedReceiver<Outbound>) -> Ending {
    match outbox.blocking_recv() {
        Some(Outbound::Close { why, owed }) => Ending::Twin { why, owed },
        _ => Ending::Peer("server stopping".into()),
    }
}

struct Carrier {
    stream: TcpStream,
    conn: ConnId,
    wake: std::sync::Arc<ThreadWake>,
    due: Outgoing,
}

impl Carrier {
    fn run(
        &mut self,
        front: &FrontHandle,
        clock: &RtClock,
        engine: &Sender<Inbound>,
        outbox: &mut UnboundedReceiver<Outbound>,
    ) -> Ending {
        let mut buf = vec![0u8; READ_CHUNK];
        let mut after = After::Idle;
        let backlog = front.backlog();
        loop {
            // The recording is behind: let the sink catch up before reading
            // more, so that its queue stays bounded and keeps every frame.
            backlog.wait_while_full();
            if after.listens() {
                match self.wait(after.reads()) {
                    Ok(true) => {}
                    Ok(false) => {
                        // Only the engine's frames: write them, read nothing.
                        self.wake.clear();
                        after = front.take_due(self.conn, &mut self.due);
                        if let Err(why) = self.write_due() {
                            return Ending::Peer(why);
                        }
                        continue;
                    }
                    Err(why) => return Ending::Peer(why),
                }
            }
            let n = match self.stream.read(&mut buf) {
                Ok(0) => {
                    // The peer's FIN, or the twin shut the reading side.
                    return match outbox.try_recv() {
                        Ok(Outbound::Close { why, owed }) => Ending::Twin { why, owed },
                        _ => Ending::Peer("peer closed the connection".into()),
                    };
                }
                Ok(n) => n,
                Err(e) if e.kind() == ErrorKind::Interrupted => continue,
                Err(e) => return Ending::Peer(format!("read failed: {e}")),
            };
            let at = clock.now();
            let bytes = buf.get(..n).unwrap_or_default();
            after = front.receive(self.conn, at, bytes, true, &mut self.due);
            // The engine sleeps through a batch of ticks and the plant is
            // behind these bytes: this thread ticks it up to their arrival,
            // then hands them again, so the reply reads the plant of then.
            if after == After::Behind {
                front.catch_up(at);
                // Caught up: answered from the plant as it stands now.
                after = front.receive(self.conn, at, bytes, false, &mut self.due);
            }
            if matches!(after, After::Timers | After::Owing) && engine.send(Inbound::Wake).is_err()
            {
                return Ending::Peer("server stopping".into());
            }
            if let Err(why) = self.write_due() {
                return Ending::Peer(why);
            }
            if after == After::Closed {
                return twin_close(outbox);
            }
        }
    }

    /// Waits for bytes (true) or the engine's signal (false); for the
    /// engine's signal alone unless `read`.
    fn wait(&self, read: bool) -> Result<bool, String> {
        let socket_events = if read {
            PollFlags::IN
        } else {
            PollFlags::empty()
        };
        let mut fds = [
            PollFd::new(&self.stream, socket_events),
            PollFd::new(&self.wake.frames, PollFlags::IN),
        ];
        loop {
            match poll(&mut fds, None) {
                Ok(_) => break,
                Err(rustix::io::Errno::INTR) => continue,
                Err(e) => return Err(format!("poll failed: {e}")),
            }
        }
        let socket = !fds[0].revents().is_empty();
        Ok(socket || fds[1].revents().is_empty())
    }

    /// Writes each due frame in one write.
    fn write_due(&mut self) -> Result<(), String> {
        for frame in self.due.iter() {
            if let Err(e) = self.stream.write_all(frame) {
                return Err(
                    if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) {
                        format!("the client took no reply for {} s", WRITE_STALL.as_secs())
                    } else {
                        format!("write failed: {e}")
                    },
                );
            }
        }
        self.due.clear();
        Ok(())
    }

    /// Writes the frames owed, then closes the connection; returns `why`.
    fn close(&mut self, why: String, mut owed: Outgoing) -> String {
        owed.move_to(&mut self.due);
        let _ = self.write_due();
        let _ = self.stream.shutdown(Shutdown::Write);
        why
    }
}
