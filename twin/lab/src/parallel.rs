//! Parallel modules (the PWM-capture paper's three-phase load): the same three EV modules,
//! the master's speed reference sent to the two slaves over each link, and
//! what the recordings say about it.
//!
//! From each recording:
//! - **command-to-actuation latency**: every change of a slave's `vel_volts`
//!   actuator is matched with the master module's latest change to the same
//!   value at or before it (the instant the master issued that reference);
//!   the difference is the latency, from the PI's decision to the slave's
//!   inverter input. Master changes that no slave ever took (superseded by
//!   the next before the link delivered them) are counted as skipped; a
//!   slave change to a value older than one it already took, or to one the
//!   master never issued, is a reference decoded wrong and applied (the
//!   PWM-capture frame has no check).
//! - **tracking**: at every recorded plant instant from the first set point
//!   on, each slave's wheel rpm minus the master's; the largest magnitude
//!   and the RMS over slaves and instants.

use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use twin_recording::Recording;
use twin_recording::topics::Topic;
use twin_sim::scenario::{NodeSpec, Scenario};
use twin_sim::virtual_run;

/// Why a parallel-module experiment could not run or be read back.
#[derive(Debug, thiserror::Error)]
pub enum ParallelError {
    #[error("scenario {scenario} has no parallel-master node")]
    NoMaster { scenario: String },
    #[error(transparent)]
    Scenario(#[from] twin_sim::scenario::ScenarioError),
    #[error(transparent)]
    Run(#[from] virtual_run::RunError),
    #[error(transparent)]
    Read(#[from] twin_recording::ReadError),
}

type Result<T, E = ParallelError> = std::result::Result<T, E>;

/// The embedded scenarios compared, in the order printed.
pub const VARIANTS: [&str; 4] = [
    "parallel-pwm-broadcast",
    "parallel-pwm-designated",
    "parallel-rtu-115200",
    "parallel-rtu-1m",
];

/// What one variant's recording says.
#[derive(Debug, Clone, PartialEq)]
pub struct ParallelFigures {
    pub scenario: String,
    pub recording: PathBuf,
    /// Mean time between the master's send cycles, s.
    pub cycle_s: f64,
    /// Matched slave actuator changes.
    pub latencies: usize,
    pub latency_mean_s: f64,
    pub latency_max_s: f64,
    /// Master VEL changes no slave took, of all master VEL changes.
    pub skipped: usize,
    pub master_changes: usize,
    /// Slave actuator changes to a value the master had not just issued
    /// (a reference decoded wrong and applied).
    pub wrong_values: usize,
    /// Slave wheel minus master wheel, rpm.
    pub track_max_rpm: f64,
    pub track_rms_rpm: f64,
    /// `/events` by kind.
    pub events: BTreeMap<String, u64>,
    pub frames: u64,
}

/// Runs one embedded variant (optionally shorter, or with another seed) into
/// `out_dir` and analyses its recording; `progress` gets the fraction of the
/// run done.
pub fn run_variant(
    name: &str,
    out_dir: &Path,
    duration_s: Option<f64>,
    seed: Option<u64>,
    progress: impl FnMut(f64),
) -> Result<ParallelFigures> {
    let mut scenario = Scenario::load(name)?;
    if let Some(d) = duration_s {
        scenario.duration_s = d;
    }
    if let Some(s) = seed {
        scenario.seed = s;
    }
    let out = out_dir.join(format!("{name}.mcap"));
    let outcome = virtual_run::run(&scenario, &out, progress)?;
    analyse(&scenario, &outcome.recording)
}

/// The master module and the slave modules of a parallel scenario.
fn roles(scenario: &Scenario) -> Result<(String, Vec<String>, f64)> {
    let Some(NodeSpec::ParallelMaster {
        module, set_points, ..
    }) = scenario
        .nodes
        .iter()
        .find(|n| matches!(n, NodeSpec::ParallelMaster { .. }))
    else {
        return Err(ParallelError::NoMaster {
            scenario: scenario.name.clone(),
        });
    };
    let first_set_point = set_points
        .iter()
        .map(|[t, _]| *t)
        .fold(f64::INFINITY, f64::min);
    let slaves = scenario
        .modules
        .iter()
        .map(|m| m.name.clone())
        .filter(|m| m != module)
        .collect();
    Ok((module.clone(), slaves, first_set_point))
}

/// Reads a parallel scenario's recording back and computes its figures.
pub fn analyse(scenario: &Scenario, recording: &Path) -> Result<ParallelFigures> {
    let (master, slaves, first_set_point) = roles(scenario)?;
    let mut vel: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    let mut rpm: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    let mut events = BTreeMap::new();
    let mut frames = 0u64;
    let mut last_loop = Value::Null;
    Recording::scan(recording, |message| {
        let t = message.time_s();
        match Topic::parse(message.topic) {
            Topic::PlantActuators(Some(module)) => {
                let value: Value = message.json()?;
                let v = value["vel_volts"].as_f64().unwrap_or(f64::NAN);
                let series = vel.entry(module.to_string()).or_default();
                if series.last().is_none_or(|&(_, last)| last != v) {
                    series.push((t, v));
                }
            }
            Topic::PlantSensors(Some(module)) => {
                let value: Value = message.json()?;
                rpm.entry(module.to_string())
                    .or_default()
                    .push((t, value["wheel_rpm"].as_f64().unwrap_or(f64::NAN)));
            }
            Topic::Events => {
                let value: Value = message.json()?;
                let kind = value["kind"].as_str().unwrap_or("?").to_string();
                *events.entry(kind).or_default() += 1;
            }
            Topic::BusFrames(_) => frames += 1,
            Topic::MasterLoop(node) if node == master => last_loop = message.json()?,
            _ => {}
        }
        Ok(())
    })?;
    let empty = Vec::new();
    let master_vel = vel.get(&master).unwrap_or(&empty);
    let mut latencies = Vec::new();
    let mut wrong_values = 0usize;
    let mut taken = vec![false; master_vel.len()];
    for slave in &slaves {
        // References reach a slave in the order they were issued; a value
        // that matches only an older one than the slave already took (or
        // none) was decoded wrong on the way.
        let mut newest = 0usize;
        let mut recovering = false;
        // What the modules' pins hold at time zero is their power-up state,
        // not a reference: neither side's counts.
        for &(t2, v) in vel
            .get(slave)
            .unwrap_or(&empty)
            .iter()
            .filter(|(t, _)| *t > 0.0)
        {
            let upto = master_vel.partition_point(|(t1, _)| *t1 <= t2);
            let issued = master_vel[..upto]
                .iter()
                .enumerate()
                .rev()
                .find(|(_, (t1, v1))| *v1 == v && *t1 > 0.0);
            match issued {
                // Back to the right value after a wrong one: a recovery,
                // not a reference newly issued.
                Some((i, _)) if i >= newest && recovering => {
                    recovering = false;
                    newest = i;
                }
                Some((i, (t1, _))) if i >= newest => {
                    latencies.push(t2 - t1);
                    taken[i] = true;
                    newest = i;
                }
                _ => {
                    wrong_values += 1;
                    recovering = true;
                }
            }
        }
    }
    let issued = |i: &usize| master_vel[*i].0 > 0.0;
    let master_changes = (0..master_vel.len()).filter(issued).count();
    let skipped = (0..master_vel.len())
        .filter(|i| issued(i) && !taken[*i])
        .count();
    let mut track_max: f64 = 0.0;
    let mut square_sum = 0.0;
    let mut samples = 0usize;
    let master_rpm = rpm.get(&master).unwrap_or(&empty);
    for slave in &slaves {
        for (&(t, m), &(_, s)) in master_rpm.iter().zip(rpm.get(slave).unwrap_or(&empty)) {
            if t < first_set_point {
                continue;
            }
            let d = s - m;
            track_max = track_max.max(d.abs());
            square_sum += d * d;
            samples += 1;
        }
    }
    let cycles = last_loop["cycles"].as_f64().unwrap_or(0.0);
    let n = latencies.len().max(1) as f64;
    Ok(ParallelFigures {
        scenario: scenario.name.clone(),
        recording: recording.to_path_buf(),
        cycle_s: scenario.duration_s / cycles.max(1.0),
        latencies: latencies.len(),
        latency_mean_s: latencies.iter().sum::<f64>() / n,
        latency_max_s: latencies.iter().copied().fold(0.0, f64::max),
        skipped,
        master_changes,
        wrong_values,
        track_max_rpm: track_max,
        track_rms_rpm: (square_sum / samples.max(1) as f64).sqrt(),
        events,
        frames,
    })
}
