//! A calibration job: the measured log (a CSV file, or a recording that
//! `twin supervise` or the twin made), what its columns or signals are, the
//! scenario that ran the experiment, and the parameters to fit. Every
//! mistake in it is reported with the file, line and column or field.

use super::CalibrateError as E;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use twin_sim::scenario::{NodeSpec, Scenario};

use super::csv_log::Table;
use super::recorded::Recorded;
use super::signal::{TwinSignal, Unit};

/// Where the measured samples come from.
enum Source {
    Csv(Table),
    Recording(Recorded),
}

impl Source {
    /// `(time s, value)` of a column or signal.
    fn column(&self, name: &str, skip_empty: bool) -> Result<Vec<(f64, f64)>, E> {
        match self {
            Source::Csv(table) => table.column(name, skip_empty),
            Source::Recording(recorded) => recorded.signal(name),
        }
    }
}

/// `scenario` whose supervisors step their set point as the log's did.
fn follow_schedule(mut scenario: Scenario, schedule: &[(f64, f64)]) -> Scenario {
    for node in &mut scenario.nodes {
        if let NodeSpec::Supervisor { set_points, .. } = node {
            *set_points = schedule.iter().map(|&(t, v)| [t, v]).collect();
        }
    }
    scenario
}

/// The job file as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct JobFile {
    /// The CSV file, relative to the job file.
    log: Option<String>,
    /// Or an MCAP recording, relative to the job file.
    recording: Option<String>,
    /// Scenario file (relative to the job file) or embedded scenario name.
    scenario: String,
    #[serde(default = "default_time_column")]
    time_column: String,
    #[serde(default = "default_time_unit")]
    time_unit: String,
    step: Option<StepFile>,
    /// The column or signal that holds the set point: the step is its first
    /// change, and a supervisor in the scenario follows its schedule.
    set_point: Option<String>,
    /// Levels whose first crossing after the step the report compares.
    crossings: Option<Vec<f64>>,
    #[serde(rename = "signal")]
    signals: Vec<SignalFile>,
    #[serde(rename = "fit")]
    parameters: Vec<ParameterFile>,
    /// `[from, to]` (s): the part of the log the fit uses.
    fit_window_s: Option<[f64; 2]>,
    /// `[from, to]` (s): a part left out of the fit, to check it on.
    check_window_s: Option<[f64; 2]>,
}

fn default_time_column() -> String {
    "time_s".into()
}
fn default_time_unit() -> String {
    "s".into()
}

