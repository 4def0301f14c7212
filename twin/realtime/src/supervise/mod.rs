//! `twin supervise`: the supervisor and server of the M3CVME tool. A master on
//! a serial line (or a TCP connection to a slave) polls the EV module's
//! controller over MEB and closes its speed loop, or holds a manual `VEL`; a
//! TCP server answers remote MEB clients from the supervisor's image
//! (`docs/protocols/meb.md`). Runs on `twin serve`'s real-time engine and is recorded to
//! MCAP like a virtual run.

pub mod endpoint;

use nodes::master::image_server::ImageServerConfig;
use nodes::master::{
    LoopMode, Protocol, SlaveLoopConfig, SpeedSource, Supervisor, SupervisorConfig,
    SupervisorConfigError,
};
use protocols::time::{SimDuration, SimTime};
use std::collections::BTreeMap;
use std::sync::mpsc::Sender;
use std::time::Duration;
use tokio::runtime::Runtime;

use crate::io::spec::LinkSpecError;
use crate::io::{LinkAddr, LinkDefaults, LinkSpec, OpenError};
use crate::links::{ClientLimit, ConnIds, serve_stream};
use crate::session::{self, Links, Role, SessionError, SessionOptions, SessionOutcome};
use crate::{Device, Inbound, LinkConfig, NodeEndpoint, RtClock, RtEngine};
use endpoint::ImageEndpoint;
use twin_sim::nodes_build::SupervisorNode;

