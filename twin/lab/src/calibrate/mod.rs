//! `twin calibrate`: the plant's parameters fitted to a log of the real bench.
//!
//! A job file names the log (a CSV file, or an MCAP recording), what its
//! columns or signals are, the scenario that ran the experiment and the
//! parameters to fit with their bounds. The same
//! experiment runs on the virtual clock with trial values, the node code the
//! bench ran reading the plant as the bench's master read it, until the
//! readings match the log's (see `fit` for the method and why).

pub mod apply;
pub mod csv_log;
pub mod fit;
pub mod job;
pub mod recorded;
pub mod report;
pub mod signal;
pub mod twin_run;
pub mod uncertainty;

use serde::Serialize;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub use job::Job;
use report::{SignalFit, StepFigures};
use twin_run::TwinReads;

/// Why a calibration could not run: its job file, its log, the twin's runs
/// or the search, each in the words of the file it is about.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    #[error("cannot read the calibration file {}", path.display())]
    ReadJob {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Text that is not TOML, or does not fit the job's fields.
    #[error("{at}:{field} {why}")]
    JobToml {
        at: String,
        field: String,
        why: String,
    },
    #[error("{at}: the scenario `{scenario}`")]
    JobScenario {
        at: String,
        scenario: String,
        #[source]
        source: twin_sim::scenario::ScenarioError,
    },
    #[error("{at}: time unit `{unit}` is not one the twin knows: s, ms or us")]
    TimeUnit { at: String, unit: String },
    #[error("{}: no `[[signal]]`: name at least one measured column", path.display())]
    NoSignals { path: PathBuf },
    #[error("{}: no `[[fit]]`: name at least one parameter to fit", path.display())]
    NoParametersToFit { path: PathBuf },
    #[error("{at}: both `log` and `recording`: name one measured log")]
    TwoLogs { at: String },
    #[error(
        "{}: no measured log: name a CSV file as `log = \"…\"` or an MCAP \
         recording as `recording = \"…\"` (or give one with --log)",
        path.display()
    )]
    NoLog { path: PathBuf },
    /// What is wrong at a place of the job file.
    #[error("{at}")]
    At {
        at: String,
        #[source]
        source: Box<CalibrateError>,
    },
    #[error("{at}: `empty = \"{given}\"`: the one choice is \"skip\"")]
    EmptyChoice { at: String, given: String },
    #[error("{at}: `empty` is for a CSV file's cells; a recording has no empty cells")]
    EmptyInRecording { at: String },
    #[error("{at}: `weight` must be a number above 0, not {weight}")]
    Weight { at: String, weight: f64 },
    #[error(
        "{at}: the set point `{set_point}` never changes in {}: a constant command excites \
         nothing, so there is nothing to identify",
        log.display()
    )]
    SetPointConstant {
        at: String,
        set_point: String,
        log: PathBuf,
    },
    #[error(
        "{}: no `[step]` and no `set_point`: say when the command stepped, \
         or which column holds the set point",
        path.display()
    )]
    NoStepGiven { path: PathBuf },
    #[error(
        "{at}: the step goes from {from} to {to}: a constant command excites nothing, \
         so there is nothing to identify"
    )]
    StepConstant { at: String, from: f64, to: f64 },
    #[error(
        "{at}: the step at {step_s} s is outside the log, which runs from {first} s to {last} s"
    )]
    StepOutsideLog {
        at: String,
        step_s: f64,
        first: f64,
        last: f64,
    },
    #[error(
        "{}: the log ends {after_s:.3} s after the step: too short to identify anything \
         (at least {least_s} s)",
        log.display()
    )]
    LogTooShort {
        log: PathBuf,
        after_s: f64,
        least_s: f64,
    },
    #[error("{at}: `{key}` must be [from, to] with from < to")]
    WindowOrder { at: String, key: String },
    #[error(
        "{at}: `{key}` [{from}, {to}] holds nothing after the step at {step_s} s in a log ending at {last} s"
    )]
    WindowEmpty {
        at: String,
        key: String,
        from: f64,
        to: f64,
        step_s: f64,
        last: f64,
    },
    #[error("{at}: `{path}`: min, max and start must be numbers")]
    BoundsNotNumbers { at: String, path: String },
    #[error("{at}: `{path}`: min {min} is not below max {max}")]
    BoundsOrder {
        at: String,
        path: String,
        min: f64,
        max: f64,
    },
    #[error("{at}: `{path}`: the start {start} is outside its bounds [{min}, {max}]")]
    StartOutside {
        at: String,
        path: String,
        start: f64,
        min: f64,
        max: f64,
    },
    #[error("{at}: `{path}` is fitted twice")]
    FittedTwice { at: String, path: String },
    #[error("`{path}` is no parameter of the plant (no table `{table}`)")]
    NoTable { path: String, table: String },
    #[error("`{path}` is a whole number (a count), so it cannot be fitted")]
    WholeNumber { path: String },
    #[error("`{path}` is not a number, so it cannot be fitted")]
    NotANumberParameter { path: String },
    #[error("`{path}` is no parameter of the plant; `{table}` has: {has}")]
    NoParameter {
        path: String,
        table: String,
        has: String,
    },
    #[error("`twin = \"{name}\"` is no signal the twin has: {known}")]
    UnknownSignal { name: String, known: String },
    #[error("unit `{unit}`{kind} does not fit the twin's {signal}: use one of {known}")]
    Unit {
        unit: String,
        kind: &'static str,
        signal: &'static str,
        known: String,
    },
    #[error("cannot read the log {}", path.display())]
    ReadLog {
        path: PathBuf,
        #[source]
        source: csv::Error,
    },
    #[error("{}: no header row", path.display())]
    NoHeader {
        path: PathBuf,
        #[source]
        source: csv::Error,
    },
    #[error("{}: no column `{column}` for the time (columns: {columns})", path.display())]
    NoTimeColumn {
        path: PathBuf,
        column: String,
        columns: String,
    },
    #[error("{at}: column `{column}`: `{cell}` is not a time")]
    NotATime {
        at: String,
        column: String,
        cell: String,
        #[source]
        source: csv_log::NotANumber,
    },
    #[error("{at}: column `{column}`: time goes backwards or stands still ({cell} after {before})")]
    TimeBackwards {
        at: String,
        column: String,
        cell: String,
        before: f64,
    },
    #[error("{}: fewer than two rows of data", path.display())]
    TooFewRows { path: PathBuf },
    #[error("{at}: {len} cells where the header has {expected}")]
    UnequalRow { at: String, len: u64, expected: u64 },
    #[error("{at}: not UTF-8 text: is this a CSV file?")]
    NotUtf8 { at: String },
    #[error("{}: {why}", path.display())]
    Csv { path: PathBuf, why: String },
    #[error("{}: no column `{column}` (columns: {columns})", path.display())]
    NoColumn {
        path: PathBuf,
        column: String,
        columns: String,
    },
    #[error(
        "{at}: column `{column}` is empty; if the signal was not measured there, \
         say `empty = \"skip\"` for it in the calibration file"
    )]
    EmptyCell { at: String, column: String },
    #[error("{at}: column `{column}`: `{cell}`")]
    NotANumber {
        at: String,
        column: String,
        cell: String,
        #[source]
        source: csv_log::NotANumber,
    },
    #[error("{}: column `{column}` has fewer than two values", path.display())]
    TooFewValues { path: PathBuf, column: String },
    #[error("cannot read the recording {}", path.display())]
    ReadRecording {
        path: PathBuf,
        #[source]
        source: twin_recording::ReadError,
    },
    #[error("{}: no signal `{name}`{hint}", path.display())]
    NoSignal {
        path: PathBuf,
        name: String,
        hint: String,
    },
    #[error("{}: signal `{name}` has fewer than two values", path.display())]
    TooFewSignalValues { path: PathBuf, name: String },
    #[error(
        "scenario {scenario} has no master the calibration can read (a `controller-network-master` \
         or a `supervisor`): calibration compares what a master read"
    )]
    NoMaster { scenario: String },
    #[error(
        "in scenario {scenario}, the master never {what} within {until_s} s: \
         there is no step to compare"
    )]
    NoStep {
        scenario: String,
        what: String,
        until_s: f64,
    },
    #[error("column `{column}` has fewer than two values in the fit window [{from}, {to}] s")]
    FewInWindow { column: String, from: f64, to: f64 },
    #[error("column `{column}` is constant in the fit window: nothing to identify from it")]
    Constant { column: String },
    /// The optimiser refused its starting simplex, in its own words.
    #[error("{why}")]
    Optimiser { why: String },
    #[error("the optimiser failed: {why}")]
    OptimiserFailed { why: String },
    #[error("the optimiser found no parameters at all")]
    NoParameters,
    #[error("no search finished")]
    NoSearchFinished,
    #[error("the plant refused every trial: no parameters in the bounds give a run")]
    EveryTrialRefused,
    #[error("a simulation thread failed")]
    SimulationThread,
    /// The twin with the starting values, which does not run.
    #[error("the twin with the starting values")]
    Start(#[source] Box<CalibrateError>),
    #[error(
        "{}: column `{column}` ({unit}) averages {measured} after the step, {ratio:.1} times what \
         the twin's {signal} gives ({twin}): is the unit right?",
        log.display()
    )]
    Magnitude {
        log: PathBuf,
        column: String,
        unit: &'static str,
        measured: String,
        ratio: f64,
        signal: &'static str,
        twin: String,
    },
    #[error("cannot create {}", dir.display())]
    CreateDir {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
    #[error(transparent)]
    Toml(#[from] toml::ser::Error),
    #[error(transparent)]
    Build(#[from] twin_sim::nodes_build::BuildError),
    #[error(transparent)]
    Engine(#[from] twin_sim::engine::EngineError),
}

type Result<T, E = CalibrateError> = std::result::Result<T, E>;

/// How long the fit may search.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Most Nelder–Mead iterations of each simplex.
    pub max_iterations: u64,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            max_iterations: 150,
        }
    }
}

