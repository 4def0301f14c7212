//! `twin step`: the step-response experiment (the Controller_network project's
//! plot of both speed sensors), with its figures for the motor's and the light
//! sensor's rpm.

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use std::path::PathBuf;
use twin_lab::step::{self, StepConfig, StepDrive, StepReport};
use twin_sim::scenario::{NodeSpec, Scenario};
use twin_sim::step_metrics::StepMetrics;

use super::output::Earlier;
use super::progress::Progress;
use super::serve::LightDetector;
use twin_lab::step::short;

/// Step response of the wheel, the hall rpm and the light-sensor rpm: rise, overshoot, settling, delay.
///
/// Steps the set point and measures the true wheel speed, the motor's own
/// rpm (hall edges; the encoder on the Controller_network bench) and the light
/// sensor's rpm: 10–90 % rise time, overshoot, 2 % settling time,
/// steady-state error and each sensor's delay behind the true speed.
///
/// Closed loop (default): SCENARIO's supervisor (default `ev-meb`) steps its
/// set point from FROM to TO rpm and closes the loop over the bus; in the
/// `controller-network` scenario the Controller_network master runs its own set
/// points and its first step after `--at` is measured. With
/// `--open-loop` the bench alone steps VEL from FROM to TO (fractions of its
/// 5 V range) while the firmware's estimators read its sensors.
///
/// Prints a table and writes step.json (the figures), step.png (the plot) and
/// step.mcap (the recording) into the current folder, or into `--out DIR`,
/// replacing those there.
#[derive(Debug, Args)]
#[command(
    mut_arg("preset", |a| a.requires("open_loop"))
)]
pub struct StepArgs {
    /// Embedded scenario name or scenario file with a supervisor [default: ev-meb].
    #[arg(value_name = "SCENARIO", conflicts_with = "open_loop")]
    scenario: Option<String>,
    /// Step VEL on the bench alone instead of a set point through a master.
    #[arg(long)]
    open_loop: bool,
    /// Set point before the step: rpm, or VEL fraction with --open-loop
    /// [default: 100 rpm; 0.025 open loop].
    #[arg(long, value_name = "VALUE", allow_negative_numbers = true, value_parser = super::numbers::number)]
    from: Option<f64>,
    /// Set point after the step: rpm, or VEL fraction with --open-loop
    /// [default: 200 rpm; 0.045 open loop].
    #[arg(long, value_name = "VALUE", allow_negative_numbers = true, value_parser = super::numbers::number)]
    to: Option<f64>,
    /// Time of the step (s); with the Controller_network master, the first
    /// change of its set point at or after this time is measured [default: 2 s;
    /// 0 s controller-network].
    #[arg(long, value_name = "SECONDS", value_parser = super::numbers::zero_or_more)]
    at: Option<f64>,
    /// Simulated duration (s) [default: 6 s; 30 s controller-network].
    #[arg(long, value_name = "SECONDS", value_parser = super::numbers::above_zero)]
    duration: Option<f64>,
    /// Seed of every random draw (sensor noise, bit errors).
    #[arg(long, default_value_t = 1, value_parser = super::numbers::whole::<u64>)]
    seed: u64,
    #[command(flatten)]
    plant: super::plant_args::PlantArgs,
    /// Open loop: the EV controller's light detector, `adaptive` (the
    /// default, as `twin serve` and the `ev-meb` scenario have it: it follows
    /// the wheel up to about 1800 rpm) or `fixed` (the firmware's threshold
    /// at power-up: about 260 rpm). The Controller_network light-sensor Nano
    /// has its fixed threshold only.
    #[arg(long, value_enum, value_name = "DETECTOR", requires = "open_loop")]
    light_detector: Option<LightDetector>,
    /// The adaptive light detector: the default now (--light-detector).
    #[arg(
        long,
        hide = true,
        requires = "open_loop",
        conflicts_with = "light_detector"
    )]
    adaptive_light: bool,
    /// Closed loop: the speed the supervisor's PI closes on, the hall rpm or
    /// the light-sensor rpm.
    #[arg(long, value_enum, default_value_t = Feedback::Hall, conflicts_with = "open_loop")]
    feedback: Feedback,
    /// A real bench's step log to compare with: a CSV file in the layout of
    /// the Controller_network step log (`time_s`, `motor_value`,
    /// `sensor_value`, as recordings/calibration/controller-network-step.csv).
    /// Its curves are drawn over the twin's and its figures printed beside them.
    #[arg(long, value_name = "FILE.csv", conflicts_with = "open_loop")]
    against: Option<PathBuf>,
    /// When the step came in the --against log, on its own clock (s).
    #[arg(long, value_name = "SECONDS", default_value_t = 1.0, requires = "against", value_parser = super::numbers::zero_or_more)]
    against_step_at: f64,
    /// Folder for step.json, step.png and step.mcap (created if needed) [default: the
    /// current folder].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Feedback {
    Hall,
    Light,
}

