//! `twin bench`: how much faster than real time the engine runs.

use anyhow::{Context, Result, bail};
use clap::Args;
use twin_lab::bench::{self, DEFAULT_SCENARIOS, Measurement};

use super::progress::Progress;

/// Measure how much faster than real time scenarios run.
///
/// The real-time factor is simulated seconds per wall-clock second, measured
/// without recording (everything the engine reports is discarded) and with
/// recording (MCAP to a temporary file, deleted after), and their ratio.
/// Without --scenario, runs `ev-meb` (one module, 115200 baud, 100 Hz speed
/// loop; goal 200x) and `ten-modules` (ten modules on one bus, each polled at
/// 10 Hz; goal 30x). Each figure is the fastest of --repeat runs, the
/// unrecorded and the recorded runs taking turns so that a machine whose
/// speed drifts weighs on both alike. Build with --release.
///
/// With two runs or more of each, the last line compares them pair by pair
/// (each recorded run with the unrecorded one just before it) and gives the
/// median ratio and the range: on a busy or noisy machine, the steadiest
/// figure of what recording costs.
///
/// Beside the wall clock, the CPU time the process spent per simulated second
/// (user and system, every thread; the mean of the runs): on a machine other
/// work shares, it moves far less than the wall clock, so the cost of
/// recording reads from it too. It is counted in 10 ms ticks: give runs of a
/// second or more (ev-meb: --seconds 200). The recording is compressed and written by a thread of its
/// own: on two cores it runs beside the engine, and pinned to one
/// (`taskset -c 0 twin bench`) its whole cost adds to the engine's.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Scenario to measure: an embedded name (`twin run --list`) or a
    /// scenario file; repeat the option for several.
    #[arg(long, value_name = "NAME|FILE")]
    scenario: Vec<String>,
    /// Simulated seconds per run [default: each scenario's duration].
    #[arg(long, value_name = "N", value_parser = super::numbers::above_zero)]
    seconds: Option<f64>,
    /// Runs per figure (unrecorded and recorded in turn); the fastest counts.
    #[arg(long, default_value_t = 3, value_name = "N", value_parser = super::numbers::whole::<u32>)]
    repeat: u32,
}

pub fn execute(args: &BenchArgs) -> Result<()> {
    if let Some(s) = args.seconds
        && !(s.is_finite() && s > 0.0)
    {
        bail!("--seconds must be a positive number of seconds, got {s}");
    }
    if args.repeat == 0 {
        bail!("--repeat must be at least 1");
    }
    let names: Vec<&str> = if args.scenario.is_empty() {
        DEFAULT_SCENARIOS.to_vec()
    } else {
        args.scenario.iter().map(String::as_str).collect()
    };
    println!(
        "twin bench: best of {} run{} per figure",
        args.repeat,
        if args.repeat == 1 { "" } else { "s" }
    );
    println!(
        "  {:<20} {:<10} {:>11} {:>9} {:>10} {:>14} {:>10} {:>13}",
        "scenario",
        "recording",
        "simulated",
        "wall",
        "real time",
        "events/s",
        "frames",
        "CPU/sim s"
    );
    for name in names {
        let mut scenario = twin_sim::scenario::Scenario::load(name)?;
        if let Some(s) = args.seconds {
            scenario.duration_s = s;
        }
        // The bar's redraws are few (at most five a second, from the
        // engine's progress hook): they cost the measurement nothing visible.
        // The unrecorded and recorded runs take turns: the k-th of each
        // kind is pair k.
        let pair = std::cell::Cell::new(0);
        let new_bar = |recording: &str| {
            let what = format!(
                "{}, {recording}, run {} of {}",
                scenario.name,
                pair.get(),
                args.repeat
            );
            Progress::simulated(&what, scenario.duration_s)
        };
        let out = bench::scratch_recording(&scenario.name);
        let runs = bench::best_of_alternating(
            args.repeat,
            || {
                pair.set(pair.get() + 1);
                let bar = new_bar("not recorded");
                // Boxed: a run's error is large to pass by value.
                bench::run_discarding(&scenario, |done| bar.show(done)).map_err(Box::new)
            },
            || {
                let bar = new_bar("recorded");
                bench::run_recording(&scenario, &out, |done| bar.show(done)).map_err(Box::new)
            },
        );
        // Remove the scratch file whatever happened, then report.
        let _ = std::fs::remove_file(&out);
        let runs = runs.with_context(|| format!("scenario {} failed", scenario.name))?;
        let (discarded, recorded) = (&runs.a, &runs.b);
        print_row(&scenario.name, "off", discarded, discarded.events);
        // The observer does not steer the engine: a recorded run handles the
        // same events as the discarding one.
        print_row(&scenario.name, "mcap", recorded, discarded.events);
        if let Some(bytes) = recorded.recording_bytes {
            println!(
                "  {:<20} {:<10} {:.1} kB per simulated second; recorded at {:.2}x the rate without \
                 (wall clock), {:.2}x (CPU time)",
                "",
                "",
                bytes as f64 / 1e3 / recorded.simulated_s.max(1e-9),
                recorded.real_time_factor() / discarded.real_time_factor().max(1e-9),
                discarded.cpu_ms_per_simulated_s() / recorded.cpu_ms_per_simulated_s().max(1e-9)
            );
        }
        if runs.pairs.len() > 1 {
            print_pairs(&runs);
        }
    }
    Ok(())
}

/// The recorded run over the unrecorded one just before it, pair by pair.
fn print_pairs(runs: &bench::Alternated) {
    let spread = |s: Option<bench::Spread>, what: &str| {
        s.map(|s| format!("{:.2}x {what} ({:.2}x to {:.2}x)", s.median, s.low, s.high))
    };
    let figures: Vec<String> = [
        spread(runs.wall_spread(), "wall clock"),
        spread(runs.cpu_spread(), "CPU time"),
    ]
    .into_iter()
    .flatten()
    .collect();
    println!(
        "  {:<20} {:<10} pair by pair ({} pairs), the median: {}",
        "",
        "",
        runs.pairs.len(),
        figures.join(", ")
    );
}

fn print_row(scenario: &str, recording: &str, m: &Measurement, events: Option<u64>) {
    let events_per_s = events.map_or_else(
        || "-".to_string(),
        |e| format!("{:.0}", e as f64 / m.wall_s.max(1e-9)),
    );
    println!(
        "  {:<20} {:<10} {:>9.1} s {:>7.3} s {:>9.0}x {:>14} {:>10} {:>8.3} ms",
        scenario,
        recording,
        m.simulated_s,
        m.wall_s,
        m.real_time_factor(),
        events_per_s,
        m.frames,
        m.cpu_ms_per_simulated_s()
    );
}
