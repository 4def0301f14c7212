//! A class checked from a roster, whatever the role: a line per student as
//! they finish, their reports (and recordings) in the out folder, and the
//! class's scores.csv.

use super::write;
use anyhow::{Context, Result, bail};
use std::path::{Path, PathBuf};
use std::time::Instant;
use twin_check::class::{self, Student};
use twin_check::{SuiteRun, record, report};

/// How a class is run.
pub(super) struct Class<'a> {
    /// The suite's own name, for the first line.
    pub suite_name: &'a str,
    /// The suite as given (a built-in name or a file): names the default
    /// out folder.
    pub suite_arg: &'a str,
    /// The role checked: names each recording's link channel.
    pub role: &'a str,
    pub out: Option<&'a Path>,
    pub jobs: u16,
    /// The suite's TOML, to record each run with; `None`: no recordings.
    pub suite_toml: Option<&'a str>,
}

/// Checks every student with `check`, `class.jobs` at once.
pub(super) fn run(
    class: &Class<'_>,
    students: &[Student],
    check: impl Fn(&Student) -> SuiteRun + Sync,
) -> Result<()> {
    let out = class.out.map_or_else(
        || {
            let name = Path::new(class.suite_arg).file_stem().map_or_else(
                || class.suite_arg.to_string(),
                |s| s.to_string_lossy().into_owned(),
            );
            PathBuf::from(format!("check-{name}-reports"))
        },
        Path::to_path_buf,
    );
    std::fs::create_dir_all(&out)
        .with_context(|| format!("cannot make the folder {}", out.display()))?;
    let width = students
        .iter()
        .map(|s| s.name.chars().count())
        .max()
        .unwrap_or(0);
    println!(
        "{} suite: {} students, {} at once",
        class.suite_name,
        students.len(),
        usize::from(class.jobs).min(students.len())
    );
    let started = Instant::now();
    let mut unwritten = None;
    let runs = class::run_each(students, class.jobs.into(), check, |student, run| {
        println!("  {:width$}  {}", student.name, verdict(run));
        if let Err(e) = reports(&out, student, run, class) {
            unwritten.get_or_insert(e);
        }
    });
    if let Some(e) = unwritten {
        return Err(e);
    }
    write(&out.join("scores.csv"), &class::scores_csv(students, &runs))?;
    let unreachable = runs.iter().filter(|r| r.error.is_some()).count();
    let failed = runs
        .iter()
        .filter(|r| r.error.is_none() && r.first_failure().is_some())
        .count();
    println!(
        "{} students in {:.1} s: {} passed every check, {failed} failed a check, {unreachable} could not be checked; reports{} and scores.csv in {}",
        students.len(),
        started.elapsed().as_secs_f64(),
        students.len() - failed - unreachable,
        if class.suite_toml.is_some() {
            ", recordings"
        } else {
            ""
        },
        out.display()
    );
    if failed + unreachable > 0 {
        bail!(
            "{} of {} students did not pass every check",
            failed + unreachable,
            students.len()
        );
    }
    Ok(())
}

/// A student's line: the score, or why it could not be checked.
fn verdict(run: &SuiteRun) -> String {
    if let Some(why) = &run.error {
        return format!("could not be checked: {why}");
    }
    let score = format!(
        "{} of {} points, {} of {} checks",
        run.score(),
        run.points(),
        run.passed().count(),
        run.checks.len() - run.not_applicable()
    );
    match (&run.hung_up, run.first_failure()) {
        (Some(gone), _) => format!(
            "{score}; hung up at {:.3} s, during: {}",
            gone.at, gone.check
        ),
        (None, Some(check)) => format!("{score}; first failed: {}", check.name),
        (None, None) => score,
    }
}

/// A student's reports, and their run's recording unless the class's
/// `suite_toml` is `None` (--no-record).
fn reports(out: &Path, student: &Student, run: &SuiteRun, class: &Class<'_>) -> Result<()> {
    let stem = student.file_stem();
    let file = |ext: &str| out.join(format!("{stem}.{ext}"));
    write(
        &file("txt"),
        &format!("{}\n{}", student.name, report::text(run)),
    )?;
    write(&file("json"), &report::json(run))?;
    write(&file("html"), &report::html(run, Some(&student.name)))?;
    write(&file("junit.xml"), &report::junit(run))?;
    if let Some(toml) = class.suite_toml {
        let path = file("mcap");
        record::record(&path, class.role, toml, run)
            .with_context(|| format!("cannot record the run to {}", path.display()))?;
    }
    Ok(())
}
