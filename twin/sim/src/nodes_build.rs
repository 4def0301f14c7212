//! Turning a scenario's bus and node declarations into the nodes crate's
//! objects, and what the engine needs from each kind of node.

use nodes::controller_network::{
    ControllerNetworkMaster, LightConfig, LightNode, MasterConfig, MasterProgram, MotorConfig,
    MotorNode, ScriptedRequest,
};
use nodes::firmware::{
    EvController, EvControllerConfig, LightDetectorConfig, Readings, Refusal, SlaveProtocol, ea,
};
use nodes::link::{
    BusConfig, BusConfigError, CheckKind, Fault, FaultWindow, FaultyNode, Junk, JunkBytes,
    JunkPlace, PortId, SimBus, Wiring,
};
use nodes::master::Supervisor;
use nodes::master::{Protocol, SetPointStep, SlaveLoopConfig, SpeedSource, SupervisorConfig};
use nodes::node::Firmware;
use plant::PlantParams;
use protocols::time::{SimDuration, SimTime};
use serde_json::{Value, json};

use crate::engine::{SimNode, SpeedReadings};
use crate::scenario::{
    BusSpec, CrcSpec, FaultKind, FaultSpec, JunkPlaceSpec, LightDetectorSpec, MasterProgramSpec,
    NodeSpec, ProtocolSpec, RequestSpec, WiringSpec,
};
use twin_recording::topics::{LoopReport, MebWords, ReadingsSample, SlaveLoop, SupervisorReport};

