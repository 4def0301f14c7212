//! `twin check master`: the built-in MEB master suite against the twin's
//! own supervisor (every check passes) and against a student's master
//! written outside the twin (a Python program), once correct and once per
//! planted bug: each bug found, and nothing else reported; and a class of
//! masters from a roster. Each master is on one end of a `twin vsp` pair,
//! the check on the other. Both sides are given a 300 ms reply timeout
//! (the check told so by --timeout-ms): a loaded machine may hold a reply
//! up, and what is checked here is the logic.

use crate::supervise::{pair_paths, s};
use crate::support::{Proc, scratch, text, twin};
use std::path::Path;
use std::process::{Child, Command};

/// A student's master (Python) on `device`, polling `ids`.
struct StudentMaster(Child);

impl StudentMaster {
    fn start(device: &Path, ids: &str, bug: Option<&str>) -> Self {
        let script =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/meb_student_master.py");
        let mut command = Command::new("python3");
        command.arg(script).args(["serial", s(device), "--id", ids]);
        command.args(["--timeout-ms", "300", "--seconds", "120"]);
        if let Some(bug) = bug {
            command.args(["--bug", bug]);
        }
        StudentMaster(command.spawn().expect("python3 runs"))
    }
}

impl Drop for StudentMaster {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The names of the checks that failed, from the JSON report.
fn failed(json: &Path) -> Vec<String> {
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    run["checks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["result"] == "fail")
        .map(|c| c["name"].as_str().unwrap().to_string())
        .collect()
}

const WELL_FORMED: &str = "polls every slave with well-formed requests, one at a time";
const SLOW: &str =
    "waits for a slow reply (60 ms, within the 100 ms timeout) and sends nothing before it";
const BAD_FCS: &str = "discards a reply with a bad FCS";
const SILENT: &str = "gives up on a slave that does not answer, and polls the others meanwhile";

#[test]
fn the_twins_own_supervisor_passes_every_check_of_the_meb_master_suite() {
    let (a, b) = pair_paths("check-master-supervise");
    let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let _supervise = Proc::start(&[
        "supervise",
        "--meb",
        s(&a),
        "--id",
        "1",
        "--id",
        "2",
        "--timeout-ms",
        "300",
        "--no-server",
        "--no-record",
        "--quiet",
        "--status-every",
        "0",
    ]);
    let json = scratch("check", "master-supervise.json");
    let out = twin(&[
        "check",
        "master",
        s(&b),
        "--id",
        "1,2",
        "--timeout-ms",
        "300",
        "--json",
        s(&json),
        "--no-record",
    ]);
    let printed = text(&out);
    assert!(out.status.success(), "{printed}");
    assert!(
        printed.contains("score: 11 of 11 points (8 of 8 checks passed)"),
        "{printed}"
    );
    // What the supervisor reads and writes is said, not graded.
    assert!(
        printed.contains("reads EA 00-05, ED 00, FA 00-01, FD 00; writes SA 00, SD 00-01"),
        "{printed}"
    );
    assert!(printed.contains("slave 02 polled"), "{printed}");
    assert_eq!(failed(&json), Vec::<String>::new());
    held_to_the_book(&printed.replace(s(&b), "/tmp/ttyV1"));
}

/// Every line of the report in docs/check.md's "Checking a master" is a
/// line of `printed`, numbers aside (counts and times differ run to run).
fn held_to_the_book(printed: &str) {
    let page =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/check.md"))
            .unwrap();
    let excerpt = page
        .split("the_twins_own_supervisor test")
        .nth(1)
        .and_then(|rest| rest.split("```text\n").nth(1))
        .and_then(|block| block.split("```").next())
        .expect("docs/check.md shows the supervisor's report");
    let numbers_aside = |line: &str| {
        let mut out = String::new();
        for c in line.chars() {
            if c.is_ascii_digit() || c == '.' {
                if !out.ends_with('#') {
                    out.push('#');
                }
            } else {
                out.push(c);
            }
        }
        out
    };
    let real: Vec<String> = printed.lines().map(numbers_aside).collect();
    for line in excerpt.lines() {
        assert!(
            real.contains(&numbers_aside(line)),
            "docs/check.md shows `{line}`, which the program does not print:\n{printed}"
        );
    }
}

#[test]
fn a_students_master_passes_and_each_planted_bug_is_found_and_nothing_else() {
    let cases: [(Option<&str>, &[&str]); 5] = [
        (None, &[]),
        (Some("never-times-out"), &[SILENT]),
        (Some("floods"), &[WELL_FORMED, SLOW]),
        (Some("bad-fcs"), &[WELL_FORMED]),
        (Some("acts-on-bad-fcs"), &[BAD_FCS]),
    ];
    // Side by side: each is a real master on a pty pair of its own.
    std::thread::scope(|scope| {
        for (bug, expected) in cases {
            scope.spawn(move || {
                let name = bug.unwrap_or("correct");
                let (a, b) = pair_paths(&format!("check-master-{name}"));
                let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
                let _master = StudentMaster::start(&a, "1,2", bug);
                let json = scratch("check", &format!("master-{name}.json"));
                let out = twin(&[
                    "check",
                    "master",
                    s(&b),
                    "--id",
                    "1,2",
                    "--timeout-ms",
                    "300",
                    "--json",
                    s(&json),
                    "--no-record",
                ]);
                let printed = text(&out);
                assert_eq!(
                    out.status.success(),
                    expected.is_empty(),
                    "{name}: {printed}"
                );
                assert_eq!(failed(&json), expected, "{name}: {printed}");
            });
        }
    });
}

#[test]
fn a_class_of_masters_is_checked_from_a_roster() {
    let (a1, b1) = pair_paths("check-master-ann");
    let (a2, b2) = pair_paths("check-master-ben");
    let _vsp1 = Proc::start(&["vsp", s(&a1), s(&b1)]);
    let _vsp2 = Proc::start(&["vsp", s(&a2), s(&b2)]);
    let _ann = StudentMaster::start(&a1, "3", None);
    let _ben = StudentMaster::start(&a2, "3", Some("acts-on-bad-fcs"));
    let roster = scratch("check", "masters.csv");
    std::fs::write(
        &roster,
        format!("student,link,id\nAnn,{},3\nBen,{},3\n", s(&b1), s(&b2)),
    )
    .unwrap();
    let out_dir = scratch("check", "masters-reports");
    let out = twin(&[
        "check",
        "master",
        "--roster",
        s(&roster),
        "--timeout-ms",
        "300",
        "--out",
        s(&out_dir),
    ]);
    let printed = text(&out);
    assert_eq!(out.status.code(), Some(1), "{printed}");
    let scores = std::fs::read_to_string(out_dir.join("scores.csv")).unwrap();
    assert!(scores.contains("Ann,11,11,8,8,,0\n"), "{scores}");
    assert!(
        scores.contains(&format!("Ben,9,11,7,8,{BAD_FCS},0\n")),
        "{scores}"
    );
    let ben = std::fs::read_to_string(out_dir.join("Ben.txt")).unwrap();
    assert!(
        ben.contains("the master on") && ben.contains("(the twin's slave 03)"),
        "{ben}"
    );
}
