//! How sure the fit is: the parameters' standard errors and correlations
//! from the residuals' sensitivity at the optimum.
//!
//! The sensitivity is a central difference with a step of 5 % of each value:
//! large enough to see through the readings' quantisation (a step of 1e-6
//! would change no reading at all), small enough to stay local. The
//! residuals of one master reading repeat on every log row until the next
//! one, so the error variance counts the master's readings, not the rows.

use super::CalibrateError;
use nalgebra::DMatrix;
use serde::Serialize;

use super::fit::Model;

/// Relative steps of the sensitivity, each taken up and down: the slope is
/// a least-squares line through the six, so that the jumps of single
/// readings (the PI acting on quantised readings) average out of it.
const STEPS: [f64; 3] = [0.03, 0.06, 0.12];
/// Correlation above which two parameters are reported as not separable.
pub const ENTANGLED: f64 = 0.9;

/// Standard errors and correlations of the fitted values.
#[derive(Debug, Clone, Serialize)]
pub struct Uncertainty {
    /// One standard error per parameter; `None` where the log does not
    /// determine it at all (no reading changes with it).
    pub std_errors: Vec<Option<f64>>,
    /// Pairs `(i, j, correlation)` with |correlation| ≥ [`ENTANGLED`].
    pub entangled: Vec<(usize, usize, f64)>,
    /// Parameters no reading depends on.
    pub unseen: Vec<usize>,
}

/// The uncertainty at `values`; the 6 × p simulations run on every core.
pub fn estimate(
    model: &Model<'_>,
    values: &[f64],
    readings: usize,
) -> Result<Uncertainty, CalibrateError> {
    let p = values.len();
    let window = model.job.fit_window;
    let base = model.residuals(&model.simulate(values)?, window);
    let n = base.len();
    let ssr: f64 = base.iter().map(|r| r * r).sum();
    // Each parameter's ± trial, on as many threads as there are cores.
    let trials: Vec<(usize, f64)> = (0..p)
        .flat_map(|i| {
            STEPS
                .iter()
                .flat_map(move |&h| [(i, 1.0 + h), (i, 1.0 - h)])
        })
        .collect();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let chunk = trials.len().div_ceil(cores).max(1);
    let mut results: Vec<Result<Vec<f64>, CalibrateError>> = Vec::new();
    std::thread::scope(|scope| {
        let handles: Vec<_> = trials
            .chunks(chunk)
            .map(|part| {
                scope.spawn(move || {
                    part.iter()
                        .map(|&(i, f)| {
                            let mut v = values.to_vec();
                            v[i] *= f;
                            Ok(model.residuals(&model.simulate(&v)?, window))
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        for h in handles {
            match h.join() {
                Ok(r) => results.extend(r),
                Err(_) => results.push(Err(CalibrateError::SimulationThread)),
            }
        }
    });
    let mut jacobian = DMatrix::<f64>::zeros(n, p);
    let per = 2 * STEPS.len();
    for i in 0..p {
        let trials = &results[per * i..per * (i + 1)];
        let offsets: Vec<f64> = STEPS.iter().flat_map(|&h| [h, -h]).collect();
        if trials.iter().any(Result::is_err) {
            continue;
        }
        // Least squares through the origin's value: Σ h·Δr / Σ h², with
        // h the change of the value itself.
        let h2: f64 = offsets.iter().map(|h| (h * values[i]).powi(2)).sum();
        for k in 0..n {
            let mut sum = 0.0;
            for (trial, &h) in trials.iter().zip(&offsets) {
                if let Ok(r) = trial
                    && let Some(rk) = r.get(k)
                {
                    sum += h * values[i] * (rk - base[k]);
                }
            }
            jacobian[(k, i)] = sum / h2;
        }
    }
    let unseen: Vec<usize> = (0..p)
        .filter(|&i| jacobian.column(i).iter().all(|d| *d == 0.0))
        .collect();
    let dof = readings.saturating_sub(p).max(1) as f64;
    let variance = ssr / dof;
    // The parameters some reading depends on; the others have no error bar.
    let seen: Vec<usize> = (0..p).filter(|i| !unseen.contains(i)).collect();
    let sub = jacobian.select_columns(seen.iter());
    let normal = sub.transpose() * &sub;
    let mut std_errors = vec![None; p];
    let mut entangled = Vec::new();
    // Columns that point the same way: the log moves with the two alike. A
    // singular normal matrix (an exact tie) leaves only this to tell.
    let cosine = |i: usize, j: usize| {
        let (a, b) = (jacobian.column(i), jacobian.column(j));
        a.dot(&b) / (a.norm() * b.norm())
    };
    let inverse = normal.try_inverse();
    if inverse.is_none() {
        for (a, &i) in seen.iter().enumerate() {
            for &j in seen.iter().skip(a + 1) {
                let r = cosine(i, j);
                if r.abs() >= ENTANGLED {
                    entangled.push((i, j, r));
                }
            }
        }
    }
    if let Some(inverse) = inverse {
        let cov = inverse * variance;
        for (a, &i) in seen.iter().enumerate() {
            if cov[(a, a)] > 0.0 {
                std_errors[i] = Some(cov[(a, a)].sqrt());
            }
        }
        for (a, &i) in seen.iter().enumerate() {
            for (b, &j) in seen.iter().enumerate().skip(a + 1) {
                if cov[(a, a)] > 0.0 && cov[(b, b)] > 0.0 {
                    let r = cov[(a, b)] / (cov[(a, a)] * cov[(b, b)]).sqrt();
                    if r.abs() >= ENTANGLED {
                        entangled.push((i, j, r));
                    }
                }
            }
        }
    }
    Ok(Uncertainty {
        std_errors,
        entangled,
        unseen,
    })
}
