//! The panel's HTTP server inside a budget of its own, as a public service
//! must be: the panel shares the process with the links, and every
//! connection is a file descriptor the links may need.
//!
//! - At most [`Limits::connections`] connections at once, by default a
//!   quarter of the process's open-file limit and never more than
//!   [`MAX_CONNECTIONS`], shared by every panel of the process (a class has
//!   one per module). A connection over it is answered a short 503 and
//!   closed at once, never queued: a flood of connections costs the links
//!   nothing.
//! - A request head must arrive whole within [`Limits::header`] of the
//!   connection's opening or of its previous answer (hyper's header
//!   timeout, which is therefore also the keep-alive wait).
//! - A body must arrive whole within [`Limits::body`], and be at most
//!   [`Limits::body_bytes`]: a larger `Content-Length` gets 413 at once.
//! - A connection on which no byte has moved either way for
//!   [`Limits::idle`] while no request is being worked on is closed: a
//!   client that stopped reading its event stream. An open stream is never
//!   idle: it carries 20 updates a second.
//!
//! Refusals are said on the console as a count every [`SAY_EVERY`], never
//! a line per connection.

use axum::Router;
use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use http_body_util::{BodyExt, LengthLimitError, Limited};
use serde_json::json;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tower_service::Service;

/// The panel's connections never exceed this, however high the limit.
pub const MAX_CONNECTIONS: usize = 256;

/// How often refusals are said on the console, at most.
pub const SAY_EVERY: Duration = Duration::from_secs(10);

/// What one panel server allows a client.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Connections at once; `None`: the process's share ([`share_of`] its
    /// open-file limit), shared by every panel of the process.
    pub connections: Option<usize>,
    /// The whole request head, from the connection's opening or its last answer.
    pub header: Duration,
    /// The whole request body, from the end of its head.
    pub body: Duration,
    /// No byte either way, and no request being worked on.
    pub idle: Duration,
    /// The largest request body (the panel's commands are small JSON objects).
    pub body_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            connections: None,
            header: Duration::from_secs(10),
            body: Duration::from_secs(10),
            idle: Duration::from_secs(60),
            body_bytes: 64 * 1024,
        }
    }
}

impl Limits {
    /// The defaults, with `TWIN_PANEL_HEADER_TIMEOUT_MS`,
    /// `TWIN_PANEL_BODY_TIMEOUT_MS` and `TWIN_PANEL_IDLE_TIMEOUT_MS` if set:
    /// knobs for the tests of the real binary, which cannot wait the shipped
    /// timeouts out; not options.
    pub fn from_env() -> Limits {
        let ms = |name: &str, default: Duration| {
            std::env::var(name)
                .ok()
                .and_then(|v| v.trim().parse::<u64>().ok())
                .filter(|&ms| ms > 0)
                .map_or(default, Duration::from_millis)
        };
        let d = Limits::default();
        Limits {
            header: ms("TWIN_PANEL_HEADER_TIMEOUT_MS", d.header),
            body: ms("TWIN_PANEL_BODY_TIMEOUT_MS", d.body),
            idle: ms("TWIN_PANEL_IDLE_TIMEOUT_MS", d.idle),
            ..d
        }
    }
}

/// The panel's connections under an open-file limit of `open_files`
/// (`None`: unlimited): a quarter, so three quarters stay for the links'
/// clients (two descriptors each), the recording and the serial ports.
pub fn share_of(open_files: Option<u64>) -> usize {
    open_files.map_or(MAX_CONNECTIONS, |n| {
        usize::try_from(n / 4)
            .unwrap_or(MAX_CONNECTIONS)
            .clamp(1, MAX_CONNECTIONS)
    })
}

/// The places a server hands out, and what to say of them.
#[derive(Debug, Clone)]
struct Budget {
    places: Arc<Semaphore>,
    why: String,
}

