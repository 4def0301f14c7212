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
    super::held_to_the_book(
        "check::master's the_twins_own_supervisor",
        &printed.replace(s(&b), "/tmp/ttyV1"),
    );
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
                assert!(
                    json.is_file(),
                    "{name}: no report ({}): {printed}",
                    out.status
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
    // Each master's run recorded beside its reports.
    let ann = super::recorded::read(&out_dir.join("Ann.mcap"));
    assert_eq!(ann["check"]["score"], "11", "{ann}");
    assert_eq!(ann["run"]["role"], "master", "{ann}");
    let ben = std::fs::read_to_string(out_dir.join("Ben.txt")).unwrap();
    assert!(
        ben.contains("the master on") && ben.contains("(the twin's slave 03)"),
        "{ben}"
    );
}

/// A master's recording, read by the Python `mcap` package: every frame
/// the master sent and the twin's slaves answered, each in its check (the
/// report's frames among them, in order), the verdicts and the score;
/// `twin export` and `twin view` read it and `twin replay` says what it is.
#[test]
fn a_masters_run_is_recorded_with_every_frame_in_its_check() {
    let dir = crate::support::folder("check", "master-recorded");
    let (mcap, json) = (dir.join("run.mcap"), dir.join("run.json"));
    let (a, b) = pair_paths("check-master-recorded");
    let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let _master = StudentMaster::start(&a, "1,2", Some("acts-on-bad-fcs"));
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
        "--record",
        s(&mcap),
    ]);
    let printed = text(&out);
    assert_eq!(out.status.code(), Some(1), "{printed}");
    assert!(
        printed.contains(&format!("recorded to {}\n", mcap.display())),
        "{printed}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let recorded = super::recorded::read(&mcap);
    assert_eq!(recorded["run"]["kind"], "check");
    assert_eq!(recorded["run"]["role"], "master");
    assert_eq!(recorded["run"]["suite"], "MEB master");
    assert!(
        recorded["run"]["suite_toml"]
            .as_str()
            .unwrap()
            .contains("role = \"master\""),
        "{recorded}"
    );
    assert_eq!(recorded["check"]["score"], "9");
    assert_eq!(recorded["check"]["checks_passed"], "7");

    let checks = recorded["checks"].as_array().unwrap();
    let reported = report["checks"].as_array().unwrap();
    assert_eq!(checks.len(), reported.len());
    let frames = recorded["frames"].as_array().unwrap();
    let (mut next, mut shown) = (0, 0);
    for (check, expected) in checks.iter().zip(reported) {
        assert_eq!(check["name"], expected["name"]);
        assert_eq!(check["result"], expected["result"]);
        let n = check["frames"].as_u64().unwrap() as usize;
        let own = &frames[next..next + n];
        next += n;
        // The master polled throughout: both ways, MEB requests decoded.
        assert!(own.iter().any(|f| f["from"] == "master"), "{check}");
        assert!(own.iter().any(|f| f["from"] == "twin"), "{check}");
        for f in own {
            assert_eq!(f["topic"], "/link/master/frames");
        }
        // The report's frames are among them, in order, at their times.
        let want = expected["frames"].as_array().unwrap();
        shown += want.len();
        let mut rest = own.iter();
        for w in want {
            let at = w["at"].as_f64().unwrap();
            let from = if w["way"] == "sent" { "twin" } else { "master" };
            assert!(
                rest.any(
                    |got| super::recorded::spelt(got["text"].as_str().unwrap()) == w["text"]
                        && got["from"] == from
                        && (got["time_s"].as_f64().unwrap() - at).abs() < 1e-6
                ),
                "{}: {w} not recorded",
                check["name"]
            );
        }
    }
    assert_eq!(next, frames.len(), "no frame outside a check");
    assert!(
        frames.len() > 2 * shown,
        "{} frames, {shown} shown",
        frames.len()
    );
    let first = frames
        .iter()
        .find(|f| f["from"] == "master")
        .expect("a request");
    assert_eq!(first["protocol"], "meb", "{first}");
    let times: Vec<f64> = frames
        .iter()
        .map(|f| f["time_s"].as_f64().unwrap())
        .collect();
    assert!(times.windows(2).all(|w| w[0] <= w[1]), "in time order");

    let csv = dir.join("csv");
    let out = twin(&["export", s(&mcap), "--csv", s(&csv)]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(csv.join("link_master_frames.csv").is_file());
    let rrd = dir.join("run.rrd");
    let out = twin(&["view", s(&mcap), "--save", s(&rrd)]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(rrd.is_file(), "{}", text(&out));
    let out = twin(&["replay", s(&mcap)]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("is a `twin check` run"),
        "{}",
        text(&out)
    );
}
