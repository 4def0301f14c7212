//! `twin check slave`: the built-in MEB slave suite against the twin's own
//! slave (every check passes) and against a student's slave written
//! outside the twin (a Python program), once correct and once per planted
//! bug: each bug found, and nothing else reported; the JUnit and HTML
//! reports read back; and a class ([`class`]).

mod bench;
mod class;
mod client;
mod hang_up;
mod master;
mod master_modbus;
mod modbus;
mod patience;
mod recorded;
mod server;

use crate::support::{Proc, scratch, text, twin};
use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

/// The student's slave with `bugs` planted, listening on a free port.
pub(crate) struct Student {
    child: Child,
    pub(crate) link: String,
}

impl Drop for Student {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub(crate) fn student(name: &str, bugs: &[&str]) -> Student {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/meb_student_slave.py");
    let port_file = scratch("check", &format!("{name}.port"));
    let _ = std::fs::remove_file(&port_file);
    let mut command = Command::new("python3");
    command.arg(script).arg(&port_file);
    for bug in bugs {
        // `hangs-up-after 5` is the flag and its number.
        command.arg("--bug").args(bug.split(' '));
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

/// `twin check slave LINK MORE…`, the slave given 1 s to answer: a loaded
/// test machine may answer late, and what is checked here is the logic.
/// Not recorded unless MORE says where (the tests' folder is no place for
/// recordings).
pub(crate) fn check_slave(link: &str, more: &[&str]) -> std::process::Output {
    let mut args = vec!["check", "slave", link, "--timeout-ms", "1000"];
    args.extend_from_slice(more);
    if !more
        .iter()
        .any(|a| a.starts_with("--record") || *a == "--no-record")
    {
        args.push("--no-record");
    }
    twin(&args)
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
    let out = check_slave(&link, &[]);
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
    let out = check_slave(&correct.link, &["--json", json.to_str().unwrap()]);
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
        let out = check_slave(&slave.link, &["--json", json.to_str().unwrap()]);
        let shown = text(&out);
        assert!(!out.status.success(), "{bug}: {shown}");
        assert_eq!(failed(&json), expected, "{bug}: {shown}");
        assert!(shown.contains("checks failed"), "{shown}");
    }

    // Replies whose FCS leaves out the @: every reply is refused for it,
    // with the FCS its bytes give; the silences still pass.
    let slave = student("fcs-without-at", &["fcs-without-at"]);
    let out = check_slave(&slave.link, &["--json", json.to_str().unwrap()]);
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
            if line.starts_with("recorded to ") && line.ends_with(".mcap") {
                return "recorded to a file named by the start".into();
            }
            let trimmed = line.trim_start();
            match trimmed.split_once(" s  ") {
                Some((time, rest)) if time.parse::<f64>().is_ok() => format!("… s  {rest}"),
                _ => line.to_string(),
            }
        })
        .collect()
}

/// The `text` block of docs/check.md after the comment naming `test`:
/// every one of its lines is a line `printed`, numbers aside (ports,
/// times and counts differ run to run), in any order (a class's students
/// finish in any order).
pub(crate) fn held_to_the_book(test: &str, printed: &str) {
    let page =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/check.md"))
            .unwrap();
    let block = page
        .split(&format!("the output of {test} test"))
        .nth(1)
        .and_then(|rest| rest.split("```text\n").nth(1))
        .and_then(|block| block.split("```").next())
        .unwrap_or_else(|| panic!("docs/check.md shows the output of {test}"));
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
    for line in block.lines() {
        assert!(
            real.contains(&numbers_aside(line)),
            "docs/check.md shows `{line}`, which {test} does not print:\n{printed}"
        );
    }
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
    let dir = crate::support::folder("check", "book");
    let out = check_slave(&slave.link, &["--record-dir", dir.to_str().unwrap()]);
    assert_eq!(comparable(&text(&out)), comparable(shown));
}

