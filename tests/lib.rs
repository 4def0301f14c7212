//! End-to-end tests live beside this file, one `[[test]]` each. This library
//! holds what several of them share: an observer that keeps everything the
//! engine reports in memory, and a way to run a scenario into it.

use nodes::node::NodeEvent;
use plant::{Actuators, Sensors};
use protocols::time::{SimDuration, SimTime};
use twin_sim::engine::{BusSlot, Engine, ModuleSlot, NodeSlot, ObserveError, Observer};
use twin_sim::scenario::Scenario;

type Result<T, E = ObserveError> = std::result::Result<T, E>;

/// One frame as it went on the wire.
#[derive(Debug, Clone)]
pub struct WireFrame {
    pub from: String,
    pub start: SimTime,
    pub end: SimTime,
    pub bytes: Vec<u8>,
}

/// Everything the engine reported, in order. Plant samples and actuator
/// changes of every module go into one list each (the tests run one module).
#[derive(Debug, Default)]
pub struct Capture {
    pub frames: Vec<WireFrame>,
    pub actuators: Vec<(SimTime, Actuators)>,
    pub plant: Vec<(SimTime, Sensors)>,
    /// Node name and event.
    pub events: Vec<(String, NodeEvent)>,
    /// Time, node name and report.
    pub telemetry: Vec<(SimTime, String, serde_json::Value)>,
}

impl Observer for Capture {
    fn plant(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        self.plant.push((now, *module.plant.sensors()));
        Ok(())
    }

    fn actuators(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        self.actuators.push((now, module.actuators));
        Ok(())
    }

    fn frame(
        &mut self,
        _bus: &BusSlot,
        from: &NodeSlot,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<()> {
        self.frames.push(WireFrame {
            from: from.name.clone(),
            start,
            end,
            bytes: bytes.to_vec(),
        });
        Ok(())
    }

    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<()> {
        self.events.push((node.name.clone(), event.clone()));
        Ok(())
    }

    fn telemetry(
        &mut self,
        now: SimTime,
        node: &NodeSlot,
        report: &twin_recording::topics::LoopReport,
    ) -> Result<()> {
        self.telemetry
            .push((now, node.name.clone(), report.to_value()));
        Ok(())
    }
}

/// `seconds` after the start of a run.
pub fn at(seconds: f64) -> SimTime {
    SimTime::ZERO + SimDuration::from_secs_f64(seconds)
}

/// Run `scenario` to `until_s` seconds; the engine comes back for its final state.
pub fn run_captured(scenario: &Scenario, until_s: f64) -> (Capture, Engine) {
    let mut engine = twin_sim::virtual_run::build(scenario).expect("engine builds");
    let mut capture = Capture::default();
    engine
        .run_until(at(until_s), &mut capture, |_| {})
        .expect("run completes");
    (capture, engine)
}
