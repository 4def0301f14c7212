//! Running a manifest's entries: each entry's scenario loaded, changed by
//! its `--set`s and seed, run on the virtual clock and recorded to
//! `NAME.mcap`, then summarised in `NAME.json`. An entry whose summary says
//! it succeeded is skipped unless forced; one that fails says why in its
//! summary and is never marked done, so a scheduler's retry runs it again.
//! Several entries run at once on threads of this process, each run on one
//! thread (and its recording's writer on another).

use super::BatchError;

type Result<T, E = BatchError> = std::result::Result<T, E>;
use protocols::time::SimDuration;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use super::figures::{self, Step};
use super::manifest::Manifest;
use super::summary::{Status, Summary, temporary};
use twin_sim::error_text::in_full;
use twin_sim::interrupt;
use twin_sim::replay::{RunSpec, parse_value};
use twin_sim::scenario::Scenario;
use twin_sim::virtual_run;

/// How the wheel is sampled for the step figures (as `twin step` does).
const STEP_SAMPLE_HZ: f64 = 500.0;

/// What became of one entry.
#[derive(Debug, Clone, PartialEq)]
pub enum Report {
    /// It ran; its summary says whether it succeeded.
    Ran(Summary),
    /// It had succeeded before: its summary as it was.
    Skipped(Summary),
    /// Not run, or stopped, by Ctrl-C or SIGTERM: it stays as it was.
    Stopped { entry: usize, name: String },
}

impl Report {
    pub fn entry(&self) -> usize {
        match self {
            Report::Ran(s) | Report::Skipped(s) => s.entry,
            Report::Stopped { entry, .. } => *entry,
        }
    }

    pub fn failed(&self) -> bool {
        matches!(self, Report::Ran(s) if s.status == Status::Failed)
    }
}

/// Where and how entries run.
#[derive(Debug, Clone)]
pub struct Options {
    /// The folder of recordings and summaries.
    pub dir: PathBuf,
    /// Run entries that succeeded before again.
    pub force: bool,
    /// Entries run at once.
    pub jobs: usize,
}

/// Entry `index`'s scenario, with its changes and seed.
pub fn prepare(manifest: &Manifest, index: usize) -> Result<Scenario> {
    let entry = &manifest.entries[index];
    let scenario = Scenario::load(&manifest.scenario_of(index))?;
    let mut scenario = RunSpec::scenario_with_overrides(scenario, &entry.set)?;
    if let Some(seed) = entry.seed {
        scenario.seed = seed;
    }
    Ok(scenario)
}

/// Run `indices` of `manifest`, `options.jobs` at a time; `on_done` hears of
/// each as it ends. The reports come back in manifest order.
pub fn run(
    manifest: &Manifest,
    indices: &[usize],
    options: &Options,
    on_done: impl Fn(&Report) + Sync,
) -> Result<Vec<Report>> {
    std::fs::create_dir_all(&options.dir).map_err(|source| BatchError::CreateDir {
        dir: options.dir.clone(),
        source,
    })?;
    let next = AtomicUsize::new(0);
    let reports = Mutex::new(Vec::with_capacity(indices.len()));
    let work = || {
        loop {
            let k = next.fetch_add(1, Ordering::Relaxed);
            let Some(&index) = indices.get(k) else { break };
            let report = if interrupt::requested() {
                Report::Stopped {
                    entry: index,
                    name: manifest.name(index),
                }
            } else {
                run_entry(manifest, index, &options.dir, options.force)
            };
            on_done(&report);
            reports
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(report);
        }
    };
    let workers = options.jobs.clamp(1, indices.len().max(1));
    if workers == 1 {
        work();
    } else {
        std::thread::scope(|s| -> Result<()> {
            for w in 0..workers {
                std::thread::Builder::new()
                    .name(format!("batch-{w}"))
                    // As much stack as the main thread has: a run needs no
                    // less on a worker.
                    .stack_size(8 << 20)
                    .spawn_scoped(s, work)
                    .map_err(BatchError::Worker)?;
            }
            Ok(())
        })?;
    }
    let mut reports = reports.into_inner().unwrap_or_else(|e| e.into_inner());
    reports.sort_by_key(Report::entry);
    Ok(reports)
}

