//! Building the PWM-capture link and the parallel-module nodes of a
//! scenario, and what the engine records of them.

use nodes::firmware::EvControllerConfig;
use nodes::link::{Medium, PwmBus, PwmCalibration, PwmLine};
use nodes::master::SetPointStep;
use nodes::node::Firmware;
use nodes::parallel::{
    ParallelLink, ParallelMaster, ParallelMasterConfig, PwmAddressing, PwmSlave, PwmSlaveConfig,
};
use plant::PlantParams;
use protocols::modbus::serial::standard_rtu_silence;
use protocols::time::{SimDuration, SimTime};
use serde_json::{Value, json};

use crate::engine::SimNode;
use crate::nodes_build::{BuildError, build_bus, build_node};

type Result<T, E = BuildError> = std::result::Result<T, E>;
use crate::scenario::{
    AddressingSpec, BusSpec, FaultSpec, MediumSpec, NodeSpec, ParallelLinkSpec, RequestSpec,
};

fn ms(v: f64) -> SimDuration {
    SimDuration::from_secs_f64(v / 1000.0)
}

/// A `[[bus]]` as the run uses it: with `calibrate = true` on a PWM-capture
/// link, the start width and guard gap found at initialisation by sending
/// training frames through the same line model (its own noise stream from
/// `seed`) replace the file's `start_ticks` and `guard_ticks`. The training
/// takes a few milliseconds of line time before the run's clock starts.
pub fn calibrated(spec: &BusSpec, seed: u64) -> Result<(BusSpec, Option<PwmCalibration>)> {
    let Some(pwm) = spec
        .pwmcap
        .as_ref()
        .filter(|p| p.calibrate && spec.medium == MediumSpec::Pwmcap)
    else {
        return Ok((spec.clone(), None));
    };
    let config =
        pwm.bus_config(seed, Some(0))
            .map_err(|(field, message)| BuildError::BusSetting {
                bus: spec.name.clone(),
                field,
                message,
            })?;
    let line_error = |source| BuildError::PwmLine {
        bus: spec.name.clone(),
        source,
    };
    let mut line = PwmLine::new(config.line, config.coding.clock_hz(), seed).map_err(line_error)?;
    let Some(found) = PwmCalibration::find(&mut line, &config.coding).map_err(line_error)? else {
        return Err(BuildError::CalibrationFailed {
            bus: spec.name.clone(),
            max_ticks: PwmCalibration::MAX_ALLOWANCE_TICKS,
        });
    };
    let mut spec = spec.clone();
    if let Some(p) = spec.pwmcap.as_mut() {
        p.start_ticks = found.coding.start_ticks();
        p.guard_ticks = p.guard_ticks.saturating_add(found.guard_ticks);
    }
    Ok((spec, Some(found)))
}

/// The medium for a scenario's `[[bus]]`: the serial bus or the PWM-capture
/// link; `master` is the port of its master node, if any.
pub fn build_medium(spec: &BusSpec, seed: u64, master: Option<usize>) -> Result<Medium> {
    match spec.medium {
        MediumSpec::Serial => build_bus(spec, seed, master).map(Medium::from),
        MediumSpec::Pwmcap => {
            let pwm = spec.pwmcap.clone().unwrap_or_default();
            let config = pwm.bus_config(seed, master).map_err(|(field, message)| {
                BuildError::BusSetting {
                    bus: spec.name.clone(),
                    field,
                    message,
                }
            })?;
            let link = PwmBus::new(config).map_err(|source| BuildError::PwmLine {
                bus: spec.name.clone(),
                source,
            })?;
            Ok(Medium::from(link))
        }
    }
}