pub fn execute(args: &StepArgs) -> Result<()> {
    let drive = if args.open_loop {
        let params = args.plant.load()?;
        let geared = args.plant.preset == "controller-network";
        let adaptive_light = match (args.light_detector, args.adaptive_light) {
            (Some(LightDetector::Adaptive), _) | (None, true) if geared => bail!(
                "the Controller_network light-sensor Nano has its fixed threshold only: \
                 leave out --light-detector, or give `fixed`"
            ),
            (Some(detector), _) => detector == LightDetector::Adaptive,
            (None, adaptive) => adaptive || !geared,
        };
        StepDrive::OpenLoop {
            params: Box::new(params),
            preset: args.plant.preset.clone(),
            adaptive_light,
        }
    } else {
        let name = args.scenario.as_deref().unwrap_or("ev-meb");
        let mut scenario = Scenario::load(name)?;
        if let Some(file) = &args.plant.params {
            super::plant_args::apply_to_scenario(&mut scenario, file)?;
        }
        StepDrive::ClosedLoop {
            scenario: Box::new(scenario),
            on_light: args.feedback == Feedback::Light,
        }
    };
    // The Controller_network master runs its own set points: its step is measured.
    let own_schedule = match &drive {
        StepDrive::ClosedLoop { scenario, .. } => !scenario
            .nodes
            .iter()
            .any(|n| matches!(n, NodeSpec::Supervisor { .. })),
        StepDrive::OpenLoop { .. } => false,
    };
    if own_schedule && (args.from.is_some() || args.to.is_some()) {
        bail!(
            "this scenario's master (the Controller_network Raspberry Pi) runs its own set \
             points, so --from and --to do not apply: give --at to pick which of its steps to \
             measure"
        );
    }
    let (from, to) = if args.open_loop {
        (args.from.unwrap_or(0.025), args.to.unwrap_or(0.045))
    } else {
        (args.from.unwrap_or(100.0), args.to.unwrap_or(200.0))
    };
    let (at, duration) = if own_schedule {
        (0.0, 30.0)
    } else {
        (2.0, 6.0)
    };
    let config = StepConfig {
        drive,
        from,
        to,
        step_at_s: args.at.unwrap_or(at),
        duration_s: args.duration.unwrap_or(duration),
        seed: args.seed,
    };
    // The current folder as `step.json`, not `./step.json`.
    let dir = args.out.clone().unwrap_or_default();
    if args.out.is_some() {
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create folder {}", dir.display()))?;
    }
    let [json, png, recording] = ["step.json", "step.png", "step.mcap"].map(|f| dir.join(f));
    let earlier = [&json, &png, &recording].map(|p| Earlier::at(p));
    let progress = Progress::fraction("step response");
    let report = step::run(&config, &recording, |f| progress.show(f))?;
    progress.clear();
    print_report(&report);
    let against = match &args.against {
        Some(file) => Some(twin_lab::step_against::load(
            file,
            args.against_step_at,
            &report,
        )?),
        None => None,
    };
    if let Some(a) = &against {
        print_against(a);
    }
    std::fs::write(&json, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", json.display()))?;
    println!(
        "figures: {}{}",
        json.display(),
        Earlier::note(earlier[0].as_ref())
    );
    let extra = against
        .as_ref()
        .map(|a| twin_lab::step_against::series(a).to_vec())
        .unwrap_or_default();
    step::plot_with(&report, extra, &png)?;
    println!(
        "plot: {}{}",
        png.display(),
        Earlier::note(earlier[1].as_ref())
    );
    println!(
        "recording: {}{}",
        report.recording.display(),
        Earlier::note(earlier[2].as_ref())
    );
    Ok(())
}

/// The bench's figures, in the columns of the twin's table.
fn print_against(a: &twin_lab::step_against::Against) {
    println!("  the bench ({}), its step laid on the twin's:", a.name);
    print_row("motor (encoder)", a.motor_figures.as_ref(), None);
    print_row("light sensor", a.light_figures.as_ref(), None);
}

/// One signal's row of the table.
fn print_row(signal: &str, metrics: Option<&StepMetrics>, delay_s: Option<f64>) {
    let secs = |v: Option<f64>| v.map_or("—".to_string(), |s| format!("{s:.3} s"));
    match metrics {
        Some(m) => println!(
            "  {:16} {:>9.1} {:>9.1} {:>11} {:>8.1} % {:>12} {:>13} {:>10}",
            signal,
            m.initial,
            m.final_value,
            secs(m.rise_time_s),
            m.overshoot_pct,
            secs(m.settling_time_s),
            m.steady_state_error
                .map_or("—".to_string(), |e| format!("{e:.1}")),
            secs(delay_s)
        ),
        None => println!("  {signal:16} no step figures"),
    }
}

fn print_report(r: &StepReport) {
    let (what, unit, scale) = if r.mode == "closed-loop" {
        (format!("scenario {}, set point", r.bench), "rpm", 1.0)
    } else {
        (format!("{} preset, VEL", r.bench), "%", 100.0)
    };
    println!(
        "twin step: {}, {what} {} → {} {unit} at {} s, {} s simulated, seed {}",
        r.mode,
        short(r.from * scale),
        short(r.to * scale),
        r.step_at_s,
        r.duration_s,
        r.seed
    );
    println!(
        "  light detector: {}; it sees the flag up to {:.0} rpm",
        r.light_detector, r.light_limit_rpm
    );
    if r.figures_until_s + 1e-6 < r.duration_s {
        println!(
            "  figures from the step to {:.3} s, where the set point changes again",
            r.figures_until_s
        );
    }
    println!(
        "  {:16} {:>9} {:>9} {:>11} {:>10} {:>12} {:>13} {:>10}",
        "signal (rpm)",
        "initial",
        "final",
        "rise 10-90",
        "overshoot",
        "settling 2%",
        "steady error",
        "delay"
    );
    for s in &r.signals {
        print_row(s.signal, s.metrics.as_ref(), s.delay_s);
        if let Some(note) = &s.note {
            println!("  {:16} ({note})", "");
        }
    }
    if r.mode == "open-loop" {
        println!("  open loop the sensors' steady-state error is against the true wheel speed");
    }
}
