//! The fit: Nelder–Mead (argmin) on the bounded parameters, mapped to an
//! unbounded space, minimising the weighted squared difference between what
//! the bench's master read and what the twin's master reads.
//!
//! Why Nelder–Mead: what a master reads is quantised (the motor node's
//! 428.57-rpm steps, its 20 ms windows, the light node's 20 ms grid), so the
//! objective is a staircase in every parameter: a finite-difference gradient
//! is zero or huge, and gradient and Gauss–Newton methods stall on it. A
//! simplex method compares costs only. The residuals are 50 ms averages (see
//! [`Model::residuals`]); a quasi-random scan picks two starts, two simplexes
//! run from them, one per core, each restarted smaller from its best, and
//! the better end wins.

use super::CalibrateError;
use argmin::core::{CostFunction, Executor, State, TerminationReason, TerminationStatus};
use argmin::solver::neldermead::NelderMead;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use super::apply;
use super::job::{Job, Parameter};
use super::twin_run::{self, TwinReads};

/// A bounded parameter seen through an unbounded coordinate `u`: a logistic
/// curve between the bounds, on a log scale where both bounds are positive
/// (inertias and resistances span decades). Bounds hold by construction.
fn to_value(p: &Parameter, u: f64) -> f64 {
    let s = 1.0 / (1.0 + (-u).exp());
    if p.min > 0.0 {
        (p.min.ln() + s * (p.max.ln() - p.min.ln()))
            .exp()
            .clamp(p.min, p.max)
    } else {
        (p.min + s * (p.max - p.min)).clamp(p.min, p.max)
    }
}

fn to_coordinate(p: &Parameter, v: f64) -> f64 {
    let s = if p.min > 0.0 {
        (v.ln() - p.min.ln()) / (p.max.ln() - p.min.ln())
    } else {
        (v - p.min) / (p.max - p.min)
    };
    let s = s.clamp(1e-6, 1.0 - 1e-6);
    (s / (1.0 - s)).ln()
}

/// Width of the bins the residuals are averaged over (s).
pub const BIN_S: f64 = 0.05;

/// The twin's curve as the bench's plot draws one: the master's samples
/// joined by straight lines.
pub fn curve_at(samples: &[(f64, f64)], t: f64) -> f64 {
    let i = samples.partition_point(|p| p.0 <= t);
    match (
        i.checked_sub(1).and_then(|j| samples.get(j)),
        samples.get(i),
    ) {
        (Some(a), Some(b)) => a.1 + (b.1 - a.1) * (t - a.0) / (b.0 - a.0),
        (Some(a), None) => a.1,
        (None, Some(b)) => b.1,
        (None, None) => 0.0,
    }
}

/// The experiment with trial values, and how it compares with the log.
#[derive(Debug)]
pub struct Model<'a> {
    pub job: &'a Job,
    paths: Vec<String>,
    /// Per signal: the spread of its measured values in the fit window, so
    /// that signals in different units weigh alike.
    scales: Vec<f64>,
    evaluations: AtomicU64,
    failures: AtomicU64,
}

impl<'a> Model<'a> {
    pub fn new(job: &'a Job) -> Result<Self, CalibrateError> {
        let (a, b) = job.fit_window;
        let mut scales = Vec::new();
        for s in &job.signals {
            let v: Vec<f64> = s.rows_in((a, b)).iter().map(|p| p.1).collect();
            if v.len() < 2 {
                return Err(CalibrateError::FewInWindow {
                    column: s.column.clone(),
                    from: a,
                    to: b,
                });
            }
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            let sd = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
            if sd == 0.0 {
                return Err(CalibrateError::Constant {
                    column: s.column.clone(),
                });
            }
            scales.push(sd);
        }
        Ok(Model {
            job,
            paths: job.parameters.iter().map(|p| p.path.clone()).collect(),
            scales,
            evaluations: AtomicU64::new(0),
            failures: AtomicU64::new(0),
        })
    }

    /// Simulations run so far.
    pub fn evaluations(&self) -> u64 {
        self.evaluations.load(Ordering::Relaxed)
    }

    /// The experiment with `values` (in the order of the job's parameters).
    pub fn simulate(&self, values: &[f64]) -> Result<TwinReads, CalibrateError> {
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        let scenario = apply::with_values(&self.job.scenario, &self.paths, values);
        twin_run::run(
            &scenario,
            self.job.end_s() + 0.1,
            self.job.step_at_s,
            (self.job.step_from, self.job.step_to),
        )
    }

