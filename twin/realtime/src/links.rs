//! The tokio side of the real links: one task per TCP listener, per serial
//! port and per connection the twin opens itself (a supervisor's to a TCP
//! slave); an accepted TCP connection gets a thread ([`super::tcp_thread`]).
//! A task reads what arrives, stamps it with the session clock and has the
//! connection's endpoint answer it on the spot, through the front it shares
//! with the engine ([`super::front::FrontHandle`]); it writes each frame in
//! one write, whether it came from its own request or from the engine's
//! timers (a turnaround, pacing). Nothing here knows a protocol.

use std::os::fd::OwnedFd;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::Sender;
use std::time::Duration;

use tokio::io::Interest;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::sync::Notify;
use tokio::sync::mpsc::unbounded_channel;

use super::allow::AllowList;
use super::clock::RtClock;
use super::engine::{ConnId, Inbound, LinkTask, Outbound};
use super::frame_log::Outgoing;
use super::front::{After, Probation};
use super::slots::Slots;
use super::tcp_thread::{READ_CHUNK, serve_tcp};
use super::wake::Wake;
use crate::io::{SerialSettings, serial};
use protocols::time::SimDuration;

/// Hands out connection ids.
#[derive(Debug, Clone, Default)]
pub struct ConnIds(Arc<AtomicU64>);

impl ConnIds {
    pub fn next(&self) -> ConnId {
        self.0.fetch_add(1, Ordering::Relaxed) + 1
    }
}

/// Carries one open stream: sends [`Inbound::Opened`], waits for the front
/// (or a refusal), then bytes both ways until either side closes. Returns
/// why it ended.
pub async fn serve_stream<S>(
    mut stream: S,
    link: usize,
    conn: ConnId,
    peer: String,
    clock: RtClock,
    engine: Sender<Inbound>,
    eof: &'static str,
) -> String
where
    S: LinkStream,
{
    let (out, mut outbox) = unbounded_channel();
    let ready = Arc::new(Notify::new());
    if engine
        .send(Inbound::Opened {
            link,
            conn,
            peer,
            task: LinkTask {
                out,
                wake: Wake::Task(ready.clone()),
            },
            probation: None,
        })
        .is_err()
    {
        return "server stopping".into();
    }
    // Nothing is read before the front is here, so every request is
    // answered in the order it came.
    let front = match outbox.recv().await {
        Some(Outbound::Direct(front)) => front,
        Some(Outbound::Close { why, owed }) => return close(&mut stream, why, &owed).await,
        None => return "server stopping".into(),
    };
    let mut buf = vec![0u8; READ_CHUNK];
    let mut due = Outgoing::default();
    // The frames just written, while the front hears of them.
    let mut written = Outgoing::default();
    // Kept registered across passes of the loop rather than made anew for
    // each (which locks the Notify's waiter list twice per request).
    let notified = ready.notified();
    tokio::pin!(notified);
    let mut after = After::Idle;
    let why = loop {
        tokio::select! {
            // A connection that owes many paced replies is not read until
            // some are written (see `After::Owing`).
            read = stream.read_chunk(&mut buf), if after.reads() => match read {
                Ok(0) => break eof.to_string(),
                Ok(n) => {
                    let at = clock.now();
                    let bytes = buf.get(..n).unwrap_or_default();
                    after = front.receive(conn, at, bytes, false, &mut due);
                    if matches!(after, After::Timers | After::Owing)
                        && engine.send(Inbound::Wake).is_err()
                    {
                        break "server stopping".into();
                    }
                }
                Err(e) => break format!("read failed: {e}"),
            },
            () = notified.as_mut() => {
                notified.set(ready.notified());
                after = front.take_due(conn, &mut due);
            }
            message = outbox.recv() => match message {
                Some(Outbound::Close { why, mut owed }) => {
                    owed.move_to(&mut due);
                    return close(&mut stream, why, &due).await;
                }
                Some(Outbound::Direct(_)) => {}
                None => break "server stopping".into(),
            },
        }
        // The replies due now, each in one write, before the next read;
        // a master's requests reported as written (its reply timeout runs
        // from then), which may make more due.
        let mut failed = None;
        while !due.is_empty() {
            if let Err(e) = write_frames(&mut stream, &due).await {
                failed = Some(format!("write failed: {e}"));
                break;
            }
            if !due.reports() {
                due.clear();
                break;
            }
            std::mem::swap(&mut due, &mut written);
            after = front.written(conn, clock.now(), &written, &mut due);
            written.clear();
            if matches!(after, After::Timers | After::Owing) && engine.send(Inbound::Wake).is_err()
            {
                failed = Some("server stopping".into());
                break;
            }
        }
        if let Some(why) = failed {
            break why;
        }
    };
    let _ = engine.send(Inbound::Closed {
        conn,
        why: why.clone(),
    });
    why
}

