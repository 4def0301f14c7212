//! `twin`: the digital twin of the EV lab bench.

#![allow(
    clippy::disallowed_methods,
    reason = "commands time their runs and wait on real links and viewers"
)]

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use std::process::ExitCode;

use twin::commands;

/// Digital twin of the EV lab bench: battery + BMS, buck-boost converter,
/// inverter + BLDC motor with hall sensors, a wheel and the photoresistor that
/// watches a paper flag on it, with the lab's controller boards and masters.
/// On a virtual clock (`run`) they talk over a simulated RS-485 bus or
/// PWM-capture link; in real time (`serve`, `supervise`, `client`, `vsp`) real
/// masters reach them over serial ports, pseudo-terminals and TCP (MEB, Modbus
/// RTU/ASCII/TCP, the Controller_network project's 8-byte Modbus). Every run is
/// recorded to MCAP.
#[derive(Debug, Parser)]
#[command(name = "twin", version, propagate_version = true, max_term_width = 100)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    Run(commands::run::RunArgs),
    Serve(commands::serve::ServeArgs),
    Supervise(commands::supervise::SuperviseArgs),
    Client(commands::client::ClientArgs),
    Panel(commands::panel::PanelArgs),
    Vsp(commands::vsp::VspArgs),
    View(commands::view::ViewArgs),
    Replay(commands::replay::ReplayArgs),
    Compare(commands::compare::CompareArgs),
    Export(commands::export::ExportArgs),
    Scope(commands::scope::ScopeArgs),
    Recover(commands::recover::RecoverArgs),
    Baseline(commands::baseline::BaselineArgs),
    Batch(commands::batch::BatchArgs),
    Step(commands::step::StepArgs),
    Calibrate(commands::calibrate::CalibrateArgs),
    Check(commands::check::CheckArgs),
    Sweep(commands::sweep::SweepArgs),
    Experiment(commands::experiment::ExperimentArgs),
    Bench(commands::bench::BenchArgs),
    Completions(commands::completions::CompletionsArgs),
    Man(commands::man::ManArgs),
}

impl Command {
    /// The commands whose runs an interrupt stops cleanly (the real-time
    /// ones handle their own signals).
    fn runs_on_the_virtual_clock(&self) -> bool {
        if let Command::Replay(args) = self {
            return !args.sends_frames();
        }
        matches!(
            self,
            Command::Run(_)
                | Command::Baseline(_)
                | Command::Batch(_)
                | Command::Step(_)
                | Command::Calibrate(_)
                | Command::Sweep(_)
                | Command::Experiment(_)
                | Command::Bench(_)
        )
    }
}

/// The command line of `twin`. `serve` shares its options with `twin-avr
/// serve`, but a compiled sketch runs only in `twin-avr` (it links simavr):
/// `--firmware` and `--wiring` are not offered here (given anyway, they get
/// a message that names `twin-avr serve`).
fn twin_command() -> clap::Command {
    Cli::command().mut_subcommand("serve", |serve| {
        serve
            .mut_arg("firmware", |a| a.hide(true))
            .mut_arg("wiring", |a| a.hide(true))
    })
}

fn main() -> ExitCode {
    exit_quietly_on_broken_pipe();
    // Negative numbers are values, never flags: the parsers say which
    // options cannot take them.
    let command = commands::take_negative_numbers(twin_command());
    let matches = command.get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    // What the command line itself gave (a configuration file's options
    // give way to it).
    let given = |name: &str| {
        matches
            .subcommand_matches(name)
            .cloned()
            .unwrap_or_default()
    };
    if cli.command.runs_on_the_virtual_clock() {
        commands::finish_recordings_on_signals();
    }
    let result = match cli.command {
        Command::Run(args) => commands::run::execute(&args),
        Command::Serve(args) => commands::serve::execute(&args, &given("serve")),
        Command::Supervise(args) => commands::supervise::execute(&args, &given("supervise")),
        Command::Client(args) => commands::client::execute(&args),
        Command::Panel(args) => commands::panel::execute(&args),
        Command::Vsp(args) => commands::vsp::execute(&args),
        Command::View(args) => commands::view::execute(&args),
        Command::Replay(args) => commands::replay::execute(&args),
        Command::Compare(args) => commands::compare::execute(&args),
        Command::Export(args) => commands::export::execute(&args),
        Command::Scope(args) => commands::scope::execute(&args),
        Command::Recover(args) => commands::recover::execute(&args),
        Command::Baseline(args) => commands::baseline::execute(&args),
        Command::Batch(args) => commands::batch::execute(&args),
        Command::Step(args) => commands::step::execute(&args),
        Command::Calibrate(args) => commands::calibrate::execute(&args),
        Command::Check(args) => commands::check::execute(&args),
        Command::Sweep(args) => commands::sweep::execute(&args),
        Command::Experiment(args) => commands::experiment::execute(&args),
        Command::Bench(args) => commands::bench::execute(&args),
        Command::Completions(args) => commands::completions::execute(&args, twin_command()),
        Command::Man(args) => commands::man::execute(&args, twin_command()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        // Stopped as asked, not failed: say where (a run cut short ends on
        // `Interrupted`, the root of its error), and exit as a shell
        // reports a command stopped by Ctrl-C.
        Err(e) if twin_sim::interrupt::requested() => {
            eprintln!("{}", e.root_cause());
            ExitCode::from(130)
        }
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// `twin run | head` closes our stdout early. Rust ignores SIGPIPE, so the next
/// `println!` panics; end the way a command killed by SIGPIPE does instead (exit
/// status 141, nothing on stderr). Any other panic still reports as usual.
fn exit_quietly_on_broken_pipe() {
    let report = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let payload = info.payload();
        let message = payload
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| payload.downcast_ref::<&str>().copied())
            .unwrap_or("");
        if message.starts_with("failed printing to std") && message.contains("Broken pipe") {
            std::process::exit(141);
        }
        report(info);
    }));
}
