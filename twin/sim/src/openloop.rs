//! The first `twin run`: the bench in open loop, no nodes yet. Enable the
//! inverter, release the brake, step `VEL` at a given time, record everything.

use plant::{Actuators, EvModule, PlantParams, Sensors};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use twin_recording::topics;

use crate::scenario::ScenarioError;
use crate::virtual_run::RunError;

type Result<T, E = RunError> = std::result::Result<T, E>;

/// What to run.
#[derive(Debug, Clone)]
pub struct OpenLoop {
    pub params: PlantParams,
    /// Name of the preset the parameters started from (recorded).
    pub preset: String,
    pub seed: u64,
    /// Simulated duration (s).
    pub duration_s: f64,
    /// Plant step (s).
    pub step_s: f64,
    /// `VEL` step: time (s) and level (fraction of 5 V).
    pub vel_step_at_s: f64,
    pub vel_fraction: f64,
    /// `VEL` before the step (fraction of 5 V); 0 unless a step experiment
    /// starts from a running wheel.
    pub vel_before_fraction: f64,
    /// Plant-state messages per simulated second.
    pub record_hz: f64,
    /// What an experiment run on the bench adds to the run's identity
    /// (`twin.run`), so that `twin replay` can run the experiment again.
    pub experiment: BTreeMap<String, String>,
}

impl OpenLoop {
    pub fn new(params: PlantParams, preset: &str) -> Self {
        Self {
            params,
            preset: preset.to_string(),
            seed: 1,
            duration_s: 3.0,
            step_s: 1e-3,
            vel_step_at_s: 0.5,
            vel_fraction: 0.6,
            vel_before_fraction: 0.0,
            record_hz: 1000.0,
            experiment: BTreeMap::new(),
        }
    }

    /// Actuators at time `t`.
    pub fn actuators_at(&self, t: f64) -> Actuators {
        let vel = if t + 1e-12 >= self.vel_step_at_s {
            5.0 * self.vel_fraction
        } else {
            5.0 * self.vel_before_fraction
        };
        Actuators {
            enable: true,
            vel_volts: vel,
            ..Default::default()
        }
    }
}

/// The run's outcome.
#[derive(Debug, Clone)]
pub struct Summary {
    pub final_state: Sensors,
    /// Energy taken from the battery terminals (J).
    pub battery_energy: f64,
    pub recording: PathBuf,
    pub steps: u64,
}

/// Run the bench and record it to `out`; `progress` is called with the
/// fraction done about every 1 % of the run.
pub fn run(config: &OpenLoop, out: &Path, progress: impl FnMut(f64)) -> Result<Summary> {
    run_with(config, out, progress, |_, _| Ok(()))
}

/// [`run`], calling `after_step` with the recording and the sensors after
/// every plant step (an experiment's own instruments read the bench there).
pub fn run_with(
    config: &OpenLoop,
    out: &Path,
    mut progress: impl FnMut(f64),
    mut after_step: impl FnMut(
        &mut twin_recording::record::Recorder,
        &Sensors,
    ) -> Result<(), twin_recording::WriteError>,
) -> Result<Summary> {
    let mut module = EvModule::new(&config.params, config.seed);
    let mut rec = twin_recording::record::Recorder::create(out)?;
    rec.write_metadata(topics::RUN_METADATA, run_metadata(config)?)?;
    rec.add_channel(topics::PLANT_SENSORS, module.sensors())?;
    rec.add_channel(topics::PLANT_ACTUATORS, &config.actuators_at(0.0))?;

    let steps = (config.duration_s / config.step_s).round().max(0.0) as u64;
    let record_every = ((1.0 / config.record_hz) / config.step_s).round().max(1.0) as u64;
    let progress_every = (steps / 100).max(1);
    let mut last_actuators = None;
    rec.write(topics::PLANT_SENSORS, 0.0, module.sensors())?;
    for k in 0..steps {
        let t = k as f64 * config.step_s;
        let act = config.actuators_at(t);
        if last_actuators != Some(act) {
            rec.write(topics::PLANT_ACTUATORS, t, &act)?;
            last_actuators = Some(act);
        }
        let sensors = module.step(config.step_s, &act);
        if (k + 1) % record_every == 0 {
            rec.write(topics::PLANT_SENSORS, sensors.time_s, sensors)?;
        }
        after_step(&mut rec, sensors)?;
        if k % progress_every == 0 {
            progress(k as f64 / steps as f64);
            if crate::interrupt::requested() {
                let at_s = sensors.time_s;
                let recording = rec.finish()?;
                let recording = Some(recording);
                return Err(crate::interrupt::Interrupted { at_s, recording }.into());
            }
        }
    }
    progress(1.0);
    let final_state = *module.sensors();
    let recording = rec.finish()?;
    Ok(Summary {
        final_state,
        battery_energy: final_state.energy.battery_out,
        recording,
        steps,
    })
}

fn run_metadata(config: &OpenLoop) -> Result<BTreeMap<String, String>, ScenarioError> {
    let mut fields = BTreeMap::from([
        ("kind".into(), "open-loop".into()),
        ("twin_version".into(), env!("CARGO_PKG_VERSION").into()),
        ("preset".into(), config.preset.clone()),
        ("seed".into(), config.seed.to_string()),
        ("duration_s".into(), config.duration_s.to_string()),
        ("step_s".into(), config.step_s.to_string()),
        ("vel_step_at_s".into(), config.vel_step_at_s.to_string()),
        ("vel_fraction".into(), config.vel_fraction.to_string()),
        ("record_hz".into(), config.record_hz.to_string()),
        (
            "params_toml".into(),
            toml::to_string(&config.params).map_err(ScenarioError::from)?,
        ),
    ]);
    fields.extend(config.experiment.clone());
    // Only when set, so that a plain open-loop run's file stays as it was.
    if config.vel_before_fraction != 0.0 {
        fields.insert(
            "vel_before_fraction".into(),
            config.vel_before_fraction.to_string(),
        );
    }
    Ok(fields)
}