/// Why `twin supervise` cannot supervise: its bus, its listeners, its
/// loop's settings, or the session around them.
#[derive(Debug, thiserror::Error)]
pub enum SuperviseError {
    /// A link's text that is not a link (the bus's option, `--listen`).
    #[error("{option} {text}")]
    Spec {
        option: &'static str,
        text: String,
        #[source]
        source: Box<LinkSpecError>,
    },
    #[error("--modbus-rtu {text}: Modbus RTU runs on a serial port or pty; over TCP use --meb")]
    RtuOverTcp { text: String },
    #[error(
        "--listen {text}: the server listens on tcp://HOST:PORT (remote clients come over TCP)"
    )]
    ListenNotTcp { text: String },
    /// The bus or a listener that could not be opened, or a serial port
    /// not there (`--check`).
    #[error("{option} {text}")]
    Open {
        option: &'static str,
        text: String,
        #[source]
        source: OpenError,
    },
    #[error(
        "--meb {text}: cannot connect to an MEB slave at {addr} (is `twin serve --meb tcp://{addr}` running?)"
    )]
    Connect {
        text: String,
        addr: std::net::SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Supervisor(#[from] SupervisorConfigError),
    #[error("internal: {0}")]
    Internal(&'static str),
    #[error(transparent)]
    Session(#[from] SessionError),
}

type Result<T, E = SuperviseError> = std::result::Result<T, E>;

/// Everything `twin supervise` is told.
#[derive(Debug, Clone)]
pub struct SuperviseOptions {
    /// What every session is told (duration, recording, monitor, view, …).
    pub session: SessionOptions,
    /// The bus: a serial device or pty, or `tcp://HOST:PORT` of an MEB slave.
    pub bus: String,
    /// What the bus speaks: MEB, or Modbus RTU (serial only; remote clients
    /// still speak MEB to the server, forwarded writes get `ER 01`).
    pub protocol: Protocol,
    /// Where remote MEB clients connect (`tcp://HOST:PORT`), any number.
    pub listen: Vec<String>,
    pub baud: u32,
    /// Slave ids polled, in order.
    pub slaves: Vec<u8>,
    /// Set point from the start (rpm).
    pub set_point: f64,
    /// A manual `VEL` (DAC counts) instead of the loop.
    pub open_loop: Option<u16>,
    pub kp: f64,
    pub ki: f64,
    pub speed_source: SpeedSource,
    pub poll_period: SimDuration,
    pub reply_timeout: SimDuration,
    pub retries: u8,
    /// Read the status words (ED 00, FA 00-01, FD 00) every this many cycles (0: never).
    pub status_poll: u32,
    /// Where the slaves keep their signals on MEB (`--map`; `None`:
    /// `docs/protocols/meb.md`'s map). Remote clients still see that map.
    pub meb_map: Option<nodes::firmware::MebMap>,
    pub server: ImageServerConfig,
    /// Close a client sending more bytes than this in one second.
    pub rate_limit_bytes: Option<u64>,
    /// Close a remote client that has sent nothing for this long.
    pub idle_timeout: Option<SimDuration>,
    /// A newcomer beyond the client limit takes the place of a client quiet
    /// this long (see [`ClientLimit`]).
    pub room_after_idle: Option<SimDuration>,
}

/// One open link, as printed before `ready`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OpenLink {
    pub protocol: &'static str,
    pub address: String,
    /// `master 01` for the bus, `server` for a listener.
    pub role: String,
}

/// What a session reports at its end.
#[derive(Debug)]
pub struct SuperviseOutcome {
    /// What every session reports.
    pub session: SessionOutcome,
    /// The supervisor's status line at the end.
    pub status: Vec<String>,
}

/// The supervisor the options describe.
pub fn build_supervisor(options: &SuperviseOptions) -> Result<Supervisor> {
    let loops = options
        .slaves
        .iter()
        .map(|&id| {
            let mut l = SlaveLoopConfig::new(id);
            l.kp = options.kp;
            l.ki = options.ki;
            l.speed_source = options.speed_source;
            l.mode = match options.open_loop {
                Some(vel) => LoopMode::Open { vel },
                None => LoopMode::Closed,
            };
            l
        })
        .collect();
    let mut config = SupervisorConfig::new(options.protocol, loops);
    config.poll_period = options.poll_period;
    config.reply_timeout = options.reply_timeout;
    config.retries = options.retries;
    config.status_every = options.status_poll;
    if let Some(map) = &options.meb_map {
        config.layout = nodes::master::MebLayout::from_map(map);
    }
    if options.protocol == Protocol::ModbusRtu {
        // A pty carries no timing: the silence that ends a frame must be
        // longer than the gaps between the chunks it arrives in. A bus spec's
        // `silence_ms` says what it is; on a serial port, the line's rule.
        let line = protocols::modbus::serial::standard_rtu_silence(options.baud, 10);
        config.rtu_silence = LinkSpec::parse(&options.bus, &LinkDefaults::default())
            .map_or(line, |spec| spec.silence_with(line));
    }
    let mut supervisor = Supervisor::new(config)?;
    for &id in &options.slaves {
        supervisor.set_set_point(id, Some(options.set_point));
    }
    Ok(supervisor)
}

/// The communication status of every slave: loop, counters, last reply age.
pub fn status_lines(supervisor: &Supervisor, now: SimTime) -> Vec<String> {
    supervisor
        .slave_ids()
        .filter_map(|id| supervisor.loop_state(id).map(|s| (id, s)))
        .map(|(id, s)| {
            let c = s.counters;
            let age = s.measured_at.map_or("no reply yet".to_string(), |at| {
                format!(
                    "last reply {:.0} ms ago",
                    now.saturating_since(at).as_secs_f64() * 1e3
                )
            });
            let mode = match supervisor.mode(id) {
                Some(LoopMode::Open { vel }) => format!("open loop, VEL {vel}"),
                _ => format!(
                    "set point {:.0} rpm",
                    supervisor.set_point(id, now).unwrap_or(0.0)
                ),
            };
            format!(
                "slave {id:02}: {mode}, measured {:.0} rpm, VEL {}; {} requests, {} replies, {} timeouts, {} bad checks, {} errors, {} lost; {age}",
                s.measured_rpm,
                s.vel_written.unwrap_or(s.output),
                c.requests,
                c.replies,
                c.timeouts,
                c.bad_checks,
                c.exceptions,
                c.lost,
            )
        })
        .collect()
}

/// The line said at the first timeout of each slave: a real bus's ids are
/// the twin's to guess, so it asks rather than tells (`twin run` knows its
/// scenario's nodes and names an id no node has).
fn first_timeout_hint(options: &SuperviseOptions) -> crate::engine::EventHint {
    let bus = options.bus.clone();
    let within = options.reply_timeout.as_secs_f64() * 1e3;
    let mut hinted = std::collections::BTreeSet::new();
    Box::new(move |event| {
        if event.kind != "timeout" {
            return None;
        }
        // The supervisor's detail: `slave ID: TRANSACTION not answered`.
        let id: u8 = event
            .detail
            .strip_prefix("slave ")?
            .split_once(':')?
            .0
            .parse()
            .ok()?;
        hinted.insert(id).then(|| {
            format!(
                "no reply from id {id} within {within:.0} ms on {bus}: is a module with id {id} \
                 on this link? A slave answers only its own id (`twin serve --id {id}`, the \
                 M3CVME tool's slave number); the status lines count the timeouts from now on"
            )
        })
    })
}

/// Index of the supervisor among the engine's devices.
const SUPERVISOR: usize = 0;

/// How far behind the wall the supervisor's engine catches up before its
/// clock slips. It has no plant to step through lost time, only timers:
/// after a stall of the process (stopped, or starved by a busy machine) a
/// burst of catch-up would count the stall as time a request waited for
/// its reply, and time out a request whose reply lay in the port's buffer
/// all along. Five ticks: a busy machine's scheduling delay passes
/// unnoticed, a stall is the slip the session counts and says.
const CATCH_UP: SimDuration = SimDuration::from_millis(5);

/// `twin supervise` as a session's role: the supervisor, its bus and the
/// server's listeners.
struct Supervising<'a, C> {
    options: &'a SuperviseOptions,
    supervisor: Option<Supervisor>,
    bus: Option<LinkSpec>,
    listen: Vec<LinkSpec>,
    /// Gets a sender for commands once the engine runs (the web panel).
    console: Option<C>,
}

impl<C: FnOnce(Sender<Inbound>)> Role for Supervising<'_, C> {
    type Link = OpenLink;
    /// The supervisor's status lines at the end.
    type End = Vec<String>;
    type Error = SuperviseError;
    const KIND: &'static str = "supervise";

    fn build(&mut self, engine: &mut RtEngine) -> Result<()> {
        let Some(supervisor) = self.supervisor.take() else {
            return Err(SuperviseError::Internal("the supervisor is built once"));
        };
        // The status lines are the supervisor's (`status_loop`), not the
        // engine's; and no plant here: the module is on the other end of the bus.
        engine.set_status_period(SimDuration::ZERO);
        engine.event_hint = Some(first_timeout_hint(self.options));
        engine.set_catch_up(CATCH_UP, "so that no reply's wait counts the stall");
        engine.devices.push(Device::new(
            "supervisor",
            Box::new(SupervisorNode::new(supervisor)),
            None,
        ));
        Ok(())
    }

    async fn open(&mut self, engine: &mut RtEngine, links: &mut Links) -> Result<Vec<OpenLink>> {
        let Some(bus) = self.bus.take() else {
            return Err(SuperviseError::Internal("the bus is opened once"));
        };
        let listen = std::mem::take(&mut self.listen);
        open_links(self.options, bus, listen, engine, links).await
    }

    fn metadata(&self) -> Result<BTreeMap<String, String>> {
        let options = self.options;
        Ok(BTreeMap::from([
            ("bus".into(), options.bus.clone()),
            ("listen".into(), options.listen.join(" ")),
            ("slaves".into(), format!("{:?}", options.slaves)),
        ]))
    }

    fn started(&mut self, runtime: &Runtime, engine: &Sender<Inbound>) {
        let every = self.options.session.status_every;
        if every > 0.0 {
            runtime.spawn(status_loop(Duration::from_secs_f64(every), engine.clone()));
        }
        if let Some(console) = self.console.take() {
            console(engine.clone());
        }
    }

    fn stopped(
        &mut self,
        engine: &mut RtEngine,
        totals: &mut BTreeMap<String, String>,
    ) -> Vec<String> {
        let now = engine.clock.now();
        let status = engine
            .devices
            .get_mut(SUPERVISOR)
            .and_then(|d| d.node.supervisor_mut())
            .map(|s| status_lines(s, now))
            .unwrap_or_default();
        let final_state = engine
            .devices
            .get(SUPERVISOR)
            .and_then(|d| d.node.final_state())
            .map(|v| v.to_string())
            .unwrap_or_default();
        totals.insert("supervisor".into(), final_state);
        status
    }
}

