//! Scenario files: modules, buses, nodes, masters, a set-point schedule,
//! faults and the seed, in TOML. The lab's scenarios are embedded in the binary ([`EMBEDDED`]).
//!
//! ```toml
//! name = "ev-meb"
//! seed = 1
//! duration_s = 10.0
//!
//! [[module]]
//! name = "ev1"
//! preset = "vemodule"          # plus [module.params] overrides, as in a plant parameter file
//!
//! [[bus]]
//! name = "rs485"
//! baud = 115200
//!
//! [[node]]
//! name = "ev1-controller"
//! kind = "ev-controller"       # ev-controller | motor-node | light-node | supervisor | controller-network-master
//! bus = "rs485"
//! module = "ev1"
//! id = 1
//! ```

pub mod check;
mod fault_check;
mod request_check;

pub use request_check::frame as request_frame;

use plant::PlantParams;
use plant::params::ParamsError;
use plant::toml_errors::{self, line_col};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub use crate::scenario_pwm::{
    AddressingSpec, DuplexSpec, MediumSpec, ParallelLinkSpec, PwmcapSpec,
};

/// The scenarios built into the binary: name, one-line description, TOML text.
pub const EMBEDDED: [(&str, &str, &str); 12] = [
    (
        "ev-meb",
        "the EV module's speed loop closed by a supervisor over MEB at 115200 baud (default)",
        include_str!("../../../recordings/scenarios/ev-meb.toml"),
    ),
    (
        "controller-network",
        "the Controller_network project: motor node, light-sensor node, Raspberry Pi master",
        include_str!("../../../recordings/scenarios/controller-network.toml"),
    ),
    (
        "controller-network-bad-crc-master",
        "the Controller_network scope capture: the Pi's request with a wrong CRC, ignored",
        include_str!("../../../recordings/scenarios/controller-network-bad-crc-master.toml"),
    ),
    (
        "controller-network-bad-crc-slave",
        "the Controller_network scope capture: the motor's reply with a wrong CRC, refused",
        include_str!("../../../recordings/scenarios/controller-network-bad-crc-slave.toml"),
    ),
    (
        "controller-network-illegal-address",
        "the Controller_network scope capture: a write to a register the motor lacks (02)",
        include_str!("../../../recordings/scenarios/controller-network-illegal-address.toml"),
    ),
    (
        "controller-network-illegal-value",
        "the Controller_network scope capture: a write of 120 to the motor's state (03)",
        include_str!("../../../recordings/scenarios/controller-network-illegal-value.toml"),
    ),
    (
        "controller-network-illegal-function",
        "the Controller_network scope capture: a request with function 04 (01)",
        include_str!("../../../recordings/scenarios/controller-network-illegal-function.toml"),
    ),
    (
        "ten-modules",
        "ten EV modules on one 115200-baud bus, one supervisor polling each at 10 Hz",
        include_str!("../../../recordings/scenarios/ten-modules.toml"),
    ),
    (
        "parallel-pwm-broadcast",
        "three parallel modules: the master's VEL to two slaves by PWM-capture broadcast, every 1 ms",
        include_str!("../../../recordings/scenarios/parallel-pwm-broadcast.toml"),
    ),
    (
        "parallel-pwm-designated",
        "three parallel modules: designated PWM-capture frames, answered, retransmitted on timeout",
        include_str!("../../../recordings/scenarios/parallel-pwm-designated.toml"),
    ),
    (
        "parallel-rtu-115200",
        "three parallel modules: the master's VEL to two slaves by Modbus RTU at 115200 baud",
        include_str!("../../../recordings/scenarios/parallel-rtu-115200.toml"),
    ),
    (
        "parallel-rtu-1m",
        "three parallel modules: the master's VEL to two slaves by Modbus RTU at 1 Mbit/s",
        include_str!("../../../recordings/scenarios/parallel-rtu-1m.toml"),
    ),
];

/// A whole scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    pub name: String,
    #[serde(default)]
    pub description: String,
    #[serde(default = "default_seed")]
    pub seed: u64,
    pub duration_s: f64,
    /// Plant step (s).
    #[serde(default = "default_plant_step")]
    pub plant_step_s: f64,
    /// Plant state messages per simulated second in the recording.
    #[serde(default = "default_record_hz")]
    pub record_hz: f64,
    #[serde(rename = "module", default)]
    pub modules: Vec<ModuleSpec>,
    #[serde(rename = "bus", default)]
    pub buses: Vec<BusSpec>,
    #[serde(rename = "node", default)]
    pub nodes: Vec<NodeSpec>,
    #[serde(rename = "fault", default)]
    pub faults: Vec<FaultSpec>,
    /// Frames a master sends at given times (`[[request]]`).
    #[serde(rename = "request", default, skip_serializing_if = "Vec::is_empty")]
    pub requests: Vec<RequestSpec>,
}

fn default_seed() -> u64 {
    1
}
fn default_plant_step() -> f64 {
    1e-3
}
fn default_record_hz() -> f64 {
    200.0
}

/// One EV bench module: a preset plus parameter overrides.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModuleSpec {
    pub name: String,
    #[serde(default = "default_preset")]
    pub preset: String,
    /// Overrides, in the layout of a plant parameter file.
    #[serde(default)]
    pub params: toml::Table,
}

fn default_preset() -> String {
    "vemodule".into()
}

/// Which Pi program a `controller-network-master` runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MasterProgramSpec {
    /// The handshake, then the loop that toggles the set point.
    #[default]
    Loop,
    /// The step-response program: reads both nodes and writes operational.
    StepResponse,
    /// Only the scenario's `[[request]]`s, as the project's command-line
    /// `modbus` program sent them for its oscilloscope captures.
    Requests,
}

/// How a bus is wired.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WiringSpec {
    /// Every node hears every other (RS-485 multi-drop).
    MultiDrop,
    /// The master's TX reaches every slave, every slave's TX reaches only the
    /// master (as in the Controller_network project).
    MasterSlaves,
}

/// A simulated serial bus.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusSpec {
    pub name: String,
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Bits per character: 10 for 8N1, 11 for 8E1 or 8N2.
    #[serde(default = "default_bits")]
    pub bits_per_char: u32,
    #[serde(default)]
    pub bit_error_rate: f64,
    #[serde(default = "default_wiring")]
    pub wiring: WiringSpec,
    /// `serial` (default) or `pwmcap` (the PWM-capture paper's link).
    #[serde(default, skip_serializing_if = "MediumSpec::is_serial")]
    pub medium: MediumSpec,
    /// The PWM-capture link's coding and line, for `medium = "pwmcap"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pwmcap: Option<PwmcapSpec>,
}

