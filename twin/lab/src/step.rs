//! The step-response experiment of the Controller_network project: step the
//! set point and watch both speed sensors, the motor's own (hall edges, or the
//! Controller_network motor node's encoder) and the photoresistor's, against the true wheel speed.
//!
//! Open loop, the bench alone steps `VEL` (as `twin run --open-loop`) while
//! the module's firmware estimators, not connected to anything, read its
//! sensors at their loop period. Closed loop, a scenario's supervisor gets
//! the set-point step and closes the loop over the bus; the controller's
//! `RPM_M` and `RPM_L` registers are read from the running engine.

use plant::{PlantParams, Sensors};
use protocols::time::{SimDuration, SimTime};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::instruments::{Instruments, light_limit, read_instruments};
use super::plot::{self, Axes, PlotError, Series};
use twin_recording::Recording;
use twin_sim::openloop::{self, OpenLoop};
use twin_sim::replay::RunSpec;
use twin_sim::scenario::{NodeSpec, Scenario};
use twin_sim::step_metrics::{StepMetrics, StepOptions, delay, step_metrics};
use twin_sim::virtual_run::{self, RunError};

/// Why a step experiment could not be read back, changed, run or drawn.
#[derive(Debug, thiserror::Error)]
pub enum StepError {
    #[error("{origin}: the step experiment's `twin.run` lacks `{field}`")]
    MissingField { origin: String, field: String },
    #[error("{origin}: `twin.run` field `{field}` is not a number")]
    NotANumber {
        origin: String,
        field: String,
        #[source]
        source: std::num::ParseFloatError,
    },
    #[error("--set `{change}`: write PATH=VALUE, e.g. step.to=300")]
    SetSyntax { change: String },
    #[error("--set `{change}`: {path} must be a number")]
    SetNotANumber { change: String, path: String },
    #[error(
        "--set `{change}`: this scenario's master runs its own set points (the \
         Controller_network master), so the step's levels are its own; `step.at_s` \
         picks which of its steps is measured"
    )]
    OwnSetPoints { change: String },
    #[error("--set `{change}`: open loop, the step is a fraction of VEL's 5 V range, 0 to 1")]
    NotAFraction { change: String },
    #[error("--set `{change}`: a set point in rpm, 0 or more")]
    NegativeSetPoint { change: String },
    #[error(
        "--set `{change}`: the step's time must fall within the run, above 0 and below {duration_s} s"
    )]
    StepOutsideRun { change: String, duration_s: f64 },
    #[error("--set `{change}`: the step has `step.from`, `step.to` and `step.at_s`, not `{path}`")]
    UnknownStepField { change: String, path: String },
    #[error("the duration must be a positive number of seconds, got {duration_s}")]
    Duration { duration_s: f64 },
    #[error("the step at {step_at_s} s must come within the run of {duration_s} s")]
    StepAt { step_at_s: f64, duration_s: f64 },
    #[error("open loop, --{name} is VEL as a fraction of its 5 V range: 0 to 1, got {value}")]
    VelFraction { name: &'static str, value: f64 },
    #[error("scenario `{scenario}`: only a supervisor can close its loop on the light sensor")]
    LightNeedsSupervisor { scenario: String },
    #[error(
        "scenario `{scenario}` has neither a supervisor with an ev-controller slave nor a \
         Controller_network motor node to give a set-point step to: use --open-loop, or \
         such a scenario"
    )]
    NothingToStep { scenario: String },
    #[error("the watched module is not declared")]
    ModuleNotDeclared,
    #[error("module `{module}` is missing from the engine")]
    ModuleMissing { module: String },
    #[error("scenario {scenario} failed")]
    ScenarioFailed {
        scenario: String,
        #[source]
        source: RunError,
    },
    #[error(
        "the motor node's set point does not change after {at_s} s in {duration_s} s of scenario {scenario}: \
         give a longer --duration or an earlier --at"
    )]
    NoChange {
        at_s: f64,
        duration_s: f64,
        scenario: String,
    },
    #[error(transparent)]
    Replay(#[from] twin_sim::replay::ReplayError),
    #[error(transparent)]
    Scenario(#[from] twin_sim::scenario::ScenarioError),
    #[error(transparent)]
    Run(#[from] RunError),
    #[error(transparent)]
    Plot(#[from] PlotError),
}

type Result<T, E = StepError> = std::result::Result<T, E>;

/// Samples of the traces per simulated second.
pub const SAMPLE_HZ: f64 = 500.0;
/// Longest lag looked for between a sensor and the true speed (s).
const MAX_DELAY_S: f64 = 5.0;

/// What drives the step.
#[derive(Debug, Clone)]
pub enum StepDrive {
    /// The bench alone: `VEL` from `from` to `to` (fractions of 5 V).
    OpenLoop {
        params: Box<PlantParams>,
        preset: String,
        /// The EV controller's light detector in adaptive mode.
        adaptive_light: bool,
    },
    /// A scenario whose supervisor's set point steps from `from` to `to` rpm.
    ClosedLoop {
        scenario: Box<Scenario>,
        /// Close the supervisor's loop on the light-sensor rpm, not the hall rpm.
        on_light: bool,
    },
}

/// One step experiment.
#[derive(Debug, Clone)]
pub struct StepConfig {
    pub drive: StepDrive,
    pub from: f64,
    pub to: f64,
    pub step_at_s: f64,
    pub duration_s: f64,
    pub seed: u64,
}

/// The value of `experiment` in a step recording's `twin.run`.
const EXPERIMENT: &str = "step";

impl StepConfig {
    /// What the experiment adds to its recording's `twin.run` (beside the
    /// scenario or the bench it ran on), so that `twin replay` runs it again.
    fn identity(&self) -> BTreeMap<String, String> {
        let mut fields = BTreeMap::from([
            ("experiment".to_string(), EXPERIMENT.to_string()),
            ("step_from".into(), self.from.to_string()),
            ("step_to".into(), self.to.to_string()),
            ("step_at_s".into(), self.step_at_s.to_string()),
        ]);
        match &self.drive {
            StepDrive::OpenLoop { adaptive_light, .. } => {
                fields.insert("step_adaptive_light".into(), adaptive_light.to_string())
            }
            StepDrive::ClosedLoop { on_light, .. } => {
                fields.insert("step_light_feedback".into(), on_light.to_string())
            }
        };
        fields
    }

    /// The step experiment a recording holds, `None` when it holds another
    /// kind of run. `overrides` (`--set PATH=VALUE`) change the scenario or
    /// the bench first, as for a plain run; open loop, `vel_before_fraction`,
    /// `vel_fraction` and `vel_step_at_s` are the step itself.
    pub fn of_recording(recording: &Recording, overrides: &[String]) -> Result<Option<Self>> {
        if recording.run_field("experiment") != Some(EXPERIMENT) {
            return Ok(None);
        }
        let origin = recording.path.display().to_string();
        let field = |k: &str| -> Result<&str> {
            recording
                .run_field(k)
                .ok_or_else(|| StepError::MissingField {
                    origin: origin.clone(),
                    field: k.to_string(),
                })
        };
        let number = |k: &str| -> Result<f64> {
            field(k)?.parse().map_err(|source| StepError::NotANumber {
                origin: origin.clone(),
                field: k.to_string(),
                source,
            })
        };
        let flag = |k: &str| recording.run_field(k) == Some("true");
        // `step.from`, `step.to`, `step.at_s` change the step itself; every
        // other path, the scenario or the bench it ran on.
        let (step_changes, others): (Vec<&String>, Vec<&String>) =
            overrides.iter().partition(|o| o.starts_with("step."));
        let others: Vec<String> = others.into_iter().cloned().collect();
        let spec = RunSpec::from_recording(recording)?.with_overrides(&others)?;
        let mut config = match spec {
            RunSpec::Scenario(scenario) => StepConfig {
                from: number("step_from")?,
                to: number("step_to")?,
                step_at_s: number("step_at_s")?,
                duration_s: scenario.duration_s,
                seed: scenario.seed,
                drive: StepDrive::ClosedLoop {
                    scenario: Box::new(scenario),
                    on_light: flag("step_light_feedback"),
                },
            },
            RunSpec::OpenLoop(o) => StepConfig {
                from: o.vel_before_fraction,
                to: o.vel_fraction,
                step_at_s: o.vel_step_at_s,
                duration_s: o.duration_s,
                seed: o.seed,
                drive: StepDrive::OpenLoop {
                    params: Box::new(o.params),
                    preset: o.preset,
                    adaptive_light: flag("step_adaptive_light"),
                },
            },
        };
        for change in step_changes {
            config.change_step(change)?;
        }
        Ok(Some(config))
    }

    /// One `--set step.from=V` (or `step.to`, `step.at_s`): rpm closed loop,
    /// a fraction of VEL's range open loop, as `twin step` takes them.
    fn change_step(&mut self, change: &str) -> Result<()> {
        let change_owned = || change.to_string();
        let Some((path, value)) = change.split_once('=') else {
            return Err(StepError::SetSyntax {
                change: change_owned(),
            });
        };
        let value: f64 = value
            .trim()
            .parse()
            .ok()
            .filter(|v: &f64| v.is_finite())
            .ok_or_else(|| StepError::SetNotANumber {
                change: change_owned(),
                path: path.trim().to_string(),
            })?;
        let open_loop = matches!(self.drive, StepDrive::OpenLoop { .. });
        let own_set_points = match &self.drive {
            StepDrive::ClosedLoop { scenario, .. } => !scenario
                .nodes
                .iter()
                .any(|n| matches!(n, NodeSpec::Supervisor { .. })),
            StepDrive::OpenLoop { .. } => false,
        };
        match path.trim() {
            "step.from" | "step.to" if own_set_points => {
                return Err(StepError::OwnSetPoints {
                    change: change_owned(),
                });
            }
            "step.from" | "step.to" if open_loop && !(0.0..=1.0).contains(&value) => {
                return Err(StepError::NotAFraction {
                    change: change_owned(),
                });
            }
            "step.from" | "step.to" if value < 0.0 => {
                return Err(StepError::NegativeSetPoint {
                    change: change_owned(),
                });
            }
            "step.from" => self.from = value,
            "step.to" => self.to = value,
            "step.at_s" if !(value > 0.0 && value < self.duration_s) => {
                return Err(StepError::StepOutsideRun {
                    change: change_owned(),
                    duration_s: self.duration_s,
                });
            }
            "step.at_s" => self.step_at_s = value,
            other => {
                return Err(StepError::UnknownStepField {
                    change: change_owned(),
                    path: other.to_string(),
                });
            }
        }
        Ok(())
    }

    /// A line naming the experiment, as `twin replay` prints it.
    pub fn describe(&self) -> String {
        match &self.drive {
            StepDrive::OpenLoop { preset, .. } => format!(
                "step response, open loop on the {preset} preset, VEL {} → {} % at {} s, seed {}, {:.3} s",
                percent(self.from),
                percent(self.to),
                self.step_at_s,
                self.seed,
                self.duration_s
            ),
            StepDrive::ClosedLoop { scenario, .. } => format!(
                "step response, scenario {}, set point {} → {} rpm at {} s, seed {}, {:.3} s",
                scenario.name,
                short(self.from),
                short(self.to),
                self.step_at_s,
                self.seed,
                self.duration_s
            ),
        }
    }
}

/// A number with at most one decimal, and none when it is whole.
pub fn short(v: f64) -> String {
    let s = format!("{v:.1}");
    s.strip_suffix(".0").map(str::to_string).unwrap_or(s)
}

/// A VEL fraction as a percentage: 0.025 → `2.5`.
fn percent(fraction: f64) -> String {
    short(fraction * 100.0)
}

/// The sampled signals, in wheel rpm (the set point in its own unit).
#[derive(Debug, Clone, Default, Serialize)]
pub struct Trace {
    pub time_s: Vec<f64>,
    pub set_point: Vec<f64>,
    pub wheel_rpm: Vec<f64>,
    pub motor_rpm: Vec<f64>,
    pub light_rpm: Vec<f64>,
}

/// One signal's figures, or why it has none.
#[derive(Debug, Clone, Serialize)]
pub struct SignalFigures {
    pub signal: &'static str,
    pub metrics: Option<StepMetrics>,
    /// Its lag behind the true wheel speed (s).
    pub delay_s: Option<f64>,
    pub note: Option<String>,
}

/// The experiment's outcome: what `step.json` holds.
#[derive(Debug, Clone, Serialize)]
pub struct StepReport {
    pub mode: &'static str,
    /// Preset (open loop) or scenario (closed loop).
    pub bench: String,
    pub set_point_unit: &'static str,
    pub from: f64,
    pub to: f64,
    pub step_at_s: f64,
    /// The figures are taken up to here (the next set-point change, or the end).
    pub figures_until_s: f64,
    pub duration_s: f64,
    pub seed: u64,
    /// Fastest wheel speed the light detector sees (plant/src/light.rs).
    pub light_limit_rpm: f64,
    pub light_detector: String,
    pub signals: Vec<SignalFigures>,
    pub recording: PathBuf,
    #[serde(skip)]
    pub trace: Trace,
}

/// What the motor's own speed sensor is on a bench.
fn motor_signal(preset: &str) -> &'static str {
    if preset == "controller-network" {
        "motor (encoder)"
    } else {
        "motor (hall)"
    }
}

/// What the recording's `/experiment/step` channel holds.
#[derive(Debug, Serialize)]
struct StepSample {
    set_point: f64,
    wheel_rpm: f64,
    motor_rpm: f64,
    light_rpm: f64,
}

impl Trace {
    fn push<D: twin_recording::record::Deferred>(
        &mut self,
        rec: &mut twin_recording::record::Recorder<D>,
        t: f64,
        s: StepSample,
    ) -> Result<(), twin_recording::WriteError> {
        let topic = twin_recording::topics::EXPERIMENT_STEP;
        if !rec.has_channel(topic) {
            rec.add_channel(topic, &s)?;
        }
        rec.write(topic, t, &s)?;
        self.time_s.push(t);
        self.set_point.push(s.set_point);
        self.wheel_rpm.push(s.wheel_rpm);
        self.motor_rpm.push(s.motor_rpm);
        self.light_rpm.push(s.light_rpm);
        Ok(())
    }
}

/// What a runner hands back: the traces, the bench, and the step it made.
struct Ran {
    trace: Trace,
    params: PlantParams,
    preset: String,
    /// The EV controller's light detector is adaptive.
    adaptive_light: bool,
    from: f64,
    to: f64,
    step_at_s: f64,
    /// Samples the figures are taken over: up to the next set-point change.
    until: usize,
}

/// Run the experiment, record it to `recording`, and measure it.
pub fn run(config: &StepConfig, recording: &Path, progress: impl FnMut(f64)) -> Result<StepReport> {
    if !(config.duration_s.is_finite() && config.duration_s > 0.0) {
        return Err(StepError::Duration {
            duration_s: config.duration_s,
        });
    }
    if !(config.step_at_s >= 0.0 && config.step_at_s < config.duration_s) {
        return Err(StepError::StepAt {
            step_at_s: config.step_at_s,
            duration_s: config.duration_s,
        });
    }
    let (ran, mode, bench, unit, adaptive) = match &config.drive {
        StepDrive::OpenLoop {
            params,
            preset,
            adaptive_light,
        } => {
            let trace =
                run_open_loop(config, params, preset, *adaptive_light, recording, progress)?;
            let ran = Ran {
                until: trace.time_s.len(),
                trace,
                params: (**params).clone(),
                preset: preset.clone(),
                adaptive_light: *adaptive_light,
                from: config.from,
                to: config.to,
                step_at_s: config.step_at_s,
            };
            (
                ran,
                "open-loop",
                preset.clone(),
                "VEL fraction",
                *adaptive_light,
            )
        }
        StepDrive::ClosedLoop { scenario, on_light } => {
            let ran = run_closed_loop(config, scenario, *on_light, recording, progress)?;
            let adaptive = ran.adaptive_light;
            (ran, "closed-loop", scenario.name.clone(), "rpm", adaptive)
        }
    };
    let (light_detector, light_limit_rpm) = light_limit(&ran.params, &ran.preset, adaptive);
    let closed = mode == "closed-loop";
    let n = ran.until;
    let t = &ran.trace.time_s[..n];
    let wheel = &ran.trace.wheel_rpm[..n];
    let at = ran.step_at_s;
    let options = StepOptions::default();
    let wheel_final = step_metrics(t, wheel, at, None, &options)
        .ok()
        .map(|m| m.final_value);
    let mut signals = Vec::new();
    for (signal, y) in [
        ("wheel (true)", wheel),
        (motor_signal(&ran.preset), &ran.trace.motor_rpm[..n]),
        ("light sensor", &ran.trace.light_rpm[..n]),
    ] {
        let is_wheel = signal.starts_with("wheel");
        // Closed loop the set point is the reference; open loop a sensor is
        // held against the true speed.
        let reference = if closed {
            Some(ran.to)
        } else if is_wheel {
            None
        } else {
            wheel_final
        };
        let (mut metrics, mut note) = match step_metrics(t, y, at, reference, &options) {
            Ok(m) => (Some(m), None),
            Err(e) => (None, Some(e.to_string())),
        };
        // A light sensor that ends at 0 has not responded: it lost the flag.
        let reads_zero = match (&metrics, y.last()) {
            (Some(m), _) => m.final_value.abs() < 1.0,
            (None, Some(last)) => last.abs() < 1.0,
            (None, None) => false,
        };
        // Above the detector's limit a reading is no measurement, whether
        // it fell to 0 (the fixed threshold) or counts the dips the wheel
        // still makes (the adaptive one misses some and reads far too low).
        let beyond = wheel_final.filter(|&w| w > light_limit_rpm);
        if signal.starts_with("light") && (reads_zero || beyond.is_some()) {
            let last = metrics
                .as_ref()
                .map(|m| m.final_value)
                .or(y.last().copied())
                .unwrap_or(0.0);
            metrics = None;
            note = Some(match beyond {
                Some(w) => format!(
                    "reads {last:.0} at the end: the wheel runs at {w:.0} rpm, above the {light_limit_rpm:.0} rpm the detector can see"
                ),
                None => "reads 0 at the end: it does not see the flag".to_string(),
            });
        }
        let delay_s = match metrics {
            Some(_) if !is_wheel => match delay(t, wheel, y, at, MAX_DELAY_S) {
                Ok(d) => Some(d),
                Err(e) => {
                    note = note.or(Some(format!("no delay: {e}")));
                    None
                }
            },
            _ => None,
        };
        signals.push(SignalFigures {
            signal,
            metrics,
            delay_s,
            note,
        });
    }
    Ok(StepReport {
        mode,
        bench,
        set_point_unit: unit,
        from: ran.from,
        to: ran.to,
        step_at_s: at,
        figures_until_s: t.last().copied().unwrap_or(0.0),
        duration_s: config.duration_s,
        seed: config.seed,
        light_limit_rpm,
        light_detector,
        signals,
        recording: recording.to_path_buf(),
        trace: ran.trace,
    })
}

fn run_open_loop(
    config: &StepConfig,
    params: &PlantParams,
    preset: &str,
    adaptive: bool,
    recording: &Path,
    progress: impl FnMut(f64),
) -> Result<Trace> {
    for (name, v) in [("from", config.from), ("to", config.to)] {
        if !(0.0..=1.0).contains(&v) {
            return Err(StepError::VelFraction { name, value: v });
        }
    }
    let mut ol = OpenLoop::new(params.clone(), preset);
    ol.experiment = config.identity();
    ol.seed = config.seed;
    ol.duration_s = config.duration_s;
    ol.vel_before_fraction = config.from;
    ol.vel_fraction = config.to;
    ol.vel_step_at_s = config.step_at_s;
    ol.record_hz = 200.0;
    let step = SimDuration::from_secs_f64(ol.step_s);
    let sample_every = ((1.0 / SAMPLE_HZ) / ol.step_s).round().max(1.0) as u64;
    let mut instruments = Instruments::new(params, preset, adaptive);
    let mut trace = Trace::default();
    let mut k = 0u64;
    openloop::run_with(&ol, recording, progress, |rec, sensors: &Sensors| {
        k += 1;
        let now = SimTime::ZERO + SimDuration(step.0 * k);
        instruments.tick(now, sensors);
        if k.is_multiple_of(sample_every) {
            let r = instruments.read();
            let vel = ol.actuators_at(sensors.time_s - 0.5 * ol.step_s).vel_volts / 5.0;
            let sample = StepSample {
                set_point: vel,
                wheel_rpm: sensors.wheel_rpm,
                motor_rpm: r.motor,
                light_rpm: r.light,
            };
            trace.push(rec, now.as_secs_f64(), sample)?;
        }
        Ok(())
    })?;
    Ok(trace)
}

fn run_closed_loop(
    config: &StepConfig,
    scenario: &Scenario,
    on_light: bool,
    recording: &Path,
    progress: impl FnMut(f64),
) -> Result<Ran> {
    let mut scenario = scenario.clone();
    scenario.duration_s = config.duration_s;
    scenario.seed = config.seed;
    let supervised = scenario.nodes.iter_mut().find_map(|n| match n {
        NodeSpec::Supervisor {
            slaves,
            set_points,
            bus,
            use_light_rpm,
            ..
        } => {
            *set_points = vec![[0.0, config.from], [config.step_at_s, config.to]];
            *use_light_rpm |= on_light;
            slaves.first().map(|s| (*s, bus.clone()))
        }
        _ => None,
    });
    if supervised.is_none() && on_light {
        return Err(StepError::LightNeedsSupervisor {
            scenario: scenario.name.clone(),
        });
    }
    // The node whose module is watched: the supervisor's first slave, or
    // the Controller_network motor node, whose master runs its own set-point
    // schedule.
    let watched = match &supervised {
        Some((slave, bus)) => scenario.nodes.iter().find_map(|n| match n {
            NodeSpec::EvController {
                bus: b, module, id, ..
            } if id == slave && b == bus => Some(module.clone()),
            _ => None,
        }),
        None => scenario.nodes.iter().find_map(|n| match n {
            NodeSpec::MotorNode { module, .. } => Some(module.clone()),
            _ => None,
        }),
    };
    let Some(module) = watched else {
        return Err(StepError::NothingToStep {
            scenario: scenario.name.clone(),
        });
    };
    let spec = scenario
        .modules
        .iter()
        .find(|m| m.name == module)
        .ok_or(StepError::ModuleNotDeclared)?;
    let params = scenario.module_params(spec)?;
    let preset = spec.preset.clone();
    // The watched module's controller runs the detector the scenario gives it.
    let adaptive_light = scenario.nodes.iter().any(|n| {
        matches!(n, NodeSpec::EvController { module: m, light_detector, .. }
            if *m == module && light_detector.adaptive())
    });
    let ratio = params.gearbox.ratio;
    let mut trace = Trace::default();
    let (from, to, at) = (config.from, config.to, config.step_at_s);
    let period = SimDuration::from_secs_f64(1.0 / SAMPLE_HZ);
    // The engine is built from the scenario, whose module this is: a
    // module missing from it is a bug, said after the run.
    let mut missing = false;
    virtual_run::run_sampled(
        &scenario,
        recording,
        progress,
        &config.identity(),
        Some(period),
        |now, engine, rec| {
            let Some(m) = engine.modules.iter().position(|m| m.name == module) else {
                missing = true;
                return Ok(());
            };
            let nodes = engine
                .nodes
                .iter()
                .filter(|n| n.module == Some(m))
                .map(|n| n.node.as_ref());
            let r = read_instruments(nodes, ratio);
            let t = now.as_secs_f64();
            let set_point = match (&supervised, r.set_point) {
                (Some(_), _) => {
                    if t + 1e-12 >= at {
                        to
                    } else {
                        from
                    }
                }
                (None, sp) => sp.unwrap_or(f64::NAN),
            };
            let sample = StepSample {
                set_point,
                wheel_rpm: engine.modules[m].plant.sensors().wheel_rpm,
                motor_rpm: r.motor,
                light_rpm: r.light,
            };
            trace.push(rec, t, sample)
        },
    )
    .map_err(|source| StepError::ScenarioFailed {
        scenario: scenario.name.clone(),
        source,
    })?;
    if missing {
        return Err(StepError::ModuleMissing { module });
    }
    if supervised.is_some() {
        return Ok(Ran {
            until: trace.time_s.len(),
            trace,
            params,
            preset,
            adaptive_light,
            from,
            to,
            step_at_s: at,
        });
    }
    // The Controller_network master's own step: the first change of the motor node's
    // set point at or after `at`, measured until the next change.
    let sp = &trace.set_point;
    let tt = &trace.time_s;
    let Some(i) = (1..sp.len()).find(|&i| tt[i] >= at && sp[i] != sp[i - 1]) else {
        return Err(StepError::NoChange {
            at_s: at,
            duration_s: config.duration_s,
            scenario: scenario.name.clone(),
        });
    };
    let until = (i + 1..sp.len())
        .find(|&j| sp[j] != sp[i])
        .unwrap_or(sp.len());
    Ok(Ran {
        from: sp[i - 1],
        to: sp[i],
        step_at_s: tt[i - 1],
        until,
        trace,
        params,
        preset,
        adaptive_light,
    })
}

/// The plot of `step.png`: set point (closed loop), true wheel, motor and
/// light rpm against time.
pub fn plot(report: &StepReport, path: &Path) -> Result<(), PlotError> {
    plot_with(report, Vec::new(), path)
}

/// [`plot`], with `extra` curves drawn after the twin's (a bench's own).
pub fn plot_with(
    report: &StepReport,
    extra: Vec<Series<'_>>,
    path: &Path,
) -> Result<(), PlotError> {
    let tr = &report.trace;
    let pts = |y: &[f64]| -> Vec<(f64, f64)> {
        tr.time_s
            .iter()
            .zip(y)
            .filter(|(_, v)| v.is_finite())
            .map(|(&t, &v)| (t, v))
            .collect()
    };
    let mut series = Vec::new();
    if report.mode == "closed-loop" {
        series.push(Series {
            name: "set point",
            color: plot::SET_POINT,
            points: pts(&tr.set_point),
            dots: false,
            width: 2,
        });
    }
    series.push(Series {
        name: "wheel (true)",
        color: plot::WHEEL,
        points: pts(&tr.wheel_rpm),
        dots: false,
        width: 2,
    });
    series.push(Series {
        name: report.signals[1].signal,
        color: plot::MOTOR,
        points: pts(&tr.motor_rpm),
        dots: false,
        width: 2,
    });
    series.push(Series {
        name: "light sensor",
        color: plot::LIGHT,
        points: pts(&tr.light_rpm),
        dots: false,
        width: 2,
    });
    series.extend(extra);
    let y_range = plot::fit_range(
        series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.1))
            .chain([0.0]),
        0.05,
    );
    let title = plot_title(report);
    let axes = Axes {
        title: &title,
        x_label: "time (s)",
        y_label: "wheel rpm",
        x_range: (0.0, report.duration_s),
        y_range,
        legend_upper_left: false,
    };
    plot::line_plot(path, &axes, &series, (960, 560))
}

