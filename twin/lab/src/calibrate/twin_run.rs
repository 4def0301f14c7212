//! One simulation of the experiment a log was taken in: the scenario on the
//! virtual clock with trial parameters, and what its master read, when.
//!
//! The twin is compared with the bench on what a master saw, not on an ideal
//! signal: the motor node's 20 ms encoder windows, its PI, the light node's
//! smoothing and the master's own schedule all shape the curve. Two masters
//! are read: the Controller_network Raspberry Pi (its requests and the
//! nodes' replies on the bus) and the EV module's MEB supervisor (its loop
//! report, once per poll cycle, as `twin supervise` records it).

use nodes::controller_network::{
    LIGHT_ID, MOTOR_ID, MasterConfig, REG_LIGHT_VALUE, REG_RPM, REG_STATE,
};
use protocols::modbus8::{self, CrcOrder, FRAME_LEN, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};
use twin_recording::topics::LoopReport;
use twin_sim::engine::{BusSlot, NodeSlot, ObserveError, Observer};
use twin_sim::scenario::{NodeSpec, Scenario};
use twin_sim::virtual_run;

use super::CalibrateError;
use super::signal::TwinSignal;

/// What the master read in one run, per signal: `(time s, value)`, the time
/// shifted so that the experiment's step falls where the log has it.
#[derive(Debug, Clone, Default)]
pub struct TwinReads {
    pub motor_rpm: Vec<(f64, f64)>,
    pub sensor_value: Vec<(f64, f64)>,
    pub supervisor_rpm: Vec<(f64, f64)>,
    pub supervisor_vel: Vec<(f64, f64)>,
    /// When the master made the step (simulated s, before the shift): the
    /// Pi's first write of the motor to operational, or the supervisor's
    /// first poll cycle at the step's new set point.
    pub step_at_s: Option<f64>,
}

impl TwinReads {
    /// The samples of `signal`.
    pub fn of(&self, signal: TwinSignal) -> &[(f64, f64)] {
        match signal {
            TwinSignal::MotorRpmRead => &self.motor_rpm,
            TwinSignal::SensorValueRead => &self.sensor_value,
            TwinSignal::SupervisorRpm => &self.supervisor_rpm,
            TwinSignal::SupervisorVel => &self.supervisor_vel,
        }
    }
}

/// The master whose reads are compared.
enum Master<'a> {
    /// The Controller_network Pi; it reads its reply this long (s) after
    /// its request (`usleep`).
    ControllerNetwork { name: &'a str, reply_wait: f64 },
    /// An MEB supervisor; its first slave's loop is read.
    Supervisor { name: &'a str },
}

impl Master<'_> {
    fn name(&self) -> &str {
        match self {
            Master::ControllerNetwork { name, .. } | Master::Supervisor { name } => name,
        }
    }
}

/// Collects the master's reads: from the frames on the bus (the Pi), or
/// from its loop reports (a supervisor).
struct ReadsObserver<'a> {
    master: Master<'a>,
    /// The step: from this set point to that one (a supervisor's).
    step: (f64, f64),
    /// The supervisor's set point in its last report.
    last_set_point: Option<f64>,
    /// The last request the master sent, and when its last bit left.
    request: Option<(Modbus8Repr, f64)>,
    reads: TwinReads,
}

impl Observer for ReadsObserver<'_> {
    fn frame(
        &mut self,
        _bus: &BusSlot,
        from: &NodeSlot,
        _start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<(), ObserveError> {
        let Some(frame) = bytes
            .get(..FRAME_LEN)
            .and_then(|b| Modbus8Repr::parse(b, CrcOrder::HighFirst).ok())
        else {
            return Ok(());
        };
        let Master::ControllerNetwork { name, reply_wait } = self.master else {
            return Ok(());
        };
        let end = end.as_secs_f64();
        if from.name == name {
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
        let at = sent + reply_wait;
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
    fn telemetry(
        &mut self,
        now: SimTime,
        node: &NodeSlot,
        report: &LoopReport,
    ) -> Result<(), ObserveError> {
        if node.name != self.master.name() {
            return Ok(());
        }
        let LoopReport::Supervisor(report) = report else {
            return Ok(());
        };
        let Some(slave) = report.loops.first() else {
            return Ok(());
        };
        let t = now.as_secs_f64();
        let (from, to) = self.step;
        if self.reads.step_at_s.is_none()
            && slave.set_point_rpm == to
            && self.last_set_point == Some(from)
        {
            self.reads.step_at_s = Some(t);
        }
        self.last_set_point = Some(slave.set_point_rpm);
        self.reads.supervisor_rpm.push((t, slave.measured_rpm));
        self.reads.supervisor_vel.push((t, f64::from(slave.output)));
        Ok(())
    }
    fn wants_loop_reports(&self) -> bool {
        matches!(self.master, Master::Supervisor { .. })
    }
}

/// The master of `scenario` whose reads are compared.
fn master_of(scenario: &Scenario) -> Result<Master<'_>, CalibrateError> {
    for node in &scenario.nodes {
        match node {
            NodeSpec::ControllerNetworkMaster { name, program, .. } => {
                let config = match program {
                    twin_sim::scenario::MasterProgramSpec::Loop => MasterConfig::default(),
                    twin_sim::scenario::MasterProgramSpec::StepResponse => {
                        MasterConfig::step_response()
                    }
                    // Only scripted requests: the default reply wait.
                    twin_sim::scenario::MasterProgramSpec::Requests => MasterConfig::default(),
                };
                return Ok(Master::ControllerNetwork {
                    name,
                    reply_wait: config.reply_wait.as_secs_f64(),
                });
            }
            NodeSpec::Supervisor { name, .. } => return Ok(Master::Supervisor { name }),
            _ => {}
        }
    }
    Err(CalibrateError::NoMaster {
        scenario: scenario.name.clone(),
    })
}

/// Runs `scenario` (its parameters already set) to `until_s` and returns what
/// its master read, shifted so that its step (from `step.0` to `step.1`)
/// is at `step_at_s`.
pub fn run(
    scenario: &Scenario,
    until_s: f64,
    step_at_s: f64,
    step: (f64, f64),
) -> Result<TwinReads, CalibrateError> {
    let master = master_of(scenario)?;
    let mut engine = virtual_run::build(scenario)?;
    let mut observer = ReadsObserver {
        master,
        step,
        last_set_point: None,
        request: None,
        reads: TwinReads::default(),
    };
    let end = SimTime::ZERO + SimDuration::from_secs_f64(until_s);
    engine.run_until(end, &mut observer, |_| {})?;
    let mut reads = observer.reads;
    let Some(step_s) = reads.step_at_s else {
        let what = match observer.master {
            Master::ControllerNetwork { .. } => "wrote the motor operational".to_string(),
            Master::Supervisor { .. } => {
                format!("stepped its set point from {} to {} rpm", step.0, step.1)
            }
        };
        return Err(CalibrateError::NoStep {
            scenario: scenario.name.clone(),
            what,
            until_s,
        });
    };
    let shift = step_at_s - step_s;
    for series in [
        &mut reads.motor_rpm,
        &mut reads.sensor_value,
        &mut reads.supervisor_rpm,
        &mut reads.supervisor_vel,
    ] {
        for (t, _) in series.iter_mut() {
            *t += shift;
        }
    }
    Ok(reads)
}