fn default_baud() -> u32 {
    115_200
}
fn default_bits() -> u32 {
    10
}
fn default_wiring() -> WiringSpec {
    WiringSpec::MultiDrop
}

/// Which protocol a slave or master speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ProtocolSpec {
    Meb,
    ModbusRtu,
}

/// The EV controller's light dip detector at power-up.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LightDetectorSpec {
    /// A dip is the signal below `LDR_TH`, midway between lit and shaded:
    /// the flag is seen up to about 260 rpm on the EV module.
    #[default]
    Fixed,
    /// A dip is a fall of a fifth of the swing the detector tracks: seen up
    /// to about 1800 rpm.
    Adaptive,
}

impl LightDetectorSpec {
    pub fn is_fixed(&self) -> bool {
        *self == Self::Fixed
    }
    pub fn adaptive(self) -> bool {
        self == Self::Adaptive
    }
}

/// A node on a bus.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum NodeSpec {
    /// The EV module's controller board: a slave that runs the module.
    EvController {
        name: String,
        bus: String,
        module: String,
        #[serde(default = "default_id")]
        id: u8,
        #[serde(default = "default_protocol")]
        protocol: ProtocolSpec,
        #[serde(default = "default_turnaround_ms")]
        turnaround_ms: f64,
        #[serde(default = "default_loop_ms")]
        loop_period_ms: f64,
        /// How the firmware finds the flag's dips at power-up (`VD0` LDR_ADAPT):
        /// `fixed` (the threshold midway between lit and shaded) or `adaptive`.
        #[serde(default, skip_serializing_if = "LightDetectorSpec::is_fixed")]
        light_detector: LightDetectorSpec,
    },
    /// The Controller_network motor node (id 01).
    MotorNode {
        name: String,
        bus: String,
        module: String,
        #[serde(default = "default_turnaround_ms")]
        turnaround_ms: f64,
    },
    /// The Controller_network light-sensor node (id 02), watching the same module's wheel.
    LightNode {
        name: String,
        bus: String,
        module: String,
        #[serde(default = "default_turnaround_ms")]
        turnaround_ms: f64,
    },
    /// A supervisor closing the speed loop over the bus.
    Supervisor {
        name: String,
        bus: String,
        slaves: Vec<u8>,
        #[serde(default = "default_protocol")]
        protocol: ProtocolSpec,
        #[serde(default = "default_poll_ms")]
        poll_period_ms: f64,
        #[serde(default)]
        gap_ms: f64,
        #[serde(default = "default_timeout_ms")]
        reply_timeout_ms: f64,
        #[serde(default = "default_retries")]
        retries: u32,
        kp: f64,
        ki: f64,
        /// Close the loop on the light-sensor rpm instead of the hall rpm.
        #[serde(default)]
        use_light_rpm: bool,
        /// `[time_s, rpm]` steps.
        set_points: Vec<[f64; 2]>,
    },
    /// The Controller_network project's Raspberry Pi master. Scenarios
    /// written before it had this name call it `seed002-master`.
    #[serde(alias = "seed002-master")]
    ControllerNetworkMaster {
        name: String,
        bus: String,
        /// Reply timeout (ms); the original has none and hangs on a lost reply.
        #[serde(default)]
        reply_timeout_ms: Option<f64>,
        /// Which of the project's Pi programs runs: `loop` (its `main.cpp`)
        /// or `step-response` (its step-response program).
        #[serde(default)]
        program: MasterProgramSpec,
        /// When the program starts (s): the Pi starts after the Nanos have
        /// booted. Unset, it is [`Scenario::masters_start_s`]: the longest
        /// `boot_ms` of the scenario's firmware nodes and [`SETUP_S`] (0
        /// without any), filled in by [`Scenario::parse`].
        #[serde(default, skip_serializing_if = "Option::is_none")]
        start_s: Option<f64>,
    },
    /// The master of parallel modules: closes the speed loop on its own
    /// module's wheel and sends the resulting VEL to the slave modules.
    ParallelMaster {
        name: String,
        bus: String,
        module: String,
        link: ParallelLinkSpec,
        slaves: Vec<u8>,
        /// PI update and send period (the paper's retransmission period).
        #[serde(default = "default_update_ms")]
        update_period_ms: f64,
        #[serde(default = "default_pwm_timeout_ms")]
        reply_timeout_ms: f64,
        #[serde(default = "default_retries")]
        retries: u32,
        kp: f64,
        ki: f64,
        set_points: Vec<[f64; 2]>,
        #[serde(default = "default_loop_ms")]
        loop_period_ms: f64,
        #[serde(default)]
        turnaround_ms: f64,
    },
    /// Compiled firmware (an Arduino sketch's ELF) run instruction by
    /// instruction in simavr, wired to its module's plant by a wiring map.
    /// Only `twin-avr`, the GPL build of the twin that links simavr, runs it.
    Firmware {
        name: String,
        bus: String,
        module: String,
        /// The sketch's ELF file (relative to the working directory).
        elf: String,
        /// Its wiring map: `ev-controller` (the map `twin-avr` ships for
        /// our EV controller sketch) or a TOML file.
        wiring: String,
        /// The microcontroller the ELF must be built for.
        #[serde(default = "default_mcu")]
        mcu: String,
        /// Its clock (Hz).
        #[serde(default = "default_clock_hz")]
        clock_hz: u32,
        /// From power-up to the sketch's first instruction (ms): the reset
        /// and the bootloader's wait, during which the core does not run and
        /// its UART hears nothing. An Arduino Nano with optiboot takes
        /// [`NANO_BOOT_MS`]. 0 (the default, so recordings made before it
        /// replay the same): the sketch starts at once.
        #[serde(default, skip_serializing_if = "is_zero")]
        boot_ms: f64,
    },
    /// A slave module's controller on a PWM-capture link.
    PwmSlave {
        name: String,
        bus: String,
        module: String,
        id: u8,
        addressing: AddressingSpec,
        #[serde(default = "default_loop_ms")]
        loop_period_ms: f64,
        #[serde(default)]
        turnaround_ms: f64,
    },
}

fn default_update_ms() -> f64 {
    1.0
}
fn default_pwm_timeout_ms() -> f64 {
    0.5
}

/// An Arduino Nano's start-up after a reset, ms: 65 ms of start-up delay
/// its fuses set (low fuse 0xFF: a crystal, 16K cycles + 65 ms), then
/// optiboot's 1 s watchdog (`watchdogConfig(WATCHDOG_1S)` in its `main`),
/// which waits for a programmer and, hearing none, resets into the sketch.
/// A Nano resets when the port to it is opened (DTR), as on the bench.
pub const NANO_BOOT_MS: f64 = 1065.0;

