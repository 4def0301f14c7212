//! `twin run`: run the bench in simulated time and record it.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;
use twin_sim::openloop::{self, OpenLoop};
use twin_sim::replay::RunSpec;
use twin_sim::scenario::{EMBEDDED, Scenario};
use twin_sim::virtual_run::{self, ControllerOutcome};
use twin_view::{self as view, RerunObserver, ViewLayout, ViewTarget};

use super::output::Earlier;
use super::progress::Progress;

/// Run a scenario in simulated time, far faster than real time, and record it.
///
/// SCENARIO is the name of an embedded scenario (`twin run --list`) or a
/// scenario file (TOML); without it, `ev-meb` runs: the EV module's speed loop
/// closed by a supervisor over MEB. `--open-loop` runs the bench alone instead:
/// inverter enabled, brake released, VEL stepped to 60 % at 0.5 s, 3 s in all.
/// Every run prints a summary and the path of its MCAP recording (Foxglove,
/// `mcap`, and rerun open it). Ctrl-C or SIGTERM stops a run where it has got
/// to, with its recording finished (exit status 130); a recording also stops,
/// closed whole, when its disk has less than 256 MB free
/// (TWIN_MIN_FREE_DISK_MB sets another floor). A recording already at the path
/// is replaced, and the summary says so with what it held.
///
/// `--set PATH=VALUE` changes one field of the scenario before it runs, dotted
/// as in its TOML with list items by name or index, as `twin replay` and
/// `twin batch` take it: `--set node.supervisor.kp=0.6`,
/// `--set module.ev1.params.wheel.brake_torque_nm=3`; open loop, a setting
/// (`vel_fraction`) or a plant parameter (`params.motor.current_limit_amps=8`).
#[derive(Debug, Args)]
#[command(
    mut_arg("preset", |a| a.requires("open_loop"))
)]
pub struct RunArgs {
    /// Embedded scenario name or scenario file.
    #[arg(value_name = "SCENARIO", conflicts_with = "open_loop")]
    scenario: Option<String>,
    /// List the embedded scenarios and exit.
    #[arg(long)]
    list: bool,
    /// Run the bench alone in open loop (no nodes, no bus).
    #[arg(long)]
    open_loop: bool,
    /// Simulated duration in seconds (default: the scenario's; 3 s open loop).
    #[arg(long, value_name = "SECONDS", value_parser = super::numbers::above_zero)]
    duration: Option<f64>,
    /// Where to write the recording, replacing one there [default: SCENARIO.mcap,
    /// twin-run.mcap open loop].
    #[arg(long, value_name = "PATH")]
    out: Option<PathBuf>,
    /// Seed of every random draw (noise, bit errors) [default: the scenario's; 1].
    #[arg(long, value_parser = super::numbers::whole::<u64>)]
    seed: Option<u64>,
    /// Change a field of the scenario before it runs (repeatable), e.g.
    /// `node.supervisor.kp=0.6`.
    #[arg(long = "set", value_name = "PATH=VALUE")]
    overrides: Vec<String>,
    /// Stream the run to rerun as it goes, beside the MCAP recording:
    /// `--view` opens a viewer (or uses the one already running),
    /// `--view rerun+http://HOST:PORT/proxy` streams to a running viewer,
    /// `--view FILE.rrd` writes the stream to a file. Without a viewer the
    /// run goes on and records as usual.
    #[arg(
        long,
        value_name = "TARGET",
        num_args = 0..=1,
        default_missing_value = "spawn",
        conflicts_with = "open_loop"
    )]
    view: Option<String>,
    #[command(flatten)]
    plant: super::plant_args::PlantArgs,
    /// Open loop: VEL level after the step, as a fraction of its 5 V range.
    #[arg(
        long,
        default_value_t = 0.6,
        value_name = "FRACTION",
        requires = "open_loop"
, value_parser = super::numbers::number)]
    vel: f64,
    /// Open loop: time of the VEL step in seconds.
    #[arg(
        long,
        default_value_t = 0.5,
        value_name = "SECONDS",
        requires = "open_loop"
, value_parser = super::numbers::zero_or_more)]
    vel_at: f64,
    /// Open loop: plant state messages recorded per simulated second.
    #[arg(
        long,
        default_value_t = 1000.0,
        value_name = "HZ",
        requires = "open_loop"
, value_parser = super::numbers::above_zero)]
    record_hz: f64,
}

