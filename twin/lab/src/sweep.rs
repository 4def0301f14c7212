//! The light sensor against the true wheel speed over a range of speeds: the
//! bench runs open loop at one `VEL` after another, and at each the firmware's
//! light rpm is averaged against the true rpm once the wheel has settled.
//! Where the light rpm stops tracking is where the photoresistor stops seeing
//! the flag; plant/src/light.rs derives that speed, and the sweep prints both.

use plant::PlantParams;
use protocols::time::{SimDuration, SimTime};
use serde::Serialize;
use std::path::{Path, PathBuf};

use super::instruments::{Instruments, light_limit};
use super::plot::{self, Axes, Series};
use twin_sim::openloop::{self, OpenLoop};

/// Why a sweep could not run.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    #[error("no speeds to sweep")]
    NoSpeeds,
    #[error("settling and measuring times must be positive")]
    NotPositive,
    #[error(
        "{rpm:.1} rpm is beyond what the {preset} bench's motor reaches at full VEL (its no-load \
         speed on this supply): give a lower --rpm range"
    )]
    BeyondNoLoad { rpm: f64, preset: String },
    #[error(
        "{rpm:.1} rpm needs VEL at {percent:.0} % of its range: the {preset} bench cannot reach it"
    )]
    OutOfRange {
        rpm: f64,
        percent: f64,
        preset: String,
    },
    #[error(transparent)]
    Run(#[from] twin_sim::virtual_run::RunError),
}

/// Within this fraction of the true speed the light sensor tracks it.
pub const TRACKING_TOLERANCE: f64 = 0.03;

/// One sweep.
#[derive(Debug, Clone)]
pub struct SweepConfig {
    pub params: PlantParams,
    pub preset: String,
    /// The EV controller's light detector in adaptive mode.
    pub adaptive: bool,
    /// Wheel speeds to run at (rpm); each is reached by the `VEL` the DC
    /// motor's steady state asks for, and the true speed is measured.
    pub target_rpm: Vec<f64>,
    /// Time to reach the speed before measuring, and time measured (s).
    pub settle_s: f64,
    pub measure_s: f64,
    pub seed: u64,
}

/// One speed of the sweep.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct SweepPoint {
    pub vel_fraction: f64,
    /// Means over the measuring window.
    pub wheel_rpm: f64,
    pub motor_rpm: f64,
    pub light_rpm: f64,
    /// Light rpm / true rpm.
    pub light_ratio: f64,
    pub tracks: bool,
}

/// A whole sweep: what `sweep.json` holds.
#[derive(Debug, Clone, Serialize)]
pub struct SweepReport {
    pub preset: String,
    pub light_detector: String,
    /// The fastest speed the detector sees by the formula (plant/src/light.rs).
    pub light_limit_rpm: f64,
    /// Below this speed the dip stays under the threshold for at least one
    /// sample period, so a sampled detector catches every one; between it
    /// and the limit some dips fall between samples.
    pub every_dip_sampled_below_rpm: f64,
    /// The measured speeds over which it tracks (from the first point that
    /// does), and the first speed above them where it does not.
    pub tracks_from_rpm: Option<f64>,
    pub tracks_up_to_rpm: Option<f64>,
    pub first_failure_rpm: Option<f64>,
    pub tolerance: f64,
    pub points: Vec<SweepPoint>,
}