/// A JUnit file as a JUnit reader sees it (Python's XML parser, which
/// refuses a badly escaped file): the suite's counts and every case, a
/// failure's or an error's message and text.
pub(crate) fn junit_read(path: &Path) -> serde_json::Value {
    let script = r#"
import json, sys, xml.etree.ElementTree as ET
root = ET.parse(sys.argv[1]).getroot()
suite = root.find("testsuite")
cases = []
for c in suite.findall("testcase"):
    f = c.find("failure")
    if f is None:
        f = c.find("error")
    cases.append({"name": c.get("name"), "classname": c.get("classname"), "time": float(c.get("time")),
                  "message": None if f is None else f.get("message"), "text": None if f is None else f.text})
print(json.dumps({"name": suite.get("name"), "tests": int(suite.get("tests")),
                  "failures": int(suite.get("failures")), "errors": int(suite.get("errors")), "time": float(suite.get("time")), "cases": cases}))
"#;
    let out = Command::new("python3")
        .args(["-c", script])
        .arg(path)
        .output()
        .expect("python3 runs");
    assert!(out.status.success(), "{}", text(&out));
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn the_junit_report_counts_the_checks_and_holds_a_failures_frames() {
    let junit = scratch("check", "broadcast.junit.xml");
    let slave = student("junit", &["answers-broadcast"]);
    let out = check_slave(&slave.link, &["--junit", junit.to_str().unwrap()]);
    assert!(!out.status.success(), "{}", text(&out));
    let read = junit_read(&junit);
    assert_eq!(read["name"], "MEB slave");
    // The bench checks are there too, skipped: no --bench.
    assert_eq!(read["tests"], 31);
    assert_eq!(read["failures"], 1, "{}", text(&out));
    assert!(
        read["time"].as_f64().unwrap() > 0.3,
        "the silences alone take longer"
    );
    let cases = read["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 31);
    let failed: Vec<_> = cases.iter().filter(|c| !c["message"].is_null()).collect();
    assert_eq!(failed.len(), 1);
    let case = failed[0];
    assert_eq!(case["name"], "a broadcast write (id 00) is not answered");
    assert_eq!(case["classname"], "MEB page, Data model and commands");
    assert!(
        case["time"].as_f64().unwrap() >= 0.15,
        "it waits 150 ms: {case}"
    );
    assert_eq!(
        case["message"],
        "answered `@01SD000157*\\n` where it must stay silent for 150 ms"
    );
    let frames = case["text"].as_str().unwrap();
    assert!(
        frames.contains(" s  sent      @00SD0001001F21*\\n\n"),
        "{frames}"
    );
    assert!(
        frames.contains(" s  received  @01SD000157*\\n\n"),
        "{frames}"
    );
}

/// A teacher's suite whose failing check sends markup and ampersands: the
/// page and the XML show them as sent, escaped.
#[test]
fn markup_from_the_suite_and_the_wire_is_escaped_in_the_page_and_the_xml() {
    let suite = scratch("check", "markup.toml");
    std::fs::write(
        &suite,
        r#"name = "Tags & <b>bold</b>"
protocol = "meb"

[[check]]
name = "reads the status word"
requirement = "MEB page"
steps = [{ send = "@{id}FD0001" }, { expect = "@{id}FD0001", words = 1 }]

[[check]]
name = "reads <EA> & more"
requirement = 'M3CVME paper, Table "3"'
points = 3
steps = [
  { raw = "<b>&amp;'x'</b>\n" },
  { send = "@{id}EA0001" },
  { expect = "@{id}EA0002", words = 1 },
]
"#,
    )
    .unwrap();
    let (html, junit) = (
        scratch("check", "markup.html"),
        scratch("check", "markup.xml"),
    );
    let slave = student("markup", &[]);
    let out = check_slave(
        &slave.link,
        &[
            "--suite",
            suite.to_str().unwrap(),
            "--html",
            html.to_str().unwrap(),
            "--junit",
            junit.to_str().unwrap(),
        ],
    );
    assert!(!out.status.success(), "{}", text(&out));
    let page = std::fs::read_to_string(&html).unwrap();
    assert!(page.starts_with("<!DOCTYPE html>"), "{page}");
    assert!(
        !page.contains("src=") && !page.contains("href="),
        "self-contained: {page}"
    );
    assert!(
        page.contains("Score: 1 of 4 points (1 of 2 checks passed)"),
        "{page}"
    );
    assert!(
        page.contains("<h1>Tags &amp; &lt;b&gt;bold&lt;/b&gt; on tcp://"),
        "{page}"
    );
    assert!(page.contains("reads &lt;EA&gt; &amp; more"), "{page}");
    assert!(page.contains("M3CVME paper, Table &quot;3&quot;"), "{page}");
    assert!(
        page.contains(" s  sent      &lt;b&gt;&amp;amp;&#39;x&#39;&lt;/b&gt;\\n\n"),
        "{page}"
    );
    assert!(page.contains("the reply was `@01EA0001"), "{page}");
    assert!(
        !page.contains("<b>&amp;") && !page.contains("<EA>"),
        "{page}"
    );

    let read = junit_read(&junit);
    assert_eq!(read["name"], "Tags & <b>bold</b>");
    assert_eq!(
        (read["tests"].as_u64(), read["failures"].as_u64()),
        (Some(2), Some(1))
    );
    let case = &read["cases"][1];
    assert_eq!(case["name"], "reads <EA> & more");
    assert_eq!(case["classname"], "M3CVME paper, Table \"3\"");
    assert!(
        case["text"]
            .as_str()
            .unwrap()
            .contains("sent      <b>&amp;'x'</b>\\n\n"),
        "{case}"
    );
}