/// One fitted parameter.
#[derive(Debug, Clone, Serialize)]
pub struct Fitted {
    pub path: String,
    pub start: f64,
    pub value: f64,
    /// One standard error; `None` where the log does not determine it.
    pub std_error: Option<f64>,
    pub min: f64,
    pub max: f64,
    /// Within 1 % (of the log span) of a bound: the bound, not the log, set it.
    pub at_bound: bool,
}

/// Two parameters the log cannot tell apart.
#[derive(Debug, Clone, Serialize)]
pub struct Entangled {
    pub a: String,
    pub b: String,
    pub correlation: f64,
    /// What measurement would separate them, in words.
    pub separate_by: String,
}

/// What a calibration found.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    pub job: String,
    pub log: String,
    pub parameters: Vec<Fitted>,
    pub cost_start: f64,
    pub cost: f64,
    pub converged: bool,
    pub stopped: String,
    pub iterations: u64,
    pub simulations: u64,
    pub refused_simulations: u64,
    pub fit: Vec<SignalFit>,
    pub check: Vec<SignalFit>,
    pub fit_at_start: Vec<SignalFit>,
    pub steps: Vec<StepFigures>,
    pub entangled: Vec<Entangled>,
    /// Parameters no reading depends on.
    pub unseen: Vec<String>,
    #[serde(skip)]
    pub reads_start: TwinReads,
    #[serde(skip)]
    pub reads: TwinReads,
}

