//! `twin check slave` with the binary suites: the twin's own slaves pass
//! every check of `modbus-tcp-slave`, `modbus-rtu-slave` (on a
//! pseudo-terminal) and `modbus8-slave`; a slave written with pymodbus, a
//! stack we did not write, passes the Modbus TCP and RTU suites with nothing
//! reported; and each bug planted in it is found, and nothing else.

use super::{check_slave, failed};
use crate::peers::PtyPair;
use crate::support::{Proc, scratch, text};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// `twin serve` with its slaves on `links` (`--modbus tcp://…` and the
/// like), for a minute.
fn serve(links: &[&str]) -> Proc {
    let mut args = vec![
        "serve",
        "--no-record",
        "--quiet",
        "--status-every",
        "0",
        "--duration",
        "120",
    ];
    args.extend_from_slice(links);
    Proc::start(&args)
}

/// The suite's score line said every check passed, and nothing failed.
fn passes_every_check(suite: &str, link: &str) {
    let json = scratch("check-modbus", &format!("{suite}.json"));
    let out = check_slave(link, &["--suite", suite, "--json", json.to_str().unwrap()]);
    let shown = text(&out);
    assert!(out.status.success(), "{shown}");
    assert_eq!(failed(&json), Vec::<String>::new(), "{shown}");
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    // The bench checks are not applicable here (no --bench): not scored.
    let checks = run["checks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["result"] != "not applicable")
        .count();
    assert!(checks > 20, "{suite}: {checks} checks");
    assert!(
        shown.contains(&format!(
            "score: {0} of {0} points ({checks} of {checks} checks passed)",
            run["points"]
        )),
        "{shown}"
    );
}

#[test]
fn the_twins_own_modbus_tcp_server_passes_every_check() {
    let serve = serve(&["--modbus", "tcp://127.0.0.1:0"]);
    let link = format!("tcp://{}", serve.tcp_of("modbus-tcp"));
    passes_every_check("modbus-tcp-slave", &link);
    // Its recording reads back as Modbus TCP, not as MEB gone wrong.
    let mcap = scratch("check-modbus", "modbus-tcp-slave.mcap");
    let out = check_slave(
        &link,
        &[
            "--suite",
            "modbus-tcp-slave",
            "--record",
            mcap.to_str().unwrap(),
        ],
    );
    assert!(out.status.success(), "{}", text(&out));
    let recorded = super::recorded::read(&mcap);
    let frames = recorded["frames"].as_array().unwrap();
    assert!(!frames.is_empty(), "{recorded}");
    assert_eq!(frames[0]["protocol"], "modbus-tcp", "{}", frames[0]);
    serve.terminate();
}

#[test]
fn the_twins_own_modbus_rtu_slave_on_a_pty_passes_every_check() {
    let dir = crate::support::folder("check-modbus", "rtu");
    let pair = PtyPair::new(&dir);
    let serve = serve(&["--modbus-rtu", pair.a.to_str().unwrap()]);
    passes_every_check("modbus-rtu-slave", pair.b.to_str().unwrap());
    serve.terminate();
}

#[test]
fn the_twins_own_eight_byte_modbus_nodes_pass_every_check() {
    let dir = crate::support::folder("check-modbus", "modbus8");
    let pair = PtyPair::new(&dir);
    let serve = serve(&["--modbus8", pair.a.to_str().unwrap()]);
    passes_every_check("modbus8-slave", pair.b.to_str().unwrap());
    serve.terminate();
}

/// Whether pymodbus can be imported; if not, why the test skips.
fn pymodbus_missing() -> Option<String> {
    let out = Command::new("python3")
        .args(["-c", "import pymodbus"])
        .output();
    match out {
        Ok(o) if o.status.success() => None,
        Ok(o) => Some(String::from_utf8_lossy(&o.stderr).trim().to_string()),
        Err(e) => Some(format!("python3 cannot be run: {e}")),
    }
}

/// The pymodbus student's slave with `bugs` planted: over TCP on a free
/// port, or over RTU on one end of a pty pair whose other end is `link`.
struct Student {
    child: Child,
    link: String,
    _pair: Option<PtyPair>,
}

impl Drop for Student {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/pymodbus_student_slave.py")
}

fn student(framing: &str, name: &str, bugs: &[&str]) -> Student {
    let mut command = Command::new("python3");
    command.arg(script()).arg(framing);
    let (pair, target) = if framing == "tcp" {
        let port_file = scratch("check-modbus", &format!("{name}.port"));
        let _ = std::fs::remove_file(&port_file);
        (None, port_file)
    } else {
        let pair = PtyPair::new(&crate::support::folder("check-modbus", name));
        let a = pair.a.clone();
        (Some(pair), a)
    };
    command.arg(&target);
    for bug in bugs {
        command.args(["--bug", bug]);
    }
    let mut child = command
        .stdout(Stdio::piped())
        .spawn()
        .expect("python3 runs");
    let link = match &pair {
        None => {
            let deadline = Instant::now() + Duration::from_secs(20);
            let port = loop {
                if let Ok(port) = std::fs::read_to_string(&target) {
                    break port;
                }
                assert!(
                    Instant::now() < deadline,
                    "the pymodbus slave never listened"
                );
                std::thread::sleep(Duration::from_millis(20));
            };
            format!("tcp://127.0.0.1:{}", port.trim())
        }
        Some(pair) => {
            use std::io::BufRead;
            let mut line = String::new();
            let stdout = child.stdout.as_mut().expect("stdout");
            let _ = std::io::BufReader::new(stdout).read_line(&mut line);
            assert_eq!(line.trim(), "serving", "the pymodbus slave opened its port");
            pair.b.to_str().unwrap().to_string()
        }
    };
    Student {
        child,
        link,
        _pair: pair,
    }
}

/// The checks of `suite` whose run failed against the student with `bugs`.
fn failures(framing: &str, suite: &str, name: &str, bugs: &[&str]) -> (Vec<String>, String) {
    let slave = student(framing, name, bugs);
    let json = scratch("check-modbus", &format!("{name}.json"));
    let out = check_slave(
        &slave.link,
        &["--suite", suite, "--json", json.to_str().unwrap()],
    );
    let shown = text(&out);
    assert_eq!(
        out.status.success(),
        bugs.is_empty(),
        "{name}: the exit status says whether a check failed\n{shown}"
    );
    (failed(&json), shown)
}

#[test]
fn a_pymodbus_slave_passes_the_modbus_tcp_and_rtu_suites() {
    if let Some(why) = pymodbus_missing() {
        println!("skipped: pymodbus is missing ({why}); .ci/install installs it");
        return;
    }
    for (framing, suite) in [("tcp", "modbus-tcp-slave"), ("rtu", "modbus-rtu-slave")] {
        let (fails, shown) = failures(framing, suite, &format!("pymodbus-{framing}"), &[]);
        assert_eq!(fails, Vec::<String>::new(), "{shown}");
        assert!(!shown.contains("FAIL"), "{shown}");
    }
}

const BAD_ADDRESS: [&str; 5] = [
    "an address past the input registers (10) gets exception 02",
    "a read running past the holding registers' end gets exception 02",
    "a write to a hole in the coils (6) gets exception 02",
    "a write past the holding registers (3) gets exception 02",
    "a read of 125 input registers, the most a request may ask, gets exception 02 (there are ten)",
];

#[test]
fn each_bug_planted_in_the_pymodbus_slave_is_found_and_nothing_else() {
    if let Some(why) = pymodbus_missing() {
        println!("skipped: pymodbus is missing ({why}); .ci/install installs it");
        return;
    }
    let cases: [(&str, &str, &[&str]); 6] = [
        (
            "rtu",
            "answers-bad-crc",
            &["a bad CRC gets no reply, and the next good request is answered"],
        ),
        (
            "rtu",
            "answers-broadcast",
            &[
                "a broadcast write (unit 0) is carried out and not answered",
                "a broadcast read is not answered",
            ],
        ),
        ("rtu", "wrong-exception-code", &BAD_ADDRESS),
        (
            "tcp",
            "wrong-exception-code",
            &[
                BAD_ADDRESS[0],
                BAD_ADDRESS[1],
                BAD_ADDRESS[2],
                BAD_ADDRESS[3],
                BAD_ADDRESS[4],
                // Its last request is one past the holding registers.
                "requests back to back, each sent as its reply comes, are answered with their transaction ids",
            ],
        ),
        (
            "rtu",
            "no-range-check",
            &[
                "VEL above 12 bits (4096) gets exception 03",
                "an RPM_WIN of 0 ms gets exception 03",
            ],
        ),
        (
            "tcp",
            "no-range-check",
            &[
                "VEL above 12 bits (4096) gets exception 03",
                "an RPM_WIN of 0 ms gets exception 03",
            ],
        ),
    ];
    // Each student waits on its own line: they are checked side by side.
    std::thread::scope(|scope| {
        for (framing, bug, expected) in cases {
            scope.spawn(move || {
                let suite = format!("modbus-{framing}-slave");
                let name = format!("{framing}-{bug}");
                let (fails, shown) = failures(framing, &suite, &name, &[bug]);
                assert_eq!(fails, expected, "{name}: {shown}");
            });
        }
        // Replies whose CRC is high byte first, or whose transaction id is
        // not the request's: every check with a reply in it fails for
        // that reason, the silent ones pass.
        scope.spawn(|| {
            let (fails, shown) = failures(
                "rtu",
                "modbus-rtu-slave",
                "rtu-swapped",
                &["crc-byte-order-swapped"],
            );
            let silent = [
                "a request for another unit gets no reply",
                "a broadcast read is not answered",
            ];
            assert!(
                !fails.iter().any(|f| silent.contains(&f.as_str())),
                "{shown}"
            );
            assert_eq!(fails.len(), 29 - silent.len(), "{shown}");
            assert_eq!(
                shown
                    .matches("(the two bytes swapped: Modbus RTU sends the CRC's low byte first)")
                    .count(),
                fails.len(),
                "{shown}"
            );
        });
        scope.spawn(|| {
            let (fails, shown) = failures(
                "tcp",
                "modbus-tcp-slave",
                "tcp-transaction",
                &["wrong-transaction-id"],
            );
            assert_eq!(fails.len(), 25, "every check has a reply: {shown}");
            assert_eq!(
                shown
                    .matches("carries transaction id 0000; the request's was")
                    .count(),
                25,
                "{shown}"
            );
        });
    });
}

/// The book's Modbus report is the program's: every line it shows, in
/// order, and every failure the program reports.
#[test]
fn the_books_modbus_report_is_what_twin_check_prints() {
    if let Some(why) = pymodbus_missing() {
        println!("skipped: pymodbus is missing ({why}); .ci/install installs it");
        return;
    }
    let page =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/check.md"))
            .unwrap();
    let start = page
        .find("```text\nModbus TCP slave suite")
        .expect("the Modbus report on the page")
        + 8;
    let shown = super::comparable(&page[start..start + page[start..].find("\n```").unwrap()]);
    let slave = student("tcp", "book", &["no-range-check"]);
    let out = check_slave(&slave.link, &["--suite", "modbus-tcp-slave"]);
    let printed = super::comparable(&text(&out));
    let mut rest = printed.iter();
    for line in &shown {
        assert!(
            rest.any(|l| l == line),
            "the page's line {line:?} is not in what the program printed, in order:\n{}",
            printed.join("\n")
        );
    }
    let failures = |lines: &[String]| lines.iter().filter(|l| l.contains("FAIL")).count();
    assert_eq!(
        failures(&shown),
        failures(&printed),
        "{}",
        printed.join("\n")
    );
}