    /// Weighted, scaled residuals of `reads` in `window`: per signal, the
    /// difference of bench and twin averaged over consecutive [`BIN_S`] bins
    /// of the measured rows.
    ///
    /// Why averages: the motor node's PI acts on quantised readings, so a
    /// small change of a parameter changes which reading comes when, and
    /// the raw difference jumps by whole 428.57-rpm steps: a cost made of
    /// it is a needle at the exact answer in a field of noise. Averaged
    /// over 50 ms (one and a half master cycles) the readings keep the rise
    /// and the level and lose most of that noise, so the cost has a slope a
    /// search can follow.
    pub fn residuals(&self, reads: &TwinReads, window: (f64, f64)) -> Vec<f64> {
        let mut out = Vec::new();
        for (s, scale) in self.job.signals.iter().zip(&self.scales) {
            let twin = reads.of(s.twin);
            let w = s.weight.sqrt() / scale;
            let rows = s.rows_in(window);
            let mut i = 0;
            while i < rows.len() {
                let bin = ((rows[i].0 - window.0) / BIN_S).floor();
                let mut j = i;
                let mut sum = 0.0;
                while j < rows.len() && ((rows[j].0 - window.0) / BIN_S).floor() == bin {
                    sum += curve_at(twin, rows[j].0) - rows[j].1;
                    j += 1;
                }
                out.push(sum / (j - i) as f64 * w);
                i = j;
            }
        }
        out
    }

    /// The cost of `values`: the sum of squared residuals in the fit window.
    pub fn cost_of(&self, values: &[f64]) -> Result<f64, CalibrateError> {
        let reads = self.simulate(values)?;
        Ok(self
            .residuals(&reads, self.job.fit_window)
            .iter()
            .map(|r| r * r)
            .sum())
    }
}

/// The optimiser's view: unbounded coordinates.
struct Problem<'m, 'a> {
    model: &'m Model<'a>,
    progress: &'m (dyn Fn(u64) + Sync),
}

/// A cost for values the plant refuses (a simulation that fails): worse
/// than any real fit, finite so that the simplex arithmetic stays finite.
const REFUSED: f64 = 1e30;

impl CostFunction for Problem<'_, '_> {
    type Param = Vec<f64>;
    type Output = f64;

    fn cost(&self, u: &Vec<f64>) -> Result<f64, argmin::core::Error> {
        let values: Vec<f64> = self
            .model
            .job
            .parameters
            .iter()
            .zip(u)
            .map(|(p, &u)| to_value(p, u))
            .collect();
        let cost = match self.model.cost_of(&values) {
            Ok(c) if c.is_finite() => c,
            _ => {
                self.model.failures.fetch_add(1, Ordering::Relaxed);
                REFUSED
            }
        };
        (self.progress)(self.model.evaluations());
        Ok(cost)
    }
}

/// How one simplex ended.
#[derive(Debug, Clone)]
pub struct Search {
    pub values: Vec<f64>,
    pub cost: f64,
    pub iterations: u64,
    /// Why it stopped, in words.
    pub stopped: String,
    pub converged: bool,
}

/// Restarts of a search from its own best point, each with a simplex half
/// the size of the one before: on a staircase a simplex can shrink onto a
/// step's edge, and a fresh one around the best point walks on.
const RESTARTS: usize = 3;