/// `VEL` (fraction of 5 V) for a steady wheel speed: the DC motor's steady
/// state against the wheel's Coulomb and viscous friction, at `bus_volts`.
/// With fast decay each pulse applies the whole bus, so the duty scales the
/// torque, not the voltage; a speed beyond the no-load speed needs more than
/// the whole range (the result is above 1).
pub fn vel_for_rpm(p: &PlantParams, rpm: f64, bus_volts: f64) -> f64 {
    let omega = rpm * std::f64::consts::TAU / 60.0;
    let (k, r, n) = (
        p.motor.torque_constant,
        p.motor.resistance_ohm,
        p.gearbox.ratio,
    );
    let torque = p.wheel.coulomb_friction_nm + p.wheel.viscous_friction_nms * omega;
    match p.motor.pwm_decay {
        plant::motor::PwmDecay::Slow => (k * n * omega + r * torque / (k * n)) / bus_volts,
        plant::motor::PwmDecay::Fast => {
            // The pulse current, held at the controller's limit near standstill.
            let pulse_amps = ((bus_volts - k * n * omega) / r).min(p.motor.current_limit_amps);
            if pulse_amps > 0.0 {
                torque / (k * n * pulse_amps)
            } else {
                f64::INFINITY
            }
        }
    }
}

/// Run the sweep; `progress` gets the fraction done. Each run is recorded in
/// `runs_dir` (one MCAP per speed) when given, else to a scratch file.
pub fn run(
    config: &SweepConfig,
    runs_dir: Option<&Path>,
    mut progress: impl FnMut(f64),
) -> Result<SweepReport, SweepError> {
    if config.target_rpm.is_empty() {
        return Err(SweepError::NoSpeeds);
    }
    if !(config.settle_s > 0.0 && config.measure_s > 0.0) {
        return Err(SweepError::NotPositive);
    }
    let bus = config
        .params
        .battery
        .ocv_at(config.params.battery.initial_soc);
    let (light_detector, light_limit_rpm) =
        light_limit(&config.params, &config.preset, config.adaptive);
    let mut points = Vec::new();
    let n = config.target_rpm.len();
    for (i, &rpm) in config.target_rpm.iter().enumerate() {
        let vel = vel_for_rpm(&config.params, rpm, bus);
        if !vel.is_finite() {
            return Err(SweepError::BeyondNoLoad {
                rpm,
                preset: config.preset.clone(),
            });
        }
        if !(0.0..=1.0).contains(&vel) {
            return Err(SweepError::OutOfRange {
                rpm,
                percent: vel * 100.0,
                preset: config.preset.clone(),
            });
        }
        let path = match runs_dir {
            Some(dir) => dir.join(format!("sweep-{:05.0}rpm.mcap", rpm)),
            None => std::env::temp_dir().join(format!("twin-sweep-{}.mcap", std::process::id())),
        };
        let point = run_one(config, rpm, vel, &path, |f| {
            progress((i as f64 + f) / n as f64)
        })?;
        if runs_dir.is_none() {
            let _ = std::fs::remove_file(&path);
        }
        points.push(point);
    }
    points.sort_by(|a, b| a.wheel_rpm.total_cmp(&b.wheel_rpm));
    // The band where it tracks: from the first point that does up to the
    // point before the first that no longer does.
    let first_ok = points.iter().position(|p| p.tracks);
    let first_bad = first_ok.and_then(|i| (i..points.len()).find(|&j| !points[j].tracks));
    let tracks_from_rpm = first_ok.map(|i| points[i].wheel_rpm);
    let tracks_up_to_rpm =
        first_ok.map(|_| points[first_bad.unwrap_or(points.len()) - 1].wheel_rpm);
    let first_failure_rpm = first_bad.map(|j| points[j].wheel_rpm);
    // The shadow lasts `arc_s / n`; the formula's limit is where all of it
    // is needed to reach the threshold, so at `n` the dip spends
    // `arc_s / n - arc_s / limit` below it.
    let arc_s = config.params.light.flag_arc_deg / 360.0 * 60.0;
    let sample_s =
        Instruments::new(&config.params, &config.preset, config.adaptive).sample_period_s();
    let every_dip_sampled_below_rpm = arc_s / (arc_s / light_limit_rpm + sample_s);
    Ok(SweepReport {
        preset: config.preset.clone(),
        light_detector,
        light_limit_rpm,
        every_dip_sampled_below_rpm,
        tracks_from_rpm,
        tracks_up_to_rpm,
        first_failure_rpm,
        tolerance: TRACKING_TOLERANCE,
        points,
    })
}

