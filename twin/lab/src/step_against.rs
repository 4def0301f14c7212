//! `twin step --against FILE.csv`: a real bench's step response beside the
//! twin's, in the layout of the Controller_network step log (`time_s`,
//! `motor_value`, `sensor_value`, the registers as its master read them).

use std::path::Path;
use twin_sim::step_metrics::{StepMetrics, StepOptions, step_metrics};

use crate::calibrate::csv_log;
use plotters::style::RGBColor;

use crate::plot::Series;

/// Why a bench's step log cannot be laid over the twin's.
#[derive(Debug, thiserror::Error)]
pub enum AgainstError {
    #[error(
        "--against compares with a Controller_network bench's step log: give the \
         controller-network scenario (or one with its motor and light-sensor nodes)"
    )]
    NotControllerNetwork,
    /// The log itself, in the words of its file.
    #[error(transparent)]
    Log(#[from] crate::calibrate::CalibrateError),
}
use crate::step::StepReport;

/// The bench's curves in wheel rpm, moved onto the twin's time axis.
#[derive(Debug, Clone)]
pub struct Against {
    /// The file, for the table and the legend.
    pub name: String,
    /// The motor's encoder reading and the light sensor's, in wheel rpm.
    pub motor: Vec<(f64, f64)>,
    pub light: Vec<(f64, f64)>,
    /// Their figures, measured as the twin's are.
    pub motor_figures: Option<StepMetrics>,
    pub light_figures: Option<StepMetrics>,
}

/// The motor reads motor rpm and the light sensor wheel rpm × 100: both are
/// a hundred times the wheel's rpm on the 100:1 bench.
const REGISTER_PER_WHEEL_RPM: f64 = 100.0;

/// Reads `path`, whose step came at `bench_step_s` on its own clock, and
/// lays it over `report` (its step at the twin's `step_at_s`).
pub fn load(path: &Path, bench_step_s: f64, report: &StepReport) -> Result<Against, AgainstError> {
    if report.mode != "closed-loop" || !report.signals.iter().any(|s| s.signal == "motor (encoder)")
    {
        return Err(AgainstError::NotControllerNetwork);
    }
    let table = csv_log::read(path, "time_s", 1.0)?;
    let shift = report.step_at_s - bench_step_s;
    let column = |name: &str| -> Result<Vec<(f64, f64)>, AgainstError> {
        Ok(table
            .column(name, true)?
            .into_iter()
            .map(|(t, v)| (t + shift, v / REGISTER_PER_WHEEL_RPM))
            .filter(|(t, _)| *t >= 0.0 && *t <= report.duration_s)
            .collect())
    };
    let (motor, light) = (column("motor_value")?, column("sensor_value")?);
    let figures = |curve: &[(f64, f64)]| {
        let (t, y) = crate::calibrate::report::after_step(
            curve,
            report.step_at_s,
            report.from,
            report.figures_until_s,
        );
        step_metrics(
            &t,
            &y,
            report.step_at_s - 5e-4,
            Some(report.to),
            &StepOptions::default(),
        )
        .ok()
    };
    Ok(Against {
        name: path.display().to_string(),
        motor_figures: figures(&motor),
        light_figures: figures(&light),
        motor,
        light,
    })
}

/// The bench's curves as plot series, beside the twin's.
pub fn series(against: &Against) -> [Series<'static>; 2] {
    [
        Series {
            name: "motor (encoder), bench",
            color: RGBColor(110, 170, 220),
            points: against.motor.clone(),
            dots: false,
            width: 1,
        },
        Series {
            name: "light sensor, bench",
            color: RGBColor(240, 140, 140),
            points: against.light.clone(),
            dots: false,
            width: 1,
        },
    ]
}
