//! The figures a batch run is compared by, named `MODULE.FIGURE` as the run
//! summary prints them (`twin run`): the wheel's true speed and what the
//! controller reads of it (RPM_M from the halls, RPM_L from the light
//! sensor), V1, V2, I and the state of charge at the end; per bus its noise
//! and collision counts; the events by kind; and where the scenario's
//! supervisor steps its set point, the wheel's step figures as `twin step`
//! gives them (`step.settling_s`, `step.rise_s`, `step.overshoot_pct`,
//! `step.error_rpm`), for the first step, up to the next.

use std::collections::BTreeMap;

use twin_sim::scenario::{NodeSpec, Scenario};
use twin_sim::step_metrics::{StepOptions, step_metrics};
use twin_sim::virtual_run::RunOutcome;

pub type Figures = BTreeMap<String, Option<f64>>;

/// The end-of-run figures of `outcome`.
pub fn of_outcome(outcome: &RunOutcome) -> Figures {
    let mut f = Figures::new();
    f.insert("simulated_s".into(), Some(outcome.simulated_s));
    f.insert("frames".into(), Some(outcome.frames as f64));
    for (module, s) in &outcome.modules {
        f.insert(format!("{module}.wheel_rpm"), Some(s.wheel_rpm));
        f.insert(format!("{module}.battery_volts"), Some(s.battery_volts));
        f.insert(format!("{module}.bus_volts"), Some(s.bus_volts));
        f.insert(format!("{module}.inverter_amps"), Some(s.inverter_current));
        f.insert(format!("{module}.soc_pct"), Some(s.soc * 100.0));
    }
    for c in &outcome.controllers {
        let d = &c.detector;
        let shared = outcome
            .controllers
            .iter()
            .filter(|o| o.detector.module == d.module)
            .count()
            > 1;
        // A module read by two controllers names each.
        let who = if shared {
            format!("{}.{}", d.module, d.node)
        } else {
            d.module.clone()
        };
        f.insert(
            format!("{who}.hall_rpm"),
            Some(f64::from(c.readings.hall_rpm)),
        );
        f.insert(
            format!("{who}.light_rpm"),
            Some(f64::from(c.readings.light_rpm)),
        );
        f.insert(format!("{who}.light_limit_rpm"), Some(d.limit_rpm));
    }
    for (bus, stats, checks) in &outcome.buses {
        f.insert(format!("{bus}.collisions"), Some(stats.collisions as f64));
        f.insert(
            format!("{bus}.bytes_corrupted_by_noise"),
            Some(stats.bytes_corrupted_by_noise as f64),
        );
        f.insert(
            format!("{bus}.frames_received"),
            Some(checks.frames_received as f64),
        );
        f.insert(
            format!("{bus}.frames_corrupted"),
            Some(checks.frames_corrupted as f64),
        );
        f.insert(
            format!("{bus}.corrupted_passed_check"),
            Some(checks.corrupted_passed_check as f64),
        );
    }
    for (kind, n) in &outcome.events {
        f.insert(format!("events.{kind}"), Some(*n as f64));
    }
    f
}

/// The set-point step a scenario's supervisor makes, and the module whose
/// wheel answers it.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    pub module: String,
    pub from: f64,
    pub to: f64,
    pub at_s: f64,
    /// The next change of set point, or the end of the run.
    pub until_s: f64,
}

impl Step {
    /// The first change of the supervisor's set point after the run's
    /// start, when the supervisor's first slave is an EV controller.
    pub fn of_scenario(scenario: &Scenario) -> Option<Self> {
        let (slave, bus, points) = scenario.nodes.iter().find_map(|n| match n {
            NodeSpec::Supervisor {
                slaves,
                bus,
                set_points,
                ..
            } => Some((*slaves.first()?, bus, set_points)),
            _ => None,
        })?;
        let module = scenario.nodes.iter().find_map(|n| match n {
            NodeSpec::EvController {
                bus: b, module, id, ..
            } if *id == slave && b == bus => Some(module.clone()),
            _ => None,
        })?;
        let mut before = 0.0;
        for (i, [t, v]) in points.iter().copied().enumerate() {
            if t > 0.0 && t < scenario.duration_s && v != before {
                let until_s = points[i + 1..]
                    .iter()
                    .find(|p| p[1] != v)
                    .map_or(scenario.duration_s, |p| p[0].min(scenario.duration_s));
                return Some(Self {
                    module,
                    from: before,
                    to: v,
                    at_s: t,
                    until_s,
                });
            }
            before = v;
        }
        None
    }

    /// Its figures from the wheel's speed sampled at `time_s`; `None` for
    /// those the run was too short to give.
    pub fn figures(&self, time_s: &[f64], wheel_rpm: &[f64]) -> Figures {
        let n = time_s.partition_point(|&t| t <= self.until_s + 1e-9);
        let metrics = step_metrics(
            &time_s[..n],
            &wheel_rpm[..n],
            self.at_s,
            Some(self.to),
            &StepOptions::default(),
        )
        .ok();
        let mut f = Figures::new();
        f.insert("step.at_s".into(), Some(self.at_s));
        f.insert("step.from_rpm".into(), Some(self.from));
        f.insert("step.to_rpm".into(), Some(self.to));
        f.insert(
            "step.settling_s".into(),
            metrics.and_then(|m| m.settling_time_s),
        );
        f.insert("step.rise_s".into(), metrics.and_then(|m| m.rise_time_s));
        f.insert(
            "step.overshoot_pct".into(),
            metrics.map(|m| m.overshoot_pct),
        );
        f.insert(
            "step.error_rpm".into(),
            metrics.and_then(|m| m.steady_state_error),
        );
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_step_of_the_supervisor_up_to_the_next() {
        let s = Scenario::load("ev-meb").unwrap();
        let step = Step::of_scenario(&s).unwrap();
        assert_eq!(
            step,
            Step {
                module: "ev1".into(),
                from: 0.0,
                to: 1000.0,
                at_s: 0.5,
                until_s: 5.0
            }
        );
        // A first-order answer with a time constant of 0.1 s settles within
        // 2 % after 0.1·ln 50 = 0.391 s.
        let t: Vec<f64> = (0..2500).map(|i| f64::from(i) * 0.002).collect();
        let y: Vec<f64> = t
            .iter()
            .map(|&t| {
                if t <= 0.5 {
                    0.0
                } else {
                    1000.0 * (1.0 - (-(t - 0.5) / 0.1).exp())
                }
            })
            .collect();
        let f = step.figures(&t, &y);
        let settling = f["step.settling_s"].unwrap();
        assert!((settling - 0.391).abs() < 0.003, "{settling}");
        assert_eq!(f["step.overshoot_pct"], Some(0.0));
    }
}
