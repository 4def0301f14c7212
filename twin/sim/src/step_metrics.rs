//! Step-response figures from sampled time series, as a lab report gives them
//! (the definitions of MATLAB's `stepinfo`, so students can check them):
//!
//! - the response runs from its initial value `y0` (the last sample at or
//!   before the step) to its final value `yf` (the mean of the last part of
//!   the record, so a sensor that reads in steps or with noise still has one);
//! - rise time: from the first crossing of `y0 + 10 %` of `yf - y0` to the
//!   first crossing of 90 %, crossings interpolated between samples;
//! - overshoot: how far the peak goes past `yf`, in % of `yf - y0`;
//! - settling time: from the step until the response enters the band of
//!   ±2 % of `yf - y0` around `yf` for the last time;
//! - steady-state error: the reference's final value minus `yf`.
//!
//! [`delay`] finds the lag of one signal behind another: the shift that
//! best lays the first's normalised step onto the second's.

use serde::Serialize;

/// What the figures are measured with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepOptions {
    /// Half-width of the settling band, as a fraction of the step (0.02).
    pub settling_band: f64,
    /// Fraction of the samples after the step whose mean is the final value (0.1).
    pub final_fraction: f64,
}

impl Default for StepOptions {
    fn default() -> Self {
        Self {
            settling_band: 0.02,
            final_fraction: 0.1,
        }
    }
}

/// A signal's step response. Times are seconds after the step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StepMetrics {
    pub initial: f64,
    pub final_value: f64,
    /// 10–90 % rise time; `None` if the response never reaches 90 %.
    pub rise_time_s: Option<f64>,
    /// Peak past the final value, in % of the step; 0 for a response that
    /// never passes it.
    pub overshoot_pct: f64,
    /// The extreme value in the step's direction, and when it came.
    pub peak: f64,
    pub peak_time_s: f64,
    /// `None` if the response is still outside the band at the last sample.
    pub settling_time_s: Option<f64>,
    /// The reference's final value minus this signal's, when there is a reference.
    pub steady_state_error: Option<f64>,
}

/// Why a series has no step figures.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StepMetricsError {
    #[error("time and value series differ in length ({times} times, {values} values)")]
    LengthMismatch { times: usize, values: usize },
    #[error("need samples before and after the step at {step_at_s} s")]
    NoStep { step_at_s: f64 },
    #[error("times must increase (sample {index})")]
    TimesNotIncreasing { index: usize },
    #[error("the signal does not move: initial and final value are both {value}")]
    Flat { value: f64 },
    #[error("non-finite value at sample {index}")]
    NotFinite { index: usize },
    #[error("the lag is {max_delay_s} s or more, beyond what was searched")]
    DelayBeyondSearch { max_delay_s: f64 },
}

