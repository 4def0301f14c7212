//! One simulation of the experiment a log was taken in: the scenario on the
//! virtual clock with trial parameters, and what its master read, when.
//!
//! The twin is compared with the bench on what a master saw, not on an ideal
//! signal: the motor node's 20 ms encoder windows, its PI, the light node's
//! smoothing and the master's own schedule all shape the curve.

use anyhow::{Result, bail};
use nodes::controller_network::{
    LIGHT_ID, MOTOR_ID, MasterConfig, REG_LIGHT_VALUE, REG_RPM, REG_STATE,
};
use nodes::node::NodeEvent;
use nodes::proto::modbus8::{self, CrcOrder, FRAME_LEN, Frame};
use nodes::time::{SimDuration, SimTime};
use twin_sim::engine::{BusSlot, ModuleSlot, NodeSlot, Observer};
use twin_sim::scenario::{NodeSpec, Scenario};
use twin_sim::virtual_run;

use super::signal::TwinSignal;

/// What the master read in one run, per signal: `(time s, value)`, the time
/// shifted so that the experiment's step falls where the log has it.
#[derive(Debug, Clone, Default)]
pub struct TwinReads {
    pub motor_rpm: Vec<(f64, f64)>,
    pub sensor_value: Vec<(f64, f64)>,
    /// When the master wrote the motor operational for the first time
    /// (simulated s, before the shift).
    pub step_at_s: Option<f64>,
}

impl TwinReads {
    /// The samples of `signal`.
    pub fn of(&self, signal: TwinSignal) -> &[(f64, f64)] {
        match signal {
            TwinSignal::MotorRpmRead => &self.motor_rpm,
            TwinSignal::SensorValueRead => &self.sensor_value,
        }
    }
}

/// Collects the master's reads from the frames on the bus.
struct ReadsObserver<'a> {
    master: &'a str,
    /// The Pi reads its reply this long after its request (`usleep`).
    reply_wait: f64,
    /// The last request the master sent, and when its last bit left.
    request: Option<(Frame, f64)>,
    reads: TwinReads,
}

impl Observer for ReadsObserver<'_> {
    fn plant(&mut self, _: SimTime, _: &ModuleSlot) -> Result<()> {
        Ok(())
    }
    fn actuators(&mut self, _: SimTime, _: &ModuleSlot) -> Result<()> {
        Ok(())
    }
    fn frame(
        &mut self,
        _bus: &BusSlot,
        from: &NodeSlot,
        _start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<()> {
        let Some(frame) = bytes
            .get(..FRAME_LEN)
            .and_then(|b| Frame::parse(b, CrcOrder::HighFirst).ok())
        else {
            return Ok(());
        };
        let end = end.as_secs_f64();
        if from.name == self.master {
            if frame.function == modbus8::WRITE
                && frame.addr == REG_STATE
                && frame.value == 0x01
                && self.reads.step_at_s.is_none()
            {
                self.reads.step_at_s = Some(end);
            }
            self.request = Some((frame, end));
            return Ok(());
        }
        let Some((request, sent)) = self.request else {
            return Ok(());
        };
        if frame.function != modbus8::READ || frame.id != request.id || frame.addr != request.addr {
            return Ok(());
        }
        // The Pi has the value once its wait is over.
        let at = sent + self.reply_wait;
        match (frame.id, frame.addr) {
            (MOTOR_ID, REG_RPM) => self
                .reads
                .motor_rpm
                .push((at, f64::from(frame.value as i16))),
            (LIGHT_ID, REG_LIGHT_VALUE) => {
                self.reads.sensor_value.push((at, f64::from(frame.value)))
            }
            _ => {}
        }
        Ok(())
    }
    fn event(&mut self, _: &NodeSlot, _: &NodeEvent) -> Result<()> {
        Ok(())
    }
    fn telemetry(
        &mut self,
        _: SimTime,
        _: &NodeSlot,
        _: &twin_recording::topics::LoopReport,
    ) -> Result<()> {
        Ok(())
    }
    fn wants_loop_reports(&self) -> bool {
        false
    }
}

/// The Controller_network master of `scenario`, and how long it waits for a reply.
fn master_of(scenario: &Scenario) -> Result<(&str, f64)> {
    for node in &scenario.nodes {
        if let NodeSpec::ControllerNetworkMaster { name, program, .. } = node {
            let config = match program {
                twin_sim::scenario::MasterProgramSpec::Loop => MasterConfig::default(),
                twin_sim::scenario::MasterProgramSpec::StepResponse => {
                    MasterConfig::step_response()
                }
            };
            return Ok((name, config.reply_wait.as_secs_f64()));
        }
    }
    bail!(
        "scenario {} has no `controller-network-master`: calibration compares what a master read",
        scenario.name
    )
}

/// Runs `scenario` (its parameters already set) to `until_s` and returns what
/// its master read, shifted so that its first operational write is at `step_at_s`.
pub fn run(scenario: &Scenario, until_s: f64, step_at_s: f64) -> Result<TwinReads> {
    let (master, reply_wait) = master_of(scenario)?;
    let mut engine = virtual_run::build(scenario)?;
    let mut observer = ReadsObserver {
        master,
        reply_wait,
        request: None,
        reads: TwinReads::default(),
    };
    let end = SimTime::ZERO + SimDuration::from_secs_f64(until_s);
    engine.run_until(end, &mut observer, |_| {})?;
    let mut reads = observer.reads;
    let Some(step) = reads.step_at_s else {
        bail!(
            "in scenario {}, the master never wrote the motor operational within {until_s} s: \
             there is no step to compare",
            scenario.name
        );
    };
    let shift = step_at_s - step;
    for series in [&mut reads.motor_rpm, &mut reads.sensor_value] {
        for (t, _) in series.iter_mut() {
            *t += shift;
        }
    }
    Ok(reads)
}