impl Budget {
    fn of(limits: &Limits) -> Budget {
        if let Some(n) = limits.connections {
            return Budget {
                places: Arc::new(Semaphore::new(n)),
                why: format!("it serves at most {n} at once"),
            };
        }
        // One for the process: the links' reserve is the process's, however
        // many panels it has.
        static PROCESS: OnceLock<Budget> = OnceLock::new();
        PROCESS
            .get_or_init(|| {
                let open_files = twin_realtime::fd_limit::open_files().soft;
                let size = share_of(open_files);
                let of = match open_files {
                    Some(n) => format!("the panel's share of the process's {n} open files"),
                    None => "the panel's cap".into(),
                };
                Budget {
                    places: Arc::new(Semaphore::new(size)),
                    why: format!(
                        "it serves at most {size} at once ({of}; the rest are kept for the links)"
                    ),
                }
            })
            .clone()
    }
}

/// Says a line on the session's console.
pub type Say = Arc<dyn Fn(String) + Send + Sync>;

/// Refusals counted between two lines on the console.
struct Refusals {
    say: Say,
    why: String,
    refused: u64,
    failed: u64,
    last_error: String,
    said_any: bool,
}

impl Refusals {
    fn refused(&mut self) {
        self.refused += 1;
        // The first is said at once, so the cause is plain; then counts.
        if !self.said_any {
            self.said_any = true;
            self.refused = 0;
            (self.say)(format!(
                "refused a connection: {}; further refusals are counted every {} s",
                self.why,
                SAY_EVERY.as_secs()
            ));
        }
    }

    fn failed(&mut self, e: &io::Error) {
        self.failed += 1;
        self.last_error = e.to_string();
    }

    fn say(&mut self) {
        let every = SAY_EVERY.as_secs();
        if self.refused > 0 {
            (self.say)(format!(
                "refused {} more connection(s) in the last {every} s: {}",
                self.refused, self.why
            ));
        }
        if self.failed > 0 {
            (self.say)(format!(
                "could not accept {} connection(s) in the last {every} s ({}): the process is short of open files",
                self.failed, self.last_error
            ));
        }
        self.refused = 0;
        self.failed = 0;
    }
}

/// The answer of a panel with no place left. Short, and in one write: the
/// connection is closed right after it.
const BUSY: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\n\
Content-Type: application/json\r\n\
Retry-After: 5\r\n\
Connection: close\r\n\
Content-Length: 78\r\n\r\n\
{\"error\":\"the panel serves as many connections as it may: try again shortly\"}";

/// Serves `app` on `listener` within `limits`, saying refusals with `say`.
pub async fn run(listener: TcpListener, app: Router, limits: Limits, say: Say) {
    let budget = Budget::of(&limits);
    let mut refusals = Refusals {
        say,
        why: budget.why.clone(),
        refused: 0,
        failed: 0,
        last_error: String::new(),
        said_any: false,
    };
    let mut every = tokio::time::interval(SAY_EVERY);
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((socket, _)) => match budget.places.clone().try_acquire_owned() {
                    Ok(place) => {
                        tokio::spawn(connection(socket, app.clone(), limits, place));
                    }
                    Err(_) => {
                        // What the client already sent is read first, so that
                        // the close is a plain end of stream and not a reset
                        // that could discard the 503 before it is read.
                        let _ = socket.try_read(&mut [0u8; 4096]);
                        let _ = socket.try_write(BUSY);
                        drop(socket);
                        refusals.refused();
                    }
                },
                Err(e) => {
                    // Out of descriptors: the waiting connection stays in the
                    // kernel's queue; taking it again at once would spin.
                    refusals.failed(&e);
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            },
            _ = every.tick() => refusals.say(),
        }
    }
}

/// When a connection last moved a byte, either way.
#[derive(Clone)]
struct Activity {
    start: Instant,
    last_ms: Arc<AtomicU64>,
}

impl Activity {
    fn touch(&self) {
        let ms = u64::try_from(self.start.elapsed().as_millis()).unwrap_or(u64::MAX);
        self.last_ms.store(ms, Ordering::Relaxed);
    }

    fn quiet_for(&self) -> Duration {
        let last = Duration::from_millis(self.last_ms.load(Ordering::Relaxed));
        self.start.elapsed().saturating_sub(last)
    }
}