/// The command: a step of the set point.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
struct StepFile {
    at_s: f64,
    from: f64,
    to: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SignalFile {
    column: String,
    unit: String,
    twin: String,
    /// `skip`: an empty cell is a row where the signal was not measured
    /// (a curve read off a plot); otherwise an empty cell is an error.
    #[serde(default)]
    empty: Option<String>,
    #[serde(default = "one")]
    weight: f64,
}

fn one() -> f64 {
    1.0
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ParameterFile {
    path: String,
    min: f64,
    max: f64,
    start: f64,
}

/// One measured signal: its samples in the twin's unit.
#[derive(Debug, Clone)]
pub struct Measured {
    pub column: String,
    pub twin: TwinSignal,
    pub unit: Unit,
    pub weight: f64,
    /// `(time s, value in the twin's unit)`.
    pub samples: Vec<(f64, f64)>,
}

impl Measured {
    /// The samples within `window` (s), both ends included.
    pub fn rows_in(&self, window: (f64, f64)) -> Vec<(f64, f64)> {
        self.samples
            .iter()
            .copied()
            .filter(|p| p.0 >= window.0 && p.0 <= window.1)
            .collect()
    }
}

/// One parameter to fit.
#[derive(Debug, Clone, PartialEq)]
pub struct Parameter {
    /// Its path in a plant parameter file (`motor.rotor_inertia`).
    pub path: String,
    pub min: f64,
    pub max: f64,
    pub start: f64,
}

/// A calibration job, checked.
#[derive(Debug, Clone)]
pub struct Job {
    pub path: PathBuf,
    pub log: PathBuf,
    pub scenario: Scenario,
    pub step_at_s: f64,
    pub step_from: f64,
    pub step_to: f64,
    pub signals: Vec<Measured>,
    pub parameters: Vec<Parameter>,
    pub fit_window: (f64, f64),
    pub check_window: Option<(f64, f64)>,
    /// Levels whose first crossing after the step the report compares.
    pub crossings: Vec<f64>,
    /// The set point's next change after the step (s), where the step's
    /// figures end; infinite when there is none.
    pub step_end_s: f64,
}

/// Shortest log the fit accepts after the step (s).
const MIN_AFTER_STEP_S: f64 = 0.2;

/// `file:line:col` of a byte offset.
fn at(path: &Path, text: &str, offset: usize) -> String {
    let (line, col) = plant::toml_errors::line_col(text, offset);
    format!("{}:{line}:{col}", path.display())
}

impl Job {
    /// Reads and checks a job file and the log and scenario it names.
    pub fn load(path: &Path) -> Result<Job, E> {
        Job::load_with_log(path, None)
    }

    /// Reads and checks a job file, with `log` (a CSV file, or a recording
    /// if it ends in `.mcap`) in place of the log it names, if given.
    pub fn load_with_log(path: &Path, log: Option<&Path>) -> Result<Job, E> {
        let text = std::fs::read_to_string(path).map_err(|source| E::ReadJob {
            path: path.to_path_buf(),
            source,
        })?;
        let doc = plant::toml_errors::parse(&text).map_err(|e| {
            let place = e
                .span
                .map_or(path.display().to_string(), |s| at(path, &text, s.start));
            E::JobToml {
                at: place,
                field: String::new(),
                why: plant::toml_errors::in_words(&e.message).to_string(),
            }
        })?;
        let file: JobFile = plant::toml_errors::deserialize(&doc).map_err(|e| {
            let place = e
                .span
                .map_or(path.display().to_string(), |s| at(path, &text, s.start));
            let field = if e.path.is_empty() {
                String::new()
            } else {
                format!(" `{}`:", e.path)
            };
            E::JobToml {
                at: place,
                field,
                why: plant::toml_errors::in_words(&e.message).to_string(),
            }
        })?;
        let place = |key: &str| {
            plant::toml_errors::span_of(&doc, key)
                .map_or(path.display().to_string(), |s| at(path, &text, s.start))
        };
        let dir = path.parent().unwrap_or(Path::new("."));
        let scenario_path = dir.join(&file.scenario);
        let scenario = if scenario_path.is_file() {
            Scenario::load(&scenario_path.display().to_string())
        } else {
            Scenario::load(&file.scenario)
        }
        .map_err(|source| E::JobScenario {
            at: place("scenario"),
            scenario: file.scenario.clone(),
            source,
        })?;
        let time_scale = match file.time_unit.as_str() {
            "s" => 1.0,
            "ms" => 1e-3,
            "us" | "µs" => 1e-6,
            other => {
                return Err(E::TimeUnit {
                    at: place("time_unit"),
                    unit: other.to_string(),
                });
            }
        };
        if file.signals.is_empty() {
            return Err(E::NoSignals {
                path: path.to_path_buf(),
            });
        }
        if file.parameters.is_empty() {
            return Err(E::NoParametersToFit {
                path: path.to_path_buf(),
            });
        }
        let parameters = check_parameters(&file.parameters, |i| place(&format!("fit.{i}")))?;
        let given = log.map(|p| (p.to_path_buf(), p.extension().is_some_and(|x| x == "mcap")));
        let (log, source) = match (given, &file.log, &file.recording) {
            (Some((mcap, true)), ..) => (mcap.clone(), Source::Recording(Recorded::read(&mcap)?)),
            (Some((csv, false)), ..) => {
                let table = super::csv_log::read(&csv, &file.time_column, time_scale)?;
                (csv, Source::Csv(table))
            }
            (None, Some(csv), None) => {
                let log = dir.join(csv);
                let table = super::csv_log::read(&log, &file.time_column, time_scale)?;
                (log, Source::Csv(table))
            }
            (None, None, Some(mcap)) => {
                let log = dir.join(mcap);
                (log.clone(), Source::Recording(Recorded::read(&log)?))
            }
            (None, Some(_), Some(_)) => {
                return Err(E::TwoLogs {
                    at: place("recording"),
                });
            }
            (None, None, None) => {
                return Err(E::NoLog {
                    path: path.to_path_buf(),
                });
            }
        };
        let mut signals = Vec::new();
        for (i, s) in file.signals.iter().enumerate() {
            let where_ = place(&format!("signal.{i}"));
            let within = |source| E::At {
                at: where_.clone(),
                source: Box::new(source),
            };
            let twin = TwinSignal::from_name(&s.twin).map_err(within)?;
            let unit = Unit::parse(&s.unit, twin).map_err(within)?;
            let skip_empty = match s.empty.as_deref() {
                None => false,
                Some("skip") => true,
                Some(other) => {
                    return Err(E::EmptyChoice {
                        at: where_,
                        given: other.to_string(),
                    });
                }
            };
            if skip_empty && matches!(source, Source::Recording(_)) {
                return Err(E::EmptyInRecording { at: where_ });
            }
            if !(s.weight.is_finite() && s.weight > 0.0) {
                return Err(E::Weight {
                    at: where_,
                    weight: s.weight,
                });
            }
            let samples = source.column(&s.column, skip_empty)?;
            let samples = samples
                .into_iter()
                .map(|(t, v)| (t, unit.to_twin(v)))
                .collect();
            signals.push(Measured {
                column: s.column.clone(),
                twin,
                unit,
                weight: s.weight,
                samples,
            });
        }
        let (first, last) = match &source {
            Source::Csv(table) => table.time_span(),
            Source::Recording(_) => Recorded::time_span(
                &signals
                    .iter()
                    .map(|s| s.samples.clone())
                    .collect::<Vec<_>>(),
            ),
        };
        let set_point = match &file.set_point {
            Some(name) => source.column(name, true).map_err(|source| E::At {
                at: place("set_point"),
                source: Box::new(source),
            })?,
            None => Vec::new(),
        };
        let schedule = super::recorded::changes(&set_point);
        let step = match (&file.step, schedule.get(1)) {
            (Some(step), _) => *step,
            // At the first reading of the new set point, as the twin's
            // master reports its own step.
            (None, Some(&(_, to))) => StepFile {
                at_s: set_point.iter().find(|p| p.1 == to).map_or(0.0, |p| p.0),
                from: schedule[0].1,
                to,
            },
            (None, None) if file.set_point.is_some() => {
                return Err(E::SetPointConstant {
                    at: place("set_point"),
                    set_point: file.set_point.clone().unwrap_or_default(),
                    log,
                });
            }
            (None, None) => {
                return Err(E::NoStepGiven {
                    path: path.to_path_buf(),
                });
            }
        };
        let step = &step;
        if step.from == step.to {
            return Err(E::StepConstant {
                at: place("step"),
                from: step.from,
                to: step.to,
            });
        }
        let scenario = if schedule.is_empty() {
            scenario
        } else {
            follow_schedule(scenario, &schedule)
        };
        if step.at_s < first || step.at_s > last {
            return Err(E::StepOutsideLog {
                at: place("step"),
                step_s: step.at_s,
                first,
                last,
            });
        }
        if last - step.at_s < MIN_AFTER_STEP_S {
            return Err(E::LogTooShort {
                log,
                after_s: last - step.at_s,
                least_s: MIN_AFTER_STEP_S,
            });
        }
        let window = |w: Option<[f64; 2]>, key: &str, default: (f64, f64)| {
            let Some([a, b]) = w else {
                return Ok(default);
            };
            if !(a.is_finite() && b.is_finite() && a < b) {
                return Err(E::WindowOrder {
                    at: place(key),
                    key: key.to_string(),
                });
            }
            if b <= step.at_s || a >= last {
                return Err(E::WindowEmpty {
                    at: place(key),
                    key: key.to_string(),
                    from: a,
                    to: b,
                    step_s: step.at_s,
                    last,
                });
            }
            Ok((a, b))
        };
        let fit_window = window(file.fit_window_s, "fit_window_s", (first, last))?;
        let check_window = match file.check_window_s {
            None => None,
            Some(w) => Some(window(Some(w), "check_window_s", (first, last))?),
        };
        Ok(Job {
            path: path.to_path_buf(),
            log,
            scenario,
            step_at_s: step.at_s,
            step_from: step.from,
            step_to: step.to,
            signals,
            parameters,
            fit_window,
            check_window,
            step_end_s: schedule
                .iter()
                .map(|p| p.0)
                .find(|&t| t > step.at_s)
                .unwrap_or(f64::INFINITY),
            crossings: file.crossings.clone().unwrap_or_else(|| {
                vec![
                    step.from + 0.5 * (step.to - step.from),
                    step.from + 0.9 * (step.to - step.from),
                ]
            }),
        })
    }

    /// The last time the log covers (s).
    pub fn end_s(&self) -> f64 {
        self.signals
            .iter()
            .filter_map(|s| s.samples.last().map(|p| p.0))
            .fold(self.step_at_s, f64::max)
    }
}

/// Bounds that hold their start, and paths the plant knows.
fn check_parameters(
    files: &[ParameterFile],
    place: impl Fn(usize) -> String,
) -> Result<Vec<Parameter>, E> {
    let mut out: Vec<Parameter> = Vec::new();
    for (i, p) in files.iter().enumerate() {
        let here = place(i);
        let path = || p.path.clone();
        if !(p.min.is_finite() && p.max.is_finite() && p.start.is_finite()) {
            return Err(E::BoundsNotNumbers {
                at: here,
                path: path(),
            });
        }
        if p.min >= p.max {
            return Err(E::BoundsOrder {
                at: here,
                path: path(),
                min: p.min,
                max: p.max,
            });
        }
        if p.start < p.min || p.start > p.max {
            return Err(E::StartOutside {
                at: here,
                path: path(),
                start: p.start,
                min: p.min,
                max: p.max,
            });
        }
        if out.iter().any(|o| o.path == p.path) {
            return Err(E::FittedTwice {
                at: here,
                path: path(),
            });
        }
        super::apply::check_path(&p.path).map_err(|source| E::At {
            at: here.clone(),
            source: Box::new(source),
        })?;
        out.push(Parameter {
            path: p.path.clone(),
            min: p.min,
            max: p.max,
            start: p.start,
        });
    }
    Ok(out)
}
