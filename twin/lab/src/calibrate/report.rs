//! What a calibration found, in figures a control engineer reads: each value
//! with its standard error, the fit per signal (NRMSE FIT %, on the raw
//! readings and on 100 ms averages, in the fit window and the check window),
//! the pairs the log cannot tell apart, and the step figures of bench and twin.

use serde::Serialize;
use twin_sim::step_metrics::{StepMetrics, StepOptions, step_metrics};

use super::fit::curve_at;
use super::job::Job;
use super::twin_run::TwinReads;

/// Width of the averages the second FIT figure compares (s).
pub const AVERAGE_S: f64 = 0.1;

/// NRMSE FIT, as system-identification tools give it:
/// 100 × (1 − ‖y − ŷ‖ / ‖y − mean(y)‖), in %; 100 is a perfect fit, 0 no
/// better than the mean, negative worse.
pub fn nrmse_fit(measured: &[f64], twin: &[f64]) -> Option<f64> {
    if measured.len() < 2 || measured.len() != twin.len() {
        return None;
    }
    let mean = measured.iter().sum::<f64>() / measured.len() as f64;
    let err: f64 = measured
        .iter()
        .zip(twin)
        .map(|(y, m)| (y - m).powi(2))
        .sum();
    let spread: f64 = measured.iter().map(|y| (y - mean).powi(2)).sum();
    (spread > 0.0).then(|| 100.0 * (1.0 - (err / spread).sqrt()))
}

/// Means over consecutive `AVERAGE_S` bins of paired samples.
fn averaged(t: &[f64], a: &[f64], b: &[f64]) -> (Vec<f64>, Vec<f64>) {
    let (mut out_a, mut out_b) = (Vec::new(), Vec::new());
    let Some(&first) = t.first() else {
        return (out_a, out_b);
    };
    let mut i = 0;
    while i < t.len() {
        let bin = ((t[i] - first) / AVERAGE_S).floor();
        let j = i + t[i..]
            .iter()
            .take_while(|&&x| ((x - first) / AVERAGE_S).floor() == bin)
            .count();
        let n = (j - i) as f64;
        out_a.push(a[i..j].iter().sum::<f64>() / n);
        out_b.push(b[i..j].iter().sum::<f64>() / n);
        i = j;
    }
    (out_a, out_b)
}

/// The fit of one signal in one window.
#[derive(Debug, Clone, Serialize)]
pub struct SignalFit {
    pub column: String,
    pub twin: &'static str,
    pub window_s: (f64, f64),
    pub rows: usize,
    /// FIT % on the raw readings and on 100 ms averages.
    pub fit_raw_pct: Option<f64>,
    pub fit_averaged_pct: Option<f64>,
    pub measured_mean: f64,
    pub twin_mean: f64,
}

/// The fit of every signal in `window`.
pub fn signal_fits(job: &Job, reads: &TwinReads, window: (f64, f64)) -> Vec<SignalFit> {
    job.signals
        .iter()
        .map(|s| {
            let rows = s.rows_in(window);
            let t: Vec<f64> = rows.iter().map(|p| p.0).collect();
            let y: Vec<f64> = rows.iter().map(|p| p.1).collect();
            let m: Vec<f64> = t.iter().map(|&t| curve_at(reads.of(s.twin), t)).collect();
            let (ya, ma) = averaged(&t, &y, &m);
            let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
            SignalFit {
                column: s.column.clone(),
                twin: s.twin.name(),
                window_s: window,
                rows: rows.len(),
                fit_raw_pct: nrmse_fit(&y, &m),
                fit_averaged_pct: nrmse_fit(&ya, &ma),
                measured_mean: mean(&y),
                twin_mean: mean(&m),
            }
        })
        .collect()
}

/// The times and values of a curve from just before a step at `step_at_s`
/// to `until_s`: a curve read off a plot has no row before its step, so it
/// starts at the set point's level there, `from`.
pub fn after_step(
    curve: &[(f64, f64)],
    step_at_s: f64,
    from: f64,
    until_s: f64,
) -> (Vec<f64>, Vec<f64>) {
    let mut t = vec![step_at_s - 1e-3];
    let mut y = vec![from];
    for &(ti, yi) in curve.iter().filter(|p| p.0 > step_at_s && p.0 <= until_s) {
        t.push(ti);
        y.push(yi);
    }
    (t, y)
}

/// Step figures of the bench and the twin for one signal, both taken from
/// the curves at the log's rows.
#[derive(Debug, Clone, Serialize)]
pub struct StepFigures {
    pub column: String,
    pub measured: Option<StepMetrics>,
    pub twin: Option<StepMetrics>,
    /// When each curve first reaches these values after the step (s after it).
    pub crossings: Vec<(f64, Option<f64>, Option<f64>)>,
}

/// The step figures of every speed signal, and when each passes `levels`.
pub fn step_figures(job: &Job, reads: &TwinReads, levels: &[f64]) -> Vec<StepFigures> {
    let options = StepOptions::default();
    job.signals
        .iter()
        .filter(|s| s.twin.is_speed())
        .map(|s| {
            let (t, y) = after_step(&s.samples, job.step_at_s, job.step_from, job.step_end_s);
            let m: Vec<f64> = t.iter().map(|&t| curve_at(reads.of(s.twin), t)).collect();
            let reference = Some(job.step_to);
            let crossing = |v: &[f64], level: f64| {
                t.iter()
                    .zip(v)
                    .find(|(_, y)| **y >= level)
                    .map(|(t, _)| t - job.step_at_s)
            };
            StepFigures {
                column: s.column.clone(),
                measured: step_metrics(&t, &y, job.step_at_s - 5e-4, reference, &options).ok(),
                twin: step_metrics(&t, &m, job.step_at_s - 5e-4, reference, &options).ok(),
                crossings: levels
                    .iter()
                    .map(|&l| (l, crossing(&y, l), crossing(&m, l)))
                    .collect(),
            }
        })
        .collect()
}
