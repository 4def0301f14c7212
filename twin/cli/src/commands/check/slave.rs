//! `twin check slave`: the student's module controller, sent requests by
//! the twin; one student, or a class from a roster.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};
use std::time::SystemTime;
use twin_check::class;
use twin_check::{Bench, Suite, record, report, run_suite_on, wire::Wire};
use twin_realtime::rotate;

#[derive(Debug, Args)]
pub struct SlaveArgs {
    /// Where the slave is: tcp://HOST:PORT, or a serial device or
    /// pseudo-terminal (PATH?baud=9600&parity=E).
    #[arg(required_unless_present = "roster", conflicts_with = "roster")]
    link: Option<String>,
    /// The slave's id (MEB: the M3CVME tool's device number, 1-99; Modbus:
    /// the unit id, 1-247); with --roster, of every student whose line
    /// gives none. The 8-byte Modbus suite addresses the Controller_network
    /// project's own ids, 01 and 02.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=247))]
    id: u8,
    /// The suite: a built-in one's name (--list: meb-slave,
    /// modbus-rtu-slave, modbus-tcp-slave, modbus8-slave) or a TOML file.
    #[arg(long, default_value = "meb-slave", value_name = "NAME|FILE")]
    suite: String,
    /// A reply's deadline in ms where the suite's steps set none (the suite's
    /// own otherwise: 100 ms for MEB, the MEB page's master timeout, and
    /// for the 8-byte Modbus; 200 ms for Modbus RTU and TCP). Give a slow
    /// board more.
    #[arg(long, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..=60_000))]
    timeout_ms: Option<u64>,
    /// The bench the slave is wired to: the panel of its twin session
    /// (`twin serve --web`), http://HOST:PORT[/?token=…]. Its bench checks
    /// then hold the slave to what its registers mean on the plant (VEL
    /// moves the motor, EN, BRK and FR do what the map says, the inputs
    /// match the plant); without it they are not applicable.
    #[arg(long, value_name = "URL", conflicts_with = "roster")]
    bench: Option<String>,
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
    /// Check a class instead of one LINK: a CSV file with the columns
    /// student,link[,id], or TOML [[student]] tables of name, link, id.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["json", "junit", "html"])]
    roster: Option<PathBuf>,
    /// Where a class's reports and scores.csv go [default:
    /// check-SUITE-reports].
    #[arg(long, value_name = "DIR", requires = "roster")]
    out: Option<PathBuf>,
    /// How many students of a class are checked at once.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u16).range(1..=64))]
    jobs: u16,
    /// Where to record the run (MCAP: every frame with its time, the check
    /// it belongs to, the verdicts), replaced if it exists [default: a file
    /// named by the run's start time in UTC in --record-dir, e.g.
    /// check-slave-2026-12-03T07-35-44.mcap, as `twin serve` names its
    /// own]. With --roster, each student's recording goes beside their
    /// reports (STUDENT.mcap).
    #[arg(long, value_name = "PATH", conflicts_with_all = ["roster", "record_dir"])]
    record: Option<PathBuf>,
    /// The folder the recording goes to [default: here].
    #[arg(long, value_name = "DIR", conflicts_with = "roster")]
    record_dir: Option<PathBuf>,
    /// Do not record the run (nor, with --roster, the students' runs).
    #[arg(long, conflicts_with_all = ["record", "record_dir"])]
    no_record: bool,
}

/// One student's slave checked, or a class's from a roster.
pub fn execute(slave: &SlaveArgs) -> Result<()> {
    let mut suite = Suite::load(&slave.suite)?;
    let ids = suite.protocol.ids();
    if !ids.contains(&slave.id) {
        bail!(
            "--id {}: the {} suite's slaves have ids {} to {}",
            slave.id,
            suite.name,
            ids.start(),
            ids.end()
        );
    }
    if let Some(ms) = slave.timeout_ms {
        suite.timeout_ms = ms;
    }
    if let Some(roster) = &slave.roster {
        return class(slave, &suite, roster);
    }
    let link = slave.link.as_deref().unwrap_or_default();
    let bench = match &slave.bench {
        Some(url) => Some(Bench::connect(url).map_err(|why| anyhow::anyhow!("--bench: {why}"))?),
        None => None,
    };
    let mut wire = Wire::open(link)?;
    let run = run_suite_on(&suite, &mut wire, slave.id, bench.as_ref());
    print!("{}", report::text(&run));
    if !slave.no_record {
        let path = match &slave.record {
            Some(path) => path.clone(),
            None => rotate::next_name(
                slave.record_dir.as_deref().unwrap_or(Path::new(".")),
                "check-slave",
                SystemTime::now(),
            ),
        };
        let toml = record::suite_toml(&slave.suite);
        let path = record::record(&path, "slave", &toml, &run)
            .with_context(|| format!("cannot record the run to {}", path.display()))?;
        println!("recorded to {}", path.display());
    }
    super::reports_and_verdict(
        &run,
        slave.json.as_deref(),
        slave.junit.as_deref(),
        slave.html.as_deref(),
    )
}

/// Every student of the roster checked (see [`super::class`]).
fn class(slave: &SlaveArgs, suite: &Suite, roster: &Path) -> Result<()> {
    let students = class::load_roster(roster, slave.id)?;
    let toml = (!slave.no_record).then(|| record::suite_toml(&slave.suite));
    let options = super::class::Class {
        suite_name: &suite.name,
        suite_arg: &slave.suite,
        out: slave.out.as_deref(),
        jobs: slave.jobs,
        suite_toml: toml.as_deref(),
    };
    super::class::run(&options, &students, |student| class::check(suite, student))
}
