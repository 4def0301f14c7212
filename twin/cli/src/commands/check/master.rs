//! `twin check master`: the student's supervisor, polling slaves the twin
//! plays; one student, or a class from a roster.

use anyhow::{Result, bail};
use clap::Args;
use std::path::Path;
use std::time::Duration;
use twin_check::class::{self, Student};
use twin_check::master::{self as check, MasterLine, MasterOptions, MasterSuite};
use twin_check::{SuiteRun, record, report};

#[derive(Debug, Args)]
pub struct MasterArgs {
    /// Where the twin's slaves are: a serial device or pseudo-terminal the
    /// master is on (PATH?baud=9600&parity=E), or tcp://HOST:PORT for the
    /// twin to listen on until the master connects (port 0: any, printed).
    #[arg(required_unless_present = "roster", conflicts_with = "roster")]
    link: Option<String>,
    /// The slaves the twin plays (the M3CVME tool's device numbers, Modbus
    /// unit ids), e.g. `--id 1,2`; the situations happen to the first
    /// [default: the suite's: 1, or the 8-byte Modbus motor and light
    /// nodes 1,2]. With --roster, of every student whose line gives none.
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u8).range(1..=247))]
    id: Vec<u8>,
    /// The suite: a built-in one's name (twin check --list: meb-master,
    /// modbus-rtu-master, modbus-tcp-master, modbus8-master) or a TOML file.
    #[arg(long, default_value = "meb-master", value_name = "NAME|FILE")]
    suite: String,
    /// The master's reply timeout in ms, if it was given another than the
    /// suite's (the MEB page's 100 ms): how long it may wait for a reply
    /// before it gives up is judged against it.
    #[arg(long, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..=10_000))]
    timeout_ms: Option<u64>,
    /// How long to wait for the master to connect and send its first
    /// request, seconds.
    #[arg(long, default_value_t = 10, value_name = "SECONDS", value_parser = clap::value_parser!(u64).range(1..=3600))]
    wait: u64,
    #[command(flatten)]
    reports: super::reports::ReportArgs,
}

/// One student's master checked, or a class's from a roster.
pub fn execute(args: &MasterArgs) -> Result<()> {
    let mut suite = MasterSuite::load(&args.suite)?;
    if let Some(ms) = args.timeout_ms {
        suite.timeout_ms = ms;
    }
    let mut ids = Vec::new();
    for id in &args.id {
        if ids.contains(id) {
            bail!("--id {id:02} is given twice");
        }
        if !suite.protocol.ids().contains(id) {
            bail!(
                "--id {id}: the suite's slaves are numbered {} to {}",
                suite.protocol.ids().start(),
                suite.protocol.ids().end()
            );
        }
        ids.push(*id);
    }
    if ids.is_empty() {
        ids = suite.ids.clone();
    }
    if let Some(roster) = &args.reports.roster {
        return class(args, &suite, roster, ids[0]);
    }
    let link = args.link.as_deref().unwrap_or_default();
    let line = MasterLine::open(link)?;
    eprintln!(
        "the twin's slaves {} wait for the master on {}",
        ids_text(&ids),
        line.shown()
    );
    let wait = Duration::from_secs(args.wait);
    let mut wire = line.connected(wait)?;
    let options = MasterOptions { ids, wait };
    let run = check::run_master(&suite, &mut wire, &options)?;
    print!("{}", report::text(&run));
    args.reports
        .record("master", &record::suite_toml(&args.suite), &run)?;
    args.reports.reports_and_verdict(&run)
}

/// One student of a class: the twin waits on their line for their master.
fn student_run(suite: &MasterSuite, student: &Student, wait: Duration) -> SuiteRun {
    let ids = vec![student.id];
    let run = MasterLine::open(&student.link)
        .and_then(|line| line.connected(wait))
        .map_err(|e| e.to_string())
        .and_then(|mut wire| {
            let options = MasterOptions {
                ids: ids.clone(),
                wait,
            };
            check::run_master(suite, &mut wire, &options).map_err(|e| e.to_string())
        });
    run.unwrap_or_else(|why| check::unreachable(suite, &student.link, &ids, why))
}

/// Every student's master checked (see [`super::class`]).
fn class(args: &MasterArgs, suite: &MasterSuite, roster: &Path, id: u8) -> Result<()> {
    let students = class::load_roster(roster, id, suite.protocol)?;
    class::no_bench(&students, roster, "master")?;
    let wait = Duration::from_secs(args.wait);
    let toml = (!args.reports.no_record).then(|| record::suite_toml(&args.suite));
    let options = super::class::Class {
        suite_name: &suite.name,
        suite_arg: &args.suite,
        role: "master",
        out: args.reports.out.as_deref(),
        jobs: args.reports.jobs,
        suite_toml: toml.as_deref(),
    };
    super::class::run(&options, &students, |student| {
        student_run(suite, student, wait)
    })
}

fn ids_text(ids: &[u8]) -> String {
    ids.iter()
        .map(|id| format!("{id:02}"))
        .collect::<Vec<_>>()
        .join(", ")
}
