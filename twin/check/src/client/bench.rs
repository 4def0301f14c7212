//! The server a student's remote client connects to while it is checked:
//! the twin's own supervisor image server (`ImageServer` over a
//! `Supervisor`, as `twin supervise` serves) with the twin's own MEB slave
//! behind it on an in-process bus, no plant: the inputs hold fixed values.
//! A thread drives the supervisor and the slave every millisecond; each
//! connection has a thread of its own. Everything a client sends and gets
//! is kept with its time; a fault asked for is played on the next request.

use crate::framing::shown_text as shown;
use crate::run::Way;
use nodes::firmware::{Framing, RegisterImage, SlaveFrontend};
use nodes::master::image_server::{ImageServer, ImageServerConfig};
use nodes::master::{LoopMode, Protocol, SlaveLoopConfig, Supervisor, SupervisorConfig};
use nodes::node::Node;
use protocols::meb::{MebErrorCode, MebRepr};
use protocols::time::{SimDuration, SimTime};
use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// The slave's inputs (EA 00-05), as a client reads them.
pub const INPUTS: [u16; 6] = [0x0BD6, 0x0800, 0x0D05, 1500, 1490, 0x0CD3];

/// A frame on a client's connection: what it sent (`Received` by the
/// twin) or the twin's reply (`Sent`); `conn` numbers the connections
/// from 1.
#[derive(Debug, Clone)]
pub struct Heard {
    pub at: f64,
    pub conn: u64,
    pub way: Way,
    pub text: String,
    /// The bytes, for the recording.
    pub bytes: Vec<u8>,
    /// The frame, when it is a well-formed one.
    pub repr: Option<MebRepr>,
}

/// A fault the twin plays on a client's next request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// Answered with this error instead.
    Error(MebErrorCode),
    /// Not answered: the connection is closed.
    HangUp,
}

struct State {
    supervisor: Supervisor,
    server: ImageServer,
    image: RegisterImage,
    slave: SlaveFrontend,
    heard: Vec<Heard>,
    fault: Option<Fault>,
    connections: u64,
    /// The connection the twin hung up on.
    hung_up: Option<u64>,
}

struct Shared {
    stop: AtomicBool,
    started: Instant,
    state: Mutex<State>,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn now(&self) -> (f64, SimTime) {
        let at = self.started.elapsed().as_secs_f64();
        (at, SimTime(SimDuration::from_secs_f64(at).0))
    }
}

/// The twin's server, listening until dropped.
pub struct Bench {
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
    addr: SocketAddr,
}

impl std::fmt::Debug for Bench {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bench")
            .field("addr", &self.addr)
            .finish_non_exhaustive()
    }
}

impl Bench {
    /// Listens on `addr` (port 0 for any), supervising slave `id`.
    pub fn listen(addr: SocketAddr, id: u8) -> std::io::Result<Bench> {
        let listener = TcpListener::bind(addr)?;
        listener.set_nonblocking(true)?;
        let local = listener.local_addr()?;
        let mut slave_loop = SlaveLoopConfig::new(id);
        // VEL is the client's to set: the supervisor holds what it wrote.
        slave_loop.mode = LoopMode::Open { vel: 0 };
        let mut config = SupervisorConfig::new(Protocol::Meb, vec![slave_loop]);
        config.status_every = 10;
        let supervisor = Supervisor::new(config).map_err(std::io::Error::other)?;
        let mut image = RegisterImage::new(12, 12, 2048, 100);
        image.inputs = INPUTS;
        let shared = Arc::new(Shared {
            stop: AtomicBool::new(false),
            started: Instant::now(),
            state: Mutex::new(State {
                supervisor,
                server: ImageServer::new(ImageServerConfig::default()),
                image,
                slave: SlaveFrontend::new(Framing::Meb, id),
                heard: Vec::new(),
                fault: None,
                connections: 0,
                hung_up: None,
            }),
        });
        let engine = {
            let shared = shared.clone();
            std::thread::spawn(move || drive(&shared))
        };
        let accept = {
            let shared = shared.clone();
            std::thread::spawn(move || accept(&listener, &shared))
        };
        Ok(Bench {
            shared,
            threads: vec![engine, accept],
            addr: local,
        })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Seconds since it started listening.
    pub fn now(&self) -> f64 {
        self.shared.started.elapsed().as_secs_f64()
    }

    /// Everything heard so far.
    pub fn heard(&self) -> Vec<Heard> {
        self.shared.lock().heard.clone()
    }

    /// Plays `fault` on the next request of any client.
    pub fn play(&self, fault: Fault) {
        self.shared.lock().fault = Some(fault);
    }

    /// Whether the fault asked for is still to be played.
    pub fn fault_pending(&self) -> bool {
        self.shared.lock().fault.is_some()
    }

    /// How many connections the client made.
    pub fn connections(&self) -> u64 {
        self.shared.lock().connections
    }

    /// The connection the twin hung up on, once it has.
    pub fn hung_up_on(&self) -> Option<u64> {
        self.shared.lock().hung_up
    }

    /// What the slave holds now: VEL (SA 00) and SD 00.
    pub fn outputs(&self) -> (u16, u16) {
        let state = self.shared.lock();
        (state.image.stored.vel, state.image.stored.sd0)
    }
}

impl Drop for Bench {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        for thread in self.threads.drain(..) {
            let _ = thread.join();
        }
    }
}

