//! The lab's panel in a browser: gauges, controls, a trend and the frame
//! monitor of a real-time session (`twin serve --web`, `twin supervise
//! --web`), served by the twin itself so a lab PC or a phone needs nothing
//! but a browser.
//!
//! Threads: the HTTP server runs on a runtime of its own, on a thread of its
//! own, at a lower priority than the links, so no page, stream or slow client
//! can delay a reply or the plant tick. What it shows comes two ways, both
//! paths the console and the live view already use:
//!
//! - the engine's state (register images, forces, faults, connections,
//!   counters, a supervisor's loops) is read by a closure the panel sends the
//!   engine as an [`Inbound::Command`], 20 times a second whatever the number
//!   of browsers ([`snapshot`]); commands (force, fault, set point) are
//!   closures too ([`commands`]);
//! - frames and events arrive through the sink's [`LiveView`] hook
//!   ([`view::PanelView`]), off the engine's thread.
//!
//! `twin panel` fronts no session: its own MEB-TCP connection
//! ([`remote`]) polls a slave and writes the outputs the page sets.
//!
//! Every 50 ms one message is built and handed to every stream client
//! ([`hub`]); a client too slow to take it is told how many it missed.
//! The JSON API is documented in `docs/panel-api.md`.
//!
//! The panel keeps within a budget of its own ([`server`]): all panels of a
//! process hold at most a quarter of its open files (at most 256
//! connections), a newcomer over that is refused at once, and a request
//! must send its head and its body in time, so browsers, however many or
//! slow, never take the descriptors the links serve their clients with.

#![allow(
    clippy::disallowed_methods,
    reason = "the panel is a real-time front end: it paces its stream and times its frames by the wall clock"
)]

pub mod access;
pub mod assets;
pub mod class_index;
pub mod commands;
pub mod http;
pub mod hub;
pub mod monitor;
pub mod outputs;
pub mod remote;
pub mod server;
pub mod snapshot;
pub mod step;
pub mod view;

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::mpsc::Sender;

pub use access::{Access, AccessOptions, TokenError};
pub use class_index::{ClassIndex, ClassModule, IndexError};
pub use hub::Hub;
pub use remote::RemoteError;
pub use server::Limits;
use twin_realtime::Inbound;
pub use twin_realtime::sink::LiveView;

/// Why a session's panel cannot be served.
#[derive(Debug, thiserror::Error)]
pub enum PanelError {
    #[error(transparent)]
    Token(#[from] TokenError),
    /// The address is taken, or not this machine's.
    #[error("--web {addr}: cannot listen there")]
    Listen {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("the panel was started twice")]
    StartedTwice,
    #[error("cannot start the panel's thread")]
    Thread(#[source] std::io::Error),
}

/// Which session the panel fronts: what it shows and which controls it has.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum PanelRole {
    /// `twin serve`: the simulated controller; inputs can be forced, links faulted.
    Serve,
    /// `twin supervise`: the master; set point, gains, loop, step.
    Supervise,
    /// `twin panel`: a remote MEB-TCP client; outputs set, inputs shown.
    Client,
}

impl PanelRole {
    /// The part of the lab the page stands for, as its title and heading
    /// say it: a teacher with several pages open tells them apart by it.
    pub fn described(self) -> &'static str {
        match self {
            PanelRole::Serve => "module (twin serve)",
            PanelRole::Supervise => "supervisor (twin supervise)",
            PanelRole::Client => "client (twin panel)",
        }
    }
}

/// Everything the panel is told.
#[derive(Debug, Clone)]
pub struct PanelOptions {
    pub role: PanelRole,
    /// Where to listen (`--web`).
    pub addr: SocketAddr,
    pub access: AccessOptions,
    /// Stream messages per second.
    pub rate_hz: f64,
}

/// A session time for the API: whole microseconds, so that a client reads
/// `1.522848`, not the float's last digits (`1.5228476739999999`).
pub(crate) fn seconds(t: f64) -> f64 {
    (t * 1e6).round() / 1e6
}

/// A panel being served: its address and the URL to open.
#[derive(Debug, Clone)]
pub struct Running {
    pub addr: SocketAddr,
    /// The URL to open, with the token when one is needed.
    pub url: String,
    pub read_only: bool,
}

/// The panel's half made before the session starts: the hub the live view
/// feeds, and what the server needs once the engine runs.
#[derive(Debug, Clone)]
pub struct Panel {
    options: PanelOptions,
    hub: Arc<Hub>,
    access: Arc<Access>,
    listener: Arc<std::sync::Mutex<Option<std::net::TcpListener>>>,
    addr: SocketAddr,
    /// Where the MEB links place each signal (`--map`), for the labels.
    layout: Option<Arc<remote::layout::Layout>>,
    /// The module the page names (a class file's `name`).
    name: Option<String>,
    /// What the server allows a client (connections, timeouts, body).
    limits: Limits,
}

