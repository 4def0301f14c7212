//! `twin serve`: the simulated controller of seed 000's tool. Runs the bench
//! in real time and exposes its slave nodes on real links — MEB on a serial
//! port, a pty or TCP; Modbus TCP, RTU and ASCII; the seed-002 8-byte
//! network — all serving one module, recorded to MCAP like a virtual run.

pub mod console;
pub mod map;

use anyhow::{Context, Result, bail};
use nodes::firmware::{EvController, EvControllerConfig, Framing, SlaveFrontend};
use nodes::link::{CheckKind, FaultyNode};
use nodes::proto::modbus::serial::{PTY_SILENCE, standard_rtu_silence};
use nodes::controller_network::{LightConfig, LightNode, MotorConfig, MotorNode};
use nodes::time::{SimDuration, SimTime};
use plant::{EvModule, PlantParams};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::sync::mpsc::{Sender, channel};
use std::time::Duration;

use twin_sim::engine::ModuleSlot;
use crate::io::{LinkAddr, LinkDefaults, LinkSpec, serial, tcp};
use crate::links::{ConnIds, accept_loop, serial_loop};
use crate::session;
use crate::sink::{self, SinkConfig, SinkMsg, ViewOpener};
use crate::{
    Device, Inbound, LatenessSummary, LinkConfig, NodeEndpoint, RtClock, RtEngine, SlaveEndpoint,
};

/// The protocols `twin serve` speaks, as its options name them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServeProtocol {
    /// `--meb`: MEB on a serial port, pty or TCP.
    Meb,
    /// `--modbus`: Modbus TCP.
    ModbusTcp,
    /// `--modbus-rtu`: Modbus RTU on a serial port or pty.
    ModbusRtu,
    /// `--modbus-ascii`: Modbus ASCII on a serial port or pty.
    ModbusAscii,
    /// `--modbus8`: the seed-002 network (motor 01, light sensor 02).
    Modbus8,
}

impl ServeProtocol {
    /// The name printed for the link (and wt-peers' tests parse).
    pub fn name(self) -> &'static str {
        match self {
            ServeProtocol::Meb => "meb",
            ServeProtocol::ModbusTcp => "modbus-tcp",
            ServeProtocol::ModbusRtu => "modbus-rtu",
            ServeProtocol::ModbusAscii => "modbus-ascii",
            ServeProtocol::Modbus8 => "modbus8",
        }
    }

    fn option(self) -> &'static str {
        match self {
            ServeProtocol::Meb => "--meb",
            ServeProtocol::ModbusTcp => "--modbus",
            ServeProtocol::ModbusRtu => "--modbus-rtu",
            ServeProtocol::ModbusAscii => "--modbus-ascii",
            ServeProtocol::Modbus8 => "--modbus8",
        }
    }
}

/// Everything `twin serve` is told.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// The links, in the order given.
    pub links: Vec<(ServeProtocol, String)>,
    pub defaults: LinkDefaults,
    /// Slave id of the EV module's controller (MEB slave number, Modbus unit).
    pub id: u8,
    /// Where MEB links put the signals (`--map`; `None`: `spec/meb.md`'s map).
    pub meb_map: Option<nodes::firmware::MebMap>,
    pub params: PlantParams,
    pub seed: u64,
    /// Stop after this long (none: until SIGINT/SIGTERM).
    pub duration: Option<f64>,
    /// Recording (none: not recorded).
    pub out: Option<PathBuf>,
    pub monitor: bool,
    pub status_every: f64,
    pub max_clients: Option<usize>,
    pub partial_timeout: Option<SimDuration>,
    pub rate_limit: Option<u64>,
    pub read_only: bool,
    /// Wait for serial paths that do not exist yet (ptys made later).
    pub wait_for_ports: bool,
    pub record_hz: f64,
    /// Real-time FIFO priority of the engine's thread, if asked for.
    pub rt_priority: Option<u8>,
    /// Opens the session's live view (`--view`), if it has one.
    pub view: Option<ViewOpener>,
    /// The command line, for the recording's metadata.
    pub command_line: String,
}

/// One open link, as printed before `ready`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OpenLink {
    pub protocol: &'static str,
    pub address: String,
    /// Slave ids served, as printed (`01`, `01,02`).
    pub ids: String,
}

/// What a session reports at its end.
#[derive(Debug)]
pub struct ServeOutcome {
    pub elapsed_s: f64,
    pub lateness: LatenessSummary,
    pub counters: crate::engine::RtCounters,
    pub refused_clients: u64,
    pub stopped_by: String,
    pub recording: Option<PathBuf>,
    /// Samples streamed to the live view (`--view`), if it ran.
    pub view_samples: Option<u64>,
    /// What the live view's viewer did not take, if anything.
    pub view_error: Option<String>,
}