/// Step figures of `y(t)` for a step at `step_at_s`; `reference_final` is the
/// value it should end at (the set point), for the steady-state error.
pub fn step_metrics(
    t: &[f64],
    y: &[f64],
    step_at_s: f64,
    reference_final: Option<f64>,
    options: &StepOptions,
) -> Result<StepMetrics, StepMetricsError> {
    check_series(t, y)?;
    // First sample after the step.
    let first = t.partition_point(|&ti| ti <= step_at_s);
    if first == 0 || first >= t.len() {
        return Err(StepMetricsError::NoStep { step_at_s });
    }
    let initial = y[first - 1];
    let after = &y[first..];
    let tail =
        ((after.len() as f64 * options.final_fraction).ceil() as usize).clamp(1, after.len());
    let final_value = after[after.len() - tail..].iter().sum::<f64>() / tail as f64;
    let span = final_value - initial;
    if span == 0.0 {
        return Err(StepMetricsError::Flat { value: initial });
    }
    // Work on the normalised response: 0 before the step, 1 at its end.
    let norm = |v: f64| (v - initial) / span;
    let crossing = |level: f64| {
        (first..t.len()).find_map(|i| {
            let (a, b) = (norm(y[i - 1]), norm(y[i]));
            (b >= level && a < level).then(|| {
                let f = (level - a) / (b - a);
                t[i - 1] + f * (t[i] - t[i - 1])
            })
        })
    };
    let rise_time_s = match (crossing(0.1), crossing(0.9)) {
        (Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    let (peak_index, peak_norm) =
        (first..t.len())
            .map(|i| (i, norm(y[i])))
            .fold((first, f64::NEG_INFINITY), |best, x| {
                if x.1 > best.1 { x } else { best }
            });
    let overshoot_pct = ((peak_norm - 1.0) * 100.0).max(0.0);
    let band = options.settling_band;
    let outside = |i: usize| (norm(y[i]) - 1.0).abs() > band;
    let settling_time_s = match (first..t.len()).rev().find(|&i| outside(i)) {
        None => Some(0.0),
        Some(last) if last + 1 == t.len() => None,
        Some(last) => {
            // Interpolate where it crossed into the band between the last
            // sample outside and the first inside.
            let (a, b) = ((norm(y[last]) - 1.0).abs(), (norm(y[last + 1]) - 1.0).abs());
            let f = if a > b { (a - band) / (a - b) } else { 1.0 };
            Some(t[last] + f * (t[last + 1] - t[last]) - step_at_s)
        }
    };
    Ok(StepMetrics {
        initial,
        final_value,
        rise_time_s,
        overshoot_pct,
        peak: y[peak_index],
        peak_time_s: t[peak_index] - step_at_s,
        settling_time_s,
        steady_state_error: reference_final.map(|r| r - final_value),
    })
}

fn check_series(t: &[f64], y: &[f64]) -> Result<(), StepMetricsError> {
    if t.len() != y.len() {
        return Err(StepMetricsError::LengthMismatch {
            times: t.len(),
            values: y.len(),
        });
    }
    if let Some(index) = (0..t.len()).find(|&i| !t[i].is_finite() || !y[i].is_finite()) {
        return Err(StepMetricsError::NotFinite { index });
    }
    if let Some(index) = (1..t.len()).find(|&i| t[i] <= t[i - 1]) {
        return Err(StepMetricsError::TimesNotIncreasing { index });
    }
    Ok(())
}

/// How long `lagging` trails `reference` after a step at `step_at_s`: the
/// shift, from 0 to under `max_delay_s`, that minimises the squared difference of
/// their normalised step responses over the samples after the step, refined
/// between samples by a parabola through the best three shifts. Both series
/// share the times `t`, which must be evenly spaced (a recording's are).
pub fn delay(
    t: &[f64],
    reference: &[f64],
    lagging: &[f64],
    step_at_s: f64,
    max_delay_s: f64,
) -> Result<f64, StepMetricsError> {
    check_series(t, reference)?;
    check_series(t, lagging)?;
    let options = StepOptions::default();
    let r = step_metrics(t, reference, step_at_s, None, &options)?;
    let l = step_metrics(t, lagging, step_at_s, None, &options)?;
    let first = t.partition_point(|&ti| ti <= step_at_s);
    let dt = (t[t.len() - 1] - t[0]) / (t.len() - 1) as f64;
    let max_lag = ((max_delay_s / dt).round() as usize).min(t.len() - 1);
    let rn = |i: usize| (reference[i] - r.initial) / (r.final_value - r.initial);
    let ln = |i: usize| (lagging[i] - l.initial) / (l.final_value - l.initial);
    // Compare over the same samples (all those after the step) at every
    // lag, so the costs are comparable; before its first sample the
    // reference is taken as its first value.
    let cost = |lag: usize| {
        (first..t.len())
            .map(|i| (ln(i) - rn(i.saturating_sub(lag))).powi(2))
            .sum::<f64>()
    };
    let costs: Vec<f64> = (0..=max_lag).map(cost).collect();
    let best = (0..costs.len())
        .min_by(|&a, &b| costs[a].total_cmp(&costs[b]))
        .unwrap_or(0);
    if best == max_lag && max_lag > 0 {
        return Err(StepMetricsError::DelayBeyondSearch {
            max_delay_s: max_lag as f64 * dt,
        });
    }
    let mut lag = best as f64;
    if best > 0 && best + 1 < costs.len() {
        let (a, b, c) = (costs[best - 1], costs[best], costs[best + 1]);
        let curvature = a - 2.0 * b + c;
        if curvature > 0.0 {
            lag += 0.5 * (a - c) / curvature;
        }
    }
    Ok(lag * dt)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn grid(dt: f64, end: f64) -> Vec<f64> {
        (0..=((end / dt).round() as usize))
            .map(|i| i as f64 * dt)
            .collect()
    }

    /// Unit step of a first-order lag `tau` at `t0`.
    fn first_order(t: &[f64], t0: f64, tau: f64) -> Vec<f64> {
        t.iter()
            .map(|&ti| {
                if ti <= t0 {
                    0.0
                } else {
                    1.0 - (-(ti - t0) / tau).exp()
                }
            })
            .collect()
    }

    /// Unit step of `wn² / (s² + 2ζ wn s + wn²)` at time 0, ζ < 1.
    fn second_order(t: f64, zeta: f64, wn: f64) -> f64 {
        if t <= 0.0 {
            return 0.0;
        }
        let wd = wn * (1.0 - zeta * zeta).sqrt();
        let phi = zeta.acos();
        1.0 - (-zeta * wn * t).exp() / (1.0 - zeta * zeta).sqrt() * (wd * t + phi).sin()
    }

    /// The exact 2 % settling time of the second-order step: its extremes
    /// sit at k π / wd with |y - 1| = exp(-ζ wn t_k); after the last one
    /// outside the band the response crosses into it once, found by bisection.
    fn second_order_settling(zeta: f64, wn: f64, band: f64) -> f64 {
        let wd = wn * (1.0 - zeta * zeta).sqrt();
        let k = (1..)
            .take_while(|&k| (-zeta * wn * f64::from(k) * PI / wd).exp() > band)
            .last()
            .expect("underdamped");
        let (mut lo, mut hi) = (f64::from(k) * PI / wd, f64::from(k + 1) * PI / wd);
        for _ in 0..100 {
            let mid = 0.5 * (lo + hi);
            if (second_order(mid, zeta, wn) - 1.0).abs() > band {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        hi
    }

    #[test]
    fn first_order_rise_is_2_197_tau_and_settling_3_912_tau() {
        let (tau, t0, dt) = (0.2, 0.5, 1e-4);
        let t = grid(dt, t0 + 12.0 * tau);
        let y = first_order(&t, t0, tau);
        let m = step_metrics(&t, &y, t0, Some(1.0), &StepOptions::default()).unwrap();
        let rise = m.rise_time_s.unwrap();
        assert!((rise - 9f64.ln() * tau).abs() < 2.0 * dt, "rise {rise}");
        assert!((rise / tau - 2.197).abs() < 1e-3);
        let settle = m.settling_time_s.unwrap();
        assert!(
            (settle - 50f64.ln() * tau).abs() < 2.0 * dt,
            "settle {settle}"
        );
        assert!(m.overshoot_pct < 0.01, "overshoot {} %", m.overshoot_pct);
        assert!(m.steady_state_error.unwrap().abs() < 1e-4);
    }

    #[test]
    fn second_order_overshoot_and_settling_match_the_damping_ratio() {
        let (wn, dt) = (2.0 * PI * 2.0, 1e-4);
        for zeta in [0.2, 0.43, 0.7] {
            let t = grid(dt, 12.0 / (zeta * wn));
            let y: Vec<f64> = t.iter().map(|&ti| second_order(ti, zeta, wn)).collect();
            let m = step_metrics(&t, &y, 0.0, Some(1.0), &StepOptions::default()).unwrap();
            let overshoot = 100.0 * (-zeta * PI / (1.0 - zeta * zeta).sqrt()).exp();
            assert!(
                (m.overshoot_pct - overshoot).abs() < 0.01,
                "ζ {zeta}: overshoot {} %, expected {overshoot} %",
                m.overshoot_pct
            );
            let peak_time = PI / (wn * (1.0 - zeta * zeta).sqrt());
            assert!((m.peak_time_s - peak_time).abs() <= dt, "ζ {zeta}");
            let settling = second_order_settling(zeta, wn, 0.02);
            let got = m.settling_time_s.unwrap();
            assert!(
                (got - settling).abs() < 2.0 * dt,
                "ζ {zeta}: settling {got} s, exact {settling} s"
            );
            // And it lies under the usual envelope bound.
            assert!(got <= -(0.02 * (1.0 - zeta * zeta).sqrt()).ln() / (zeta * wn));
        }
    }

    #[test]
    fn steady_state_error_and_a_downward_step() {
        let (tau, dt) = (0.05, 1e-3);
        let t = grid(dt, 1.0);
        // 1500 -> 600 rpm, ending 30 rpm above a 570 rpm set point.
        let y: Vec<f64> = first_order(&t, 0.1, tau)
            .iter()
            .map(|v| 1500.0 - 900.0 * v)
            .collect();
        let m = step_metrics(&t, &y, 0.1, Some(570.0), &StepOptions::default()).unwrap();
        assert!((m.steady_state_error.unwrap() + 30.0).abs() < 1e-3);
        assert!((m.rise_time_s.unwrap() - 9f64.ln() * tau).abs() < 2.0 * dt);
        assert!(m.overshoot_pct < 0.01, "overshoot {} %", m.overshoot_pct);
    }

    #[test]
    fn a_response_that_never_arrives_has_no_rise_or_settling_time() {
        let t = grid(0.01, 2.0);
        // Rises to 0.5, then falls back to 0.1 and wobbles there: ends at 0.1,
        // but the last sample is outside the band.
        let y: Vec<f64> = t
            .iter()
            .map(|&ti| {
                if ti < 0.5 {
                    0.0
                } else {
                    0.1 + 0.05 * (ti * 40.0).sin()
                }
            })
            .collect();
        let m = step_metrics(&t, &y, 0.5, None, &StepOptions::default()).unwrap();
        assert!(m.settling_time_s.is_none());
        let flat = vec![3.0; t.len()];
        assert!(matches!(
            step_metrics(&t, &flat, 0.5, None, &StepOptions::default()),
            Err(StepMetricsError::Flat { .. })
        ));
    }

    #[test]
    fn bad_series_are_refused_not_panicked_on() {
        let opts = StepOptions::default();
        assert!(step_metrics(&[0.0, 1.0], &[0.0], 0.5, None, &opts).is_err());
        assert!(step_metrics(&[0.0, 1.0], &[0.0, 1.0], 2.0, None, &opts).is_err());
        assert!(step_metrics(&[0.0, 0.0, 1.0], &[0.0, 1.0, 1.0], 0.5, None, &opts).is_err());
        assert!(step_metrics(&[0.0, 1.0], &[0.0, f64::NAN], 0.5, None, &opts).is_err());
        assert!(step_metrics(&[], &[], 0.5, None, &opts).is_err());
        assert!(delay(&[0.0, 1.0], &[0.0, 1.0], &[0.0], 0.5, 1.0).is_err());
        // A lag longer than the search is refused, not clamped.
        let t = grid(1e-3, 2.0);
        let (a, b) = (first_order(&t, 0.2, 0.05), first_order(&t, 0.9, 0.05));
        assert!(matches!(
            delay(&t, &a, &b, 0.2, 0.3),
            Err(StepMetricsError::DelayBeyondSearch { .. })
        ));
    }

    #[test]
    fn a_pure_delay_is_recovered_between_samples() {
        let (tau, t0, dt) = (0.08, 0.3, 2e-3);
        let t = grid(dt, 2.0);
        let reference = first_order(&t, t0, tau);
        for true_delay in [0.0, 0.0123, 0.05, 0.137] {
            let lagging = first_order(&t, t0 + true_delay, tau);
            // A sensor that reads 5 % low must not bias the lag.
            let lagging: Vec<f64> = lagging.iter().map(|v| 0.95 * v).collect();
            let d = delay(&t, &reference, &lagging, t0, 1.5).unwrap();
            assert!(
                (d - true_delay).abs() < 0.1 * dt,
                "delay {d} s, expected {true_delay} s"
            );
        }
    }
}