fn run_one(
    config: &SweepConfig,
    target_rpm: f64,
    vel: f64,
    path: &Path,
    progress: impl FnMut(f64),
) -> Result<SweepPoint, twin_sim::virtual_run::RunError> {
    // A slow wheel needs a few turns to settle and a few to be measured: the
    // light sensor gives one reading per turn.
    let turn_s = 60.0 / target_rpm.max(1.0);
    let settle_s = config.settle_s.max(4.0 * turn_s);
    let measure_s = config.measure_s.max(3.0 * turn_s);
    let mut ol = OpenLoop::new(config.params.clone(), &config.preset);
    ol.seed = config.seed;
    ol.duration_s = settle_s + measure_s;
    ol.vel_step_at_s = 0.0;
    ol.vel_fraction = vel;
    ol.record_hz = 100.0;
    let step = SimDuration::from_secs_f64(ol.step_s);
    let mut instruments = Instruments::new(&config.params, &config.preset, config.adaptive);
    let (mut wheel, mut motor, mut light, mut count) = (0.0, 0.0, 0.0, 0u64);
    let mut k = 0u64;
    openloop::run_with(&ol, path, progress, |_, sensors| {
        k += 1;
        let now = SimTime::ZERO + SimDuration(step.0 * k);
        instruments.tick(now, sensors);
        if sensors.time_s > settle_s {
            let r = instruments.read();
            wheel += sensors.wheel_rpm;
            motor += r.motor;
            light += r.light;
            count += 1;
        }
        Ok(())
    })?;
    let c = count.max(1) as f64;
    let (wheel_rpm, motor_rpm, light_rpm) = (wheel / c, motor / c, light / c);
    let light_ratio = if wheel_rpm > 0.0 {
        light_rpm / wheel_rpm
    } else {
        0.0
    };
    Ok(SweepPoint {
        vel_fraction: vel,
        wheel_rpm,
        motor_rpm,
        light_rpm,
        light_ratio,
        tracks: (light_ratio - 1.0).abs() <= TRACKING_TOLERANCE,
    })
}

/// `sweep.png`: light rpm against true rpm, the line where they agree, and
/// the documented limit.
pub fn plot(reports: &[SweepReport], path: &Path) -> Result<PathBuf, plot::PlotError> {
    let colors = [plot::LIGHT, plot::MOTOR, plot::EXTRA];
    let max = reports
        .iter()
        .flat_map(|r| r.points.iter().map(|p| p.wheel_rpm.max(p.light_rpm)))
        .fold(0.0_f64, f64::max)
        * 1.05;
    let mut series = vec![Series {
        name: "light = true",
        color: plot::SET_POINT,
        points: vec![(0.0, 0.0), (max, max)],
        dots: false,
        width: 2,
    }];
    let names: Vec<String> = reports
        .iter()
        .map(|r| format!("{} (limit {:.0} rpm)", r.light_detector, r.light_limit_rpm))
        .collect();
    for (i, r) in reports.iter().enumerate() {
        let color = colors[i % colors.len()];
        series.push(Series {
            name: &names[i],
            color,
            points: r
                .points
                .iter()
                .map(|p| (p.wheel_rpm, p.light_rpm))
                .collect(),
            dots: true,
            width: 2,
        });
        if r.light_limit_rpm < max {
            series.push(Series {
                name: "",
                color,
                points: vec![(r.light_limit_rpm, 0.0), (r.light_limit_rpm, max)],
                dots: false,
                width: 1,
            });
        }
    }
    let title = format!(
        "{}: light-sensor rpm against true wheel rpm",
        reports[0].preset
    );
    let axes = Axes {
        title: &title,
        x_label: "true wheel rpm",
        y_label: "light-sensor rpm",
        x_range: (0.0, max),
        y_range: (0.0, max),
        legend_upper_left: true,
    };
    plot::line_plot(path, &axes, &series, (880, 580))?;
    Ok(path.to_path_buf())
}