impl Panel {
    /// Binds the address (so a busy port is said before the session starts)
    /// and decides the access rules; the server itself starts with
    /// [`Panel::start`].
    pub fn bind(options: PanelOptions) -> Result<Self, PanelError> {
        let access = Access::new(&options.access, &options.addr)?;
        let listen = |source| PanelError::Listen {
            addr: options.addr,
            source,
        };
        let listener = std::net::TcpListener::bind(options.addr).map_err(listen)?;
        listener.set_nonblocking(true).map_err(listen)?;
        let addr = listener.local_addr().map_err(listen)?;
        Ok(Self {
            hub: Arc::new(Hub::new(options.role)),
            options,
            access: Arc::new(access),
            listener: Arc::new(std::sync::Mutex::new(Some(listener))),
            addr,
            layout: None,
            name: None,
            limits: Limits::from_env(),
        })
    }

    /// A feed with no page of its own: the state and frames of a class's
    /// module that has no panel, for the class's index ([`ClassIndex`]).
    pub fn unserved(role: PanelRole) -> Self {
        Self {
            hub: Arc::new(Hub::new(role)),
            options: PanelOptions {
                role,
                addr: SocketAddr::from(([127, 0, 0, 1], 0)),
                access: AccessOptions::default(),
                rate_hz: 20.0,
            },
            access: Arc::new(Access::with(None, true)),
            listener: Arc::new(std::sync::Mutex::new(None)),
            addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            layout: None,
            name: None,
            limits: Limits::from_env(),
        }
    }

    /// Names the module on the page (its title and heading): a class's
    /// module, `student07`.
    pub fn named(mut self, name: &str) -> Self {
        self.name = Some(name.to_string());
        self
    }

    /// Whether the panel serves a page (an [`unserved`](Panel::unserved) one
    /// only feeds the class's index).
    pub fn served(&self) -> bool {
        self.addr.port() != 0
    }

    /// The module's token, if its panel needs one (the class's index links
    /// to the panel with it).
    pub fn token(&self) -> Option<&str> {
        self.access.token()
    }

    /// The panel's role.
    pub fn role(&self) -> PanelRole {
        self.options.role
    }

    /// Labels each signal where `map` places it (`twin serve --map`).
    pub fn with_map(mut self, map: &nodes::firmware::MebMap) -> Self {
        self.layout = Some(Arc::new(remote::layout::Layout::new(map)));
        self
    }

    /// Serves within `limits` instead of the defaults (tests shorten the
    /// timeouts).
    pub fn with_limits(mut self, limits: Limits) -> Self {
        self.limits = limits;
        self
    }

    /// The address bound and the URL to open.
    pub fn running(&self) -> Running {
        let host = match self.addr {
            SocketAddr::V4(a) if a.ip().is_unspecified() => {
                format!("127.0.0.1:{}", a.port())
            }
            SocketAddr::V6(a) if a.ip().is_unspecified() => format!("[::1]:{}", a.port()),
            a => a.to_string(),
        };
        let url = match self.access.token() {
            Some(token) => format!("http://{host}/?token={token}"),
            None => format!("http://{host}/"),
        };
        Running {
            addr: self.addr,
            url,
            read_only: self.access.read_only(),
        }
    }

    /// The live view that feeds this panel (hand it to the session's sink).
    pub fn view(&self) -> Box<dyn LiveView> {
        Box::new(view::PanelView::new(self.hub.clone()))
    }

    /// The hub (tests and the benchmark read it).
    pub fn hub(&self) -> Arc<Hub> {
        self.hub.clone()
    }

    /// Starts the server on a thread of its own, sending the engine its
    /// state reads and commands through `engine`.
    pub fn start(&self, engine: Sender<Inbound>) -> Result<(), PanelError> {
        self.spawn(http::Backend::Engine(Arc::new(std::sync::Mutex::new(
            engine,
        ))))
    }

    /// Starts the client panel's server over its connection (`twin panel`).
    pub fn start_remote(&self, remote: Arc<remote::Remote>) -> Result<(), PanelError> {
        self.spawn(http::Backend::Remote(remote))
    }

    fn spawn(&self, backend: http::Backend) -> Result<(), PanelError> {
        // Only a take happens under this lock: a panic elsewhere leaves the
        // listener as it was.
        let listener = self
            .listener
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take();
        if listener.is_none() && self.served() {
            return Err(PanelError::StartedTwice);
        }
        let state = http::AppState {
            hub: self.hub.clone(),
            access: self.access.clone(),
            backend,
            role: self.options.role,
            rate_hz: self.options.rate_hz.clamp(1.0, 100.0),
            written: Default::default(),
            layout: self.layout.clone(),
            limits: self.limits,
            page: Arc::new(http::Page::new(
                self.options.role,
                self.name.as_deref(),
                self.addr.port(),
            )),
        };
        std::thread::Builder::new()
            .name("twin-panel".into())
            .spawn(move || {
                // The panel waits; the links and the plant do not.
                let _ = rustix::process::setpriority_process(None, 10);
                let runtime = match tokio::runtime::Builder::new_current_thread()
                    .enable_io()
                    .enable_time()
                    .build()
                {
                    Ok(rt) => rt,
                    Err(e) => {
                        eprintln!("--web: cannot start the panel's runtime: {e}");
                        return;
                    }
                };
                match listener {
                    Some(listener) => runtime.block_on(http::serve(listener, state)),
                    None => runtime.block_on(http::feed(state)),
                }
            })
            .map_err(PanelError::Thread)?;
        Ok(())
    }
}
