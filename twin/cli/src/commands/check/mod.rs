//! `twin check`: a student's program checked against its protocol, check
//! by check, with the frames as evidence and a score. One file per role.

mod class;
mod client;
mod master;
mod reports;
mod server;
mod slave;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use std::path::Path;
use twin_check::Suite;

/// Check a program against the protocol it must speak, and grade it.
///
/// Runs a suite of checks (send a request, expect the reply the protocol
/// page requires, or silence) against a program on a serial port, a
/// pseudo-terminal or TCP, and prints one line per check, the frames that
/// show each failure, and a score. Suites are TOML files; the built-in ones
/// (--list) are written the same way a teacher writes their own (--suite).
/// A class is checked at once from a roster (--roster), whatever the role:
/// a report and a recording per student, and the scores side by side. A supervisor is checked as the
/// master of its bus (master), or from its bus and its TCP server at once
/// (server); a remote client in a session that follows a checklist
/// (client). Exits 1 when a check fails.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  twin check slave tcp://127.0.0.1:5700\n  twin check slave /dev/ttyUSB0?baud=9600 --id 3 --json report.json\n  twin check slave /tmp/ttyV0 --suite my-suite.toml --html report.html\n  twin check slave tcp://127.0.0.1:5020 --suite modbus-tcp-slave\n  twin check slave /tmp/ttyV0 --suite modbus-rtu-slave\n  twin check slave --roster class.csv --out grades/\n  twin check master /tmp/ttyV1 --id 1,2\n  twin check server tcp://127.0.0.1:5701 --bus /tmp/ttyV1\n  twin check server --roster class.csv          (columns student,link,bus)\n  twin check client --listen tcp://0.0.0.0:5701\n  twin check --list"
)]
pub struct CheckArgs {
    #[command(subcommand)]
    role: Option<Role>,
    /// Print every role's checks: the built-in suites, and the server's
    /// and the client's.
    #[arg(long)]
    list: bool,
}

#[derive(Debug, Subcommand)]
enum Role {
    /// The student's slave the twin sends requests to: the module controller
    /// over MEB, Modbus RTU or TCP, or the Controller_network nodes over the
    /// 8-byte Modbus (--suite).
    Slave(slave::SlaveArgs),
    /// The student's supervisor: a master (MEB, Modbus RTU or TCP, 8-byte
    /// Modbus) polling slaves the twin plays.
    ///
    /// The twin answers on LINK as the EV module's controller firmware does
    /// (MEB's default map or the Modbus map; the Controller_network nodes
    /// with --suite modbus8-master; a register image at power-up: no bench
    /// behind it) and puts the master through a few seconds of each
    /// situation: slaves that answer, a slow reply, a reply in two pieces,
    /// junk before a reply, an error reply, a bad FCS or CRC, another
    /// slave's id, and a slave
    /// that does not answer. The situations happen to the first --id; the
    /// others answer throughout. Each check says what a master must do
    /// there; what it may choose (retrying or not, its poll rate) is
    /// printed as figures, not graded. Exits 1 when a check fails.
    #[command(
        after_help = "Examples:\n  twin vsp /tmp/ttyV0 /tmp/ttyV1 &      # the master opens /tmp/ttyV0\n  twin check master /tmp/ttyV1 --id 1,2\n  twin check master /tmp/ttyV1 --suite modbus-rtu-master\n  twin check master tcp://0.0.0.0:5700 --html report.html\n  twin check master --roster class.csv --out grades/"
    )]
    Master(master::MasterArgs),
    /// The student's supervisor: master of the module's bus (the twin answers
    /// there as the controller) and a TCP server the twin connects to as
    /// the remote clients.
    Server(server::ServerArgs),
    /// The student's remote client: the twin is the supervisor's server it
    /// connects to, in a session that follows a checklist.
    Client(client::ClientArgs),
}

pub fn execute(args: &CheckArgs) -> Result<()> {
    if args.list {
        print!("{}", list()?);
        return Ok(());
    }
    match &args.role {
        Some(Role::Slave(slave)) => slave::execute(slave),
        Some(Role::Master(master)) => master::execute(master),
        Some(Role::Server(server)) => server::execute(server),
        Some(Role::Client(client)) => client::execute(client),
        None => bail!(
            "say what to check: `twin check slave LINK`, `twin check master LINK`, `twin check server LINK --bus LINK`, `twin check client`, or `twin check --list`"
        ),
    }
}

pub(crate) fn write(path: &Path, contents: &str) -> Result<()> {
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
    for (name, _) in twin_check::master::BUILT_IN {
        let suite = twin_check::master::MasterSuite::load(name)?;
        let _ = writeln!(
            out,
            "{name}: {} ({} checks, {} points; twin check master)\n  {}",
            suite.name,
            suite.checks.len(),
            suite.points(),
            suite.description
        );
        for check in &suite.checks {
            let _ = writeln!(out, "  - {} ({})", check.name, check.requirement);
        }
    }
    // The server's and the client's checks are code, not TOML: listed from
    // the tables their runs play.
    use twin_check::{client, server};
    let server_checks: Vec<_> = server::listed().collect();
    let client_checks = client::listed(1);
    for (name, title, role, description, checks) in [
        (
            server::NAME,
            server::SUITE,
            "server",
            server::DESCRIPTION,
            server_checks
                .iter()
                .map(|&(n, r, p)| (n, r, p))
                .collect::<Vec<_>>(),
        ),
        (
            client::NAME,
            client::SUITE,
            "client",
            client::DESCRIPTION,
            client_checks
                .iter()
                .map(|(n, r, p)| (n.as_str(), *r, *p))
                .collect(),
        ),
    ] {
        let points: u32 = checks.iter().map(|c| c.2).sum();
        let _ = writeln!(
            out,
            "{name}: {title} ({} checks, {points} points; twin check {role})\n  {description}",
            checks.len()
        );
        for (check, requirement, _) in checks {
            let _ = writeln!(out, "  - {check} ({requirement})");
        }
    }
    Ok(out)
}
