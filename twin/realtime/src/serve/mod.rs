//! `twin serve`: the simulated controller of the M3CVME tool. Runs the bench
//! in real time and exposes its slave nodes on real links — MEB on a serial
//! port, a pty or TCP; Modbus TCP, RTU and ASCII; the Controller_network
//! project's 8-byte Modbus — all serving one module, recorded to MCAP like a virtual run.

pub mod console;
pub mod map;

use nodes::controller_network::{LightConfig, LightNode, MotorConfig, MotorNode};
use nodes::firmware::{EvController, EvControllerConfig, Framing, SlaveFrontend};
use nodes::link::{CheckKind, FaultyNode};
use plant::{EvModule, PlantParams};
use protocols::time::SimDuration;
use std::collections::BTreeMap;
use std::sync::mpsc::Sender;
use tokio::runtime::Runtime;

use crate::device::SlaveAddress;
use crate::firmware_endpoint::{FirmwareEndpoint, RequestFraming};
use crate::io::spec::LinkSpecError;
use crate::io::{LinkAddr, LinkDefaults, LinkSpec, OpenError};
use crate::links::ClientLimit;
use crate::session::{self, Links, Role, SessionError, SessionOptions, SessionOutcome};
use crate::{Device, Inbound, LinkConfig, NodeEndpoint, RtEngine, SlaveEndpoint};
use twin_sim::engine::ModuleSlot;
use twin_sim::nodes_build::BuildError;

