//! `twin-avr bench`: what the twin around a sketch costs. The same firmware
//! runs the same simulated time twice in one process, in a bare simavr loop
//! (nothing fed, nothing read) and inside the twin (the scenario's plant,
//! bus, master and recording), and the two speeds are reported as simulated
//! cycles per wall second, real-time factors, and their ratio.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;
use twin_sim::scenario::{NodeSpec, Scenario};

/// Time a scenario's firmware in a bare simavr loop and inside the twin.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// A scenario file with one firmware node.
    #[arg(value_name = "SCENARIO")]
    scenario: PathBuf,
    /// Simulated seconds each way.
    #[arg(long, default_value_t = 3.0, value_name = "SECONDS")]
    seconds: f64,
    /// Rounds: bare and twin alternate, so that the machine's load falls on both.
    #[arg(long, default_value_t = 2)]
    rounds: u32,
}

pub fn execute(args: &BenchArgs) -> Result<()> {
    if !(args.seconds.is_finite() && args.seconds > 0.0 && args.seconds <= 3600.0) {
        bail!("--seconds: give 0 to 3600 s, got {}", args.seconds);
    }
    let text = std::fs::read_to_string(&args.scenario)
        .with_context(|| format!("{}: cannot read it", args.scenario.display()))?;
    let mut scenario = Scenario::parse(&text, &args.scenario.display().to_string())?;
    scenario.duration_s = args.seconds;
    let Some(NodeSpec::Firmware {
        elf, mcu, clock_hz, ..
    }) = scenario
        .nodes
        .iter()
        .find(|n| matches!(n, NodeSpec::Firmware { .. }))
        .cloned()
    else {
        bail!("{}: no firmware node to time", args.scenario.display());
    };
    let cycles = (args.seconds * f64::from(clock_hz)) as u64;
    let out = std::env::temp_dir().join(format!("twin-avr-bench-{}.mcap", std::process::id()));
    let (mut bare_wall, mut twin_wall) = (0.0, 0.0);
    for _ in 0..args.rounds.max(1) {
        let image = twin_avr::ffi::Image::read(std::path::Path::new(&elf))
            .with_context(|| format!("{elf}: simavr cannot read it"))?;
        let mut core = twin_avr::ffi::Core::start(image, &mcu, clock_hz)
            .with_context(|| format!("simavr has no MCU {mcu}"))?;
        let started = Instant::now();
        // In 1 ms steps, as a host loop with an idle UART would.
        let step = u64::from(clock_hz / 1000);
        let mut target = 0;
        while target < cycles {
            target = (target + step).min(cycles);
            core.run_until(target);
            while core.uart_output().is_some() {}
        }
        bare_wall += started.elapsed().as_secs_f64();

        let started = Instant::now();
        twin_sim::virtual_run::run(&scenario, &out, |_| {})?;
        twin_wall += started.elapsed().as_secs_f64();
    }
    let _ = std::fs::remove_file(&out);
    let rounds = f64::from(args.rounds.max(1));
    let simulated = args.seconds * rounds;
    let total_cycles = cycles as f64 * rounds;
    println!(
        "twin-avr bench: {elf}, {:.1} s simulated each way, {} rounds",
        args.seconds,
        args.rounds.max(1)
    );
    for (what, wall) in [
        ("bare simavr loop", bare_wall),
        ("inside the twin ", twin_wall),
    ] {
        println!(
            "  {what}: {:6.1} M cycles per wall second, {:5.2}x real time ({:.2} s wall)",
            total_cycles / wall / 1e6,
            simulated / wall,
            wall
        );
    }
    println!(
        "  the twin runs the firmware at {:.2} of the bare loop's speed",
        bare_wall / twin_wall
    );
    Ok(())
}