/// The supervisor and its slave, every millisecond.
fn drive(shared: &Shared) {
    let mut buf = [0u8; 512];
    let mut reply = [0u8; 512];
    while !shared.stop.load(Ordering::Relaxed) {
        let (_, now) = shared.now();
        {
            let state = &mut *shared.lock();
            if state.supervisor.poll_timeout().is_some_and(|t| t <= now) {
                state.supervisor.handle_timeout(now);
            }
            while let Some(n) = state.supervisor.poll_transmit(now, &mut buf) {
                state.supervisor.transmit_done(now);
                let request = buf.get(..n).unwrap_or_default();
                state.slave.handle_bytes(&mut state.image, now, request);
                while let Some(m) = state.slave.poll_transmit(&mut reply) {
                    state
                        .supervisor
                        .handle_bytes(now, reply.get(..m).unwrap_or_default());
                }
            }
            state.server.collect(&mut state.supervisor);
            state.server.expire(now, &mut state.supervisor);
            if state.server.poll_timeout().is_some_and(|t| t <= now) {
                state.server.handle_timeout(now);
            }
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

fn accept(listener: &TcpListener, shared: &Arc<Shared>) {
    let mut connections = Vec::new();
    while !shared.stop.load(Ordering::Relaxed) {
        match listener.accept() {
            Ok((stream, _)) => {
                let shared = shared.clone();
                connections.push(std::thread::spawn(move || serve(stream, &shared)));
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(_) => std::thread::sleep(Duration::from_millis(5)),
        }
    }
    for c in connections {
        let _ = c.join();
    }
}

/// One client's connection, until it or the twin hangs up.
fn serve(mut stream: TcpStream, shared: &Shared) {
    let _ = stream.set_nodelay(true);
    let _ = stream.set_read_timeout(Some(Duration::from_millis(5)));
    let (conn, client) = {
        let (_, now) = shared.now();
        let state = &mut *shared.lock();
        state.connections += 1;
        match state.server.accept(now) {
            Ok(client) => (state.connections, client),
            Err(_) => return,
        }
    };
    let mut line = Vec::new();
    let mut bytes = [0u8; 1024];
    let mut out = [0u8; 512];
    while !shared.stop.load(Ordering::Relaxed) {
        let got = match stream.read(&mut bytes) {
            Ok(0) => break,
            Ok(n) => bytes.get(..n).unwrap_or_default(),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => &[],
            Err(_) => break,
        };
        let (at, now) = shared.now();
        let mut replies = Vec::new();
        let mut hang_up = false;
        {
            let state = &mut *shared.lock();
            let mut forward = Vec::new();
            for &b in got {
                line.push(b);
                if b != b'\n' && line.len() <= 512 {
                    continue;
                }
                let repr = MebRepr::parse(&line).ok();
                state.heard.push(Heard {
                    at,
                    conn,
                    way: Way::Received,
                    text: shown(&line),
                    bytes: line.clone(),
                    repr,
                });
                match (state.fault, repr) {
                    (Some(Fault::HangUp), Some(_)) => {
                        state.fault = None;
                        state.hung_up = Some(conn);
                        hang_up = true;
                        break;
                    }
                    (Some(Fault::Error(code)), Some(request)) => {
                        state.fault = None;
                        let error = MebRepr::error_reply(request.id, request.addr, code);
                        let n = error.emit(&mut out).unwrap_or(0);
                        replies.push(out.get(..n).unwrap_or_default().to_vec());
                    }
                    _ => forward.extend_from_slice(&line),
                }
                line.clear();
            }
            if !forward.is_empty() {
                let (server, supervisor) = (&mut state.server, &mut state.supervisor);
                server.handle_bytes(now, client, &forward, supervisor);
            }
            while let Some(n) = state.server.poll_transmit(client, &mut out) {
                replies.push(out.get(..n).unwrap_or_default().to_vec());
            }
            for reply in &replies {
                state.heard.push(Heard {
                    at: shared.started.elapsed().as_secs_f64(),
                    conn,
                    way: Way::Sent,
                    text: shown(reply),
                    bytes: reply.clone(),
                    repr: MebRepr::parse(reply).ok(),
                });
            }
            if hang_up || state.server.close_reason(client).is_some() {
                break;
            }
        }
        for reply in replies {
            if stream.write_all(&reply).is_err() {
                break;
            }
        }
    }
    shared.lock().server.disconnect(client);
}
