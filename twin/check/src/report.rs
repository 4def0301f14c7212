//! A suite's run as a student or a teacher reads it: one line per check,
//! for a failure why and the frames that show it, and the score; or as
//! JSON for scripts, JUnit XML for CI systems and learning platforms, or
//! a page for a browser.

mod html;
mod junit;

use crate::run::{CheckOutcome, Outcome, Role, SuiteRun, Way};
use std::fmt::Write;

pub use html::html;
pub use junit::junit;

/// A check's frames, one a line: when, which way, the bytes.
pub(crate) fn frames(check: &CheckOutcome) -> String {
    let mut out = String::new();
    for f in &check.frames {
        let way = match f.way {
            Way::Sent => "sent    ",
            Way::Received => "received",
        };
        let _ = writeln!(out, "{:8.3} s  {way}  {}", f.at, f.text);
    }
    out
}

/// What the program's hang-up did to the run, in one sentence: every
/// report says it once, at the top.
pub fn hung_up(run: &SuiteRun) -> Option<String> {
    let gone = run.hung_up.as_ref()?;
    let before = run
        .checks
        .iter()
        .position(|c| c.name == gone.check)
        .unwrap_or(run.checks.len());
    // Those not applicable stay so: they neither ran nor failed.
    let after = run
        .checks
        .iter()
        .skip(before + 1)
        .filter(|c| matches!(c.outcome, Outcome::Fail(_)))
        .count();
    let kept = match before {
        0 => "no check had finished before it".to_string(),
        1 => "the check before it keeps its verdict".to_string(),
        n => format!("the {n} checks before it keep their verdicts"),
    };
    let failed = match after {
        0 => "it fails".to_string(),
        1 => "it and the one after it fail".to_string(),
        n => format!("it and the {n} after it fail"),
    };
    Some(format!(
        "the program hung up at {:.3} s ({}), during `{}`: {kept}; {failed}",
        gone.at, gone.how, gone.check
    ))
}

/// The terminal's report.
pub fn text(run: &SuiteRun) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "{}", heading(run));
    if let Some(why) = &run.error {
        let _ = writeln!(out, "  could not be checked: {why}");
    }
    if let Some(line) = hung_up(run) {
        let _ = writeln!(out, "  {line}");
    }
    for check in run.checks.iter().filter(|_| run.error.is_none()) {
        match &check.outcome {
            Outcome::Pass => {
                let _ = writeln!(out, "  pass  {}  ({})", check.name, check.requirement);
                for note in &check.notes {
                    let _ = writeln!(out, "        {note}");
                }
            }
            Outcome::NotJudged(what) => {
                let _ = writeln!(out, "  ----  {}  ({})", check.name, check.requirement);
                let _ = writeln!(out, "        not judged: {what}");
            }
            Outcome::NotApplicable(why) => {
                let _ = writeln!(out, "  n/a   {}  ({})", check.name, check.requirement);
                let _ = writeln!(out, "        not applicable: {why}");
            }
            Outcome::Fail(why) => {
                let _ = writeln!(out, "  FAIL  {}  ({})", check.name, check.requirement);
                let _ = writeln!(out, "        {why}");
                for note in &check.notes {
                    let _ = writeln!(out, "        {note}");
                }
                for line in frames(check).lines() {
                    let _ = writeln!(out, "        {line}");
                }
            }
        }
    }
    let heard = run
        .checks
        .iter()
        .flat_map(|c| &c.frames)
        .any(|f| f.way == Way::Received);
    if !heard && run.error.is_none() && run.role == Role::Slave {
        let _ = writeln!(
            out,
            "nothing came back at all: is slave {:02} there, on {}? (--id is its device number)",
            run.id, run.link
        );
    }
    if let Some(line) = not_applicable(run) {
        let _ = writeln!(out, "{line}");
    }
    let _ = write!(out, "score: {}", score(run));
    if run.error.is_none() {
        let _ = write!(out, " in {:.1} s", run.seconds);
    }
    let mut replies: Vec<f64> = run
        .checks
        .iter()
        .flat_map(|c| c.reply_ms.iter().copied())
        .collect();
    replies.sort_by(f64::total_cmp);
    if let (Some(median), Some(max)) = (replies.get(replies.len() / 2), replies.last()) {
        let _ = write!(
            out,
            "; replies began {median:.1} ms after the request (median), {max:.1} ms at most"
        );
    }
    out.push('\n');
    out
}

/// `S of P points (N of C checks passed)`: the checks not applicable
/// count in neither.
pub fn score(run: &SuiteRun) -> String {
    format!(
        "{} of {} points ({} of {} checks passed)",
        run.score(),
        run.points(),
        run.passed().count(),
        run.checks.len() - run.not_applicable(),
    )
}

/// How many checks did not apply, and what would make them apply: `None`
/// when every check applied.
pub fn not_applicable(run: &SuiteRun) -> Option<String> {
    match run.not_applicable() {
        0 => None,
        1 => Some("1 check not applicable (not scored): it needs the bench (--bench URL)".into()),
        n => Some(format!(
            "{n} checks not applicable (not scored): they need the bench (--bench URL)"
        )),
    }
}

/// What was checked, on which link (and with what patience, when not 1).
pub(crate) fn heading(run: &SuiteRun) -> String {
    let mut heading = checked(run);
    if run.patience != 1.0 {
        let _ = write!(
            heading,
            "; patience {}: its waits {} times as long, its timing checks' as written",
            run.patience, run.patience
        );
    }
    heading
}

fn checked(run: &SuiteRun) -> String {
    match run.role {
        Role::Slave => match &run.bench {
            Some(bench) => format!(
                "{} suite, slave {:02} on {}, bench {bench}",
                run.suite, run.id, run.link
            ),
            None => format!("{} suite, slave {:02} on {}", run.suite, run.id, run.link),
        },
        Role::Master => {
            let ids: Vec<String> = run.ids.iter().map(|id| format!("{id:02}")).collect();
            let slaves = if ids.len() == 1 { "slave" } else { "slaves" };
            format!(
                "{} suite, the master on {} (the twin's {slaves} {})",
                run.suite,
                run.link,
                ids.join(", ")
            )
        }
    }
}

/// The run as JSON: the suite, the link, every check with its frames.
pub fn json(run: &SuiteRun) -> String {
    let mut value = serde_json::to_value(run).unwrap_or_default();
    if let Some(map) = value.as_object_mut() {
        map.insert("score".into(), run.score().into());
        map.insert("points".into(), run.points().into());
    }
    serde_json::to_string_pretty(&value).unwrap_or_default()
}