/// Nelder–Mead from `start`, restarted from its best while that improves.
fn search(
    model: &Model<'_>,
    start: &[f64],
    max_iterations: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Search, CalibrateError> {
    let mut size = 0.8;
    let mut best = simplex_search(model, start, size, max_iterations, progress)?;
    for _ in 0..RESTARTS {
        size /= 2.0;
        let next = simplex_search(model, &best.values, size, max_iterations, progress)?;
        let iterations = best.iterations + next.iterations;
        if next.cost < best.cost * (1.0 - 1e-9) {
            best = Search { iterations, ..next };
        } else {
            best.iterations = iterations;
            break;
        }
    }
    Ok(best)
}

/// One Nelder–Mead search from `start` (values), its simplex `size` wide in
/// the unbounded coordinates.
fn simplex_search(
    model: &Model<'_>,
    start: &[f64],
    size: f64,
    max_iterations: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Search, CalibrateError> {
    let params = &model.job.parameters;
    let u0: Vec<f64> = params
        .iter()
        .zip(start)
        .map(|(p, &v)| to_coordinate(p, v))
        .collect();
    let mut simplex = vec![u0.clone()];
    for i in 0..u0.len() {
        let mut u = u0.clone();
        // Towards the middle of the bounds: 0.8 is about a fifth of their span.
        u[i] += if u[i] > 0.0 { -size } else { size };
        simplex.push(u);
    }
    let solver = NelderMead::new(simplex)
        .with_sd_tolerance(1e-6)
        .map_err(|e| CalibrateError::Optimiser { why: e.to_string() })?;
    let problem = Problem { model, progress };
    let result = Executor::new(problem, solver)
        .configure(|state| state.max_iters(max_iterations))
        .timer(false)
        .run()
        .map_err(|e| CalibrateError::OptimiserFailed { why: e.to_string() })?;
    let state = result.state();
    let Some(best) = state.get_best_param() else {
        return Err(CalibrateError::NoParameters);
    };
    let values: Vec<f64> = params
        .iter()
        .zip(best)
        .map(|(p, &u)| to_value(p, u))
        .collect();
    let (stopped, converged) = match state.get_termination_status() {
        TerminationStatus::Terminated(TerminationReason::SolverConverged) => (
            "converged: the simplex's costs agree to 1e-6".to_string(),
            true,
        ),
        TerminationStatus::Terminated(TerminationReason::MaxItersReached) => (
            format!(
                "stopped after {max_iterations} iterations, the most allowed, before converging"
            ),
            false,
        ),
        TerminationStatus::Terminated(other) => (other.text().to_string(), false),
        TerminationStatus::NotTerminated => ("did not finish".to_string(), false),
    };
    Ok(Search {
        values,
        cost: state.get_best_cost(),
        iterations: state.get_iter(),
        stopped,
        converged,
    })
}

/// Points of the quasi-random scan that picks the searches' starts.
const SCAN: usize = 24;

/// The `i`-th point of the Halton sequence in `dims` dimensions, in (0, 1).
fn halton(i: usize, dims: usize) -> Vec<f64> {
    const PRIMES: [usize; 12] = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37];
    (0..dims)
        .map(|d| {
            let base = PRIMES[d % PRIMES.len()];
            let (mut f, mut r, mut n) = (1.0, 0.0, i + 1);
            while n > 0 {
                f /= base as f64;
                r += f * (n % base) as f64;
                n /= base;
            }
            r
        })
        .collect()
}

/// The fit: a quasi-random scan of the bounds (the job's start among its
/// points, on both cores), then two searches in parallel from the two best
/// points, the better end kept. The staircase has many flat steps; starting
/// where the scan found the lowest ones keeps a search off the far ones.
pub fn fit(
    model: &Model<'_>,
    max_iterations: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Search, CalibrateError> {
    let params = &model.job.parameters;
    let start: Vec<f64> = params.iter().map(|p| p.start).collect();
    // Say why the start itself cannot run, in the simulation's own words.
    model.cost_of(&start)?;
    let mut points: Vec<Vec<f64>> = vec![start];
    for i in 0..SCAN {
        let h = halton(i, params.len());
        // Over the middle 90 % of each parameter's range (in its coordinate).
        points.push(
            params
                .iter()
                .zip(h)
                .map(|(p, x)| to_value(p, (x - 0.5) * 6.0))
                .collect(),
        );
    }
    let costs: Mutex<Vec<(usize, f64)>> = Mutex::new(Vec::new());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    std::thread::scope(|scope| {
        for lane in 0..cores {
            let (points, costs) = (&points, &costs);
            scope.spawn(move || {
                for (i, p) in points.iter().enumerate().skip(lane).step_by(cores) {
                    let c = model.cost_of(p).unwrap_or(REFUSED);
                    costs.lock().unwrap_or_else(|e| e.into_inner()).push((i, c));
                    progress(model.evaluations());
                }
            });
        }
    });
    let mut costs = costs.into_inner().unwrap_or_else(|e| e.into_inner());
    // Ties go to the earlier point, so the result does not depend on threads.
    costs.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    let starts: Vec<&Vec<f64>> = costs.iter().take(2).map(|&(i, _)| &points[i]).collect();
    let found: Mutex<Vec<(usize, Result<Search, CalibrateError>)>> = Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for (k, from) in starts.iter().enumerate() {
            let found = &found;
            scope.spawn(move || {
                let s = search(model, from, max_iterations, progress);
                found.lock().unwrap_or_else(|e| e.into_inner()).push((k, s));
            });
        }
    });
    let mut found = found.into_inner().unwrap_or_else(|e| e.into_inner());
    found.sort_by_key(|(k, _)| *k);
    let found: Vec<Result<Search, CalibrateError>> = found.into_iter().map(|(_, s)| s).collect();
    let mut best: Option<Search> = None;
    for s in found {
        let s = s?;
        if best.as_ref().is_none_or(|b| s.cost < b.cost) {
            best = Some(s);
        }
    }
    let Some(best) = best else {
        return Err(CalibrateError::NoSearchFinished);
    };
    if best.cost >= REFUSED {
        return Err(CalibrateError::EveryTrialRefused);
    }
    Ok(best)
}

/// Simulations that failed during the fit.
pub fn failures(model: &Model<'_>) -> u64 {
    model.failures.load(Ordering::Relaxed)
}
