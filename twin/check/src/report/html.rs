//! The run as one HTML page a student opens in a browser: the suite, the
//! link, the score, a table of the checks, and for each failure why, its
//! frames with their times and the requirement. Self-contained (the style
//! inline, no script, no other file), so it can be mailed or uploaded.
//!
//! Written by hand: one page of fixed shape, where a template engine would
//! add a crate and a build step for a dozen elements. Everything that came
//! from the suite or the wire goes through [`esc`].

use crate::run::{Outcome, SuiteRun};
use std::fmt::Write;

const STYLE: &str = "body{font-family:system-ui,sans-serif;max-width:60em;margin:2em auto;padding:0 1em;color:#222}\
h1{font-size:1.4em}.score{font-size:1.6em;font-weight:bold}\
table{border-collapse:collapse;width:100%}td,th{border-bottom:1px solid #ddd;padding:.35em;text-align:left;vertical-align:top}\
.pass{color:#176e2c;font-weight:bold}.fail{color:#b00020;font-weight:bold}.nj{color:#555;font-style:italic}.req{color:#555;font-size:.9em}\
pre{background:#f6f6f6;padding:.5em;overflow-x:auto;white-space:pre-wrap}";

/// The run as a page; `student` names whose program it is, when known.
pub fn html(run: &SuiteRun, student: Option<&str>) -> String {
    let title = match student {
        Some(name) => format!("{}: {}", run.suite, name),
        None => format!("{} on {}", run.suite, run.link),
    };
    let mut out = String::new();
    let _ = writeln!(
        out,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n<title>{}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>{}</h1>",
        esc(&title),
        esc(&title)
    );
    let _ = writeln!(
        out,
        "<p>{}, {:.1} s.</p>",
        esc(&super::heading(run)),
        run.seconds
    );
    let _ = writeln!(
        out,
        "<p class=\"score\">Score: {}</p>",
        esc(&super::score(run))
    );
    if let Some(line) = super::not_applicable(run) {
        let _ = writeln!(out, "<p class=\"nj\">{}</p>", esc(&line));
    }
    if let Some(why) = &run.error {
        let _ = writeln!(
            out,
            "<p class=\"fail\">Could not be checked: {}</p>",
            esc(why)
        );
    }
    if let Some(line) = super::hung_up(run) {
        let _ = writeln!(out, "<p class=\"fail\">{}</p>", esc(&capital(&line)));
    }
    out.push_str(
        "<table>\n<thead><tr><th>Check</th><th>Points</th><th>Result</th></tr></thead>\n<tbody>\n",
    );
    for check in &run.checks {
        let (class, verdict) = match check.outcome {
            Outcome::Pass => ("pass", "pass"),
            Outcome::Fail(_) => ("fail", "FAIL"),
            Outcome::NotJudged(_) => ("nj", "not judged"),
            Outcome::NotApplicable(_) => ("nj", "not applicable"),
        };
        let _ = writeln!(
            out,
            "<tr><td>{}<div class=\"req\">{}</div></td><td>{}</td><td class=\"{class}\">{verdict}</td></tr>",
            esc(&check.name),
            esc(&check.requirement),
            check.points
        );
        if !check.notes.is_empty() {
            let _ = writeln!(
                out,
                "<tr><td colspan=\"3\" class=\"req\">{}</td></tr>",
                esc(&check.notes.join("; "))
            );
        }
        let why = match &check.outcome {
            Outcome::Pass => continue,
            Outcome::NotJudged(what) => {
                let _ = writeln!(
                    out,
                    "<tr><td colspan=\"3\" class=\"req\">not judged: {}</td></tr>",
                    esc(what)
                );
                continue;
            }
            Outcome::NotApplicable(why) => {
                let _ = writeln!(
                    out,
                    "<tr><td colspan=\"3\" class=\"req\">not applicable: {}</td></tr>",
                    esc(why)
                );
                continue;
            }
            Outcome::Fail(why) => why,
        };
        if run.error.is_some() {
            continue;
        }
        let frames = super::frames(check);
        let _ = writeln!(
            out,
            "<tr><td colspan=\"3\">{}<pre>{}</pre></td></tr>",
            esc(why),
            esc(&frames)
        );
    }
    out.push_str("</tbody>\n</table>\n</body>\n</html>\n");
    out
}

/// A sentence's first letter in upper case.
fn capital(s: &str) -> String {
    let mut chars = s.chars();
    chars
        .next()
        .map_or_else(String::new, |c| c.to_uppercase().chain(chars).collect())
}

/// Text as HTML: markup and quotes escaped.
fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}