/// Why `twin serve` cannot serve: a link or a sketch it is given, or the
/// session around them.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(
        "no link given: serve at least one, e.g. --meb tcp://127.0.0.1:5700 or --modbus-rtu /tmp/ttyV1"
    )]
    NoLink,
    /// A link's text that is not a link (`--meb TEXT`, …).
    #[error("{option} {text}")]
    Spec {
        option: &'static str,
        text: String,
        #[source]
        source: Box<LinkSpecError>,
    },
    #[error(
        "--modbus {text}: Modbus TCP needs tcp://HOST:PORT; for a serial port use --modbus-rtu or --modbus-ascii"
    )]
    ModbusTcpNotTcp { text: String },
    #[error(
        "{option} {text}: this protocol runs on a serial port or pty; over TCP use --modbus (Modbus TCP) or --meb"
    )]
    SerialOnly { option: &'static str, text: String },
    #[error("--modbus8 given twice: the Controller_network nodes share one serial line")]
    Modbus8Twice,
    /// A link that could not be opened, or a serial port not there (`--check`).
    #[error("{option} {text}")]
    Open {
        option: &'static str,
        text: String,
        #[source]
        source: OpenError,
    },
    #[error("--firmware {elf}: its board answers on {link}, and none is given")]
    FirmwareWithoutLink { elf: String, link: &'static str },
    #[error("{option} {text}: the EV controller's sketch serves MEB links only (its own protocol)")]
    SketchServesMebOnly { option: &'static str, text: String },
    /// A sketch the firmware builder refused (or no builder: `twin` has none).
    #[error("--firmware {elf}")]
    Firmware {
        elf: String,
        #[source]
        source: Box<BuildError>,
    },
    #[error("cannot write the plant's parameters into the recording")]
    Params(#[source] toml::ser::Error),
    #[error("internal: link {link} has no device to serve")]
    NoDevice { link: String },
    #[error(transparent)]
    Session(#[from] SessionError),
}

type Result<T, E = ServeError> = std::result::Result<T, E>;

/// The slave ids `--id` takes, and the panel's id box: MEB's two digits,
/// and Modbus's unicast addresses below 100 (0 is a broadcast).
pub const SLAVE_IDS: std::ops::RangeInclusive<u8> = 1..=99;

/// An id checked as `--id` checks it.
pub fn check_id(id: f64) -> Result<u8, String> {
    let (lo, hi) = (*SLAVE_IDS.start(), *SLAVE_IDS.end());
    if id.fract() == 0.0 && (f64::from(lo)..=f64::from(hi)).contains(&id) {
        Ok(id as u8)
    } else {
        Err(format!(
            "{id} is not a slave id: it takes a whole number from {lo} to {hi} (as --id)"
        ))
    }
}

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
    /// `--modbus8`: the Controller_network nodes (motor 01, light sensor 02).
    Modbus8,
}

impl ServeProtocol {
    /// The name printed for the link (which the peer tests parse).
    pub fn name(self) -> &'static str {
        match self {
            ServeProtocol::Meb => "meb",
            ServeProtocol::ModbusTcp => "modbus-tcp",
            ServeProtocol::ModbusRtu => "modbus-rtu",
            ServeProtocol::ModbusAscii => "modbus-ascii",
            ServeProtocol::Modbus8 => "modbus8",
        }
    }

    /// `source`, said of the link `spec` of this protocol.
    fn open_error(self, spec: &LinkSpec, source: OpenError) -> ServeError {
        ServeError::Open {
            option: self.option(),
            text: spec.text.clone(),
            source,
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
    /// What every session is told (duration, recording, monitor, view, …).
    pub session: SessionOptions,
    /// The links, in the order given.
    pub links: Vec<(ServeProtocol, String)>,
    pub defaults: LinkDefaults,
    /// Slave id of the EV module's controller (MEB slave number, Modbus unit).
    pub id: u8,
    /// Where MEB links put the signals (`--map`; `None`: `docs/protocols/meb.md`'s map).
    pub meb_map: Option<nodes::firmware::MebMap>,
    pub params: PlantParams,
    pub seed: u64,
    pub max_clients: Option<usize>,
    pub partial_timeout: Option<SimDuration>,
    pub rate_limit: Option<u64>,
    /// Close a TCP connection quiet this long (`None`: never, as the MEB page says).
    pub idle_timeout: Option<SimDuration>,
    /// A newcomer beyond `max_clients` takes the place of a client quiet
    /// this long (`None`: never).
    pub room_after_idle: Option<SimDuration>,
    pub read_only: bool,
    /// The EV controller's light detector at power-up (`LDR_ADAPT`): the
    /// adaptive one follows the wheel far faster than the fixed threshold.
    pub light_adaptive: bool,
    /// Controller boards as compiled firmware (`firmware` nodes, built by
    /// the registered builder: `twin-avr serve --firmware`), each in place
    /// of the Rust node of its name: `ev1` (its MEB links reach the
    /// sketch's UART), `motor` and `sensor` (the Controller_network Nanos,
    /// on the --modbus8 link).
    pub firmware: Vec<twin_sim::scenario::NodeSpec>,
}

/// One open link, as printed before `ready`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OpenLink {
    pub protocol: &'static str,
    pub address: String,
    /// Slave ids served, as printed (`01`, `01,02`).
    pub ids: String,
}

/// What a link of a protocol needs from the module.
fn framing(protocol: ServeProtocol, spec: &LinkSpec) -> Option<Framing> {
    Some(match protocol {
        ServeProtocol::Meb => Framing::Meb,
        ServeProtocol::ModbusTcp => Framing::ModbusTcp,
        ServeProtocol::ModbusAscii => Framing::ModbusAscii,
        // Not the line's 3.5 characters: bytes on a pty or behind a USB
        // adapter arrive with gaps of their own (`LinkSpec::silence`).
        ServeProtocol::ModbusRtu => Framing::ModbusRtu(spec.silence()),
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

/// `--check`: the links as serving them would read them, and each serial
/// port there already (or waited for, with `--wait-for-ports`); nothing is
/// opened or bound.
pub fn check_links(options: &ServeOptions) -> Result<()> {
    for (protocol, spec) in parse_links(options)? {
        crate::io::serial::check_port(&spec, options.session.wait_for_ports)
            .map_err(|source| protocol.open_error(&spec, source))?;
    }
    Ok(())
}

/// Parses every link and checks each protocol is on a medium it runs on.
pub fn parse_links(options: &ServeOptions) -> Result<Vec<(ServeProtocol, LinkSpec)>> {
    if options.links.is_empty() {
        return Err(ServeError::NoLink);
    }
    let mut specs = Vec::new();
    for (protocol, text) in &options.links {
        let spec = LinkSpec::parse(text, &options.defaults).map_err(|source| ServeError::Spec {
            option: protocol.option(),
            text: text.clone(),
            source: Box::new(source),
        })?;
        let tcp = spec.is_tcp();
        match protocol {
            ServeProtocol::ModbusTcp if !tcp => {
                return Err(ServeError::ModbusTcpNotTcp { text: text.clone() });
            }
            ServeProtocol::ModbusRtu | ServeProtocol::ModbusAscii | ServeProtocol::Modbus8
                if tcp =>
            {
                return Err(ServeError::SerialOnly {
                    option: protocol.option(),
                    text: text.clone(),
                });
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
        return Err(ServeError::Modbus8Twice);
    }
    Ok(specs)
}

/// `twin serve` as a session's role: the module(s) and their slave nodes,
/// on the links given.
struct Serving<'a, C> {
    options: &'a ServeOptions,
    specs: Vec<(ServeProtocol, LinkSpec)>,
    names: Vec<String>,
    /// The EV module's controller among the engine's devices.
    ev: Option<usize>,
    /// The Controller_network motor and light sensor nodes.
    controller_network: Option<(usize, usize)>,
    console: Option<C>,
}

impl<C: FnOnce(Sender<Inbound>)> Role for Serving<'_, C> {
    type Link = OpenLink;
    type End = ();
    type Error = ServeError;
    const KIND: &'static str = "serve";

    fn build(&mut self, engine: &mut RtEngine) -> Result<()> {
        (self.ev, self.controller_network) = build_devices(self.options, &self.specs, engine)?;
        engine.set_read_only(self.options.read_only);
        engine.set_status_period(SimDuration::from_secs_f64(
            self.options.session.status_every.max(0.0),
        ));
        Ok(())
    }

    async fn open(&mut self, engine: &mut RtEngine, links: &mut Links) -> Result<Vec<OpenLink>> {
        let specs = std::mem::take(&mut self.specs);
        let names = std::mem::take(&mut self.names);
        open_links(
            self.options,
            specs,
            names,
            engine,
            links,
            self.ev,
            self.controller_network,
        )
        .await
    }

    fn metadata(&self) -> Result<BTreeMap<String, String>> {
        let options = self.options;
        let link_options: Vec<String> = options
            .links
            .iter()
            .map(|(p, t)| format!("{} {t}", p.option()))
            .collect();
        Ok(BTreeMap::from([
            ("links".into(), link_options.join(" ")),
            ("seed".into(), options.seed.to_string()),
            ("slave_id".into(), options.id.to_string()),
            (
                "params".into(),
                toml::to_string(&options.params).map_err(ServeError::Params)?,
            ),
            (
                "light_detector".into(),
                if options.light_adaptive {
                    "adaptive"
                } else {
                    "fixed"
                }
                .into(),
            ),
        ]))
    }

    fn started(&mut self, _runtime: &Runtime, engine: &Sender<Inbound>) {
        if let Some(console) = self.console.take() {
            console(engine.clone());
        }
    }

    fn stopped(&mut self, _engine: &mut RtEngine, _totals: &mut BTreeMap<String, String>) {}
}

/// The devices built: the EV controller's, and the Controller_network motor's and light sensor's.
type Served = (Option<usize>, Option<(usize, usize)>);

/// Builds the module(s) and devices the links need.
fn build_devices(
    options: &ServeOptions,
    specs: &[(ServeProtocol, LinkSpec)],
    engine: &mut RtEngine,
) -> Result<Served> {
    let wants_ev = specs.iter().any(|(p, _)| *p != ServeProtocol::Modbus8);
    let wants_controller_network = specs.iter().any(|(p, _)| *p == ServeProtocol::Modbus8);
    for spec in &options.firmware {
        let (wanted, link) = match spec.name() {
            "ev1" => (wants_ev, "an --meb link"),
            _ => (wants_controller_network, "a --modbus8 link"),
        };
        if !wanted {
            return Err(ServeError::FirmwareWithoutLink {
                elf: spec_elf(spec).to_string(),
                link,
            });
        }
    }
    let mut ev = None;
    if wants_ev {
        let module = engine.modules.len();
        let plant = EvModule::new(
            &options.params,
            twin_sim::virtual_run::derive_seed(options.seed, 100),
        );
        engine.modules.push(ModuleSlot::new("ev1", plant));
        let node: Box<dyn twin_sim::engine::SimNode + Send> = match sketch(options, "ev1") {
            Some(spec) => {
                if let Some((p, spec)) = specs
                    .iter()
                    .find(|(p, _)| !matches!(p, ServeProtocol::Meb | ServeProtocol::Modbus8))
                {
                    return Err(ServeError::SketchServesMebOnly {
                        option: p.option(),
                        text: spec.text.clone(),
                    });
                }
                build_sketch(spec, &options.params, options.defaults.baud)?
            }
            None => {
                let mut config = EvControllerConfig::for_plant(&options.params);
                config.light.adaptive = options.light_adaptive;
                config.slave_id = options.id;
                Box::new(FaultyNode::new(EvController::new(config), CheckKind::Meb))
            }
        };
        ev = Some(engine.devices.len());
        let mut device = Device::new("ev1", node, Some(module));
        // A sketch's id and map are compiled into it: only the Rust
        // controller's can change while it runs.
        if sketch(options, "ev1").is_none() {
            device.address = Some(SlaveAddress {
                id: options.id,
                meb_map: options.meb_map.clone(),
            });
        }
        engine.devices.push(device);
    }
    let mut controller_network = None;
    if wants_controller_network {
        let params = PlantParams::preset("controller-network").unwrap_or_default();
        let module = engine.modules.len();
        let plant = EvModule::new(
            &params,
            twin_sim::virtual_run::derive_seed(options.seed, 101),
        );
        engine.modules.push(ModuleSlot::new("bench", plant));
        // The Nanos' own ports wait for 3.5 characters of quiet; on a real
        // link the bytes come with gaps of their own (`LinkSpec::silence`).
        let silence = specs
            .iter()
            .find(|(p, _)| *p == ServeProtocol::Modbus8)
            .map(|(_, spec)| spec.silence());
        let mut motor = MotorConfig::default();
        let mut light = LightConfig::for_sensor(&params.light);
        if let Some(silence) = silence {
            motor.port.silence = silence;
            light.port.silence = silence;
        }
        let motor: Box<dyn twin_sim::engine::SimNode + Send> = match sketch(options, "motor") {
            Some(spec) => build_sketch(spec, &params, options.defaults.baud)?,
            None => Box::new(FaultyNode::new(MotorNode::new(motor), CheckKind::Modbus8)),
        };
        let light: Box<dyn twin_sim::engine::SimNode + Send> = match sketch(options, "sensor") {
            Some(spec) => build_sketch(spec, &params, options.defaults.baud)?,
            None => Box::new(FaultyNode::new(LightNode::new(light), CheckKind::Modbus8)),
        };
        let m = engine.devices.len();
        engine
            .devices
            .push(Device::new("motor", motor, Some(module)));
        engine
            .devices
            .push(Device::new("sensor", light, Some(module)));
        controller_network = Some((m, m + 1));
    }
    Ok((ev, controller_network))
}

/// The sketch given for device `name`, if any.
fn sketch<'a>(options: &'a ServeOptions, name: &str) -> Option<&'a twin_sim::scenario::NodeSpec> {
    options.firmware.iter().find(|spec| spec.name() == name)
}

fn spec_elf(spec: &twin_sim::scenario::NodeSpec) -> &str {
    match spec {
        twin_sim::scenario::NodeSpec::Firmware { elf, .. } => elf,
        other => other.name(),
    }
}

/// A sketch's node, its UART on a line at `baud` (the link's).
fn build_sketch(
    spec: &twin_sim::scenario::NodeSpec,
    params: &PlantParams,
    baud: u32,
) -> Result<Box<dyn twin_sim::engine::SimNode + Send>> {
    let bus = twin_sim::scenario::BusSpec {
        name: "link".into(),
        baud,
        bits_per_char: 10,
        bit_error_rate: 0.0,
        wiring: twin_sim::scenario::WiringSpec::MultiDrop,
        medium: Default::default(),
        pwmcap: None,
    };
    let (node, _) =
        twin_sim::external::build_firmware(spec, Some(params), &bus).map_err(|source| {
            ServeError::Firmware {
                elf: spec_elf(spec).to_string(),
                source: Box::new(source),
            }
        })?;
    Ok(node)
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
    engine: &mut RtEngine,
    links: &mut Links,
    ev: Option<usize>,
    controller_network: Option<(usize, usize)>,
) -> Result<Vec<OpenLink>> {
    let mut open = Vec::new();
    let sketches: Vec<&'static str> = ["motor", "sensor"]
        .into_iter()
        .filter(|name| sketch(options, name).is_some())
        .collect();
    for (index, ((protocol, spec), name)) in specs.into_iter().zip(names).enumerate() {
        let link = engine.links.len();
        debug_assert_eq!(link, index);
        let (address, tcp) = match &spec.addr {
            LinkAddr::Tcp(addr) => {
                let local = links
                    .listen(
                        *addr,
                        link,
                        options.max_clients.map(|max| ClientLimit {
                            max,
                            room_after_idle: options.room_after_idle,
                        }),
                        options.session.allow.clone(),
                    )
                    .await
                    .map_err(|source| protocol.open_error(&spec, source))?;
                (format!("tcp://{local}"), true)
            }
            LinkAddr::Serial(path) => {
                links
                    .serial(path, spec.serial, link)
                    .await
                    .map_err(|source| protocol.open_error(&spec, source))?;
                (path.display().to_string(), false)
            }
        };
        let id = options.id;
        let (factory, shown_ids): (crate::EndpointFactory, String) =
            match (framing(protocol, &spec), ev, controller_network) {
                // Compiled firmware answers on its own UART: the link's
                // bytes go to the sketch as to a node on a bus.
                (Some(_), Some(device), _) if sketch(options, "ev1").is_some() => (
                    Box::new(move |_devices, _peer| {
                        Box::new(FirmwareEndpoint::new(
                            vec![device],
                            &[(device, id)],
                            RequestFraming::Meb,
                            tcp,
                        ))
                    }),
                    format!("{id:02}"),
                ),
                (Some(framing), Some(device), _) => {
                    let label = format!("ev1 {name}");
                    (
                        Box::new(
                            move |devices: &mut [Device], peer: &str| -> Box<dyn crate::Endpoint> {
                                // The address in force when the client came
                                // (the panel may have changed it since start).
                                let (id, map) = devices
                                    .get(device)
                                    .and_then(|d| d.address.clone())
                                    .map_or((id, None), |a| (a.id, a.meb_map));
                                let mut frontend = SlaveFrontend::new(framing, id);
                                frontend.set_meb_map(map.filter(|_| framing == Framing::Meb));
                                Box::new(SlaveEndpoint {
                                    device,
                                    frontend,
                                    name: format!("{label} {peer}"),
                                })
                            },
                        ),
                        format!("{id:02}"),
                    )
                }
                (None, _, Some((motor, light))) => (
                    Box::new({
                        let sketches = sketches.clone();
                        move |_devices: &mut [Device], _peer: &str| -> Box<dyn crate::Endpoint> {
                            let boards: Vec<(usize, u8)> = [
                                (motor, "motor", nodes::controller_network::MOTOR_ID),
                                (light, "sensor", nodes::controller_network::LIGHT_ID),
                            ]
                            .into_iter()
                            .filter(|(_, name, _)| sketches.contains(name))
                            .map(|(d, _, id)| (d, id))
                            .collect();
                            if boards.is_empty() {
                                return Box::new(NodeEndpoint::new(vec![motor, light]));
                            }
                            Box::new(FirmwareEndpoint::new(
                                vec![motor, light],
                                &boards,
                                RequestFraming::Modbus8,
                                false,
                            ))
                        }
                    }),
                    format!(
                        "{:02},{:02}",
                        nodes::controller_network::MOTOR_ID,
                        nodes::controller_network::LIGHT_ID
                    ),
                ),
                _ => return Err(ServeError::NoDevice { link: name }),
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
            twin_is_master: false,
            check: check_kind(protocol),
            partial_timeout: if tcp { options.partial_timeout } else { None },
            rate_limit: if tcp { options.rate_limit } else { None },
            idle_timeout: if tcp { options.idle_timeout } else { None },
            spec,
            factory,
        });
    }
    Ok(open)
}

/// Why the slave's address cannot change.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct CannotReaddress(pub String);

/// Gives the module's controller a new id and/or I/O map while the session
/// runs: every open connection answers at the new ones from its next
/// request (the old id gets no answer, as any other slave's), and every
/// new connection is made with them. `id` and `map` are checked already
/// ([`check_id`], [`map::parse_text`]). Returns the address now in force.
pub fn readdress(
    engine: &mut RtEngine,
    id: Option<u8>,
    map: Option<nodes::firmware::MebMap>,
) -> Result<SlaveAddress, CannotReaddress> {
    let Some(device) = engine.devices.iter().position(|d| d.address.is_some()) else {
        let why = if engine.devices.iter().any(|d| d.name == "ev1") {
            "the module's controller is compiled firmware (--firmware): its slave id and I/O map are its own"
        } else {
            "no slave of this session changes its id or map: twin serve's EV module controller does (the --modbus8 Controller_network nodes' ids are fixed)"
        };
        return Err(CannotReaddress(why.into()));
    };
    let Some(address) = engine
        .devices
        .get_mut(device)
        .and_then(|d| d.address.as_mut())
    else {
        return Err(CannotReaddress("the controller went away".into()));
    };
    if let Some(id) = id {
        address.id = id;
    }
    if let Some(map) = map {
        address.meb_map = (!map.is_default()).then_some(map);
    }
    let address = address.clone();
    for endpoint in engine.endpoints_mut() {
        if endpoint.served_device() != Some(device) {
            continue;
        }
        if let Some(f) = endpoint.frontend_mut() {
            f.set_id(address.id);
            if f.framing() == Framing::Meb {
                f.set_meb_map(address.meb_map.clone());
            }
        }
    }
    Ok(address)
}

/// Runs a session. `ready` gets the open links once they all are (the
/// command prints them and `ready`); `console` gets a sender for commands.
pub fn serve(
    options: &ServeOptions,
    ready: impl FnOnce(&[OpenLink]),
    console: impl FnOnce(Sender<Inbound>),
) -> Result<SessionOutcome> {
    let specs = parse_links(options)?;
    let names = link_names(&specs);
    let role = Serving {
        options,
        specs,
        names,
        ev: None,
        controller_network: None,
        console: Some(console),
    };
    let (outcome, ()) = session::run(&options.session, role, ready)?;
    Ok(outcome)
}