/// A stream a link task carries: what arrived is read in chunks.
pub trait LinkStream: AsyncRead + AsyncWrite + Unpin + Send {
    /// Reads what has arrived (0: the other side closed). Cancel-safe.
    fn read_chunk<'a>(
        &'a mut self,
        buf: &'a mut [u8],
    ) -> impl Future<Output = std::io::Result<usize>> + Send + 'a;
}

impl LinkStream for tokio::net::TcpStream {
    async fn read_chunk(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        loop {
            self.readable().await?;
            // A short read empties the socket: a WouldBlock from inside
            // `try_io` tells tokio so (it clears the readiness unless new
            // data came meanwhile), where a plain read would learn it from a
            // second recv returning EAGAIN, one syscall more per request.
            let mut short = None;
            let read = self.try_io(Interest::READABLE, || {
                let n = self.try_read(buf)?;
                if n > 0 && n < buf.len() {
                    short = Some(n);
                    return Err(std::io::ErrorKind::WouldBlock.into());
                }
                Ok(n)
            });
            match (read, short) {
                (_, Some(n)) => return Ok(n),
                (Ok(n), None) => return Ok(n),
                (Err(e), None) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                (Err(e), None) => return Err(e),
            }
        }
    }
}

impl LinkStream for tokio_serial::SerialStream {
    async fn read_chunk(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        self.read(buf).await
    }
}

/// Writes each frame of `frames` in one write.
async fn write_frames<S>(stream: &mut S, frames: &Outgoing) -> std::io::Result<()>
where
    S: AsyncWrite + Unpin,
{
    for frame in frames.iter() {
        stream.write_all(frame).await?;
    }
    Ok(())
}

/// Writes the frames owed, then closes the stream; returns `why`.
async fn close<S>(stream: &mut S, why: String, owed: &Outgoing) -> String
where
    S: AsyncWrite + Unpin,
{
    let _ = write_frames(stream, owed).await;
    let _ = stream.shutdown().await;
    why
}

/// Clients a session's listeners refused: over `--max-clients`, or from
/// an address `--allow` does not name.
#[derive(Debug, Clone, Default)]
pub struct Refused {
    pub over_limit: Arc<AtomicU64>,
    pub not_allowed: Arc<AtomicU64>,
}

/// By default, a full listener's newcomer may take the place of a client
/// that has sent nothing for this long (the quietest one).
pub const ROOM_AFTER_IDLE: SimDuration = SimDuration::from_secs(30);

/// How many clients a TCP listener serves at once, and when a newcomer may
/// take the place of a quiet one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClientLimit {
    pub max: usize,
    /// A newcomer beyond `max` takes the place of the client quiet longest
    /// if that one has been quiet this long (`None`: never).
    pub room_after_idle: Option<SimDuration>,
}

impl ClientLimit {
    /// At most `max` clients; room made after [`ROOM_AFTER_IDLE`].
    pub fn new(max: usize) -> Self {
        ClientLimit {
            max,
            room_after_idle: Some(ROOM_AFTER_IDLE),
        }
    }
}

