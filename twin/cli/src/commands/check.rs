//! `twin check`: a student's program checked against its protocol, check
//! by check, with the frames as evidence and a score.

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use std::path::{Path, PathBuf};
use twin_check::{Suite, report, run_suite, wire::Wire};

/// Check a program against the protocol it must speak, and grade it.
///
/// Runs a suite of checks (send a request, expect the reply the protocol
/// page requires, or silence) against a program on a serial port, a
/// pseudo-terminal or TCP, and prints one line per check, the frames that
/// show each failure, and a score. Suites are TOML files; the built-in ones
/// (--list) are written the same way a teacher writes their own (--suite).
/// Exits 1 when a check fails.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  twin check slave tcp://127.0.0.1:5700\n  twin check slave /dev/ttyUSB0?baud=9600 --id 3 --json report.json\n  twin check slave /tmp/ttyV0 --suite my-suite.toml --html report.html\n  twin check --list"
)]
pub struct CheckArgs {
    #[command(subcommand)]
    role: Option<Role>,
    /// Print the built-in suites and their checks.
    #[arg(long)]
    list: bool,
}

#[derive(Debug, Subcommand)]
enum Role {
    /// The student's module controller: an MEB slave the twin sends requests to.
    Slave(SlaveArgs),
}

#[derive(Debug, Args)]
struct SlaveArgs {
    /// Where the slave is: tcp://HOST:PORT, or a serial device or
    /// pseudo-terminal (PATH?baud=9600&parity=E).
    link: String,
    /// The slave's id (the M3CVME tool's device number).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=99))]
    id: u8,
    /// The suite: a built-in one's name (--list) or a TOML file.
    #[arg(long, default_value = "meb-slave", value_name = "NAME|FILE")]
    suite: String,
    /// A reply's deadline in ms where the suite's steps set none (the suite's
    /// own otherwise: 100 ms for the built-in one, the MEB page's master
    /// timeout). Give a slow board more.
    #[arg(long, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..=60_000))]
    timeout_ms: Option<u64>,
    /// Also write the run as JSON (every check, its frames and times).
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Also write the run as JUnit XML, for CI systems and learning
    /// platforms (a test case per check).
    #[arg(long, value_name = "FILE")]
    junit: Option<PathBuf>,
    /// Also write the run as one HTML page, to open in a browser.
    #[arg(long, value_name = "FILE")]
    html: Option<PathBuf>,
}

pub fn execute(args: &CheckArgs) -> Result<()> {
    if args.list {
        print!("{}", list()?);
        return Ok(());
    }
    let Some(Role::Slave(slave)) = &args.role else {
        bail!("say what to check: `twin check slave LINK`, or `twin check --list`");
    };
    let mut suite = Suite::load(&slave.suite)?;
    if let Some(ms) = slave.timeout_ms {
        suite.timeout_ms = ms;
    }
    let mut wire = Wire::open(&slave.link)?;
    let run = run_suite(&suite, &mut wire, slave.id)?;
    print!("{}", report::text(&run));
    let outputs = [
        (&slave.json, report::json(&run)),
        (&slave.junit, report::junit(&run)),
        (&slave.html, report::html(&run, None)),
    ];
    for (path, contents) in outputs {
        if let Some(path) = path {
            write(path, &contents)?;
        }
    }
    let failed = run.checks.len() - run.passed().count();
    if failed > 0 {
        bail!("{failed} of {} checks failed", run.checks.len());
    }
    Ok(())
}

fn write(path: &Path, contents: &str) -> Result<()> {
    std::fs::write(path, contents).with_context(|| format!("cannot write {}", path.display()))
}

fn list() -> Result<String> {
    use std::fmt::Write;
    let mut out = String::new();
    for (name, _) in twin_check::BUILT_IN {
        let suite = Suite::load(name)?;
        let _ = writeln!(
            out,
            "{name}: {} ({} checks, {} points)\n  {}",
            suite.name,
            suite.checks.len(),
            suite.points(),
            suite.description
        );
        for check in &suite.checks {
            let _ = writeln!(out, "  - {} ({})", check.name, check.requirement);
        }
    }
    Ok(out)
}