/// What would separate two parameters, judged by their names.
fn separate_by(a: &str, b: &str) -> String {
    let has = |k: &str| a.contains(k) || b.contains(k);
    let mass = |p: &str| p.contains("inertia") || p.contains("mass_kg") || p.contains("radius");
    if mass(a) && mass(b) {
        "they add up to one inertia, so no run of this bench separates them: take one from a \
         datasheet or weigh it"
            .into()
    } else if a.contains("friction") && b.contains("friction") {
        "a log at a second speed (another set point) separates Coulomb from viscous friction".into()
    } else if has("inertia") && (has("friction") || has("mass")) {
        "a coast-down (the drive switched off at speed) separates inertia from friction".into()
    } else if has("torque_constant") && has("resistance") {
        "the current at stall, or steps of two sizes, separate the motor constant from the resistance".into()
    } else {
        "a second log with a different step (another size or set point) would separate them".into()
    }
}

/// Runs the calibration of `job`; `progress` gets the simulations run so far.
pub fn calibrate(job: &Job, options: Options, progress: &(dyn Fn(u64) + Sync)) -> Result<Outcome> {
    let model = fit::Model::new(job)?;
    let start: Vec<f64> = job.parameters.iter().map(|p| p.start).collect();
    let reads_start = model
        .simulate(&start)
        .map_err(|e| CalibrateError::Start(Box::new(e)))?;
    check_magnitudes(job, &reads_start)?;
    let cost_start = model.cost_of(&start)?;
    let search = fit::fit(&model, options.max_iterations, progress)?;
    let reads = model.simulate(&search.values)?;
    // Independent values in the fit: the residuals' bins (each holds one or
    // two master readings).
    let readings = model.residuals(&reads, job.fit_window).len();
    let spread = uncertainty::estimate(&model, &search.values, readings)?;
    let parameters: Vec<Fitted> = job
        .parameters
        .iter()
        .zip(&search.values)
        .zip(&spread.std_errors)
        .map(|((p, &value), &std_error)| {
            let near = |bound: f64| {
                if p.min > 0.0 {
                    (value.ln() - bound.ln()).abs() < 0.01 * (p.max.ln() - p.min.ln())
                } else {
                    (value - bound).abs() < 0.01 * (p.max - p.min)
                }
            };
            Fitted {
                path: p.path.clone(),
                start: p.start,
                value,
                std_error,
                min: p.min,
                max: p.max,
                at_bound: near(p.min) || near(p.max),
            }
        })
        .collect();
    let name = |i: usize| job.parameters[i].path.clone();
    let entangled = spread
        .entangled
        .iter()
        .map(|&(i, j, r)| Entangled {
            a: name(i),
            b: name(j),
            correlation: r,
            separate_by: separate_by(&name(i), &name(j)),
        })
        .collect();
    Ok(Outcome {
        job: job.path.display().to_string(),
        log: job.log.display().to_string(),
        parameters,
        cost_start,
        cost: search.cost,
        converged: search.converged,
        stopped: search.stopped.clone(),
        iterations: search.iterations,
        simulations: model.evaluations(),
        refused_simulations: fit::failures(&model),
        fit: report::signal_fits(job, &reads, job.fit_window),
        check: job
            .check_window
            .map(|w| report::signal_fits(job, &reads, w))
            .unwrap_or_default(),
        fit_at_start: report::signal_fits(job, &reads_start, job.fit_window),
        steps: report::step_figures(job, &reads, &job.crossings),
        entangled,
        unseen: spread.unseen.iter().map(|&i| name(i)).collect(),
        reads_start,
        reads,
    })
}