/// Run one entry into `dir`, unless it succeeded before and `force` is off.
pub fn run_entry(manifest: &Manifest, index: usize, dir: &Path, force: bool) -> Report {
    let name = manifest.name(index);
    let summary_path = Summary::path(dir, &name);
    let recording = dir.join(format!("{name}.mcap"));
    if !force
        && let Ok(Some(before)) = Summary::read(&summary_path)
        && before.status == Status::Ok
        && recording.exists()
    {
        return Report::Skipped(before);
    }
    let entry = &manifest.entries[index];
    let mut summary = Summary {
        entry: index,
        name: name.clone(),
        status: Status::Failed,
        scenario: entry.scenario.clone(),
        seed: entry.seed,
        set: entry
            .set
            .iter()
            .filter_map(|s| s.split_once('='))
            .map(|(path, value)| {
                let value = serde_json::to_value(parse_value(value.trim()))
                    .unwrap_or(serde_json::Value::Null);
                (path.trim().to_string(), value)
            })
            .collect(),
        simulated_s: None,
        wall_s: 0.0,
        recording: None,
        figures: figures::Figures::new(),
        error: None,
    };
    let started = Instant::now();
    let tmp = temporary(&recording);
    let ran = prepare(manifest, index).and_then(|scenario| {
        summary.seed = Some(scenario.seed);
        run_scenario(&scenario, &tmp)
    });
    summary.wall_s = started.elapsed().as_secs_f64();
    let ran = ran.and_then(|figures| {
        std::fs::rename(&tmp, &recording).map_err(|source| BatchError::MoveRecording {
            path: recording.clone(),
            source,
        })?;
        Ok(figures)
    });
    match ran {
        Ok(figures) => {
            summary.status = Status::Ok;
            summary.simulated_s = figures.get("simulated_s").copied().flatten();
            summary.recording = Some(format!("{name}.mcap"));
            summary.figures = figures;
        }
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            if e.interrupted() {
                return Report::Stopped { entry: index, name };
            }
            summary.error = Some(in_full(&e));
        }
    }
    if let Err(e) = summary.write(dir) {
        // Not written is not done: the entry runs again next time.
        summary.status = Status::Failed;
        summary.error = Some(in_full(&e));
    }
    Report::Ran(summary)
}

/// Run `scenario`, recorded to `out`, and give its figures.
fn run_scenario(scenario: &Scenario, out: &Path) -> Result<figures::Figures> {
    let Some(step) = Step::of_scenario(scenario) else {
        let outcome = virtual_run::run(scenario, out, |_| {}).map_err(failed(scenario))?;
        return Ok(figures::of_outcome(&outcome));
    };
    // Sampling between stretches of the run changes nothing in it: the
    // recording is the one `twin run` makes.
    let (mut time_s, mut wheel_rpm) = (Vec::new(), Vec::new());
    let outcome = virtual_run::run_sampled(
        scenario,
        out,
        |_| {},
        &Default::default(),
        Some(SimDuration::from_secs_f64(1.0 / STEP_SAMPLE_HZ)),
        |now, engine, _| {
            if let Some(m) = engine.modules.iter().find(|m| m.name == step.module) {
                time_s.push(now.as_secs_f64());
                wheel_rpm.push(m.plant.sensors().wheel_rpm);
            }
            Ok(())
        },
    )
    .map_err(failed(scenario))?;
    let mut f = figures::of_outcome(&outcome);
    f.extend(step.figures(&time_s, &wheel_rpm));
    Ok(f)
}

/// The error of a run of `scenario` that failed.
fn failed(scenario: &Scenario) -> impl Fn(virtual_run::RunError) -> BatchError + '_ {
    |source| BatchError::ScenarioFailed {
        scenario: scenario.name.clone(),
        source,
    }
}