/// What a link of a protocol needs from the module.
fn framing(protocol: ServeProtocol, spec: &LinkSpec) -> Option<Framing> {
    Some(match protocol {
        ServeProtocol::Meb => Framing::Meb,
        ServeProtocol::ModbusTcp => Framing::ModbusTcp,
        ServeProtocol::ModbusAscii => Framing::ModbusAscii,
        ServeProtocol::ModbusRtu => {
            let pty = matches!(&spec.addr, LinkAddr::Serial(p) if serial::is_pty(p));
            // Bytes on a pty carry no timing: the spec's 5 ms silence.
            let silence = if pty {
                PTY_SILENCE
            } else {
                standard_rtu_silence(spec.serial.baud, spec.serial.bits_per_char())
            };
            Framing::ModbusRtu(silence)
        }
        ServeProtocol::Modbus8 => return None,
    })
}

fn check_kind(protocol: ServeProtocol) -> Option<CheckKind> {
    match protocol {
        ServeProtocol::Meb => Some(CheckKind::Meb),
        ServeProtocol::ModbusRtu => Some(CheckKind::ModbusRtu),
        ServeProtocol::Modbus8 => Some(CheckKind::Modbus8),
        ServeProtocol::ModbusTcp | ServeProtocol::ModbusAscii => None,
    }
}

/// Parses every link and checks each protocol is on a medium it runs on.
pub fn parse_links(options: &ServeOptions) -> Result<Vec<(ServeProtocol, LinkSpec)>> {
    if options.links.is_empty() {
        bail!(
            "no link given: serve at least one, e.g. --meb tcp://127.0.0.1:5700 or --modbus-rtu /tmp/ttyV1"
        );
    }
    let mut specs = Vec::new();
    for (protocol, text) in &options.links {
        let spec = LinkSpec::parse(text, &options.defaults)
            .with_context(|| format!("{} {text}", protocol.option()))?;
        let tcp = spec.is_tcp();
        match protocol {
            ServeProtocol::ModbusTcp if !tcp => bail!(
                "--modbus {text}: Modbus TCP needs tcp://HOST:PORT; for a serial port use --modbus-rtu or --modbus-ascii"
            ),
            ServeProtocol::ModbusRtu | ServeProtocol::ModbusAscii | ServeProtocol::Modbus8
                if tcp =>
            {
                bail!(
                    "{} {text}: this protocol runs on a serial port or pty; over TCP use --modbus (Modbus TCP) or --meb",
                    protocol.option()
                )
            }
            _ => {}
        }
        specs.push((*protocol, spec));
    }
    if specs
        .iter()
        .filter(|(p, _)| *p == ServeProtocol::Modbus8)
        .count()
        > 1
    {
        bail!("--modbus8 given twice: the seed-002 network has one serial line");
    }
    Ok(specs)
}

/// Starts an opened link's task on the runtime, sending to the engine.
type Starter = Box<dyn FnOnce(&tokio::runtime::Handle, Sender<Inbound>)>;

/// A session being set up: the engine, and the opened links' tasks to start.
struct Setup {
    engine: RtEngine,
    open: Vec<OpenLink>,
    starters: Vec<Starter>,
    refused: Arc<AtomicU64>,
}

/// Builds the module(s) and devices the links need.
fn build_devices(
    options: &ServeOptions,
    specs: &[(ServeProtocol, LinkSpec)],
    engine: &mut RtEngine,
) -> (Option<usize>, Option<(usize, usize)>) {
    let wants_ev = specs.iter().any(|(p, _)| *p != ServeProtocol::Modbus8);
    let wants_controller_network = specs.iter().any(|(p, _)| *p == ServeProtocol::Modbus8);
    let mut ev = None;
    if wants_ev {
        let module = engine.modules.len();
        let plant = EvModule::new(
            &options.params,
            twin_sim::virtual_run::derive_seed(options.seed, 100),
        );
        engine.modules.push(ModuleSlot::new("ev1", plant));
        let mut config = EvControllerConfig::for_plant(&options.params);
        config.slave_id = options.id;
        let node = FaultyNode::new(EvController::new(config), CheckKind::Meb);
        ev = Some(engine.devices.len());
        engine
            .devices
            .push(Device::new("ev1", Box::new(node), Some(module)));
    }
    let mut controller_network = None;
    if wants_controller_network {
        let params = PlantParams::preset("controller-network").unwrap_or_default();
        let module = engine.modules.len();
        let plant = EvModule::new(&params, twin_sim::virtual_run::derive_seed(options.seed, 101));
        engine.modules.push(ModuleSlot::new("bench", plant));
        let motor = FaultyNode::new(MotorNode::new(MotorConfig::default()), CheckKind::Modbus8);
        let light = FaultyNode::new(LightNode::new(LightConfig::default()), CheckKind::Modbus8);
        let m = engine.devices.len();
        engine
            .devices
            .push(Device::new("motor", Box::new(motor), Some(module)));
        engine
            .devices
            .push(Device::new("sensor", Box::new(light), Some(module)));
        controller_network = Some((m, m + 1));
    }
    (ev, controller_network)
}