/// `--check`: the bus and the listening addresses as supervising would read
/// them, and the bus's serial port there already (or waited for); nothing is
/// opened or bound.
pub fn check_links(options: &SuperviseOptions) -> Result<()> {
    let (bus, _) = parse_links(options)?;
    crate::io::serial::check_port(&bus, options.session.wait_for_ports).map_err(|source| {
        SuperviseError::Open {
            option: bus_option(options.protocol),
            text: options.bus.clone(),
            source,
        }
    })
}

fn parse_links(options: &SuperviseOptions) -> Result<(LinkSpec, Vec<LinkSpec>)> {
    // A master sends as soon as it is ready: no turnaround of its own.
    let defaults = LinkDefaults {
        baud: options.baud,
        serial_turnaround: SimDuration::ZERO,
        tcp_turnaround: SimDuration::ZERO,
        pace: false,
    };
    let option = bus_option(options.protocol);
    let bus = LinkSpec::parse(&options.bus, &defaults).map_err(|source| SuperviseError::Spec {
        option,
        text: options.bus.clone(),
        source: Box::new(source),
    })?;
    if options.protocol == Protocol::ModbusRtu && bus.is_tcp() {
        return Err(SuperviseError::RtuOverTcp {
            text: options.bus.clone(),
        });
    }
    let mut listen = Vec::new();
    for text in &options.listen {
        let spec = LinkSpec::parse(text, &defaults).map_err(|source| SuperviseError::Spec {
            option: "--listen",
            text: text.clone(),
            source: Box::new(source),
        })?;
        if !spec.is_tcp() {
            return Err(SuperviseError::ListenNotTcp { text: text.clone() });
        }
        listen.push(spec);
    }
    Ok((bus, listen))
}