/// What a master waits beyond the boards' boot for their sketches to set
/// themselves up (s). The sketch's start-up runs as cycles after its boot:
/// the C runtime clearing RAM, the core's `init()`, then `setup()` up to
/// `Serial.begin`, under a millisecond for the Nanos here, while a master
/// sending at the boot's last instant loses its first bytes. 100 ms leaves
/// room for a `setup()` that waits a little, as many do.
pub const SETUP_S: f64 = 0.1;

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn default_mcu() -> String {
    "atmega328p".into()
}
fn default_clock_hz() -> u32 {
    16_000_000
}

fn default_id() -> u8 {
    1
}
fn default_protocol() -> ProtocolSpec {
    ProtocolSpec::Meb
}
fn default_turnaround_ms() -> f64 {
    1.0
}
fn default_loop_ms() -> f64 {
    1.0
}
fn default_poll_ms() -> f64 {
    10.0
}
fn default_timeout_ms() -> f64 {
    100.0
}
fn default_retries() -> u32 {
    2
}

/// A master polling an id that no node on its bus has: it can only time out.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnansweredId {
    pub master: String,
    pub bus: String,
    pub id: u8,
    /// The slave ids the bus has.
    pub ids_there: Vec<u8>,
}

impl std::fmt::Display for UnansweredId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let there: Vec<String> = self.ids_there.iter().map(u8::to_string).collect();
        let there = if there.is_empty() {
            "none".to_string()
        } else {
            there.join(", ")
        };
        write!(
            f,
            "no node on bus {} has id {} (ids there: {there}): `{}` polls it and can only time out",
            self.bus, self.id, self.master
        )
    }
}

impl Scenario {
    /// The longest boot of the scenario's firmware nodes (s): when every
    /// board runs its sketch.
    pub fn boards_booted_s(&self) -> f64 {
        self.nodes
            .iter()
            .filter_map(|n| match n {
                NodeSpec::Firmware { boot_ms, .. } => Some(boot_ms / 1000.0),
                _ => None,
            })
            .fold(0.0, f64::max)
    }

    /// When a master whose start is unset starts (s): once every board has
    /// booted and set itself up, as on the bench, where the Raspberry Pi
    /// boots long after the Nanos. 0 without boards that boot, so scenarios
    /// without them run as they always did.
    pub fn masters_start_s(&self) -> f64 {
        let booted = self.boards_booted_s();
        if booted > 0.0 { booted + SETUP_S } else { 0.0 }
    }

    fn start_masters_after_boot(&mut self) {
        let start = self.masters_start_s();
        for node in &mut self.nodes {
            if let NodeSpec::ControllerNetworkMaster { start_s, .. } = node {
                start_s.get_or_insert(start);
            }
        }
    }

    /// Every id a master polls that no slave on its bus has. A bus with a
    /// compiled sketch is left out: the sketch's id is in its code.
    pub fn unanswered_ids(&self) -> Vec<UnansweredId> {
        let mut found = Vec::new();
        for master in &self.nodes {
            let slaves = match master {
                NodeSpec::Supervisor { slaves, .. } | NodeSpec::ParallelMaster { slaves, .. } => {
                    slaves
                }
                _ => continue,
            };
            let on_bus = self.nodes.iter().filter(|n| n.bus() == master.bus());
            let mut ids_there = Vec::new();
            for node in on_bus {
                match node {
                    NodeSpec::EvController { id, .. } | NodeSpec::PwmSlave { id, .. } => {
                        ids_there.push(*id);
                    }
                    NodeSpec::MotorNode { .. } => {
                        ids_there.push(nodes::controller_network::MOTOR_ID)
                    }
                    NodeSpec::LightNode { .. } => {
                        ids_there.push(nodes::controller_network::LIGHT_ID)
                    }
                    _ => {}
                }
            }
            let has_sketch = self
                .nodes
                .iter()
                .any(|n| n.bus() == master.bus() && matches!(n, NodeSpec::Firmware { .. }));
            if has_sketch {
                continue;
            }
            ids_there.sort_unstable();
            ids_there.dedup();
            for &id in slaves {
                if !ids_there.contains(&id) {
                    found.push(UnansweredId {
                        master: master.name().to_string(),
                        bus: master.bus().to_string(),
                        id,
                        ids_there: ids_there.clone(),
                    });
                }
            }
        }
        found
    }
}

impl NodeSpec {
    pub fn name(&self) -> &str {
        match self {
            NodeSpec::EvController { name, .. }
            | NodeSpec::MotorNode { name, .. }
            | NodeSpec::LightNode { name, .. }
            | NodeSpec::Supervisor { name, .. }
            | NodeSpec::ControllerNetworkMaster { name, .. }
            | NodeSpec::ParallelMaster { name, .. }
            | NodeSpec::PwmSlave { name, .. }
            | NodeSpec::Firmware { name, .. } => name,
        }
    }
    pub fn bus(&self) -> &str {
        match self {
            NodeSpec::EvController { bus, .. }
            | NodeSpec::MotorNode { bus, .. }
            | NodeSpec::LightNode { bus, .. }
            | NodeSpec::Supervisor { bus, .. }
            | NodeSpec::ControllerNetworkMaster { bus, .. }
            | NodeSpec::ParallelMaster { bus, .. }
            | NodeSpec::PwmSlave { bus, .. }
            | NodeSpec::Firmware { bus, .. } => bus,
        }
    }
    pub fn module(&self) -> Option<&str> {
        match self {
            NodeSpec::EvController { module, .. }
            | NodeSpec::MotorNode { module, .. }
            | NodeSpec::LightNode { module, .. }
            | NodeSpec::ParallelMaster { module, .. }
            | NodeSpec::PwmSlave { module, .. }
            | NodeSpec::Firmware { module, .. } => Some(module),
            _ => None,
        }
    }
}

/// A frame a master sends at a given time, besides its program's polls
/// (or, with `program = "requests"`, instead of them).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RequestSpec {
    /// The master that sends it (a `controller-network-master`).
    pub node: String,
    /// When (s from the start); a transaction in flight is finished first.
    pub at_s: f64,
    /// The frame before its check bytes, in hex as a check suite's `send`:
    /// id, function, address, value (`"01 06 0001 0080"`).
    pub send: String,
    /// `bad` sends it with a wrong CRC (the right one plus one).
    #[serde(default, skip_serializing_if = "CrcSpec::is_good")]
    pub crc: CrcSpec,
}

/// A scripted request's check bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CrcSpec {
    #[default]
    Good,
    Bad,
}

impl CrcSpec {
    pub fn is_good(&self) -> bool {
        *self == Self::Good
    }
}