/// Refuses a column whose values are five times the twin's or more, or a fifth or less:
/// most likely a wrong unit (rad/s given as rpm, register counts as rpm).
fn check_magnitudes(job: &Job, reads: &TwinReads) -> Result<()> {
    for s in &job.signals {
        let after = |v: &[(f64, f64)]| -> f64 {
            let x: Vec<f64> = v
                .iter()
                .filter(|p| p.0 > job.step_at_s)
                .map(|p| p.1.abs())
                .collect();
            x.iter().sum::<f64>() / x.len().max(1) as f64
        };
        let (measured, twin) = (after(&s.samples), after(reads.of(s.twin)));
        if measured > 0.0 && twin > 0.0 {
            let ratio = measured / twin;
            if !(0.2..=5.0).contains(&ratio) {
                return Err(CalibrateError::Magnitude {
                    log: job.log.clone(),
                    column: s.column.clone(),
                    unit: s.unit.name,
                    measured: short(measured),
                    ratio,
                    signal: s.twin.describe(),
                    twin: short(twin),
                });
            }
        }
    }
    Ok(())
}

/// The fitted values as a plant parameter file, for `--params` and a
/// scenario module's `params`.
pub fn params_toml(outcome: &Outcome) -> Result<String> {
    let mut table = toml::Table::new();
    for p in &outcome.parameters {
        apply::set(&mut table, &p.path, p.value);
    }
    let mut text = format!(
        "# Fitted by `twin calibrate {}` to {}.\n",
        outcome.job, outcome.log
    );
    for p in &outcome.parameters {
        let _ = writeln!(
            text,
            "#   {} = {} ± {}",
            p.path,
            short(p.value),
            p.std_error.map_or("(not determined)".into(), short)
        );
    }
    text.push_str(&toml::to_string(&table)?);
    Ok(text)
}

