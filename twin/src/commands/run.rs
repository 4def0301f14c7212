//! `twin run`: run the bench in simulated time and record it.

use anyhow::{Context, Result, bail};
use clap::Args;
use plant::PlantParams;
use plant::params::PRESETS;
use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::time::Instant;
use twin::openloop::{self, OpenLoop};

/// Run the bench in simulated time, far faster than real time, and record it.
///
/// The built-in run is open loop: the inverter enabled, the brake released,
/// VEL stepped to 60 % at 0.5 s, 3 s in all. It prints a summary and the path
/// of the MCAP recording (Foxglove, `mcap`, and rerun open it).
#[derive(Debug, Args)]
pub struct RunArgs {
    /// Simulated duration in seconds.
    #[arg(long, default_value_t = 3.0, value_name = "SECONDS")]
    duration: f64,
    /// Where to write the recording.
    #[arg(long, default_value = "twin-run.mcap", value_name = "PATH")]
    out: PathBuf,
    /// Bench to simulate: `vemodule` (the EV module of seed 000) or
    /// `controller-network` (the geared motor + light sensor of seed 002).
    #[arg(long, default_value = "vemodule", value_name = "NAME")]
    preset: String,
    /// Plant parameter file (TOML) whose fields override the preset's.
    #[arg(long, value_name = "FILE")]
    params: Option<PathBuf>,
    /// Seed of every random draw (sensor noise); same seed, same recording.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// VEL level after the step, as a fraction of its 5 V range.
    #[arg(long, default_value_t = 0.6, value_name = "FRACTION")]
    vel: f64,
    /// Time of the VEL step in seconds.
    #[arg(long, default_value_t = 0.5, value_name = "SECONDS")]
    vel_at: f64,
    /// Plant state messages recorded per simulated second.
    #[arg(long, default_value_t = 1000.0, value_name = "HZ")]
    record_hz: f64,
}

pub fn execute(args: &RunArgs) -> Result<()> {
    let Some(base) = PlantParams::preset(&args.preset) else {
        bail!(
            "unknown preset `{}`: choose one of {}",
            args.preset,
            PRESETS.join(", ")
        );
    };
    let params = match &args.params {
        Some(file) => PlantParams::load(file, &base)?,
        None => base,
    };
    if !(args.duration.is_finite() && args.duration > 0.0) {
        bail!(
            "--duration must be a positive number of seconds, got {}",
            args.duration
        );
    }
    if !(0.0..=1.0).contains(&args.vel) {
        bail!(
            "--vel is a fraction of the 5 V range: 0 to 1, got {}",
            args.vel
        );
    }
    if !(args.record_hz.is_finite() && args.record_hz > 0.0) {
        bail!("--record-hz must be positive, got {}", args.record_hz);
    }
    let mut config = OpenLoop::new(params, &args.preset);
    config.duration_s = args.duration;
    config.seed = args.seed;
    config.vel_fraction = args.vel;
    config.vel_step_at_s = args.vel_at;
    config.record_hz = args.record_hz;

    let started = Instant::now();
    let show_progress = std::io::stderr().is_terminal();
    let mut last_shown = Instant::now();
    let summary = openloop::run(&config, &args.out, |done| {
        if show_progress && last_shown.elapsed().as_millis() > 200 {
            eprint!("\r  simulating… {:3.0} %", done * 100.0);
            let _ = std::io::stderr().flush();
            last_shown = Instant::now();
        }
    })
    .with_context(|| format!("run failed; recording at {}", args.out.display()))?;
    if show_progress {
        eprint!("\r                        \r");
    }
    let wall = started.elapsed().as_secs_f64();
    let s = &summary.final_state;
    println!(
        "twin run: {} preset, seed {}, {:.3} s simulated",
        args.preset, args.seed, s.time_s
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