/// A fault switched on for a time window.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultSpec {
    pub node: String,
    pub kind: FaultKind,
    pub from_s: f64,
    pub until_s: f64,
    /// For `delay-reply`.
    #[serde(default)]
    pub delay_ms: f64,
    /// For `exception`: 1 illegal function / command, 2 illegal address,
    /// 3 illegal data, 4 device failure (MEB `ER` codes alike).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub code: Option<u8>,
    /// For `wrong-id`: the id the replies carry (unset: the node's own + 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<u8>,
    /// For `split-reply`: quiet line between the two writes (ms of bus time).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gap_ms: Option<f64>,
    /// For `split-reply`: bytes in the first write (unset: half the reply).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub split_at: Option<u16>,
    /// For `junk`: these bytes with every reply...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub junk: Option<Vec<u8>>,
    /// ... or this many, drawn from the scenario's seed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub junk_count: Option<u32>,
    /// For `junk`: `before` (default) or `after` each reply.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub junk_place: Option<JunkPlaceSpec>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FaultKind {
    /// Replies carry a wrong FCS/CRC.
    BadCheck,
    /// Replies are not sent.
    DropReply,
    /// Replies are sent `delay_ms` late.
    DelayReply,
    /// The node neither answers nor sends anything.
    Silent,
    /// Every request refused with exception / `ER` `code`.
    Exception,
    /// Replies carry another slave's id (`id`), their check good.
    WrongId,
    /// Replies go in two writes, `gap_ms` of quiet line apart.
    SplitReply,
    /// Junk bytes go with every reply.
    Junk,
}

impl FaultKind {
    /// The kind as a scenario file writes it.
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::BadCheck => "bad-check",
            FaultKind::DropReply => "drop-reply",
            FaultKind::DelayReply => "delay-reply",
            FaultKind::Silent => "silent",
            FaultKind::Exception => "exception",
            FaultKind::WrongId => "wrong-id",
            FaultKind::SplitReply => "split-reply",
            FaultKind::Junk => "junk",
        }
    }
}

/// Where a `junk` fault's bytes go.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum JunkPlaceSpec {
    /// Just before each reply.
    #[default]
    Before,
    /// Just after each reply (between it and the master's next request).
    After,
}

/// The Controller_network master's old kind name, still read (`serde(alias)`).
const LEGACY_MASTER_KIND: &str = "seed002-master"; // the serde alias above

