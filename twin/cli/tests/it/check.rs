//! `twin check slave`: the built-in MEB slave suite against the twin's own
//! slave (every check passes) and against a student's slave written
//! outside the twin (a Python program), once correct and once per planted
//! bug: each bug found, and nothing else reported.

use crate::support::{Proc, scratch, text, twin};
use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

/// The student's slave with `bugs` planted, listening on a free port.
struct Student {
    child: Child,
    link: String,
}

impl Drop for Student {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn student(name: &str, bugs: &[&str]) -> Student {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/meb_student_slave.py");
    let port_file = scratch("check", &format!("{name}.port"));
    let _ = std::fs::remove_file(&port_file);
    let mut command = Command::new("python3");
    command.arg(script).arg(&port_file);
    for bug in bugs {
        command.args(["--bug", bug]);
    }
    let child = command.spawn().expect("python3 runs");
    let deadline = Instant::now() + Duration::from_secs(10);
    let port = loop {
        if let Ok(port) = std::fs::read_to_string(&port_file) {
            break port;
        }
        assert!(
            Instant::now() < deadline,
            "the student's slave never listened"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    Student {
        child,
        link: format!("tcp://127.0.0.1:{}", port.trim()),
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

#[test]
fn the_twins_own_slave_passes_every_check_of_the_meb_slave_suite() {
    let serve = Proc::start(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--no-record",
        "--quiet",
        "--status-every",
        "0",
        "--duration",
        "60",
    ]);
    let link = format!("tcp://{}", serve.tcp_of("meb"));
    // A loaded test machine may answer late; the logic is what is checked.
    let out = twin(&["check", "slave", &link, "--timeout-ms", "1000"]);
    let shown = text(&out);
    assert!(out.status.success(), "{shown}");
    assert!(
        shown.contains("score: 32 of 32 points (25 of 25 checks passed)"),
        "{shown}"
    );
    assert!(!shown.contains("FAIL"), "{shown}");
    serve.terminate();
}

#[test]
fn a_correct_student_slave_passes_and_each_planted_bug_is_found_alone() {
    let json = scratch("check", "run.json");
    let correct = student("correct", &[]);
    let out = twin(&[
        "check",
        "slave",
        &correct.link,
        "--timeout-ms",
        "1000",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out));
    assert_eq!(failed(&json), Vec::<String>::new());
    drop(correct);

    let cases: [(&str, &[&str]); 4] = [
        (
            "answers-bad-fcs",
            &["a bad FCS gets no reply, and the next good request is answered"],
        ),
        (
            "answers-broadcast",
            &["a broadcast write (id 00) is not answered"],
        ),
        (
            "no-resync",
            &["a partial frame is dropped at the next @ and the new frame answered"],
        ),
        (
            "wrong-error-code",
            &[
                "an address outside the block gets error 02",
                "a range running past the block's end gets error 02",
            ],
        ),
    ];
    for (bug, expected) in cases {
        let slave = student(bug, &[bug]);
        let out = twin(&[
            "check",
            "slave",
            &slave.link,
            "--timeout-ms",
            "1000",
            "--json",
            json.to_str().unwrap(),
        ]);
        let shown = text(&out);
        assert!(!out.status.success(), "{bug}: {shown}");
        assert_eq!(failed(&json), expected, "{bug}: {shown}");
        assert!(shown.contains("checks failed"), "{shown}");
    }

    // Replies whose FCS leaves out the @: every reply is refused for it,
    // with the FCS its bytes give; the silences still pass.
    let slave = student("fcs-without-at", &["fcs-without-at"]);
    let out = twin(&[
        "check",
        "slave",
        &slave.link,
        "--timeout-ms",
        "1000",
        "--json",
        json.to_str().unwrap(),
    ]);
    let shown = text(&out);
    assert!(shown.contains("its FCS is `"), "{shown}");
    let fails = failed(&json);
    let silent_only = |f: &String| f.contains("not answered") || f.contains("another slave's id");
    assert!(!fails.iter().any(silent_only), "{fails:?}");
    assert_eq!(fails.len(), 20, "every check with a reply in it: {shown}");
}

#[test]
fn a_teachers_suite_with_a_mistake_is_refused_with_its_line() {
    let suite = scratch("check", "mine.toml");
    std::fs::write(
        &suite,
        "name = \"mine\"\nprotocol = \"meb\"\n\n[[check]]\nname = \"reads\"\nrequirement = \"MEB page\"\nsteps = [\n  { send = \"@{id}EA0001\" },\n  { expect = \"@{id}EA0001\", wait_ms = 5 },\n]\n",
    )
    .unwrap();
    let out = twin(&[
        "check",
        "slave",
        "tcp://127.0.0.1:9",
        "--suite",
        suite.to_str().unwrap(),
    ]);
    let shown = text(&out);
    assert!(!out.status.success());
    assert!(
        shown.contains("mine.toml, line 9: check `reads`: a step does one thing"),
        "{shown}"
    );
    let out = twin(&[
        "check",
        "slave",
        "tcp://127.0.0.1:9",
        "--suite",
        "meb-master",
    ]);
    assert!(
        text(&out)
            .contains("no built-in suite is called `meb-master`: twin check --list names them"),
        "{}",
        text(&out)
    );
}

/// The report, with what differs from run to run taken out: the port, the
/// frames' times, the run's duration and reply times.
fn comparable(report: &str) -> Vec<String> {
    report
        .lines()
        .map(|line| {
            if let Some((head, _)) = line.split_once(" on tcp://") {
                return format!("{head} on tcp://…");
            }
            if let Some((head, _)) = line.split_once(" in ")
                && line.starts_with("score:")
            {
                return head.to_string();
            }
            let trimmed = line.trim_start();
            match trimmed.split_once(" s  ") {
                Some((time, rest)) if time.parse::<f64>().is_ok() => format!("… s  {rest}"),
                _ => line.to_string(),
            }
        })
        .collect()
}

/// The book's report is the program's, bugs and all.
#[test]
fn the_books_report_is_what_twin_check_prints() {
    let page =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/check.md"))
            .unwrap();
    let start = page
        .find("```text\nMEB slave suite")
        .expect("the report on the page")
        + 8;
    let shown = &page[start..start + page[start..].find("\n```").unwrap()];
    let slave = student("book", &["answers-bad-fcs", "answers-broadcast"]);
    let out = twin(&["check", "slave", &slave.link, "--timeout-ms", "1000"]);
    assert_eq!(comparable(&text(&out)), comparable(shown));
}