/// A socket that notes its activity.
struct Watched {
    socket: TcpStream,
    activity: Activity,
}

impl AsyncRead for Watched {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let polled = Pin::new(&mut this.socket).poll_read(cx, buf);
        if buf.filled().len() > before {
            this.activity.touch();
        }
        polled
    }
}

impl AsyncWrite for Watched {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let polled = Pin::new(&mut this.socket).poll_write(cx, buf);
        if matches!(polled, Poll::Ready(Ok(n)) if n > 0) {
            this.activity.touch();
        }
        polled
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let polled = Pin::new(&mut this.socket).poll_write_vectored(cx, bufs);
        if matches!(polled, Poll::Ready(Ok(n)) if n > 0) {
            this.activity.touch();
        }
        polled
    }

    fn is_write_vectored(&self) -> bool {
        self.socket.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().socket).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().socket).poll_shutdown(cx)
    }
}

/// Requests of one connection being worked on (their answer's head not yet given).
struct Working(Arc<AtomicUsize>);

impl Working {
    fn start(count: &Arc<AtomicUsize>) -> Working {
        count.fetch_add(1, Ordering::Relaxed);
        Working(count.clone())
    }
}

impl Drop for Working {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// One connection, holding its place until it closes.
async fn connection(socket: TcpStream, app: Router, limits: Limits, _place: OwnedSemaphorePermit) {
    let _ = socket.set_nodelay(true);
    let activity = Activity {
        start: Instant::now(),
        last_ms: Arc::new(AtomicU64::new(0)),
    };
    let working = Arc::new(AtomicUsize::new(0));
    let service = {
        let working = working.clone();
        hyper::service::service_fn(move |request: hyper::Request<hyper::body::Incoming>| {
            let mut app = app.clone();
            let working = Working::start(&working);
            async move {
                let response = app.call(request).await;
                drop(working);
                response
            }
        })
    };
    let io = hyper_util::rt::TokioIo::new(Watched {
        socket,
        activity: activity.clone(),
    });
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(hyper_util::rt::TokioTimer::new())
        .header_read_timeout(limits.header)
        .keep_alive(true);
    let served = builder.serve_connection(io, service);
    tokio::pin!(served);
    let mut check = tokio::time::interval((limits.idle / 4).max(Duration::from_millis(10)));
    check.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            // A header timeout, a client gone, a broken request: hyper has
            // answered what could be answered; nothing more to say.
            _ = served.as_mut() => return,
            _ = check.tick() => {
                if activity.quiet_for() >= limits.idle && working.load(Ordering::Relaxed) == 0 {
                    return;
                }
            }
        }
    }
}

/// The answer that closes the connection after it.
fn closing(status: StatusCode, error: String) -> Response {
    let mut response = (status, axum::Json(json!({ "error": error }))).into_response();
    response
        .headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    response
}

/// Every request's body is read whole here, within the body's limits,
/// before the guard and the handlers see it.
pub async fn bounded_body(State(limits): State<Limits>, request: Request, next: Next) -> Response {
    let most = limits.body_bytes;
    let declared = request
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    let too_large = || {
        closing(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!(
                "the body is larger than the panel takes ({most} bytes): its commands are small JSON objects"
            ),
        )
    };
    if declared.is_some_and(|n| n > most as u64) {
        return too_large();
    }
    let (parts, body) = request.into_parts();
    let read = tokio::time::timeout(limits.body, Limited::new(body, most).collect()).await;
    match read {
        Ok(Ok(collected)) => {
            let request = Request::from_parts(parts, Body::from(collected.to_bytes()));
            next.run(request).await
        }
        Ok(Err(e)) if e.is::<LengthLimitError>() => too_large(),
        Ok(Err(_)) => closing(
            StatusCode::BAD_REQUEST,
            "the body broke off before its end".into(),
        ),
        Err(_) => closing(
            StatusCode::REQUEST_TIMEOUT,
            format!(
                "the body did not arrive whole within {} s",
                limits.body.as_secs_f64()
            ),
        ),
    }
}