/// Why a scenario was refused, in the file's words: its name, the line
/// (and column) and the field at fault.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// Text that does not parse, fit the scenario's fields, or hold
    /// together; `place` is `:LINE` or `:LINE:COL` where known.
    #[error("{origin}{place}: {message}")]
    At {
        origin: String,
        place: String,
        message: String,
    },
    /// A module's `params` the plant refused (they name their own line).
    #[error("{error} (in the params of module `{module}`)")]
    ModuleParams { module: String, error: ParamsError },
    #[error("no scenario `{name}`: not a file, and the embedded ones are {embedded}")]
    NotFound { name: String, embedded: String },
    #[error("cannot read {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{0} is a recording, not a scenario: replay it with `twin replay {0}`, \
         or look at it with `twin view {0}`",
        path.display()
    )]
    Recording { path: PathBuf },
    #[error(
        "{} is not a scenario: a scenario is a TOML text file, and this one is not text",
        path.display()
    )]
    NotText { path: PathBuf },
    #[error("module `{module}`: unknown preset `{preset}`")]
    UnknownPreset { module: String, preset: String },
    /// A module's params as the scenario holds them, read again.
    #[error(transparent)]
    Params(#[from] ParamsError),
    #[error(transparent)]
    Toml(#[from] toml::ser::Error),
}

type Result<T, E = ScenarioError> = std::result::Result<T, E>;

impl Scenario {
    /// Parse scenario text; `origin` names it in errors, which give the
    /// line of the key at fault (inside a `[[node]]` or a module's `params`
    /// too) and say what a value should be in TOML's words.
    pub fn parse(text: &str, origin: &str) -> Result<Self> {
        let place = |span: Option<std::ops::Range<usize>>| {
            span.map_or_else(String::new, |s| {
                let (l, c) = line_col(text, s.start);
                format!(":{l}:{c}")
            })
        };
        let root = toml_errors::parse(text).map_err(|e| ScenarioError::At {
            origin: origin.to_string(),
            place: place(e.span),
            message: e.message,
        })?;
        let scenario: Scenario = toml_errors::deserialize(&root).map_err(|e| {
            // serde lists aliases among the kinds it expected; the old name
            // of a kind is still read but not offered.
            let message = clip_quoted(&e.message.replace(&format!(", `{LEGACY_MASTER_KIND}`"), ""));
            // The key at fault, unless the path ends at a whole table (a
            // `[[node]]`), which the line already points at.
            let field = e.path.rsplit('.').next().unwrap_or_default();
            let message = if field.is_empty()
                || field.ends_with(']')
                || message.contains(&format!("`{field}`"))
            {
                message
            } else {
                format!("`{field}`: {message}")
            };
            ScenarioError::At {
                origin: origin.to_string(),
                place: place(e.span),
                message,
            }
        })?;
        let mut scenario = scenario;
        scenario.start_masters_after_boot();
        scenario.check_module_params(&root, text, origin)?;
        scenario.validate().map_err(|(field, msg)| {
            // A field of one node or bus is found in the table naming it.
            let place = match field.split_once('@') {
                Some((key, owner)) => locate(&root, text, key, Some(owner)),
                None => locate(&root, text, &field, None),
            };
            let field = field.split('@').next().unwrap_or_default().to_string();
            let place = place.map_or_else(String::new, |l| format!(":{l}"));
            ScenarioError::At {
                origin: origin.to_string(),
                place,
                message: format!("`{field}` {msg}"),
            }
        })?;
        Ok(scenario)
    }

    /// Every module's preset and `params` read as they will be when the
    /// module is built, with the lines of the scenario file itself.
    fn check_module_params(
        &self,
        root: &toml::Spanned<toml::de::DeValue<'_>>,
        text: &str,
        origin: &str,
    ) -> Result<()> {
        let modules = match root.get_ref() {
            toml::de::DeValue::Table(t) => t.get("module"),
            _ => None,
        };
        let tables = match modules.map(toml::Spanned::get_ref) {
            Some(toml::de::DeValue::Array(a)) => a.as_ref(),
            _ => &[],
        };
        for (module, table) in self.modules.iter().zip(tables) {
            let Some(base) = PlantParams::preset(&module.preset) else {
                let line = toml_errors::span_of(table, "preset")
                    .map_or_else(String::new, |s| format!(":{}", line_col(text, s.start).0));
                return Err(ScenarioError::At {
                    origin: origin.to_string(),
                    place: line,
                    message: format!(
                        "`preset` of module `{}`: unknown preset `{}`; the presets are {}",
                        module.name,
                        module.preset,
                        plant::params::PRESETS.join(", ")
                    ),
                });
            };
            let params = match table.get_ref() {
                toml::de::DeValue::Table(t) => t.get("params"),
                _ => None,
            };
            if let Some(params) = params {
                PlantParams::from_toml_value(params, text, Path::new(origin), &base).map_err(
                    |error| ScenarioError::ModuleParams {
                        module: module.name.clone(),
                        error,
                    },
                )?;
            }
        }
        Ok(())
    }

    /// An embedded scenario by name, a scenario file by path.
    pub fn load(name_or_path: &str) -> Result<Self> {
        if let Some((name, _, text)) = EMBEDDED.iter().find(|(n, _, _)| *n == name_or_path) {
            return Self::parse(text, &format!("embedded scenario {name}"));
        }
        let path = PathBuf::from(name_or_path);
        if !path.exists() {
            let names: Vec<_> = EMBEDDED.iter().map(|(n, _, _)| *n).collect();
            return Err(ScenarioError::NotFound {
                name: name_or_path.to_string(),
                embedded: names.join(", "),
            });
        }
        let bytes = match std::fs::read(&path) {
            Ok(bytes) => bytes,
            Err(source) => return Err(ScenarioError::Read { path, source }),
        };
        if bytes.starts_with(MCAP_MAGIC) {
            return Err(ScenarioError::Recording { path });
        }
        let Ok(text) = String::from_utf8(bytes) else {
            return Err(ScenarioError::NotText { path });
        };
        Self::parse(&text, &path.display().to_string())
    }

    /// The plant parameters of a module: its preset with its overrides.
    pub fn module_params(&self, module: &ModuleSpec) -> Result<PlantParams> {
        let Some(base) = PlantParams::preset(&module.preset) else {
            return Err(ScenarioError::UnknownPreset {
                module: module.name.clone(),
                preset: module.preset.clone(),
            });
        };
        let text = toml::to_string(&module.params)?;
        let origin = format!("scenario {}, module `{}` params", self.name, module.name);
        Ok(PlantParams::from_toml(&text, Path::new(&origin), &base)?)
    }

    fn validate(&self) -> std::result::Result<(), (String, String)> {
        let named = std::iter::once(&self.name)
            .chain(self.modules.iter().map(|m| &m.name))
            .chain(self.buses.iter().map(|b| &b.name));
        for name in named
            .map(String::as_str)
            .chain(self.nodes.iter().map(NodeSpec::name))
        {
            check_name(name).map_err(|why| (format!("name@{name}"), why))?;
        }
        let mut names = std::collections::BTreeSet::new();
        for n in &self.nodes {
            if !names.insert(n.name()) {
                return Err(("name".into(), format!("`{}` names two nodes", n.name())));
            }
            if !self.buses.iter().any(|b| b.name == n.bus()) {
                return Err((
                    format!("bus@{}", n.name()),
                    format!("`{}` of node `{}` is not a declared bus", n.bus(), n.name()),
                ));
            }
            if let Some(m) = n.module()
                && !self.modules.iter().any(|x| x.name == m)
            {
                return Err((
                    format!("module@{}", n.name()),
                    format!("`{m}` of node `{}` is not a declared module", n.name()),
                ));
            }
        }
        for b in &self.buses {
            if b.baud == 0 || !crate_time_ticks().is_multiple_of(u64::from(b.baud)) {
                return Err((
                    "baud".into(),
                    format!("{} does not divide 72 GHz: use a standard rate", b.baud),
                ));
            }
            if !(0.0..0.5).contains(&b.bit_error_rate) {
                return Err(("bit_error_rate".into(), "must be in 0..0.5".into()));
            }
        }
        self.validate_pwm()?;
        for f in &self.faults {
            if !names.contains(f.node.as_str()) {
                return Err((
                    "node".into(),
                    format!("fault on `{}`, which is not a declared node", f.node),
                ));
            }
            if f.until_s < f.from_s {
                return Err(("until_s".into(), "must not be before from_s".into()));
            }
        }
        fault_check::check(self)?;
        request_check::check(self)?;
        check::check(self)
    }
}

impl Scenario {
    /// PWM-capture buses and the nodes on them. Errors name the field as
    /// `field@name`: the field after the line that names its bus or node.
    fn validate_pwm(&self) -> std::result::Result<(), (String, String)> {
        for b in &self.buses {
            let at = |field: &str| format!("{field}@{}", b.name);
            match (b.medium, &b.pwmcap) {
                (MediumSpec::Serial, Some(_)) => {
                    return Err((
                        at("medium"),
                        format!(
                            "of bus `{}` is serial, but it has a [bus.pwmcap] table: set medium = \"pwmcap\"",
                            b.name
                        ),
                    ));
                }
                (MediumSpec::Pwmcap, spec) => {
                    let spec = spec.clone().unwrap_or_default();
                    spec.bus_config(0, Some(0)).map_err(|(f, m)| (at(&f), m))?;
                }
                (MediumSpec::Serial, None) => {}
            }
        }
        for n in &self.nodes {
            let Some(bus) = self.buses.iter().find(|b| b.name == n.bus()) else {
                continue;
            };
            let pwm_node = match n {
                NodeSpec::PwmSlave { .. } => true,
                NodeSpec::ParallelMaster { link, .. } => link.is_pwm(),
                _ => false,
            };
            let pwm_bus = bus.medium == MediumSpec::Pwmcap;
            if pwm_node != pwm_bus {
                let what = if pwm_bus {
                    "is a PWM-capture link, and this node speaks a serial protocol"
                } else {
                    "is a serial bus, and this node speaks PWM-capture"
                };
                return Err((
                    format!("bus@{}", n.name()),
                    format!("`{}` of node `{}` {what}", bus.name, n.name()),
                ));
            }
            match n {
                NodeSpec::PwmSlave { id, .. } if *id == 0 || *id > 15 => {
                    return Err((
                        format!("id@{}", n.name()),
                        format!(
                            "{id} of node `{}`: a PWM slave id is 1 to 15 (the status nibble)",
                            n.name()
                        ),
                    ));
                }
                NodeSpec::ParallelMaster {
                    slaves,
                    update_period_ms,
                    reply_timeout_ms,
                    ..
                } => {
                    let max = if pwm_bus { 15 } else { 247 };
                    if let Some(id) = slaves.iter().find(|&&id| id == 0 || id > max) {
                        return Err((
                            format!("slaves@{}", n.name()),
                            format!(
                                "of node `{}` holds {id}: ids on this link are 1 to {max}",
                                n.name()
                            ),
                        ));
                    }
                    if slaves.is_empty() {
                        return Err((
                            format!("slaves@{}", n.name()),
                            "must name at least one slave id".into(),
                        ));
                    }
                    for (field, v) in [
                        ("update_period_ms", update_period_ms),
                        ("reply_timeout_ms", reply_timeout_ms),
                    ] {
                        if !(v.is_finite() && *v > 0.0) {
                            return Err((
                                format!("{field}@{}", n.name()),
                                format!("must be a positive number, got {v}"),
                            ));
                        }
                    }
                }
                _ => {}
            }
        }
        // Faults wrap a node's bytes (bad checks, dropped replies): PWM frames
        // carry no check to spoil, and the link's noise is the way to break them.
        for f in &self.faults {
            let pwm = self.nodes.iter().any(|n| {
                n.name() == f.node
                    && matches!(
                        n,
                        NodeSpec::PwmSlave { .. } | NodeSpec::ParallelMaster { .. }
                    )
            });
            if pwm {
                return Err((
                    "node".into(),
                    format!(
                        "fault on `{}`: faults apply to serial nodes; on a PWM-capture link raise the line's noise_mv or cable_m",
                        f.node
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// The line setting `key = …` in the block (up to the next `[[…]]`) of a
/// line that sets `name = "owner"`; else that name line. A module and a node
/// may share a name: the block that has the key is the one meant.
/// `message` with every backquoted value longer than a line cut to its
/// start and its length: a file's wrong value is quoted back, and a value of
/// a megabyte must not become a message of a megabyte.
fn clip_quoted(message: &str) -> String {
    const LONGEST: usize = 60;
    let mut out = String::with_capacity(message.len().min(400));
    for (i, part) in message.split('`').enumerate() {
        if i > 0 {
            out.push('`');
        }
        let chars = part.chars().count();
        if i % 2 == 1 && chars > LONGEST {
            out.extend(part.chars().take(20));
            out.push_str(&format!("… ({chars} characters)"));
        } else {
            out.push_str(part);
        }
    }
    out
}

/// How an MCAP file (a recording) begins.
const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// The longest name a scenario's nodes, buses and modules may have: it
/// goes into topics, file names, monitor lines and the panel.
pub const MAX_NAME_LEN: usize = 64;

/// Why `name` cannot name a scenario, node, bus or module (of a scenario or
/// of a class file): 1 to [`MAX_NAME_LEN`] ASCII letters, digits, `-` or
/// `_`, starting with a letter or digit.
pub fn check_name(name: &str) -> std::result::Result<(), String> {
    const RULE: &str =
        "a name is 1 to 64 letters, digits, `-` or `_`, starting with a letter or digit";
    let chars = name.chars().count();
    if chars == 0 {
        return Err(format!("is empty: {RULE}"));
    }
    if chars > MAX_NAME_LEN {
        let start: String = name.chars().take(20).collect();
        return Err(format!("\"{start}…\" is {chars} characters long: {RULE}"));
    }
    let allowed = |c: char| c.is_ascii_alphanumeric() || matches!(c, '-' | '_');
    let shown = |c: char| match c {
        ' ' => "a space".to_string(),
        c if c.is_control() || c.is_whitespace() => format!("U+{:04X}", u32::from(c)),
        c => format!("`{c}`"),
    };
    if let Some(bad) = name.chars().find(|&c| !allowed(c)) {
        let name = name.escape_default();
        return Err(format!("\"{name}\" holds {}: {RULE}", shown(bad)));
    }
    if let Some(first) = name.chars().next().filter(|c| !c.is_ascii_alphanumeric()) {
        return Err(format!("\"{name}\" starts with {}: {RULE}", shown(first)));
    }
    Ok(())
}

/// The owner of a field of the `[[fault]]` at an index: `fault#0` the first.
pub(crate) const FAULT_OWNER: &str = "fault#";
/// The owner of a field of the `[[request]]` at an index: `request#0` the first.
pub(crate) const REQUEST_OWNER: &str = "request#";

/// The line of `key` where the file sets it, from the parsed file's spans:
/// with an `owner`, in a table whose `name` is `owner` or in one of its
/// sub-tables (`[bus.pwmcap]`), else at its name line; without, the first
/// table, in file order, that sets it.
fn locate(
    root: &toml::Spanned<toml::de::DeValue<'_>>,
    text: &str,
    key: &str,
    owner: Option<&str>,
) -> Option<usize> {
    let mut tables = Vec::new();
    tables_in(root, &mut tables);
    let named = |table: &toml::Spanned<toml::de::DeValue<'_>>, owner: &str| match table.get_ref() {
        toml::de::DeValue::Table(t) => t.get("name").is_some_and(
            |n| matches!(n.get_ref(), toml::de::DeValue::String(name) if name == owner),
        ),
        _ => false,
    };
    let first_of = |within: &[&toml::Spanned<toml::de::DeValue<'_>>], key: &str| {
        within
            .iter()
            .filter_map(|t| setting(t, key))
            .map(|span| span.start)
            .min()
    };
    let offset = match owner {
        Some(owner) if owner.starts_with(FAULT_OWNER) || owner.starts_with(REQUEST_OWNER) => {
            // `fault#3`: the fourth `[[fault]]`; `request#0`: the first `[[request]]`.
            let (array, index) = owner.split_once('#')?;
            let index: usize = index.parse().ok()?;
            let entry = match root.get_ref() {
                toml::de::DeValue::Table(t) => match t.get(array)?.get_ref() {
                    toml::de::DeValue::Array(a) => a.get(index)?,
                    _ => return None,
                },
                _ => return None,
            };
            setting(entry, key)
                .or_else(|| setting(entry, "kind"))
                .or_else(|| setting(entry, "node"))
                .map(|span| span.start)
        }
        None => first_of(&tables, key),
        Some(owner) => {
            let owners: Vec<_> = tables.iter().copied().filter(|t| named(t, owner)).collect();
            let mut within = Vec::new();
            for table in &owners {
                tables_in(table, &mut within);
            }
            // A module and a node may share a name: the table that sets the key.
            first_of(&within, key).or_else(|| first_of(&owners, "name"))
        }
    };
    offset.map(|offset| line_col(text, offset).0)
}

/// The span of `key = value` in `table`, a value and not a table (the root
/// table's `node` key is every `[[node]]`, which is not where a field is set).
fn setting(
    table: &toml::Spanned<toml::de::DeValue<'_>>,
    key: &str,
) -> Option<std::ops::Range<usize>> {
    use toml::de::DeValue;
    let DeValue::Table(t) = table.get_ref() else {
        return None;
    };
    t.iter()
        .find(|(k, v)| {
            let nested = match v.get_ref() {
                DeValue::Table(_) => true,
                DeValue::Array(a) => a.iter().any(|e| matches!(e.get_ref(), DeValue::Table(_))),
                _ => false,
            };
            k.get_ref() == key && !nested
        })
        .map(|(k, _)| k.span())
}

/// Every table in `value`, itself included, arrays of tables entered.
fn tables_in<'v, 'a>(
    value: &'v toml::Spanned<toml::de::DeValue<'a>>,
    out: &mut Vec<&'v toml::Spanned<toml::de::DeValue<'a>>>,
) {
    match value.get_ref() {
        toml::de::DeValue::Table(t) => {
            out.push(value);
            for (_, child) in t.iter() {
                tables_in(child, out);
            }
        }
        toml::de::DeValue::Array(a) => {
            for child in a.iter() {
                tables_in(child, out);
            }
        }
        _ => {}
    }
}

fn crate_time_ticks() -> u64 {
    protocols::time::TICKS_PER_SECOND
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_scenarios_parse() {
        for (name, _, _) in EMBEDDED {
            let s = Scenario::load(name).expect(name);
            assert_eq!(s.name, name);
            for m in &s.modules {
                s.module_params(m).expect("module params");
            }
        }
    }

    #[test]
    fn errors_name_the_line_and_field() {
        let text = "name = \"x\"\nduration_s = 1.0\n[[bus]]\nname = \"b\"\nbaud = 115200\n[[node]]\nkind = \"ev-controller\"\nname = \"n\"\nbus = \"nowhere\"\nmodule = \"m\"\n";
        let e = Scenario::parse(text, "s.toml").unwrap_err().to_string();
        assert!(e.starts_with("s.toml:9: `bus`"), "{e}");
        let text = "name = \"x\"\nduration_s = \"long\"\n";
        let e = Scenario::parse(text, "s.toml").unwrap_err().to_string();
        assert!(e.starts_with("s.toml:2:"), "{e}");
        let text = "name = \"x\"\nduration_s = 1.0\n[[bus]]\nname = \"b\"\nbaud = 115201\n";
        let e = Scenario::parse(text, "s.toml").unwrap_err().to_string();
        assert!(e.starts_with("s.toml:5: `baud`"), "{e}");
        // Found where the file sets it, not where its text first appears (a
        // multi-line description quoting a bus's settings).
        let text = "name = \"x\"\ndescription = \"\"\"\nbaud = 9600\n\"\"\"\nduration_s = 1.0\n\
                    [[bus]]\nname = \"b\"\nbaud = 115201\n";
        let e = Scenario::parse(text, "s.toml").unwrap_err().to_string();
        assert!(e.starts_with("s.toml:8: `baud`"), "{e}");
        // A module and a node of one name: the node's table sets the key.
        let text = "name = \"x\"\nduration_s = 1.0\n[[module]]\nname = \"ev1\"\n[[bus]]\n\
                    name = \"b\"\nbaud = 115200\n[[node]]\nkind = \"ev-controller\"\n\
                    name = \"ev1\"\nbus = \"nowhere\"\nmodule = \"ev1\"\n";
        let e = Scenario::parse(text, "s.toml").unwrap_err().to_string();
        assert!(e.starts_with("s.toml:11: `bus`"), "{e}");
    }

    /// The embedded ev-meb scenario with `from` replaced by `to` (once).
    fn ev_meb_with(from: &str, to: &str) -> String {
        let (_, _, text) = EMBEDDED[0];
        assert!(text.contains(from), "ev-meb has `{from}`");
        text.replacen(from, to, 1)
    }

    fn line_of(text: &str, needle: &str) -> usize {
        text.lines().position(|l| l.contains(needle)).expect(needle) + 1
    }

    #[test]
    fn a_typo_in_a_node_points_at_its_line_not_the_node_header() {
        // An unknown key: serde reads a node's table whole before its `kind`.
        let text = ev_meb_with("kp = ", "kpp = ");
        let e = Scenario::parse(&text, "s.toml").unwrap_err().to_string();
        let line = line_of(&text, "kpp = ");
        assert!(e.starts_with(&format!("s.toml:{line}:")), "{e}");
        assert!(e.contains("unknown field `kpp`"), "{e}");
        // A value of the wrong type.
        let text = ev_meb_with("ki = ", "ki = \"fast\" #");
        let e = Scenario::parse(&text, "s.toml").unwrap_err().to_string();
        let line = line_of(&text, "ki = \"fast\"");
        assert_eq!(
            e,
            format!("s.toml:{line}:1: `ki`: expected a number, found the string \"fast\"")
        );
        // An integer out of range.
        let text = ev_meb_with("id = 1", "id = 300");
        let e = Scenario::parse(&text, "s.toml").unwrap_err().to_string();
        let line = line_of(&text, "id = 300");
        assert_eq!(
            e,
            format!("s.toml:{line}:1: `id`: expected an integer from 0 to 255, got 300")
        );
    }

    #[test]
    fn a_bad_item_of_a_list_points_at_the_list_not_a_key_with_the_same_value() {
        // `set_points` wants [time, rpm] pairs; its 0.45 is also `kp`'s value.
        let text = ev_meb_with("set_points = [", "set_points = [0.45, 1000.0] #");
        let e = Scenario::parse(&text, "s.toml").unwrap_err().to_string();
        let line = line_of(&text, "set_points = [0.45");
        assert_ne!(line, line_of(&text, "kp = 0.45"));
        assert_eq!(
            e,
            format!("s.toml:{line}:1: `set_points`: expected an array of length 2, found 0.45")
        );
    }

    #[test]
    fn an_undeclared_bus_points_at_the_node_that_names_it() {
        // The second node's bus, not the first `bus =` line of the file.
        let text = ev_meb_with("bus = \"rs485\"\nslaves", "bus = \"rs458\"\nslaves");
        let e = Scenario::parse(&text, "s.toml").unwrap_err().to_string();
        let line = line_of(&text, "rs458");
        assert!(
            e.starts_with(&format!("s.toml:{line}: `bus` `rs458`")),
            "{e}"
        );
    }

    #[test]
    fn type_errors_are_in_toml_words() {
        let text = "name = \"x\"\nduration_s = \"long\"\n";
        let e = Scenario::parse(text, "s.toml").unwrap_err().to_string();
        assert_eq!(
            e,
            "s.toml:2:14: `duration_s`: expected a number, found the string \"long\""
        );
        let text = "name = \"x\"\nduration_s = 1.0\n[[bus]]\nname = \"b\"\nbaud = 9600.5\n";
        let e = Scenario::parse(text, "s.toml").unwrap_err().to_string();
        assert_eq!(
            e,
            "s.toml:5:8: `baud`: expected an integer of 0 or more, found 9600.5"
        );
        for rust in ["f64", "u32", "u8", "struct", "enum"] {
            assert!(!e.contains(rust), "{e}");
        }
    }

    #[test]
    fn a_file_that_is_no_scenario_is_told_apart_by_what_it_is() {
        let dir = std::env::temp_dir().join(format!("twin-sim-load-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let recording = dir.join("run.mcap");
        std::fs::write(&recording, [MCAP_MAGIC, b"rest"].concat()).unwrap();
        let e = Scenario::load(&recording.display().to_string()).unwrap_err();
        assert!(matches!(e, ScenarioError::Recording { .. }), "{e:?}");
        let shown = recording.display();
        assert_eq!(
            e.to_string(),
            format!(
                "{shown} is a recording, not a scenario: replay it with `twin replay {shown}`, \
                 or look at it with `twin view {shown}`"
            )
        );
        let binary = dir.join("blob.toml");
        std::fs::write(&binary, [0xff, 0xfe, 0x00]).unwrap();
        let e = Scenario::load(&binary.display().to_string()).unwrap_err();
        assert!(matches!(e, ScenarioError::NotText { .. }), "{e:?}");
        let e = Scenario::load("no-such-scenario").unwrap_err();
        assert!(matches!(e, ScenarioError::NotFound { .. }), "{e:?}");
        let text = ev_meb_with("preset = \"vemodule\"", "preset = \"nope\"");
        let e = Scenario::parse(&text, "s.toml").unwrap_err();
        assert!(matches!(e, ScenarioError::At { .. }), "{e:?}");
        assert!(e.to_string().contains("unknown preset `nope`"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_typo_in_module_params_gives_the_scenario_file_s_line() {
        let text = ev_meb_with(
            "preset = \"vemodule\"",
            "preset = \"vemodule\"\n\n[module.params.wheel]\nmass_kg = 1.0\n\n[module.params.motor]\nresistance_ohms = 0.4",
        );
        let e = Scenario::parse(&text, "s.toml").unwrap_err().to_string();
        let line = line_of(&text, "resistance_ohms");
        assert!(e.starts_with(&format!("s.toml:{line}:1: ")), "{e}");
        assert!(e.contains("resistance_ohms"), "{e}");
        assert!(e.contains("module `ev1`"), "{e}");
        let text = ev_meb_with(
            "preset = \"vemodule\"",
            "preset = \"vemodule\"\n[module.params.wheel]\nmass_kg = -1.0",
        );
        let e = Scenario::parse(&text, "s.toml").unwrap_err().to_string();
        let line = line_of(&text, "mass_kg = -1.0");
        assert!(
            e.starts_with(&format!(
                "s.toml:{line}:1: field `wheel.mass_kg` must be a positive number"
            )),
            "{e}"
        );
    }

    #[test]
    fn the_controller_network_master_keeps_its_old_name_and_errors_give_the_new_one() {
        let embedded = EMBEDDED
            .iter()
            .find(|(name, _, _)| *name == "controller-network")
            .map(|(_, _, text)| *text)
            .expect("the controller-network scenario is embedded");
        let new = Scenario::parse(embedded, "new.toml").expect("new name");
        let old_text = embedded.replace(
            "kind = \"controller-network-master\"",
            &format!("kind = \"{LEGACY_MASTER_KIND}\""),
        );
        assert_ne!(old_text, embedded, "the scenario names its master's kind");
        let old = Scenario::parse(&old_text, "old.toml").expect("old name still read");
        assert_eq!(
            toml::to_string(&old).unwrap(),
            toml::to_string(&new).unwrap()
        );
        let wrong = embedded.replace("kind = \"controller-network-master\"", "kind = \"pi\"");
        let e = Scenario::parse(&wrong, "w.toml").unwrap_err().to_string();
        assert!(e.contains("controller-network-master"), "{e}");
        assert!(!e.contains(LEGACY_MASTER_KIND), "{e}");
    }

    /// The embedded controller-network scenario with a firmware board of
    /// `boot` (a line `boot_ms = …`, or none) beside its Rust nodes.
    fn controller_network_with_a_board(boot: &str) -> String {
        let (_, _, text) = EMBEDDED
            .iter()
            .find(|(name, _, _)| *name == "controller-network")
            .expect("embedded");
        format!(
            "{text}\n[[node]]\nkind = \"firmware\"\nname = \"nano\"\nbus = \"serial\"\n\
             module = \"bench\"\nelf = \"nano.elf\"\nwiring = \"motor-nano\"\n{boot}\n"
        )
    }

    fn master_start(s: &Scenario) -> Option<f64> {
        s.nodes.iter().find_map(|n| match n {
            NodeSpec::ControllerNetworkMaster { start_s, .. } => Some(start_s.unwrap_or(f64::NAN)),
            _ => None,
        })
    }

    #[test]
    fn a_master_starts_once_the_boards_have_booted_unless_told() {
        // No board that boots: the master starts at 0 s, as it always did.
        let plain = Scenario::load("controller-network").expect("embedded");
        assert_eq!(master_start(&plain), Some(0.0));
        let unbooted = controller_network_with_a_board("");
        let s = Scenario::parse(&unbooted, "s.toml").expect("parses");
        assert_eq!(s.boards_booted_s(), 0.0);
        assert_eq!(master_start(&s), Some(0.0));
        // A Nano's boot: the master waits for it and the sketch's setup().
        let booted = controller_network_with_a_board(&format!("boot_ms = {NANO_BOOT_MS:.1}"));
        let s = Scenario::parse(&booted, "s.toml").expect("parses");
        assert_eq!(s.boards_booted_s(), 1.065);
        assert_eq!(master_start(&s), Some(1.065 + SETUP_S));
        // A start of its own wins.
        let told = booted.replace(
            "kind = \"controller-network-master\"",
            "kind = \"controller-network-master\"\nstart_s = 0.25",
        );
        let s = Scenario::parse(&told, "s.toml").expect("parses");
        assert_eq!(master_start(&s), Some(0.25));
    }

    #[test]
    fn a_boot_out_of_range_names_its_line() {
        let text = controller_network_with_a_board("boot_ms = -5.0");
        let e = Scenario::parse(&text, "s.toml").unwrap_err().to_string();
        let line = line_of(&text, "boot_ms");
        assert!(e.starts_with(&format!("s.toml:{line}: `boot_ms`")), "{e}");
        assert!(e.contains("node `nano`"), "{e}");
    }
}