/// Unique link names: the protocol, numbered when it repeats.
fn link_names(specs: &[(ServeProtocol, LinkSpec)]) -> Vec<String> {
    let mut seen: BTreeMap<&str, usize> = BTreeMap::new();
    specs
        .iter()
        .map(|(p, _)| {
            let n = seen.entry(p.name()).or_default();
            *n += 1;
            if *n == 1 {
                p.name().to_string()
            } else {
                format!("{}-{n}", p.name())
            }
        })
        .collect()
}

/// Opens every link (inside the runtime) and adds it to the engine.
async fn open_links(
    options: &ServeOptions,
    specs: Vec<(ServeProtocol, LinkSpec)>,
    names: Vec<String>,
    mut engine: RtEngine,
    ev: Option<usize>,
    controller_network: Option<(usize, usize)>,
) -> Result<Setup> {
    let ids = ConnIds::default();
    let clock = engine.clock;
    let refused = Arc::new(AtomicU64::new(0));
    let mut open = Vec::new();
    let mut starters: Vec<Starter> = Vec::new();
    for (index, ((protocol, spec), name)) in specs.into_iter().zip(names).enumerate() {
        let link = engine.links.len();
        debug_assert_eq!(link, index);
        let (address, tcp) = match &spec.addr {
            LinkAddr::Tcp(addr) => {
                let listener = tcp::bind(*addr)
                    .await
                    .with_context(|| format!("{} {}", protocol.option(), spec.text))?;
                let local = listener.local_addr()?;
                let (ids, max, refused) = (ids.clone(), options.max_clients, refused.clone());
                starters.push(Box::new(move |rt, inbound| {
                    rt.spawn(accept_loop(
                        listener, link, max, ids, clock, inbound, refused,
                    ));
                }));
                (format!("tcp://{local}"), true)
            }
            LinkAddr::Serial(path) => {
                let port = open_serial(path, &spec, options.wait_for_ports)
                    .await
                    .with_context(|| format!("{} {}", protocol.option(), spec.text))?;
                let shown = path.display().to_string();
                let (ids, path, settings) = (ids.clone(), path.clone(), spec.serial);
                starters.push(Box::new(move |rt, inbound| {
                    rt.spawn(serial_loop(path, settings, port, link, ids, clock, inbound));
                }));
                (shown, false)
            }
        };
        let id = options.id;
        let (factory, shown_ids): (crate::EndpointFactory, String) =
            match (framing(protocol, &spec), ev, controller_network) {
                (Some(framing), Some(device), _) => {
                    let label = format!("ev1 {name}");
                    let map = options.meb_map.clone().filter(|_| framing == Framing::Meb);
                    (
                        Box::new(move |_devices, peer| {
                            let mut frontend = SlaveFrontend::new(framing, id);
                            frontend.set_meb_map(map.clone());
                            Box::new(SlaveEndpoint {
                                device,
                                frontend,
                                name: format!("{label} {peer}"),
                            })
                        }),
                        format!("{id:02}"),
                    )
                }
                (None, _, Some((motor, light))) => (
                    Box::new(move |_devices, _peer| {
                        Box::new(NodeEndpoint {
                            devices: vec![motor, light],
                        })
                    }),
                    format!(
                        "{:02},{:02}",
                        nodes::controller_network::MOTOR_ID,
                        nodes::controller_network::LIGHT_ID
                    ),
                ),
                _ => bail!("internal: link {name} has no device to serve"),
            };
        open.push(OpenLink {
            protocol: protocol.name(),
            address: address.clone(),
            ids: shown_ids,
        });
        engine.links.push(LinkConfig {
            name,
            protocol: protocol.name(),
            address,
            check: check_kind(protocol),
            partial_timeout: if tcp { options.partial_timeout } else { None },
            rate_limit: if tcp { options.rate_limit } else { None },
            spec,
            factory,
        });
    }
    Ok(Setup {
        engine,
        open,
        starters,
        refused,
    })
}

