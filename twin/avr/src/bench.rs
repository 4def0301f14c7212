//! `twin-avr bench`: what the twin around a sketch costs. The same firmware
//! runs the same simulated time twice in one process, in a bare simavr loop
//! (nothing fed, nothing read) and inside the twin (the scenario's plant,
//! bus, master and recording), and the two speeds are reported as simulated
//! cycles per wall second, real-time factors, and their ratio. With two or
//! more firmware nodes the bare loop runs each core in turn, and the twin
//! runs twice: all on one thread, and with a thread per firmware node.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;
use twin_sim::scenario::{NodeSpec, Scenario};

/// Time a scenario's firmware in a bare simavr loop and inside the twin.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// A scenario file with one or more firmware nodes.
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
    // The bare loop runs every cycle of the simulated seconds: so do the
    // twin's cores, started at once rather than after their boot, or the
    // twin would be timed on fewer cycles than it is compared with.
    for node in &mut scenario.nodes {
        if let NodeSpec::Firmware { boot_ms, .. } = node {
            *boot_ms = 0.0;
        }
    }
    let boards: Vec<(String, String, u32)> = scenario
        .nodes
        .iter()
        .filter_map(|n| match n {
            NodeSpec::Firmware {
                elf, mcu, clock_hz, ..
            } => Some((elf.clone(), mcu.clone(), *clock_hz)),
            _ => None,
        })
        .collect();
    if boards.is_empty() {
        bail!("{}: no firmware node to time", args.scenario.display());
    }
    // With two or more firmware nodes the twin also runs on one thread,
    // to show what a thread per node buys.
    let ways: &[(&str, bool)] = if boards.len() > 1 {
        &[("twin, one thread", false), ("twin, threaded  ", true)]
    } else {
        &[("inside the twin ", true)]
    };
    let out = std::env::temp_dir().join(format!("twin-avr-bench-{}.mcap", std::process::id()));
    let mut bare_wall = 0.0;
    let mut board_wall = vec![0.0; boards.len()];
    let mut twin_wall = vec![0.0; ways.len()];
    let mut cycles = 0u64;
    for _ in 0..args.rounds.max(1) {
        // Every firmware node's core in turn, on one thread, in 1 ms steps
        // as a host loop with an idle UART would, nothing fed, nothing read.
        cycles = 0;
        for (b, (elf, mcu, clock_hz)) in boards.iter().enumerate() {
            let image = twin_avr::ffi::Image::read(std::path::Path::new(elf))
                .with_context(|| format!("{elf}: simavr cannot read it"))?;
            let mut core = twin_avr::ffi::Core::start(image, mcu, *clock_hz)
                .with_context(|| format!("simavr has no MCU {mcu}"))?;
            let end = (args.seconds * f64::from(*clock_hz)) as u64;
            cycles += end;
            let started = Instant::now();
            let step = u64::from(clock_hz / 1000);
            let mut target = 0;
            while target < end {
                target = (target + step).min(end);
                core.run_until(target);
                while core.uart_output().is_some() {}
            }
            let wall = started.elapsed().as_secs_f64();
            board_wall[b] += wall;
            bare_wall += wall;
        }
        for (i, (_, threaded)) in ways.iter().enumerate() {
            twin_avr::builder::set_threaded(*threaded);
            let started = Instant::now();
            twin_sim::virtual_run::run(&scenario, &out, |_| {})?;
            twin_wall[i] += started.elapsed().as_secs_f64();
        }
    }
    twin_avr::builder::set_threaded(true);
    let _ = std::fs::remove_file(&out);
    let rounds = f64::from(args.rounds.max(1));
    let simulated = args.seconds * rounds;
    let total_cycles = cycles as f64 * rounds;
    let names: Vec<&str> = boards.iter().map(|(elf, _, _)| elf.as_str()).collect();
    println!(
        "twin-avr bench: {}, {:.1} s simulated each way, {} rounds",
        names.join(" + "),
        args.seconds,
        args.rounds.max(1)
    );
    let mut rows = vec![("bare simavr loop", bare_wall)];
    rows.extend(ways.iter().map(|(w, _)| *w).zip(twin_wall.iter().copied()));
    for (what, wall) in &rows {
        println!(
            "  {what}: {:6.1} M cycles per wall second, {:5.2}x real time ({:.2} s wall)",
            total_cycles / wall / 1e6,
            simulated / wall,
            wall
        );
    }
    if boards.len() > 1 {
        // The most a thread per core can buy: the cores' total over the slowest.
        let slowest = board_wall.iter().copied().fold(0.0, f64::max);
        let shares: Vec<String> = boards
            .iter()
            .zip(&board_wall)
            .map(|((elf, _, _), wall)| {
                let name = std::path::Path::new(elf)
                    .file_stem()
                    .map_or_else(|| elf.clone(), |s| s.to_string_lossy().into_owned());
                format!("{name} {:.0} %", 100.0 * wall / bare_wall)
            })
            .collect();
        println!(
            "  bare loop's time per core: {}; a core each would be at most {:.2}x faster",
            shares.join(", "),
            bare_wall / slowest
        );
    }
    for ((what, _), wall) in ways.iter().zip(&twin_wall) {
        println!(
            "  {}: the firmware at {:.2} of the bare loop's speed",
            what.trim_end(),
            bare_wall / wall
        );
    }
    if let [one, threaded] = twin_wall[..] {
        println!(
            "  a thread per firmware node: {:.2}x faster",
            one / threaded
        );
    }
    Ok(())
}
