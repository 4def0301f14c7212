//! The run as JUnit XML, which CI systems and learning platforms read: one
//! `<testsuite>` named after the suite, one `<testcase>` per check (its
//! class the requirement it holds the program to), a failure's message its
//! reason and its text the frames.
//!
//! Written by hand: the format is a dozen elements, and the crate that
//! writes it (quick-junit 0.8) pulls in chrono, uuid, newtype-uuid,
//! quick-xml, indexmap and strip-ansi-escapes for them.

use crate::run::{Outcome, SuiteRun};
use std::fmt::Write;

/// The run as a JUnit XML document.
pub fn junit(run: &SuiteRun) -> String {
    let skipped = run
        .checks
        .iter()
        .filter(|c| matches!(c.outcome, Outcome::NotJudged(_) | Outcome::NotApplicable(_)))
        .count();
    let failures = run.failed();
    // A program that could not be reached is an error (nothing ran), not
    // a failed check.
    let (failures, errors) = if run.error.is_some() {
        (0, failures)
    } else {
        (failures, 0)
    };
    let mut out = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    let _ = writeln!(
        out,
        "<testsuites name=\"twin check\" tests=\"{}\" failures=\"{failures}\" errors=\"{errors}\" time=\"{:.3}\">",
        run.checks.len(),
        run.seconds
    );
    let _ = writeln!(
        out,
        "  <testsuite name=\"{}\" tests=\"{}\" failures=\"{failures}\" errors=\"{errors}\" skipped=\"{skipped}\" time=\"{:.3}\">",
        attr(&run.suite),
        run.checks.len(),
        run.seconds
    );
    let _ = writeln!(
        out,
        "    <properties>\n      <property name=\"link\" value=\"{}\"/>\n      <property name=\"id\" value=\"{:02}\"/>\n      <property name=\"score\" value=\"{}\"/>\n      <property name=\"points\" value=\"{}\"/>\n    </properties>",
        attr(&run.link),
        run.id,
        run.score(),
        run.points()
    );
    let hung_up_in = run
        .hung_up
        .as_ref()
        .and_then(|gone| run.checks.iter().position(|c| c.name == gone.check));
    for (i, check) in run.checks.iter().enumerate() {
        let _ = write!(
            out,
            "    <testcase name=\"{}\" classname=\"{}\" time=\"{:.3}\"",
            attr(&check.name),
            attr(&check.requirement),
            check.seconds
        );
        let why = match &check.outcome {
            Outcome::Pass => {
                out.push_str("/>\n");
                continue;
            }
            // Left to a person: a reader counts it neither passed nor failed.
            Outcome::NotJudged(what) => {
                let _ = writeln!(
                    out,
                    ">\n      <skipped message=\"not judged: {}\"/>\n    </testcase>",
                    attr(what)
                );
                continue;
            }
            // Not for this run (a bench check without a bench): skipped too,
            // its message saying which of the two it is.
            Outcome::NotApplicable(why) => {
                let _ = writeln!(
                    out,
                    ">\n      <skipped message=\"not applicable: {}\"/>\n    </testcase>",
                    attr(why)
                );
                continue;
            }
            Outcome::Fail(why) => why,
        };
        let element = if run.error.is_some() {
            "error"
        } else {
            "failure"
        };
        let frames = super::frames(check);
        let _ = writeln!(
            out,
            ">\n      <{element} message=\"{}\" type=\"{}\">{}</{element}>\n    </testcase>",
            attr(why),
            if run.error.is_some() {
                "unreachable"
            } else if hung_up_in.is_some_and(|h| i >= h) {
                "hung-up"
            } else {
                "protocol"
            },
            text(&frames)
        );
    }
    // After the cases, where the JUnit schema puts a suite's output.
    if let Some(line) = super::hung_up(run) {
        let _ = writeln!(out, "    <system-out>{}</system-out>", text(&line));
    }
    out.push_str("  </testsuite>\n</testsuites>\n");
    out
}

/// `s` as element text: markup escaped, and characters XML 1.0 forbids
/// (control bytes a teacher's suite might hold) replaced.
fn text(s: &str) -> String {
    escape(s, false)
}

/// `s` as an attribute value: also quotes, and line breaks kept as
/// references (a parser would fold them into spaces).
fn attr(s: &str) -> String {
    escape(s, true)
}

fn escape(s: &str, in_attr: bool) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' if in_attr => out.push_str("&quot;"),
            '\'' if in_attr => out.push_str("&apos;"),
            '\n' if in_attr => out.push_str("&#10;"),
            '\r' => out.push_str("&#13;"),
            '\t' if in_attr => out.push_str("&#9;"),
            '\t' | '\n' => out.push(c),
            c if c < ' ' || c == '\u{FFFE}' || c == '\u{FFFF}' => out.push('\u{FFFD}'),
            c => out.push(c),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markup_quotes_and_control_bytes_are_escaped() {
        assert_eq!(attr("a<b & \"c\"\n"), "a&lt;b &amp; &quot;c&quot;&#10;");
        assert_eq!(text("<x>'\u{1}\n"), "&lt;x&gt;'\u{FFFD}\n");
    }
}