async fn open_serial(
    path: &std::path::Path,
    spec: &LinkSpec,
    wait: bool,
) -> Result<tokio_serial::SerialStream> {
    if wait && !path.exists() {
        println!("waiting for {} to appear ...", path.display());
        while !path.exists() {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
    serial::open(path, &spec.serial)
}

/// Runs a session. `ready` gets the open links once they all are (the
/// command prints them and `ready`); `console` gets a sender for commands.
pub fn serve(
    options: &ServeOptions,
    ready: impl FnOnce(&[OpenLink]),
    console: impl FnOnce(Sender<Inbound>),
) -> Result<ServeOutcome> {
    let specs = parse_links(options)?;
    let names = link_names(&specs);
    let runtime = session::links_runtime()?;

    let clock = RtClock::start();
    let mut engine_modules = Vec::new();
    let (sink_tx, sink_handle);
    let setup = {
        let record_period = SimDuration::from_secs_f64(1.0 / options.record_hz.max(1.0));
        let (tx, rx) = channel::<SinkMsg>();
        let mut engine = RtEngine::new(clock, SimDuration::from_millis(1), record_period, tx);
        let (ev, controller_network) = build_devices(options, &specs, &mut engine);
        engine_modules.extend(engine.modules.iter().map(|m| m.name.clone()));
        let setup = runtime.block_on(open_links(options, specs, names, engine, ev, controller_network));
        // The sink starts once the link names are known; its channel was
        // made first so the engine could hold its sender.
        let setup = setup?;
        let links = session::link_labels(&setup.engine);
        let link_options: Vec<String> = options
            .links
            .iter()
            .map(|(p, t)| format!("{} {t}", p.option()))
            .collect();
        let recorder = session::create_recording(
            options.out.as_deref(),
            "serve",
            BTreeMap::from([
                ("command".into(), options.command_line.clone()),
                ("links".into(), link_options.join(" ")),
                ("seed".into(), options.seed.to_string()),
                ("slave_id".into(), options.id.to_string()),
                ("params".into(), toml::to_string(&options.params)?),
            ]),
        )?;
        let view = options.view.as_ref().and_then(|v| v.open(&engine_modules));
        let config = SinkConfig {
            modules: engine_modules,
            links,
            monitor: options.monitor,
            recorder,
            view,
        };
        sink_handle = sink::spawn_with(config, rx);
        sink_tx = setup.engine.sink();
        setup
    };
    let Setup {
        mut engine,
        open,
        starters,
        refused,
    } = setup;
    engine.set_read_only(options.read_only);
    engine.set_status_period(SimDuration::from_secs_f64(options.status_every.max(0.0)));

    ready(&open);

    let (inbound_tx, inbound_rx) = channel::<Inbound>();
    let end = options
        .duration
        .map(|s| SimTime::ZERO + SimDuration::from_secs_f64(s));
    let rt_priority = options.rt_priority;
    let rt_thread = session::spawn_engine(engine, inbound_rx, end, rt_priority)?;
    for start in starters {
        start(runtime.handle(), inbound_tx.clone());
    }
    console(inbound_tx.clone());
    // The links' runtime runs on this thread: a reply waits for it too.
    if let Some(priority) = rt_priority
        && let Err(why) =
            crate::clock::raise_this_thread(priority.saturating_sub(1).max(1))
    {
        let _ = sink_tx.send(SinkMsg::Say(format!(
            "warning: links at normal priority: {why}"
        )));
    }

    let (summary, engine) = session::run_until_stopped(&runtime, rt_thread, inbound_tx.clone())?;
    drop(engine);
    runtime.shutdown_timeout(Duration::from_millis(200));

    let refused_clients = refused.load(std::sync::atomic::Ordering::Relaxed);
    let l = summary.lateness;
    let totals = session::totals(&summary, refused_clients)?;
    let _ = sink_tx.send(SinkMsg::Finish(totals));
    drop(sink_tx);
    let outcome = sink_handle
        .join()
        .map_err(|_| anyhow::anyhow!("the recording thread failed"))??;
    Ok(ServeOutcome {
        elapsed_s: summary.elapsed.as_secs_f64(),
        lateness: l,
        counters: summary.counters,
        refused_clients,
        stopped_by: summary.stopped_by,
        recording: outcome.recording,
        view_samples: outcome.view_samples,
        view_error: outcome.view_error,
    })
}