async fn open_links(
    options: &SuperviseOptions,
    bus: LinkSpec,
    listen: Vec<LinkSpec>,
    engine: &mut RtEngine,
    links: &mut Links,
) -> Result<Vec<OpenLink>> {
    let mut open = Vec::new();
    let slaves = options
        .slaves
        .iter()
        .map(|id| format!("{id:02}"))
        .collect::<Vec<_>>()
        .join(",");

    // The bus: the supervisor drives it as a node, as on the simulated bus.
    let address = match &bus.addr {
        LinkAddr::Serial(path) => {
            links
                .serial(path, bus.serial, 0)
                .await
                .map_err(|source| SuperviseError::Open {
                    option: bus_option(options.protocol),
                    text: bus.text.clone(),
                    source,
                })?;
            path_text(&bus)
        }
        LinkAddr::Tcp(addr) => {
            let addr = *addr;
            let first = tokio::net::TcpStream::connect(addr)
                .await
                .map_err(|source| SuperviseError::Connect {
                    text: bus.text.clone(),
                    addr,
                    source,
                })?;
            let (ids, clock) = (links.ids.clone(), links.clock.clone());
            links.start(move |rt, inbound| {
                rt.spawn(tcp_bus_loop(addr, first, ids, clock, inbound));
            });
            format!("tcp://{addr}")
        }
    };
    let bus_protocol = match options.protocol {
        Protocol::Meb => "meb",
        Protocol::ModbusRtu => "modbus-rtu",
    };
    open.push(OpenLink {
        protocol: bus_protocol,
        address: address.clone(),
        role: format!("master {slaves}"),
    });
    engine.links.push(LinkConfig {
        name: "bus".into(),
        protocol: bus_protocol,
        address,
        twin_is_master: true,
        spec: bus,
        check: None,
        partial_timeout: None,
        rate_limit: None,
        idle_timeout: None,
        factory: Box::new(|_devices, _peer| Box::new(NodeEndpoint::masters(vec![SUPERVISOR]))),
    });

    for (n, spec) in listen.into_iter().enumerate() {
        let LinkAddr::Tcp(addr) = spec.addr else {
            return Err(SuperviseError::Internal("a listener that is not TCP"));
        };
        let link = engine.links.len();
        let local = links
            .listen(
                addr,
                link,
                Some(ClientLimit {
                    room_after_idle: options.room_after_idle,
                    ..ClientLimit::new(options.server.max_clients)
                }),
                options.session.allow.clone(),
            )
            .await
            .map_err(|source| SuperviseError::Open {
                option: "--listen",
                text: spec.text.clone(),
                source,
            })?;
        let address = format!("tcp://{local}");
        open.push(OpenLink {
            protocol: "meb",
            address: address.clone(),
            role: "server".into(),
        });
        let server = options.server;
        engine.links.push(LinkConfig {
            name: if n == 0 {
                "tcp".into()
            } else {
                format!("tcp-{}", n + 1)
            },
            protocol: "meb",
            address,
            twin_is_master: false,
            spec,
            check: None,
            partial_timeout: Some(server.partial_timeout),
            rate_limit: options.rate_limit_bytes,
            idle_timeout: options.idle_timeout,
            factory: Box::new(move |_devices, _peer| {
                Box::new(ImageEndpoint::new(SUPERVISOR, server, SimTime::ZERO))
            }),
        });
    }
    Ok(open)
}