/// Why a scenario's buses and nodes could not be built.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    #[error("bus `{bus}` is wired master-slaves but has no master node")]
    NoMaster { bus: String },
    /// A serial bus's line settings the bus refused.
    #[error("bus `{bus}`")]
    Bus {
        bus: String,
        #[source]
        source: BusConfigError,
    },
    /// A PWM-capture link's setting out of range.
    #[error("bus `{bus}`: `{field}` {message}")]
    BusSetting {
        bus: String,
        field: String,
        message: String,
    },
    /// A PWM-capture node's coding out of range.
    #[error("`{field}` {message}")]
    Coding { field: String, message: String },
    /// A PWM-capture line the line model refused.
    #[error("bus `{bus}`")]
    PwmLine {
        bus: String,
        #[source]
        source: nodes::link::PwmLineError,
    },
    #[error(
        "bus `{bus}`: calibration found no start width up to {max_ticks} extra ticks: the line is too slow or too noisy for this coding"
    )]
    CalibrationFailed { bus: String, max_ticks: u32 },
    /// A node that drives or reads a module, declared without one.
    #[error("{kind} needs a module")]
    NoModule { kind: &'static str },
    /// A scripted request that is not a frame.
    #[error("request at {at_s} s: {why}")]
    Request { at_s: f64, why: String },
    #[error("PWM slave id {id} is outside 1..=15")]
    PwmSlaveId { id: u8 },
    #[error("a parallel-module node needs its bus: build it with nodes_parallel::build_node_on")]
    NeedsBus,
    #[error("node `{node}`: no bus `{bus}`")]
    NoBus { node: String, bus: String },
    #[error(
        "node `{node}` runs compiled AVR firmware: run this scenario with `twin-avr run`, \
         the build of the twin that links simavr (GPL)"
    )]
    FirmwareUnavailable { node: String },
    /// What the registered builder of firmware nodes refused, in its words.
    #[error(transparent)]
    Firmware(Box<dyn std::error::Error + Send + Sync>),
    /// One node of the scenario could not be built.
    #[error("node `{node}`")]
    Node {
        node: String,
        #[source]
        source: Box<BuildError>,
    },
    /// A supervisor's settings its loop refused.
    #[error(transparent)]
    Supervisor(#[from] nodes::master::SupervisorConfigError),
    /// A parallel-module master's settings it refused.
    #[error(transparent)]
    ParallelMaster(#[from] nodes::parallel::ParallelConfigError),
    #[error(transparent)]
    Scenario(#[from] crate::scenario::ScenarioError),
}

type Result<T, E = BuildError> = std::result::Result<T, E>;

fn ms(v: f64) -> SimDuration {
    SimDuration::from_secs_f64(v / 1000.0)
}

fn at(seconds: f64) -> SimTime {
    SimTime::ZERO + SimDuration::from_secs_f64(seconds)
}

/// A simulated bus for a scenario's `[[bus]]`; in master-slaves wiring the
/// master's port is `master`.
pub fn build_bus(spec: &BusSpec, seed: u64, master: Option<usize>) -> Result<SimBus> {
    let wiring = match (spec.wiring, master) {
        (WiringSpec::MultiDrop, _) => Wiring::MultiDrop,
        (WiringSpec::MasterSlaves, Some(m)) => Wiring::MasterSlaves {
            master: PortId(m as u16),
        },
        (WiringSpec::MasterSlaves, None) => {
            return Err(BuildError::NoMaster {
                bus: spec.name.clone(),
            });
        }
    };
    let config = BusConfig {
        baud: spec.baud,
        bits_per_char: spec.bits_per_char,
        bit_error_rate: spec.bit_error_rate,
        seed,
        wiring,
    };
    SimBus::new(config).map_err(|source| BuildError::Bus {
        bus: spec.name.clone(),
        source,
    })
}

fn fault_windows(faults: &[&FaultSpec]) -> Vec<FaultWindow> {
    faults
        .iter()
        .map(|f| FaultWindow {
            from: at(f.from_s),
            until: at(f.until_s),
            fault: fault(f),
        })
        .collect()
}

/// The wrapper's fault for a checked `[[fault]]` (`scenario::fault_check`
/// refused what does not fit).
fn fault(f: &FaultSpec) -> Fault {
    match f.kind {
        FaultKind::BadCheck => Fault::BadCheck,
        FaultKind::DropReply => Fault::DropReply,
        FaultKind::DelayReply => Fault::DelayReply(ms(f.delay_ms)),
        FaultKind::Silent => Fault::Silent,
        FaultKind::Exception => Fault::Exception(
            Refusal::from_code(f.code.unwrap_or(4)).unwrap_or(Refusal::DeviceFailure),
        ),
        FaultKind::WrongId => Fault::WrongId(f.id),
        FaultKind::SplitReply => Fault::SplitReply {
            first: f.split_at,
            gap: ms(f.gap_ms.unwrap_or_default()),
        },
        FaultKind::Junk => {
            let bytes = match (&f.junk, f.junk_count) {
                (Some(given), _) => JunkBytes::given(given),
                (None, count) => JunkBytes::random(count.unwrap_or(1) as usize),
            };
            let place = match f.junk_place.unwrap_or_default() {
                JunkPlaceSpec::Before => JunkPlace::Before,
                JunkPlaceSpec::After => JunkPlace::After,
            };
            let bytes = bytes.unwrap_or(JunkBytes::Random(1));
            Fault::Junk(Junk { bytes, place })
        }
    }
}

/// Whether a node drives a master-slaves bus as its master.
pub fn is_master(spec: &NodeSpec) -> bool {
    matches!(
        spec,
        NodeSpec::Supervisor { .. }
            | NodeSpec::ControllerNetworkMaster { .. }
            | NodeSpec::ParallelMaster { .. }
    )
}

/// The light detector an `ev-controller` node runs on a module with `params`.
pub fn light_detector_config(params: &PlantParams, spec: LightDetectorSpec) -> LightDetectorConfig {
    let mut config = LightDetectorConfig::for_sensor(&params.light);
    config.adaptive = spec.adaptive();
    config
}

/// The node for a scenario's `[[node]]`, and its reply turnaround; `seed`
/// draws its faults' random junk; `requests` are the scripted frames it
/// sends (a master's).
pub fn build_node(
    spec: &NodeSpec,
    module: Option<&PlantParams>,
    faults: &[&FaultSpec],
    requests: &[&RequestSpec],
    seed: u64,
) -> Result<(Box<dyn SimNode>, SimDuration)> {
    let windows = fault_windows(faults);
    match spec {
        NodeSpec::EvController {
            id,
            protocol,
            turnaround_ms,
            loop_period_ms,
            light_detector,
            ..
        } => {
            let Some(params) = module else {
                return Err(BuildError::NoModule {
                    kind: "an ev-controller",
                });
            };
            let mut config = EvControllerConfig::for_plant(params);
            config.light = light_detector_config(params, *light_detector);
            config.slave_id = *id;
            config.loop_period = ms(*loop_period_ms);
            let (protocol, check) = match protocol {
                ProtocolSpec::Meb => (SlaveProtocol::Meb, CheckKind::Meb),
                ProtocolSpec::ModbusRtu => (SlaveProtocol::ModbusRtu, CheckKind::ModbusRtu),
            };
            config.protocol = protocol;
            let node = FaultyNode::with_schedule(EvController::new(config), check, windows)
                .with_seed(seed)
                .with_turnaround(ms(*turnaround_ms));
            Ok((Box::new(node), ms(*turnaround_ms)))
        }
        NodeSpec::Supervisor {
            slaves,
            protocol,
            poll_period_ms,
            gap_ms,
            reply_timeout_ms,
            retries,
            kp,
            ki,
            use_light_rpm,
            set_points,
            ..
        } => {
            let loops = slaves
                .iter()
                .map(|&id| {
                    let mut l = SlaveLoopConfig::new(id);
                    l.kp = *kp;
                    l.ki = *ki;
                    l.speed_source = if *use_light_rpm {
                        SpeedSource::Light
                    } else {
                        SpeedSource::Hall
                    };
                    l.set_points = set_points
                        .iter()
                        .map(|[t, rpm]| SetPointStep {
                            at: at(*t),
                            rpm: *rpm,
                        })
                        .collect();
                    l
                })
                .collect();
            let protocol = match protocol {
                ProtocolSpec::Meb => Protocol::Meb,
                ProtocolSpec::ModbusRtu => Protocol::ModbusRtu,
            };
            let mut config = SupervisorConfig::new(protocol, loops);
            config.poll_period = ms(*poll_period_ms);
            config.inter_frame_gap = ms(*gap_ms);
            config.reply_timeout = ms(*reply_timeout_ms);
            config.retries = u8::try_from(*retries).unwrap_or(u8::MAX);
            let supervisor = Supervisor::new(config)?;
            Ok((Box::new(SupervisorNode::new(supervisor)), SimDuration::ZERO))
        }
        NodeSpec::MotorNode { turnaround_ms, .. } => {
            let motor = MotorNode::new(MotorConfig::default());
            let node = FaultyNode::with_schedule(motor, CheckKind::Modbus8, windows)
                .with_seed(seed)
                .with_turnaround(ms(*turnaround_ms));
            Ok((Box::new(node), ms(*turnaround_ms)))
        }
        NodeSpec::LightNode { turnaround_ms, .. } => {
            let config =
                module.map_or_else(LightConfig::default, |p| LightConfig::for_sensor(&p.light));
            let light = LightNode::new(config);
            let node = FaultyNode::with_schedule(light, CheckKind::Modbus8, windows)
                .with_seed(seed)
                .with_turnaround(ms(*turnaround_ms));
            Ok((Box::new(node), ms(*turnaround_ms)))
        }
        NodeSpec::ControllerNetworkMaster {
            reply_timeout_ms,
            program,
            start_s,
            ..
        } => {
            let base = match program {
                MasterProgramSpec::Loop => MasterConfig::default(),
                MasterProgramSpec::StepResponse => MasterConfig::step_response(),
                MasterProgramSpec::Requests => MasterConfig {
                    program: MasterProgram::Requests,
                    ..MasterConfig::default()
                },
            };
            let config = MasterConfig {
                reply_timeout: reply_timeout_ms.map(ms),
                start: SimDuration::from_secs_f64(start_s.unwrap_or_default()),
                ..base
            };
            let script = requests
                .iter()
                .map(|r| {
                    let frame = crate::scenario::request_frame(&r.send)
                        .map_err(|why| BuildError::Request { at_s: r.at_s, why })?;
                    Ok(ScriptedRequest {
                        at: at(r.at_s),
                        frame,
                        bad_crc: r.crc == CrcSpec::Bad,
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            let node = FaultyNode::with_schedule(
                ControllerNetworkMaster::new(config).with_script(script),
                CheckKind::Modbus8,
                windows,
            )
            .with_seed(seed);
            Ok((Box::new(node), SimDuration::ZERO))
        }
        NodeSpec::Firmware { name, .. } => {
            Err(BuildError::FirmwareUnavailable { node: name.clone() })
        }
        NodeSpec::ParallelMaster { .. } | NodeSpec::PwmSlave { .. } => Err(BuildError::NeedsBus),
    }
}

impl SimNode for FaultyNode<EvController> {
    fn firmware(&mut self) -> Option<&mut dyn Firmware> {
        Some(self.inner_mut())
    }
    fn speed_readings(&self) -> SpeedReadings {
        let inputs = &self.inner().image().inputs;
        SpeedReadings {
            hall_wheel_rpm: Some(f64::from(inputs[ea::RPM_M])),
            light_rpm: Some(f64::from(inputs[ea::RPM_L])),
            ..SpeedReadings::default()
        }
    }
    fn image_mut(&mut self) -> Option<&mut nodes::firmware::RegisterImage> {
        Some(self.inner_mut().image_mut())
    }
    fn controller_readings(&self) -> Option<ReadingsSample> {
        Some(readings_sample(&self.inner().readings()))
    }
}

/// An EV controller's readings as recorded: volts and amperes to the
/// millivolt and milliampere (finer than a count of their converters:
/// 12 mV of V1, 12 mA of I), so the file holds no digits the ADC never gave.
pub fn readings_sample(r: &Readings) -> ReadingsSample {
    let milli = |v: f64| (v * 1000.0).round() / 1000.0;
    ReadingsSample {
        battery_volts: milli(r.battery_volts),
        bus_volts: milli(r.bus_volts),
        inverter_amps: milli(r.inverter_amps),
        hall_rpm: r.hall_rpm(),
        light_rpm: r.light_rpm(),
        flag_dark: r.flag_dark(),
        soc_percent: f64::from(r.soc) / 10.0,
        meb: MebWords {
            v2: r.ea[ea::V2],
            i: r.ea[ea::I],
            v1: r.ea[ea::V1],
            rpm_m: r.ea[ea::RPM_M],
            rpm_l: r.ea[ea::RPM_L],
            ldr: r.ea[ea::LDR],
            hall: r.hall,
            soc: r.soc,
            errs: r.errs,
            status: r.status,
        },
    }
}

impl SimNode for FaultyNode<MotorNode> {
    fn firmware(&mut self) -> Option<&mut dyn Firmware> {
        Some(self.inner_mut())
    }
    fn final_state(&self) -> Option<Value> {
        let m = self.inner();
        Some(
            json!({ "state": m.state().name(), "set_point": m.set_point(),
                     "latched_rpm": m.latched_rpm(), "duty": m.duty() }),
        )
    }
    fn speed_readings(&self) -> SpeedReadings {
        let m = self.inner();
        let running = m.state() == nodes::controller_network::MotorState::Operational;
        SpeedReadings {
            motor_shaft_rpm: Some(f64::from(m.latched_rpm())),
            set_point_motor_rpm: Some(if running {
                f64::from(m.set_point())
            } else {
                0.0
            }),
            ..SpeedReadings::default()
        }
    }
}

impl SimNode for FaultyNode<LightNode> {
    fn firmware(&mut self) -> Option<&mut dyn Firmware> {
        Some(self.inner_mut())
    }
    /// The light sensor only watches the wheel: the motor node drives it.
    fn drives_plant(&self) -> bool {
        false
    }
    fn final_state(&self) -> Option<Value> {
        let l = self.inner();
        Some(
            json!({ "rpm": l.rpm(), "raw_rpm": l.raw_rpm(), "register": l.register_value(), "edges": l.edges() }),
        )
    }
    fn speed_readings(&self) -> SpeedReadings {
        SpeedReadings {
            light_rpm: Some(self.inner().rpm()),
            ..SpeedReadings::default()
        }
    }
}

impl SimNode for FaultyNode<ControllerNetworkMaster> {
    fn final_state(&self) -> Option<Value> {
        let m = self.inner();
        let mut state = json!({ "phase": m.phase().name(), "cycles": m.cycles(), "motor_rpm": m.motor_rpm(),
                 "sensor_value": m.sensor_value(), "set_point": m.set_point(),
                 "crc_errors": m.crc_errors(), "timeouts": m.timeouts() });
        // Only with a script, so runs without one read as they always did.
        let (sent, of) = m.scripted();
        if of > 0 {
            state["program"] = json!(m.program().name());
            state["scripted"] = json!({ "sent": sent, "of": of });
        }
        Some(state)
    }
}

/// The supervisor, reporting its loop once per poll cycle.
#[derive(Debug)]
pub struct SupervisorNode {
    supervisor: Supervisor,
    last_cycle: u64,
    /// The last report's list, handed back for the next one (a report per
    /// poll cycle, no allocation).
    spare_loops: Vec<SlaveLoop>,
}

impl SupervisorNode {
    pub fn new(supervisor: Supervisor) -> Self {
        Self {
            supervisor,
            last_cycle: 0,
            spare_loops: Vec::new(),
        }
    }

    fn loops(&self) -> SupervisorReport {
        self.report_into(Vec::new())
    }

    /// The report, its list in `loops` (emptied first).
    fn report_into(&self, mut loops: Vec<SlaveLoop>) -> SupervisorReport {
        loops.clear();
        loops.extend(
            self.supervisor
                .slave_ids()
                .filter_map(|id| self.supervisor.loop_state(id).map(|s| (id, s)))
                .map(|(id, s)| {
                    let c = s.counters;
                    SlaveLoop {
                        slave: id,
                        set_point_rpm: s.set_point_rpm,
                        measured_rpm: s.measured_rpm,
                        error_rpm: s.error_rpm,
                        output: s.output,
                        integral: s.integral,
                        requests: c.requests,
                        replies: c.replies,
                        timeouts: c.timeouts,
                        bad_checks: c.bad_checks,
                        exceptions: c.exceptions,
                        retries: c.retries,
                        lost: c.lost,
                    }
                }),
        );
        SupervisorReport {
            cycles: self.supervisor.cycles(),
            loops,
        }
    }
}

impl nodes::node::Node for SupervisorNode {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        self.supervisor.handle_bytes(now, bytes);
    }
    fn handle_timeout(&mut self, now: SimTime) {
        self.supervisor.handle_timeout(now);
    }
    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        self.supervisor.poll_transmit(now, buf)
    }
    fn poll_timeout(&self) -> Option<SimTime> {
        self.supervisor.poll_timeout()
    }
    fn transmit_done(&mut self, now: SimTime) {
        self.supervisor.transmit_done(now);
    }
    fn poll_event(&mut self) -> Option<nodes::node::NodeEvent> {
        self.supervisor.poll_event()
    }
}

impl SimNode for SupervisorNode {
    fn telemetry(&mut self) -> Option<Value> {
        self.loop_report().map(|r| r.to_value())
    }
    fn loop_report(&mut self) -> Option<LoopReport> {
        let cycles = self.supervisor.cycles();
        if cycles == self.last_cycle {
            return None;
        }
        self.last_cycle = cycles;
        let spare = std::mem::take(&mut self.spare_loops);
        Some(LoopReport::Supervisor(self.report_into(spare)))
    }
    fn recycle_loop_report(&mut self, report: LoopReport) {
        if let LoopReport::Supervisor(report) = report {
            self.spare_loops = report.loops;
        }
    }
    fn final_state(&self) -> Option<Value> {
        Some(LoopReport::Supervisor(self.loops()).to_value())
    }
    fn supervisor_mut(&mut self) -> Option<&mut Supervisor> {
        Some(&mut self.supervisor)
    }
}
