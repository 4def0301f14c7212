//! `twin check slave --patience`: a slow slave (a student's that answers
//! 150 ms after each request) fails every check that waits for a reply
//! within the MEB suite's 100 ms; given patience it passes them, and still
//! fails the timing check, whose deadline is the page's. The report says
//! the patience in its first line and, under each check it let through,
//! how late the reply was.

use super::{failed, student};
use crate::support::{scratch, text, twin};

/// The MEB suite's checks that want no reply at all (silence alone).
const SILENT: usize = 5;

#[test]
fn a_slow_slave_passes_with_patience_but_not_the_timing_check() {
    let slave = student("slow", &["slow"]);
    let json = scratch("check-patience", "as-written.json");
    // As the suite is written: no --timeout-ms.
    let out = twin(&[
        "check",
        "slave",
        &slave.link,
        "--no-record",
        "--json",
        json.to_str().unwrap(),
    ]);
    let shown = text(&out);
    assert_eq!(out.status.code(), Some(1), "{shown}");
    assert_eq!(failed(&json).len(), 25 - SILENT, "{shown}");
    assert!(shown.contains("no reply within 100 ms"), "{shown}");
    assert!(!shown.contains("patience"), "{shown}");

    let json = scratch("check-patience", "patient.json");
    let out = twin(&[
        "check",
        "slave",
        &slave.link,
        "--patience",
        "8",
        "--no-record",
        "--json",
        json.to_str().unwrap(),
    ]);
    let shown = text(&out);
    assert_eq!(out.status.code(), Some(1), "{shown}");
    assert_eq!(
        failed(&json),
        ["two requests back to back get two replies, in order"],
        "{shown}"
    );
    assert!(
        shown.contains("        no reply within 100 ms; expected `@01EA0001` and one data word"),
        "{shown}"
    );
    assert!(
        shown
            .lines()
            .next()
            .unwrap()
            .ends_with("; patience 8: its waits 8 times as long, its timing checks' as written"),
        "{shown}"
    );
    // Each check patience let through says how late its reply was.
    let late = shown
        .matches("ms after its request, beyond the suite's 100 ms: in time only with --patience 8")
        .count();
    assert_eq!(late, 25 - SILENT - 1, "{shown}");
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(run["patience"], 8.0);

    let out = twin(&["check", "slave", &slave.link, "--patience", "0.5"]);
    assert!(
        text(&out)
            .contains("`0.5`: patience is a factor from 1 (the suite's waits as written) to 100"),
        "{}",
        text(&out)
    );
}