/// The option that names the bus, for messages.
fn bus_option(protocol: Protocol) -> &'static str {
    match protocol {
        Protocol::Meb => "--meb",
        Protocol::ModbusRtu => "--modbus-rtu",
    }
}

fn path_text(spec: &LinkSpec) -> String {
    match &spec.addr {
        LinkAddr::Serial(p) => p.display().to_string(),
        LinkAddr::Tcp(a) => format!("tcp://{a}"),
    }
}

/// Carries the bus when it is a TCP connection to an MEB slave (`twin serve
/// --meb tcp://…`): reconnects when the slave goes away.
async fn tcp_bus_loop(
    addr: std::net::SocketAddr,
    first: tokio::net::TcpStream,
    ids: ConnIds,
    clock: RtClock,
    engine: Sender<Inbound>,
) {
    let mut stream = Some(first);
    loop {
        let s = match stream.take() {
            Some(s) => s,
            None => match tokio::net::TcpStream::connect(addr).await {
                Ok(s) => s,
                Err(_) => {
                    tokio::time::sleep(Duration::from_millis(200)).await;
                    continue;
                }
            },
        };
        let _ = s.set_nodelay(true);
        let why = serve_stream(
            s,
            0,
            ids.next(),
            format!("tcp://{addr}"),
            clock.clone(),
            engine.clone(),
            "the slave closed the connection (reconnecting)",
        )
        .await;
        if why == "server stopping" {
            return;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// Every `period`, a status line of every slave on the console.
async fn status_loop(period: Duration, engine: Sender<Inbound>) {
    let mut interval = tokio::time::interval(period);
    interval.tick().await;
    loop {
        interval.tick().await;
        let sent = engine.send(Inbound::Command(Box::new(|engine: &mut RtEngine| {
            let now = engine.clock.now();
            let clients = engine.connections().filter(|(link, _)| *link > 0).count();
            let Some(supervisor) = engine
                .devices
                .get_mut(SUPERVISOR)
                .and_then(|d| d.node.supervisor_mut())
            else {
                return;
            };
            let lines = status_lines(supervisor, now);
            let cycles = supervisor.cycles();
            engine.say(format!(
                "[{:10.3} s] supervisor: {cycles} poll cycles, {clients} remote client(s)",
                now.as_secs_f64()
            ));
            for line in lines {
                engine.say(format!("  {line}"));
            }
        })));
        if sent.is_err() {
            return;
        }
    }
}

/// Runs a session; `ready` gets the open links once they all are.
pub fn supervise(
    options: &SuperviseOptions,
    ready: impl FnOnce(&[OpenLink]),
) -> Result<SuperviseOutcome> {
    supervise_with(options, ready, |_| {})
}

/// Runs a session; `ready` gets the open links once they all are, and
/// `console` a sender for commands once the engine runs.
pub fn supervise_with(
    options: &SuperviseOptions,
    ready: impl FnOnce(&[OpenLink]),
    console: impl FnOnce(Sender<Inbound>),
) -> Result<SuperviseOutcome> {
    let (bus, listen) = parse_links(options)?;
    let supervisor = build_supervisor(options)?;
    let role = Supervising {
        options,
        supervisor: Some(supervisor),
        bus: Some(bus),
        listen,
        console: Some(console),
    };
    let (session, status) = session::run(&options.session, role, ready)?;
    Ok(SuperviseOutcome { session, status })
}
