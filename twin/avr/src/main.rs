//! `twin-avr`: the twin with compiled AVR firmware in the loop (GPL-3.0-or-later,
//! for simavr). `run` is `twin run`'s own command, its arguments and runner
//! shared as library code; scenarios may hold `firmware` nodes.

#![allow(
    clippy::disallowed_methods,
    reason = "the benchmark times simavr and the twin on the wall clock"
)]

use clap::{CommandFactory, FromArgMatches, Subcommand};
use std::process::ExitCode;
use twin::commands;

mod bench;

/// The EV lab twin with real firmware: Arduino sketches compiled for the
/// ATmega328P run in simavr, instruction by instruction, against the
/// simulated bench. A scenario's `firmware` node names the sketch's ELF and
/// its wiring map (`ev-controller` or a TOML file); `serve --firmware`
/// runs a sketch in real time for a real master (`supervise`, `vsp` and
/// `check` are `twin`'s own, here so one binary holds a whole bench). This
/// binary is GPL-3.0-or-later because it links simavr; `twin` is MIT OR
/// Apache-2.0 and runs every other scenario.
#[derive(Debug, clap::Parser)]
#[command(
    name = "twin-avr",
    version,
    propagate_version = true,
    max_term_width = 100
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    Run(AvrRun),
    Replay(AvrReplay),
    Serve(commands::serve::ServeArgs),
    Supervise(commands::supervise::SuperviseArgs),
    Vsp(commands::vsp::VspArgs),
    Calibrate(commands::calibrate::CalibrateArgs),
    Check(commands::check::CheckArgs),
    Bench(bench::BenchArgs),
}

/// Run a scenario on the virtual clock, its firmware nodes in simavr: `twin
/// run`'s own options, and the firmware debugging extras (simavr's GDB stub,
/// a VCD trace of chosen pins).
#[derive(Debug, clap::Args)]
struct AvrRun {
    #[command(flatten)]
    run: commands::run::RunArgs,
    #[command(flatten)]
    debug: twin_avr::debug::DebugArgs,
}

/// Re-run a recording and check that the new run matches it, its firmware
/// nodes running the ELF files the recording stored (not the files on disk
/// today): `twin replay`'s own options, and the firmware debugging extras.
#[derive(Debug, clap::Args)]
struct AvrReplay {
    #[command(flatten)]
    replay: commands::replay::ReplayArgs,
    #[command(flatten)]
    debug: twin_avr::debug::DebugArgs,
}

fn run(args: AvrRun) -> anyhow::Result<()> {
    twin_avr::debug::set(args.debug)?;
    commands::finish_recordings_on_signals();
    let ran = commands::run::execute(&args.run);
    if let Some(note) = twin_avr::debug::unused() {
        eprintln!("twin-avr: {note}");
    }
    ran
}

fn replay(args: &AvrReplay, given: &clap::ArgMatches) -> anyhow::Result<()> {
    twin_avr::debug::set(args.debug.clone())?;
    let firmware = match given.get_one::<std::path::PathBuf>("recording") {
        Some(path) if !args.replay.sends_frames() => Some(twin_avr::replay::load(path)?),
        _ => None,
    };
    for line in firmware.iter().flat_map(|f| &f.lines) {
        println!("{line}");
    }
    commands::finish_recordings_on_signals();
    commands::replay::execute(&args.replay)
}

fn main() -> ExitCode {
    twin_avr::register();
    let command = commands::take_negative_numbers(Cli::command());
    let matches = command.get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    let given = |name: &str| {
        matches
            .subcommand_matches(name)
            .cloned()
            .unwrap_or_default()
    };
    let result = match cli.command {
        Command::Run(args) => run(args),
        Command::Replay(args) => replay(&args, &given("replay")),
        // `twin serve` itself: a configuration file's options give way to
        // the command line's.
        Command::Serve(args) => commands::serve::execute(&args, &given("serve")),
        Command::Supervise(args) => commands::supervise::execute(&args, &given("supervise")),
        Command::Vsp(args) => commands::vsp::execute(&args),
        Command::Calibrate(args) => commands::calibrate::execute(&args),
        Command::Check(args) => commands::check::execute(&args),
        Command::Bench(args) => bench::execute(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