/// Accepts clients on `listener` for link `link`. When `limit.max` are
/// connected, a newcomer gets the place of a client whose peer has gone; or,
/// if a client there could make room (quiet for `limit.room_after_idle`, or
/// holding a partial frame), it is let in on probation and takes that
/// client's place with its first whole request (see [`Probation`]); else it
/// is refused: closed at once, as libmodbus does,
/// since neither MEB nor Modbus can say "busy" before a request. A newcomer
/// is never kept waiting for a place: that queued the next ones behind it,
/// a second each.
/// A client from outside `allow` is closed at once, and the refusal logged.
#[allow(
    clippy::too_many_arguments,
    reason = "what one listener's task is given"
)]
pub async fn accept_loop(
    listener: TcpListener,
    link: usize,
    limit: Option<ClientLimit>,
    allow: AllowList,
    ids: ConnIds,
    clock: RtClock,
    engine: Sender<Inbound>,
    refused: Refused,
) {
    let slots = Arc::new(Slots::default());
    let mut quiet_refusals = Refusals::default();
    loop {
        let Ok((socket, peer)) = listener.accept().await else {
            // Out of file descriptors and the like: wait and go on.
            tokio::time::sleep(Duration::from_millis(50)).await;
            continue;
        };
        if !allow.permits(peer.ip()) {
            refused.not_allowed.fetch_add(1, Ordering::Relaxed);
            drop(socket);
            let text = format!(
                "{peer}: refused, not an allowed address (--allow {})",
                allow.shown()
            );
            say(&engine, link, text);
            continue;
        }
        let probation = match limit {
            Some(limit) => match room(&slots, limit, link, &engine).await {
                Room::Free => None,
                Room::OnProbation => Some(Probation {
                    max: limit.max,
                    min_idle: limit.room_after_idle,
                }),
                Room::None => {
                    refused.over_limit.fetch_add(1, Ordering::Relaxed);
                    drop(socket);
                    if let Some(text) = quiet_refusals.refused(peer, limit.max) {
                        say(&engine, link, text);
                    }
                    continue;
                }
            },
            None => None,
        };
        // Replies are single small writes: send them at once.
        let _ = socket.set_nodelay(true);
        let conn = ids.next();
        // A thread per connection, in blocking reads (see `tcp_thread`).
        let carried = socket.into_std().and_then(|s| {
            s.set_nonblocking(false)?;
            slots.take(conn, OwnedFd::from(s.try_clone()?));
            let (engine, slots, clock) = (engine.clone(), slots.clone(), clock.clone());
            std::thread::Builder::new()
                .name("twin-tcp".into())
                .spawn(move || {
                    serve_tcp(s, link, conn, peer.to_string(), probation, clock, engine);
                    slots.free(conn);
                })
        });
        if let Err(e) = carried {
            slots.free(conn);
            say(
                &engine,
                link,
                format!("{peer}: refused, no thread for it: {e}"),
            );
        }
    }
}

/// Has the engine print `text` about link `link`, stamped with its clock.
fn say(engine: &Sender<Inbound>, link: usize, text: String) {
    let _ = engine.send(Inbound::Command(Box::new(move |e| {
        let name = e.links.get(link).map_or("?", |l| l.name.as_str());
        let line = format!("[{:12.6} s] {name} {text}", e.clock.now().as_secs_f64());
        e.say(line);
    })));
}

/// The lines a listener prints about newcomers refused over its limit: the
/// first of a burst in full, then at most one a second with the count
/// since, so that a flood of connections does not flood the console.
#[derive(Debug, Default)]
struct Refusals {
    last_said: Option<std::time::Instant>,
    unsaid: u64,
}

impl Refusals {
    fn refused(&mut self, peer: std::net::SocketAddr, max: usize) -> Option<String> {
        let now = std::time::Instant::now();
        if self
            .last_said
            .is_some_and(|at| now.duration_since(at) < Duration::from_secs(1))
        {
            self.unsaid += 1;
            return None;
        }
        self.last_said = Some(now);
        let more = std::mem::take(&mut self.unsaid);
        let also = if more > 0 {
            format!(" ({more} more refused since the last line)")
        } else {
            String::new()
        };
        Some(format!(
            "{peer}: refused, {max} client(s) already connected (--max-clients){also}"
        ))
    }
}

/// Where a newcomer stands on a listener with a client limit.
enum Room {
    /// A place is free.
    Free,
    /// None is, but a client could make room: in on probation.
    OnProbation,
    /// None is, and none can be made: refused.
    None,
}

/// Where a newcomer stands among `limit.max` now (see [`accept_loop`]).
async fn room(slots: &Slots, limit: ClientLimit, link: usize, engine: &Sender<Inbound>) -> Room {
    if slots.in_use() < limit.max {
        return Room::Free;
    }
    let (answer, answered) = tokio::sync::oneshot::channel();
    let asked = engine.send(Inbound::Room {
        link,
        min_idle: limit.room_after_idle,
        answer,
    });
    if asked.is_ok() && answered.await.unwrap_or(false) {
        Room::OnProbation
    } else {
        Room::None
    }
}

/// Carries serial port `path` for link `link` for the whole session: when
/// the port vanishes (a pty whose other end went away), reopens it as soon
/// as it is back.
pub async fn serial_loop(
    path: PathBuf,
    settings: SerialSettings,
    first: tokio_serial::SerialStream,
    link: usize,
    ids: ConnIds,
    clock: RtClock,
    engine: Sender<Inbound>,
) {
    let mut port = Some(first);
    loop {
        let stream = match port.take() {
            Some(p) => p,
            None => match serial::open(&path, &settings) {
                Ok(p) => p,
                Err(_) => {
                    tokio::time::sleep(Duration::from_millis(200)).await;
                    continue;
                }
            },
        };
        let peer = path.display().to_string();
        let eof =
            "the port closed (a pty whose other side went away?); reopening it when it is back";
        let why = serve_stream(
            stream,
            link,
            ids.next(),
            peer,
            clock.clone(),
            engine.clone(),
            eof,
        )
        .await;
        if why == "server stopping" {
            return;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}
