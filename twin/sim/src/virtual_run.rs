//! Running a scenario on the virtual clock and recording it.

use plant::{EvModule, PlantParams};
use protocols::time::{SimDuration, SimTime};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::engine::{Engine, EngineError};
use crate::interrupt::Interrupted;
use crate::nodes_build::{BuildError, is_master, light_detector_config};
use crate::nodes_parallel::{build_medium, build_node_on, calibrated};
use crate::observe::McapObserver;
use crate::observe::SimRecorder;
use crate::scenario::{NodeSpec, Scenario, ScenarioError};
use twin_recording::WriteError;
use twin_recording::topics::{self, ReadingsSample};

/// Why a run on the virtual clock (a scenario's, or the open-loop bench's)
/// did not give its outcome.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    #[error(transparent)]
    Build(#[from] BuildError),
    /// The recording could not be written.
    #[error(transparent)]
    Recording(#[from] WriteError),
    #[error(transparent)]
    Engine(#[from] EngineError),
    /// The run stopped on its own before its end (a node that failed, a
    /// recording that could not go on); what was recorded up to there is
    /// kept, whole.
    #[error(
        "the run stopped at {at_s:.6} s simulated; its recording up to there is {}",
        recording.display()
    )]
    Stopped {
        at_s: f64,
        recording: PathBuf,
        #[source]
        source: Box<RunError>,
    },
    /// Stopped as asked (Ctrl-C): not a failure, but not the whole run.
    #[error(transparent)]
    Interrupted(#[from] Interrupted),
}

impl RunError {
    /// The stop asked from outside, if that is why the run ended.
    pub fn interrupted(&self) -> Option<&Interrupted> {
        match self {
            RunError::Interrupted(i) => Some(i),
            _ => None,
        }
    }
}

type Result<T, E = RunError> = std::result::Result<T, E>;

/// What a run reports at the end.
#[derive(Debug, Clone)]
pub struct RunOutcome {
    pub recording: PathBuf,
    pub simulated_s: f64,
    pub frames: u64,
    pub events: BTreeMap<String, u64>,
    /// Final plant state per module.
    pub modules: Vec<(String, plant::Sensors)>,
    /// Final telemetry of every node that reports any (masters).
    pub telemetry: Vec<(String, serde_json::Value)>,
    /// Per bus: its name, the line's own counters and the receivers' check tally.
    pub buses: Vec<(String, nodes::link::BusStats, crate::engine::CheckTally)>,
    /// Log lines the nodes printed (the Controller_network master's printout), last ones.
    pub log_tail: Vec<String>,
    /// Per PWM-capture bus: its name and the link's own counters.
    pub pwm: Vec<(String, nodes::link::PwmStats)>,
    /// Per calibrated PWM-capture bus: what its calibration found.
    pub pwm_calibrations: Vec<(String, nodes::link::PwmCalibration)>,
    /// Every EV module controller's last readings.
    pub controllers: Vec<ControllerOutcome>,
}

/// An EV module controller at the end of a run: what it reads, and how far
/// its light sensor can follow the wheel.
#[derive(Debug, Clone)]
pub struct ControllerOutcome {
    pub detector: LightDetectorOf,
    pub readings: ReadingsSample,
}

/// The light detector of an `ev-controller` node of a scenario.
#[derive(Debug, Clone, PartialEq)]
pub struct LightDetectorOf {
    pub node: String,
    pub module: String,
    /// In the lab's words: `fixed 2.36 V`, `adaptive (swing ≥ 0.244 V)`.
    pub description: String,
    /// The fastest wheel speed at which it sees the flag, by the formulas of
    /// `plant/src/light.rs` (rpm).
    pub limit_rpm: f64,
}

/// The light detector of each `ev-controller` of `scenario`.
pub fn light_detectors(scenario: &Scenario) -> Result<Vec<LightDetectorOf>, ScenarioError> {
    let mut found = Vec::new();
    for node in &scenario.nodes {
        let NodeSpec::EvController {
            name,
            module,
            light_detector,
            ..
        } = node
        else {
            continue;
        };
        let Some(spec) = scenario.modules.iter().find(|m| &m.name == module) else {
            continue;
        };
        let params = scenario.module_params(spec)?;
        let config = light_detector_config(&params, *light_detector);
        found.push(LightDetectorOf {
            node: name.clone(),
            module: module.clone(),
            description: config.describe(&params.light),
            limit_rpm: config.max_rpm(&params.light),
        });
    }
    Ok(found)
}

/// Independent, reproducible seeds for the parts of a run (splitmix64).
pub fn derive_seed(seed: u64, part: u64) -> u64 {
    let mut z = seed.wrapping_add(part.wrapping_add(1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The scenario's buses as the run uses them (PWM-capture links calibrated
/// where asked), with the calibration each found.
pub fn calibrated_buses(
    scenario: &Scenario,
) -> Result<
    Vec<(
        crate::scenario::BusSpec,
        Option<nodes::link::PwmCalibration>,
    )>,
    BuildError,
> {
    scenario
        .buses
        .iter()
        .enumerate()
        .map(|(i, b)| calibrated(b, derive_seed(scenario.seed, 300 + i as u64)))
        .collect()
}

/// Build the engine for a scenario.
pub fn build(scenario: &Scenario) -> Result<Engine, BuildError> {
    let plant_step = SimDuration::from_secs_f64(scenario.plant_step_s);
    let record_period = SimDuration::from_secs_f64(1.0 / scenario.record_hz);
    let mut engine = Engine::new(plant_step, record_period);
    let mut params: BTreeMap<&str, (usize, PlantParams)> = BTreeMap::new();
    for (i, m) in scenario.modules.iter().enumerate() {
        let p = scenario.module_params(m)?;
        let plant = EvModule::new(&p, derive_seed(scenario.seed, 100 + i as u64));
        let index = engine.add_module(&m.name, plant);
        params.insert(&m.name, (index, p));
    }
    let buses = calibrated_buses(scenario)?;
    let mut bus_index = BTreeMap::new();
    for (i, (b, _)) in buses.iter().enumerate() {
        // Ports are added in node order: the master's port is its place
        // among the bus's nodes.
        let master = scenario
            .nodes
            .iter()
            .filter(|n| n.bus() == b.name)
            .position(is_master);
        let bus = build_medium(b, derive_seed(scenario.seed, 200 + i as u64), master)?;
        bus_index.insert(b.name.as_str(), engine.add_bus(&b.name, bus));
    }
    for (i, spec) in scenario.nodes.iter().enumerate() {
        let Some(&bus) = bus_index.get(spec.bus()) else {
            return Err(BuildError::NoBus {
                node: spec.name().to_string(),
                bus: spec.bus().to_string(),
            });
        };
        let module = spec.module().and_then(|m| params.get(m));
        let faults: Vec<_> = scenario
            .faults
            .iter()
            .filter(|f| f.node == spec.name())
            .collect();
        let requests: Vec<_> = scenario
            .requests
            .iter()
            .filter(|r| r.node == spec.name())
            .collect();
        let Some((bus_spec, _)) = buses.iter().find(|(b, _)| b.name == spec.bus()) else {
            return Err(BuildError::NoBus {
                node: spec.name().to_string(),
                bus: spec.bus().to_string(),
            });
        };
        let seed = derive_seed(scenario.seed, 500 + i as u64);
        let (node, turnaround) = build_node_on(
            spec,
            module.map(|(_, p)| p),
            &faults,
            &requests,
            bus_spec,
            seed,
        )
        .map_err(|source| BuildError::Node {
            node: spec.name().to_string(),
            source: Box::new(source),
        })?;
        let port = engine.buses[bus]
            .bus
            .add_port(nodes::link::PortConfig { turnaround });
        engine.add_node(spec.name(), node, bus, port, module.map(|(i, _)| *i));
    }
    Ok(engine)
}

/// One line on what a PWM-capture link's calibration found.
pub fn describe_calibration(bus: &str, c: &nodes::link::PwmCalibration) -> String {
    format!(
        "bus {bus}: start {} ticks, guard {} ticks, {} training frames",
        c.coding.start_ticks(),
        c.guard_ticks,
        c.frames_sent
    )
}

/// Run `scenario` and record it to `out`; `progress` gets the fraction done.
pub fn run(scenario: &Scenario, out: &Path, progress: impl FnMut(f64)) -> Result<RunOutcome> {
    run_with(scenario, out, &mut crate::engine::DiscardObserver, progress)
}

/// Like [`run`], with `also` fed everything the recorder is (a live view).
pub fn run_with(
    scenario: &Scenario,
    out: &Path,
    also: &mut dyn crate::engine::Observer,
    progress: impl FnMut(f64),
) -> Result<RunOutcome> {
    let plain = BTreeMap::new();
    run_observed(
        scenario,
        out,
        also,
        progress,
        &plain,
        None,
        |_, _, _| Ok(()),
    )
}

/// [`run`], pausing every `sample_every` of simulated time to call
/// `on_sample` with the time, the engine and the recorder (an experiment
/// reads the nodes' registers there and records what it measured). Pausing
/// changes nothing in the run itself. `experiment` is what the experiment
/// adds to the run's identity (`twin.run`), so that `twin replay` can run it
/// again.
pub fn run_sampled(
    scenario: &Scenario,
    out: &Path,
    progress: impl FnMut(f64),
    experiment: &BTreeMap<String, String>,
    sample_every: Option<SimDuration>,
    on_sample: impl FnMut(SimTime, &Engine, &mut SimRecorder) -> Result<(), WriteError>,
) -> Result<RunOutcome> {
    let mut discard = crate::engine::DiscardObserver;
    run_observed(
        scenario,
        out,
        &mut discard,
        progress,
        experiment,
        sample_every,
        on_sample,
    )
}

/// The run behind [`run_with`] and [`run_sampled`].
fn run_observed(
    scenario: &Scenario,
    out: &Path,
    also: &mut dyn crate::engine::Observer,
    mut progress: impl FnMut(f64),
    experiment: &BTreeMap<String, String>,
    sample_every: Option<SimDuration>,
    mut on_sample: impl FnMut(SimTime, &Engine, &mut SimRecorder) -> Result<(), WriteError>,
) -> Result<RunOutcome> {
    let mut engine = build(scenario)?;
    let pwm_calibrations: Vec<(String, nodes::link::PwmCalibration)> = calibrated_buses(scenario)?
        .into_iter()
        .filter_map(|(b, c)| c.map(|c| (b.name, c)))
        .collect();
    let mut recorder = SimRecorder::create_threaded(out)?;
    let mut identity = BTreeMap::from([
        ("kind".into(), "scenario".into()),
        ("scenario".into(), scenario.name.clone()),
        (
            "scenario_toml".into(),
            toml::to_string(scenario).map_err(ScenarioError::from)?,
        ),
        ("seed".into(), scenario.seed.to_string()),
        ("twin_version".into(), env!("CARGO_PKG_VERSION").into()),
    ]);
    identity.extend(experiment.clone());
    if !pwm_calibrations.is_empty() {
        let text: Vec<String> = pwm_calibrations
            .iter()
            .map(|(b, c)| describe_calibration(b, c))
            .collect();
        identity.insert("pwm_calibration".into(), text.join("; "));
    }
    recorder.write_metadata(topics::RUN_METADATA, identity)?;
    // Compiled firmware is stored whole, so that a replay runs these bytes.
    for slot in &engine.nodes {
        if let Some(file) = slot.node.firmware_file() {
            recorder.write_metadata(&topics::firmware_metadata(&slot.name), file.fields)?;
            recorder.attach(&file.attachment, "application/x-elf", 0.0, file.bytes)?;
        }
    }
    let mut observer = McapObserver::new(recorder);
    let end = SimTime::ZERO + SimDuration::from_secs_f64(scenario.duration_s);
    let mut both = crate::observe::Tee {
        first: &mut observer,
        second: also,
    };
    let ran = match sample_every.filter(|p| *p > SimDuration::ZERO) {
        None => engine
            .run_until(end, &mut both, |t| {
                progress(t.as_secs_f64() / scenario.duration_s)
            })
            .map_err(RunError::from),
        Some(period) => (|| -> Result<()> {
            let mut t = SimTime::ZERO;
            on_sample(t, &engine, &mut both.first.recorder)?;
            while t < end && !engine.interrupted() {
                t = (t + period).min(end);
                engine.run_until(t, &mut both, |_| {})?;
                on_sample(engine.now(), &engine, &mut both.first.recorder)?;
                progress(t.as_secs_f64() / scenario.duration_s);
            }
            Ok(())
        })(),
    };
    if let Err(e) = ran {
        // A node that failed (firmware that crashed) stops the run; what
        // was recorded up to there is kept, whole.
        return Err(match observer.recorder.finish() {
            Ok(recording) => RunError::Stopped {
                at_s: engine.now().as_secs_f64(),
                recording,
                source: Box::new(e),
            },
            Err(_) => e,
        });
    }
    if engine.interrupted() {
        let recording = observer.recorder.finish()?;
        return Err(RunError::Interrupted(Interrupted {
            at_s: engine.now().as_secs_f64(),
            recording: Some(recording),
        }));
    }
    progress(1.0);
    let modules = engine
        .modules
        .iter()
        .map(|m| (m.name.clone(), *m.plant.sensors()))
        .collect();
    let telemetry = engine
        .nodes
        .iter_mut()
        .filter_map(|n| n.node.final_state().map(|v| (n.name.clone(), v)))
        .collect();
    let buses = engine
        .buses
        .iter()
        .map(|b| (b.name.clone(), *b.bus.stats(), b.checks))
        .collect();
    let pwm = engine
        .buses
        .iter()
        .filter_map(|b| b.bus.as_pwm().map(|l| (b.name.clone(), *l.pwm_stats())))
        .collect();
    let mut controllers = Vec::new();
    for detector in light_detectors(scenario)? {
        let readings = engine
            .nodes
            .iter()
            .find(|n| n.name == detector.node)
            .and_then(|n| n.node.controller_readings());
        if let Some(readings) = readings {
            controllers.push(ControllerOutcome { detector, readings });
        }
    }
    let frames = observer.frames;
    let events = observer.events.clone();
    let log_tail = observer.log_tail.iter().cloned().collect();
    let recording = observer.recorder.finish()?;
    Ok(RunOutcome {
        recording,
        simulated_s: engine.now().as_secs_f64(),
        frames,
        events,
        modules,
        telemetry,
        buses,
        log_tail,
        pwm,
        pwm_calibrations,
        controllers,
    })
}