pub fn execute(args: &RunArgs) -> Result<()> {
    if args.list {
        let width = EMBEDDED.iter().map(|(n, _, _)| n.len()).max().unwrap_or(0);
        for (name, description, _) in EMBEDDED {
            println!("{name:width$}  {description}");
        }
        return Ok(());
    }
    if args.open_loop {
        return execute_open_loop(args);
    }
    let name = args.scenario.as_deref().unwrap_or("ev-meb");
    let mut scenario = Scenario::load(name)?;
    if let Some(file) = &args.plant.params {
        super::plant_args::apply_to_scenario(&mut scenario, file)?;
    }
    let mut scenario = RunSpec::scenario_with_overrides(scenario, &args.overrides)?;
    if let Some(d) = args.duration {
        check_duration(d)?;
        scenario.duration_s = d;
    }
    if let Some(seed) = args.seed {
        scenario.seed = seed;
    }
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(format!("{}.mcap", scenario.name)));
    let earlier = Earlier::at(&out);
    let mut live = match &args.view {
        Some(target) => open_live_view(target, &scenario)?,
        None => None,
    };
    let started = Instant::now();
    let progress = Progress::simulated(&scenario.name, scenario.duration_s);
    let outcome = match live.as_mut() {
        Some(observer) => {
            virtual_run::run_with(&scenario, &out, observer, |done| progress.show(done))
        }
        None => virtual_run::run(&scenario, &out, |done| progress.show(done)),
    }
    .with_context(|| format!("scenario {} failed", scenario.name))?;
    progress.clear();
    let wall = started.elapsed().as_secs_f64();
    println!(
        "twin run: scenario {}, seed {}, {:.3} s simulated",
        scenario.name, scenario.seed, outcome.simulated_s
    );
    for (module, s) in &outcome.modules {
        println!(
            "  module {module}: wheel {:.1} rpm (its true speed), V1 {:.2} V, V2 {:.2} V, I {:.2} A, SOC {:.2} %",
            s.wheel_rpm,
            s.battery_volts,
            s.bus_volts,
            s.inverter_current,
            s.soc * 100.0
        );
        for c in outcome
            .controllers
            .iter()
            .filter(|c| &c.detector.module == module)
        {
            print_speed_sensors(c, s.wheel_rpm);
        }
    }
    for (node, state) in &outcome.telemetry {
        super::node_summary::print(node, state, outcome.simulated_s);
    }
    for unanswered in scenario.unanswered_ids() {
        println!("  {unanswered}");
    }
    for (bus, c) in &outcome.pwm_calibrations {
        println!(
            "  calibrated at initialisation: {}",
            virtual_run::describe_calibration(bus, c)
        );
    }
    for (bus, stats, checks) in &outcome.buses {
        if let Some((_, p)) = outcome.pwm.iter().find(|(name, _)| name == bus) {
            println!(
                "  bus {bus} (PWM capture): {} frames of {} symbols, {} waited for the line; \
                 {} receptions, {} clean; {} pulses lost, {} values wrong",
                p.frames_sent,
                p.symbols_sent,
                p.frames_deferred,
                p.receptions,
                p.receptions_clean,
                p.pulses_lost,
                p.symbols_wrong
            );
            continue;
        }
        println!(
            "  bus {bus}: {} bytes, {} corrupted by noise, {} collisions; {} frames received, {} corrupted, {} of them passed the check",
            stats.bytes_sent,
            stats.bytes_corrupted_by_noise,
            stats.collisions,
            checks.frames_received,
            checks.frames_corrupted,
            checks.corrupted_passed_check
        );
    }
    let events: Vec<String> = outcome
        .events
        .iter()
        .map(|(k, n)| format!("{k} {n}"))
        .collect();
    println!(
        "  {} frames sent; events: {}",
        outcome.frames,
        if events.is_empty() {
            "none".to_string()
        } else {
            events.join(", ")
        }
    );
    for line in &outcome.log_tail {
        println!("  {line}");
    }
    let factor = outcome.simulated_s / wall.max(1e-9);
    // Compiled firmware in the loop runs near real time: show its fraction.
    let digits = if factor < 10.0 { 2 } else { 0 };
    println!("  {wall:.2} s wall time: {factor:.digits$}x real time");
    println!(
        "recording: {}{}",
        outcome.recording.display(),
        Earlier::note(earlier.as_ref())
    );
    if let Some(observer) = live {
        let samples: u64 = observer.logger.samples.values().sum();
        match observer.finish() {
            Ok(()) => println!("live view: {samples} samples streamed to rerun"),
            Err(e) => eprintln!(
                "warning: {:#}; the MCAP recording is complete",
                anyhow::Error::from(e)
            ),
        }
    }
    Ok(())
}

