//! `twin check server`: the student's supervisor, checked from its bus
//! (the twin plays the module's controller there) and from its TCP server
//! (the twin connects as the remote clients).

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::Path;
use twin_check::server::{NAME, SUITE, ServerOptions, check_server, unreachable};
use twin_check::{Protocol, class, report};

#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  twin vsp /tmp/ttyV0 /tmp/ttyV1 &\n  python3 supervisor.py /tmp/ttyV0 5701 &      (the student's supervisor)\n  twin check server tcp://127.0.0.1:5701 --bus /tmp/ttyV1\n  twin check server tcp://127.0.0.1:5701 --bus /dev/ttyUSB0?baud=9600 --html report.html"
)]
pub struct ServerArgs {
    /// Where the supervisor's server listens for remote clients:
    /// tcp://HOST:PORT.
    #[arg(
        value_name = "tcp://HOST:PORT",
        required_unless_present = "roster",
        conflicts_with = "roster"
    )]
    link: Option<String>,
    /// The supervisor's bus, where the twin answers as the module's
    /// controller: the other end of its serial line or pseudo-terminal
    /// (PATH?baud=9600&parity=E).
    #[arg(long, value_name = "LINK", required_unless_present = "roster")]
    bus: Option<String>,
    /// The slave id the supervisor polls (the M3CVME tool's device number).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=99))]
    id: u8,
    /// A read's reply deadline, ms (the MEB page's master timeout); a
    /// forwarded write gets ten times as long. Give a loaded machine more.
    #[arg(long, default_value_t = 100, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..=60_000))]
    timeout_ms: u64,
    #[command(flatten)]
    reports: super::reports::ReportArgs,
}

/// The supervisor's server checked, its report printed and written; or a
/// class's from a roster.
pub fn execute(args: &ServerArgs) -> Result<()> {
    if let Some(roster) = &args.reports.roster {
        return class(args, roster);
    }
    let link = args.link.clone().unwrap_or_default();
    let bus = args.bus.clone().unwrap_or_default();
    if !link.starts_with("tcp://") {
        bail!(
            "the server is reached over TCP: give tcp://HOST:PORT, not `{link}` (its bus goes after --bus)"
        );
    }
    let options = ServerOptions {
        link,
        bus: bus.clone(),
        id: args.id,
        timeout_ms: args.timeout_ms,
    };
    let run = check_server(&options)
        .with_context(|| format!("cannot play the slave on the bus {bus}"))?;
    print!("{}", report::text(&run));
    args.reports.record("server", "", &run)?;
    args.reports.reports_and_verdict(&run)
}

/// Every student's supervisor checked (see [`super::class`]): the
/// roster's `link` is their server, its `bus` their bus (--bus where it
/// gives none). Students on one bus are checked one after the other.
fn class(args: &ServerArgs, roster: &Path) -> Result<()> {
    let mut students = class::load_roster(roster, args.id, Protocol::Meb)?;
    class::no_bench(&students, roster, "server")?;
    for student in &mut students {
        let at = || format!("{}, line {}", roster.display(), student.line);
        if !student.link.starts_with("tcp://") {
            bail!(
                "{}: `{}`'s server is reached over TCP: give tcp://HOST:PORT, not `{}` (the bus goes in the `bus` column)",
                at(),
                student.name,
                student.link
            );
        }
        if student.bus.is_none() {
            let Some(bus) = &args.bus else {
                bail!(
                    "{}: `{}` has no bus: give each student's in a `bus` column, or one for all with --bus",
                    at(),
                    student.name
                );
            };
            student.bus = Some(bus.clone());
        }
    }
    let options = super::class::Class {
        suite_name: SUITE,
        suite_arg: NAME,
        role: "server",
        out: args.reports.out.as_deref(),
        jobs: args.reports.jobs,
        suite_toml: (!args.reports.no_record).then_some(""),
    };
    super::class::run(&options, &students, |student| {
        let bus = student.bus.clone().unwrap_or_default();
        let options = ServerOptions {
            link: student.link.clone(),
            bus: bus.clone(),
            id: student.id,
            timeout_ms: args.timeout_ms,
        };
        check_server(&options).unwrap_or_else(|e| {
            let shown = format!("{}, bus {bus}", student.link);
            unreachable(
                &shown,
                student.id,
                format!("cannot play the slave on the bus: {e}"),
            )
        })
    })
}
