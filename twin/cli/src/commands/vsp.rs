//! `twin vsp`: a crossed pair of virtual serial ports (pseudo-terminals).

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::time::Duration;
use tokio::signal::unix::{SignalKind, signal};
use twin_realtime::vsp::{Crossing, DirectionCounters, Pair, PairOptions, hex_line};

/// Create a crossed pair of virtual serial ports, like the lab's VSP utility.
///
/// Makes two pseudo-terminals and symlinks FIRST and SECOND to them: what a
/// program writes to one is read from the other, so a master and a slave (for
/// instance `twin supervise --meb /tmp/ttyV0` and `twin serve --meb /tmp/ttyV1`,
/// or a student's program) talk as over a null-modem cable. Either end may be
/// closed and reopened at any time (the Controller_network master reopens the port for
/// every transaction). Prints the two links, then `ready`; runs until
/// interrupted (Ctrl-C, SIGTERM), then removes the links and prints the
/// byte counts.
#[derive(Debug, Args)]
pub struct VspArgs {
    /// Path of the first end's symlink, e.g. /tmp/ttyV0.
    first: PathBuf,
    /// Path of the second end's symlink, e.g. /tmp/ttyV1.
    second: PathBuf,
    /// Deliver bytes at this baud rate (8N1, 10 bits a byte) instead of at once:
    /// a pty ignores the rate a program sets, so this makes the line's timing real.
    #[arg(long, value_name = "BAUD", value_parser = super::numbers::whole::<u32>)]
    baud: Option<u32>,
    /// Print every chunk that crosses, in hex and ASCII, with its time.
    #[arg(long, short = 'm')]
    monitor: bool,
    /// Print the byte counters every SECONDS when they changed (0: only at the end).
    #[arg(long, default_value_t = 10.0, value_name = "SECONDS", value_parser = super::numbers::zero_or_more)]
    stats_every: f64,
}

pub fn execute(args: &VspArgs) -> Result<()> {
    if !(args.stats_every.is_finite() && args.stats_every >= 0.0) {
        anyhow::bail!("--stats-every must be 0 or a positive number of seconds");
    }
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the I/O runtime")?;
    runtime.block_on(run(args))
}

async fn run(args: &VspArgs) -> Result<()> {
    let mut interrupt = signal(SignalKind::interrupt()).context("installing the SIGINT handler")?;
    let mut terminate =
        signal(SignalKind::terminate()).context("installing the SIGTERM handler")?;
    let mut hangup = signal(SignalKind::hangup()).context("installing the SIGHUP handler")?;
    let mut pair = Pair::open([&args.first, &args.second], PairOptions { baud: args.baud })?;
    let names = [
        args.first.display().to_string(),
        args.second.display().to_string(),
    ];
    println!(
        "twin vsp: crossed pseudo-terminal pair{}",
        args.baud
            .map_or(String::new(), |b| format!(", paced at {b} baud (8N1)"))
    );
    for i in 0..2 {
        let end = pair.end(i);
        let replaced = end.replaced().map_or(String::new(), |old| {
            format!(
                " (replaced the link to {} that was there, left by an earlier run)",
                old.display()
            )
        });
        println!("  {} -> {}{replaced}", names[i], end.device().display());
    }
    println!("ready");

    let monitor = args.monitor;
    let stats_every = (args.stats_every > 0.0).then(|| Duration::from_secs_f64(args.stats_every));
    let copy = pair.run(
        stats_every,
        |crossing: &Crossing<'_>| {
            if monitor {
                let (from, to) = (crossing.direction, 1 - crossing.direction);
                println!(
                    "[{:>10.6} s] {} -> {}  {:>3} bytes  {}",
                    crossing.at.as_secs_f64(),
                    names[from],
                    names[to],
                    crossing.bytes.len(),
                    hex_line(crossing.bytes)
                );
            }
        },
        |counters| print_counters(&names, counters),
    );
    // Stopping mid-copy loses at most the chunk in flight, as pulling a cable does.
    let outcome = tokio::select! {
        result = copy => result,
        _ = interrupt.recv() => Ok(()),
        _ = terminate.recv() => Ok(()),
        _ = hangup.recv() => Ok(()),
    };
    print_counters(&names, pair.counters());
    // Dropping the pair removes the links.
    drop(pair);
    Ok(outcome?)
}

fn print_counters(names: &[String; 2], counters: [DirectionCounters; 2]) {
    let line = |i: usize| {
        let c = counters[i];
        let dropped = if c.dropped > 0 {
            format!(", {} dropped (nobody reading)", c.dropped)
        } else {
            String::new()
        };
        format!(
            "{} -> {}: {} bytes{dropped}",
            names[i],
            names[1 - i],
            c.bytes
        )
    };
    println!("  {}; {}", line(0), line(1));
}