/// The live rerun view of `--view TARGET`, or `None` (with the reason on
/// stderr) when none can be opened: the run goes on without it.
fn open_live_view(target: &str, scenario: &Scenario) -> Result<Option<RerunObserver>> {
    let layout = ViewLayout::of_scenario(scenario)?;
    match view::live_view(&ViewTarget::parse(target), &scenario.name, layout) {
        Ok(observer) => Ok(Some(observer)),
        Err(e) => {
            let e = anyhow::Error::from(e);
            eprintln!("twin run --view: {e:#}; running without the live view");
            Ok(None)
        }
    }
}

/// What a module's controller reads of the wheel's speed, beside the true
/// speed, and how fast its light sensor can follow.
fn print_speed_sensors(c: &ControllerOutcome, wheel_rpm: f64) {
    let d = &c.detector;
    println!(
        "    speed (rpm): wheel {:.1}, motor (hall) RPM_M {}, light sensor RPM_L {}  (controller {})",
        wheel_rpm, c.readings.hall_rpm, c.readings.light_rpm, d.node
    );
    let beyond = if wheel_rpm.abs() > d.limit_rpm {
        ": the wheel is faster, RPM_L cannot follow it"
    } else {
        ""
    };
    println!(
        "    light detector: {}; it sees the flag up to {:.0} rpm{beyond}",
        d.description, d.limit_rpm
    );
}

fn execute_open_loop(args: &RunArgs) -> Result<()> {
    let params = args.plant.load()?;
    let duration = args.duration.unwrap_or(3.0);
    check_duration(duration)?;
    if !(0.0..=1.0).contains(&args.vel) {
        bail!(
            "--vel is a fraction of the 5 V range: 0 to 1, got {}",
            args.vel
        );
    }
    if !(args.record_hz.is_finite() && args.record_hz > 0.0) {
        bail!("--record-hz must be positive, got {}", args.record_hz);
    }
    let mut config = OpenLoop::new(params, &args.plant.preset);
    config.duration_s = duration;
    config.seed = args.seed.unwrap_or(1);
    config.vel_fraction = args.vel;
    config.vel_step_at_s = args.vel_at;
    config.record_hz = args.record_hz;
    let config = RunSpec::open_loop_with_overrides(config, &args.overrides)?;

    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("twin-run.mcap"));
    let earlier = Earlier::at(&out);
    let started = Instant::now();
    let progress = Progress::simulated("the bench, open loop", config.duration_s);
    let summary = openloop::run(&config, &out, |done| progress.show(done))
        .with_context(|| format!("run failed; recording at {}", out.display()))?;
    progress.clear();
    let wall = started.elapsed().as_secs_f64();
    let s = &summary.final_state;
    println!(
        "twin run --open-loop: {} preset, seed {}, {:.3} s simulated",
        args.plant.preset, config.seed, s.time_s
    );
    println!(
        "  wheel speed    {:9.1} rpm   (motor {:.0} rpm)",
        s.wheel_rpm, s.motor_rpm
    );
    println!("  battery V1     {:9.2} V", s.battery_volts);
    println!("  DC bus V2      {:9.2} V", s.bus_volts);
    println!("  inverter I     {:9.2} A", s.inverter_current);
    println!("  state of charge{:9.2} %", s.soc * 100.0);
    println!(
        "  energy used    {:9.1} J   ({:.4} Wh)",
        summary.battery_energy,
        summary.battery_energy / 3600.0
    );
    if let Some(trip) = s.bms_trip {
        println!("  BMS tripped:   {trip}");
    }
    if s.motor_tripped {
        println!("  inverter tripped on over-current");
    }
    println!(
        "  {} steps in {:.2} s wall time: {:.0}x real time",
        summary.steps,
        wall,
        s.time_s / wall.max(1e-9)
    );
    println!(
        "recording: {}{}",
        summary.recording.display(),
        Earlier::note(earlier.as_ref())
    );
    Ok(())
}

/// `--duration` as a scenario's `duration_s` is held: above 0, a simulated
/// day at most.
fn check_duration(d: f64) -> Result<()> {
    let max = twin_sim::scenario::check::MAX_DURATION_S;
    if !(d.is_finite() && d > 0.0 && d <= max) {
        bail!(
            "--duration must be a number of seconds above 0 up to {max} (a simulated day), got {}",
            twin_sim::scenario::check::shown(d)
        );
    }
    Ok(())
}
