//! `twin`: the digital twin of the EV lab bench.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

mod commands;

/// Digital twin of the EV lab bench: battery + BMS, buck-boost converter,
/// inverter + BLDC motor with hall sensors, a wheel and the photoresistor that
/// watches a paper flag on it, with the lab's controller boards and masters on
/// a simulated RS-485 bus (MEB, Modbus RTU, the seed-002 8-byte Modbus). Every
/// run is recorded to MCAP.
#[derive(Debug, Parser)]
#[command(name = "twin", version, propagate_version = true, max_term_width = 100)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    Run(commands::run::RunArgs),
    Bench(commands::bench::BenchArgs),
    Experiment(commands::experiment::ExperimentArgs),
    Step(commands::step::StepArgs),
    Sweep(commands::sweep::SweepArgs),
    View(commands::view::ViewArgs),
    Serve(commands::serve::ServeArgs),
    Vsp(commands::vsp::VspArgs),
    Supervise(commands::supervise::SuperviseArgs),
    Client(commands::client::ClientArgs),
    Replay(commands::replay::ReplayArgs),
    Compare(commands::compare::CompareArgs),
    Export(commands::export::ExportArgs),
    Baseline(commands::baseline::BaselineArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Run(args) => commands::run::execute(&args),
        Command::Bench(args) => commands::bench::execute(&args),
        Command::Experiment(args) => commands::experiment::execute(&args),
        Command::Step(args) => commands::step::execute(&args),
        Command::Sweep(args) => commands::sweep::execute(&args),
        Command::View(args) => commands::view::execute(&args),
        Command::Serve(args) => commands::serve::execute(&args),
        Command::Vsp(args) => commands::vsp::execute(&args),
        Command::Supervise(args) => commands::supervise::execute(&args),
        Command::Client(args) => commands::client::execute(&args),
        Command::Replay(args) => commands::replay::execute(&args),
        Command::Compare(args) => commands::compare::execute(&args),
        Command::Export(args) => commands::export::execute(&args),
        Command::Baseline(args) => commands::baseline::execute(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
