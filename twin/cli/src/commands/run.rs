//! `twin run`: run the bench in simulated time and record it.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;
use twin_sim::openloop::{self, OpenLoop};
use twin_sim::scenario::{EMBEDDED, Scenario};
use twin_sim::virtual_run;
use twin_view::{self as view, RerunObserver, ViewLayout, ViewTarget};

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
/// (TWIN_MIN_FREE_DISK_MB sets another floor).
#[derive(Debug, Args)]
#[command(
    mut_arg("preset", |a| a.requires("open_loop")),
    mut_arg("params", |a| a.requires("open_loop"))
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
    #[arg(long, value_name = "SECONDS")]
    duration: Option<f64>,
    /// Where to write the recording [default: SCENARIO.mcap, twin-run.mcap open loop].
    #[arg(long, value_name = "PATH")]
    out: Option<PathBuf>,
    /// Seed of every random draw (noise, bit errors) [default: the scenario's; 1].
    #[arg(long)]
    seed: Option<u64>,
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
    )]
    vel: f64,
    /// Open loop: time of the VEL step in seconds.
    #[arg(
        long,
        default_value_t = 0.5,
        value_name = "SECONDS",
        requires = "open_loop"
    )]
    vel_at: f64,
    /// Open loop: plant state messages recorded per simulated second.
    #[arg(
        long,
        default_value_t = 1000.0,
        value_name = "HZ",
        requires = "open_loop"
    )]
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
            "  module {module}: wheel {:.1} rpm, V1 {:.2} V, V2 {:.2} V, I {:.2} A, SOC {:.2} %",
            s.wheel_rpm,
            s.battery_volts,
            s.bus_volts,
            s.inverter_current,
            s.soc * 100.0
        );
    }
    for (node, state) in &outcome.telemetry {
        print_node_state(node, state, outcome.simulated_s);
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
    println!(
        "  {:.2} s wall time: {:.0}x real time",
        wall,
        outcome.simulated_s / wall.max(1e-9)
    );
    println!("recording: {}", outcome.recording.display());
    if let Some(observer) = live {
        let samples: u64 = observer.logger.samples.values().sum();
        match observer.finish() {
            Ok(()) => println!("live view: {samples} samples streamed to rerun"),
            Err(e) => eprintln!("warning: {e:#}; the MCAP recording is complete"),
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
            eprintln!("twin run --view: {e:#}; running without the live view");
            Ok(None)
        }
    }
}

/// A node's end-of-run state: masters' loops spelled out, others as JSON.
fn print_node_state(node: &str, state: &serde_json::Value, simulated_s: f64) {
    if let (Some(slaves), Some(updates)) = (state["slaves"].as_array(), state["updates"].as_u64()) {
        print_parallel_master(node, state, slaves, updates, simulated_s);
        return;
    }
    if let Some(taken) = state["frames_taken"].as_u64() {
        println!(
            "  {node}: VEL {} from {taken} frames taken, {} for others, {} bad, {} cut short, {} answers",
            state["vel"],
            state["frames_ignored"],
            state["bad_frames"],
            state["incomplete_frames"],
            state["answers"]
        );
        return;
    }
    let Some(loops) = state["loops"].as_array() else {
        println!("  {node}: {state}");
        return;
    };
    let cycles = state["cycles"].as_f64().unwrap_or(0.0);
    println!(
        "  {node}: {cycles} poll cycles ({:.1} per second)",
        cycles / simulated_s.max(1e-9)
    );
    for l in loops {
        let n = |k: &str| l[k].as_f64().unwrap_or(f64::NAN);
        println!(
            "    slave {}: set point {:.0} rpm, measured {:.0} rpm, error {:.0} rpm, VEL {:.0}; \
             {} requests, {} replies, {} timeouts, {} bad checks, {} retries, {} lost",
            l["slave"],
            n("set_point_rpm"),
            n("measured_rpm"),
            n("error_rpm"),
            n("output"),
            l["requests"],
            l["replies"],
            l["timeouts"],
            l["bad_checks"],
            l["retries"],
            l["lost"]
        );
    }
}

/// A parallel-module master: its own loop, then each exchange's tally.
fn print_parallel_master(
    node: &str,
    state: &serde_json::Value,
    slaves: &[serde_json::Value],
    updates: u64,
    simulated_s: f64,
) {
    let n = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap_or(f64::NAN);
    let cycles = n(state, "cycles");
    println!(
        "  {node}: set point {:.0} rpm, measured {:.0} rpm, VEL {}; {updates} references issued, \
         {cycles} send cycles ({:.0} per second)",
        n(state, "set_point_rpm"),
        n(state, "measured_rpm"),
        state["vel"],
        cycles / simulated_s.max(1e-9)
    );
    for s in slaves {
        let who = match s["slave"].as_u64() {
            Some(0) => "broadcast".to_string(),
            Some(id) => format!("slave {id}"),
            None => "?".to_string(),
        };
        println!(
            "    {who}: {} frames, {} answers, {} timeouts, {} bad answers, {} retries, {} lost",
            s["requests"], s["replies"], s["timeouts"], s["bad_replies"], s["retries"], s["lost"]
        );
    }
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

    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("twin-run.mcap"));
    let started = Instant::now();
    let progress = Progress::simulated("the bench, open loop", duration);
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
        println!("  BMS tripped:   {trip:?}");
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
    println!("recording: {}", summary.recording.display());
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