/// A node for a scenario's `[[node]]` on `bus`, and its turnaround (`seed`:
/// the node's share of the scenario's, for its faults' random junk): the
/// parallel-module kinds here, every other kind through [`build_node`].
pub fn build_node_on(
    spec: &NodeSpec,
    module: Option<&PlantParams>,
    faults: &[&FaultSpec],
    requests: &[&RequestSpec],
    bus: &BusSpec,
    seed: u64,
) -> Result<(Box<dyn SimNode>, SimDuration)> {
    let pwm = bus.pwmcap.clone().unwrap_or_default();
    let controller = |params: Option<&PlantParams>, loop_ms: f64| -> Result<EvControllerConfig> {
        let Some(params) = params else {
            return Err(BuildError::NoModule { kind: "this node" });
        };
        let mut config = EvControllerConfig::for_plant(params);
        config.loop_period = ms(loop_ms);
        Ok(config)
    };
    let coding = || {
        pwm.coding()
            .map_err(|(field, message)| BuildError::Coding { field, message })
    };
    let period_ticks = |coding: &protocols::pwmcap::PwmCoding| {
        coding.symbol_period_ticks().saturating_add(pwm.guard_ticks)
    };
    match spec {
        NodeSpec::ParallelMaster {
            link,
            slaves,
            update_period_ms,
            reply_timeout_ms,
            retries,
            kp,
            ki,
            set_points,
            loop_period_ms,
            turnaround_ms,
            ..
        } => {
            let coding = if link.is_pwm() {
                coding()?
            } else {
                protocols::pwmcap::PwmCoding::PAPER
            };
            let config = ParallelMasterConfig {
                link: match link {
                    ParallelLinkSpec::PwmcapBroadcast => ParallelLink::PwmBroadcast,
                    ParallelLinkSpec::PwmcapDesignated => ParallelLink::PwmDesignated,
                    ParallelLinkSpec::ModbusRtu => ParallelLink::ModbusRtu,
                },
                slaves: slaves.clone(),
                coding,
                period_ticks: period_ticks(&coding),
                update_period: ms(*update_period_ms),
                reply_timeout: ms(*reply_timeout_ms),
                retries: u8::try_from(*retries).unwrap_or(u8::MAX),
                kp: *kp,
                ki: *ki,
                set_points: set_points
                    .iter()
                    .map(|[t, rpm]| SetPointStep {
                        at: SimTime::ZERO + SimDuration::from_secs_f64(*t),
                        rpm: *rpm,
                    })
                    .collect(),
                controller: controller(module, *loop_period_ms)?,
                rtu_silence: standard_rtu_silence(bus.baud, bus.bits_per_char),
            };
            let master = ParallelMaster::new(config)?;
            Ok((Box::new(MasterNode { master, last: 0 }), ms(*turnaround_ms)))
        }
        NodeSpec::PwmSlave {
            id,
            addressing,
            loop_period_ms,
            turnaround_ms,
            ..
        } => {
            let coding = coding()?;
            let config = PwmSlaveConfig {
                id: *id,
                addressing: match addressing {
                    AddressingSpec::Broadcast => PwmAddressing::Broadcast,
                    AddressingSpec::Designated => PwmAddressing::Designated,
                },
                coding,
                period_ticks: period_ticks(&coding),
                controller: controller(module, *loop_period_ms)?,
            };
            let Some(slave) = PwmSlave::new(config) else {
                return Err(BuildError::PwmSlaveId { id: *id });
            };
            Ok((Box::new(slave), ms(*turnaround_ms)))
        }
        NodeSpec::Firmware { .. } => crate::external::build_firmware(spec, module, bus)
            .map(|(node, turnaround)| (node as Box<dyn SimNode>, turnaround)),
        _ => build_node(spec, module, faults, requests, seed),
    }
}

/// The master module, reporting each reference it issues.
struct MasterNode {
    master: ParallelMaster,
    last: u64,
}

impl MasterNode {
    fn state(&self) -> Value {
        let (set_point, measured) = self.master.loop_state();
        let slaves: Vec<Value> = self
            .master
            .counters()
            .iter()
            .map(|c| {
                json!({ "slave": c.id, "requests": c.requests, "replies": c.replies,
                        "timeouts": c.timeouts, "bad_replies": c.bad_replies, "retries": c.retries,
                        "lost": c.lost, "exceptions": c.exceptions })
            })
            .collect();
        json!({
            "set_point_rpm": set_point, "measured_rpm": measured, "vel": self.master.vel(),
            "updates": self.master.updates(), "cycles": self.master.cycles(), "slaves": slaves,
        })
    }
}

impl nodes::node::Node for MasterNode {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        self.master.handle_bytes(now, bytes);
    }
    fn handle_timeout(&mut self, now: SimTime) {
        self.master.handle_timeout(now);
    }
    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        self.master.poll_transmit(now, buf)
    }
    fn poll_timeout(&self) -> Option<SimTime> {
        self.master.poll_timeout()
    }
    fn transmit_done(&mut self, now: SimTime) {
        self.master.transmit_done(now);
    }
    fn poll_event(&mut self) -> Option<nodes::node::NodeEvent> {
        self.master.poll_event()
    }
}

impl SimNode for MasterNode {
    fn firmware(&mut self) -> Option<&mut dyn Firmware> {
        Some(&mut self.master)
    }
    /// One message per reference issued (every update period).
    fn telemetry(&mut self) -> Option<Value> {
        let updates = self.master.updates();
        if updates == self.last {
            return None;
        }
        self.last = updates;
        Some(self.state())
    }
    fn final_state(&self) -> Option<Value> {
        Some(self.state())
    }
}

impl SimNode for PwmSlave {
    fn firmware(&mut self) -> Option<&mut dyn Firmware> {
        Some(self)
    }
    fn final_state(&self) -> Option<Value> {
        let c = self.counters();
        Some(json!({
            "vel": self.vel(), "frames_taken": c.frames_taken, "frames_ignored": c.frames_ignored,
            "bad_frames": c.bad_frames, "incomplete_frames": c.incomplete_frames, "answers": c.answers,
        }))
    }
}