/// The plot's title: the step as the printed table gives it.
fn plot_title(report: &StepReport) -> String {
    if report.mode == "closed-loop" {
        format!(
            "{}: set point {} → {} rpm at {} s",
            report.bench,
            short(report.from),
            short(report.to),
            report.step_at_s
        )
    } else {
        format!(
            "{} open loop: VEL {} → {} % at {} s",
            report.bench,
            percent(report.from),
            percent(report.to),
            report.step_at_s
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_plot_title_gives_the_step_as_the_table_does() {
        let report = StepReport {
            mode: "open-loop",
            bench: "vemodule".into(),
            set_point_unit: "VEL fraction",
            from: 0.025,
            to: 0.045,
            step_at_s: 2.0,
            figures_until_s: 6.0,
            duration_s: 6.0,
            seed: 1,
            light_limit_rpm: 0.0,
            light_detector: String::new(),
            signals: Vec::new(),
            recording: PathBuf::new(),
            trace: Trace::default(),
        };
        assert_eq!(
            plot_title(&report),
            "vemodule open loop: VEL 2.5 → 4.5 % at 2 s"
        );
        let closed = StepReport {
            mode: "closed-loop",
            bench: "ev-meb".into(),
            from: 100.0,
            to: 250.5,
            ..report
        };
        assert_eq!(
            plot_title(&closed),
            "ev-meb: set point 100 → 250.5 rpm at 2 s"
        );
    }
}