/// Four significant digits.
pub fn short(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let magnitude = v.abs().log10().floor() as i32;
    if (-3..5).contains(&magnitude) {
        let decimals = (3 - magnitude).max(0) as usize;
        format!("{v:.decimals$}")
    } else {
        format!("{v:.3e}")
    }
}

/// Plots of the measured and the twin's curves and their residuals into
/// `dir`: `calibrate.png` and `calibrate-residual.png`.
pub fn draw(job: &Job, outcome: &Outcome, dir: &Path) -> Result<Vec<PathBuf>> {
    use crate::plot::{self, Axes, Series};
    let colors = [plot::MOTOR, plot::LIGHT, plot::EXTRA];
    let (x0, x1) = (
        job.signals
            .iter()
            .filter_map(|s| s.samples.first().map(|p| p.0))
            .fold(f64::INFINITY, f64::min),
        job.end_s(),
    );
    let mut curves = Vec::new();
    let mut residuals = Vec::new();
    let names: Vec<(String, String, String)> = job
        .signals
        .iter()
        .map(|s| {
            (
                format!("{} (bench)", s.column),
                format!("{} (twin)", s.column),
                format!("{}: twin − bench", s.column),
            )
        })
        .collect();
    for (k, s) in job.signals.iter().enumerate() {
        let color = colors[k % colors.len()];
        let twin: Vec<(f64, f64)> = outcome
            .reads
            .of(s.twin)
            .iter()
            .copied()
            .filter(|p| p.0 >= x0 && p.0 <= x1)
            .collect();
        curves.push(Series {
            name: &names[k].0,
            color: plot::SET_POINT,
            points: s.samples.clone(),
            dots: false,
            width: 2,
        });
        curves.push(Series {
            name: &names[k].1,
            color,
            points: twin,
            dots: false,
            width: 2,
        });
        residuals.push(Series {
            name: &names[k].2,
            color,
            points: s
                .samples
                .iter()
                .map(|&(t, y)| (t, fit::curve_at(outcome.reads.of(s.twin), t) - y))
                .collect(),
            dots: false,
            width: 1,
        });
    }
    let y_range = plot::fit_range(
        curves.iter().flat_map(|s| s.points.iter().map(|p| p.1)),
        0.05,
    );
    let r_range = plot::fit_range(
        residuals.iter().flat_map(|s| s.points.iter().map(|p| p.1)),
        0.05,
    );
    std::fs::create_dir_all(dir).map_err(|source| CalibrateError::CreateDir {
        dir: dir.to_path_buf(),
        source,
    })?;
    let main = dir.join("calibrate.png");
    plot::line_plot(
        &main,
        &Axes {
            title: "Bench and calibrated twin",
            x_label: "time (s)",
            y_label: "reading",
            x_range: (x0, x1),
            y_range,
            legend_upper_left: false,
        },
        &curves,
        (1000, 560),
    )?;
    let resid = dir.join("calibrate-residual.png");
    plot::line_plot(
        &resid,
        &Axes {
            title: "Residual: twin − bench",
            x_label: "time (s)",
            y_label: "reading",
            x_range: (x0, x1),
            y_range: r_range,
            legend_upper_left: false,
        },
        &residuals,
        (1000, 360),
    )?;
    Ok(vec![main, resid])
}
