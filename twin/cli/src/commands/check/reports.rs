//! The flags every role of `twin check` shares: the reports of one run, a
//! class from a roster, and the recording. Declared once and flattened
//! into each role, so every role takes the same flags with the same help.

use super::write;
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};
use std::time::SystemTime;
use twin_check::{SuiteRun, record, report};
use twin_realtime::rotate;

#[derive(Debug, Args)]
pub struct ReportArgs {
    /// Also write the run as JSON (every check, its frames and times).
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Also write the run as JUnit XML, for CI systems and learning
    /// platforms (a test case per check; one a person judges is
    /// `skipped`).
    #[arg(long, value_name = "FILE")]
    junit: Option<PathBuf>,
    /// Also write the run as one HTML page, to open in a browser.
    #[arg(long, value_name = "FILE")]
    html: Option<PathBuf>,
    /// Check a class instead of one program: a CSV file with the columns
    /// student,link[,id][,bus][,bench], or TOML [[student]] tables of
    /// name, link, id, bus, bench. `link` is where that student's program
    /// is, as LINK (or --listen) gives it one at a time; `id` within the
    /// protocol's range; `bus` a supervisor's bus, as --bus; `bench` the
    /// panel of the bench a slave is wired to, as --bench.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["json", "junit", "html"])]
    pub roster: Option<PathBuf>,
    /// Where a class's reports and scores.csv go [default:
    /// check-SUITE-reports].
    #[arg(long, value_name = "DIR", requires = "roster")]
    pub out: Option<PathBuf>,
    /// How many students of a class are checked at once (students that
    /// share a link, one after the other).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u16).range(1..=64))]
    pub jobs: u16,
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
    pub no_record: bool,
}

impl ReportArgs {
    /// Records one run unless --no-record (`role` names the file and the
    /// link's channel; `suite_toml` is the suite as read), and says where.
    pub fn record(&self, role: &str, suite_toml: &str, run: &SuiteRun) -> Result<()> {
        if self.no_record {
            return Ok(());
        }
        let path = match &self.record {
            Some(path) => path.clone(),
            None => rotate::next_name(
                self.record_dir.as_deref().unwrap_or(Path::new(".")),
                &format!("check-{role}"),
                SystemTime::now(),
            ),
        };
        let path = record::record(&path, role, suite_toml, run)
            .with_context(|| format!("cannot record the run to {}", path.display()))?;
        println!("recorded to {}", path.display());
        Ok(())
    }

    /// The reports asked for (each made only when asked for); then the
    /// run's verdict: an error (exit 1) when a check failed. A check left
    /// to a person ("not judged") is no failure.
    pub fn reports_and_verdict(&self, run: &SuiteRun) -> Result<()> {
        if let Some(path) = &self.json {
            write(path, &report::json(run))?;
        }
        if let Some(path) = &self.junit {
            write(path, &report::junit(run))?;
        }
        if let Some(path) = &self.html {
            write(path, &report::html(run, None))?;
        }
        if let Some(why) = &run.error {
            bail!("{why}");
        }
        let failed = run.failed();
        if failed > 0 {
            bail!(
                "{failed} of {} checks failed",
                run.checks.len() - run.not_applicable()
            );
        }
        Ok(())
    }
}
