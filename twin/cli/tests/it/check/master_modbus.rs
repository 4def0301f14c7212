//! `twin check master` with the Modbus suites: masters nobody here wrote
//! (mbpoll, a pymodbus client) pass `modbus-rtu-master` on a
//! pseudo-terminal and `modbus-tcp-master` with nothing reported; a
//! student's RTU master written with raw pyserial passes, and each bug
//! planted in it is found and nothing else; the Controller_network
//! project's master passes `modbus8-master`, and its planted bugs are
//! found. These fail, rather than skip, when mbpoll or pymodbus is missing
//! (`.ci/install` installs them).

use super::failed;
use crate::peers::PtyPair;
use crate::support::{folder, host_port, scratch, text, twin};
use rustix::fs::OFlags;
use std::io::{BufRead, BufReader, Read};
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};

/// A master program, killed when dropped.
struct Master(Child);

impl Master {
    fn start(program: &str, args: &[&str]) -> Self {
        let child = Command::new(program)
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("{program} runs (.ci/install installs it): {e}"));
        Master(child)
    }
}

impl Drop for Master {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn peer(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/peers")
        .join(name)
        .to_str()
        .unwrap()
        .to_string()
}

/// `twin check master LINK --suite SUITE` and more, with a JSON report
/// whose failed checks are returned with what was printed.
fn check_master(name: &str, link: &str, suite: &str, more: &[&str]) -> (Output, Vec<String>) {
    let json = scratch("check-master", &format!("{name}.json"));
    let _ = std::fs::remove_file(&json);
    let mut args = vec![
        "check",
        "master",
        link,
        "--suite",
        suite,
        "--json",
        json.to_str().unwrap(),
    ];
    args.extend_from_slice(more);
    let out = twin(&args);
    let failed = if json.exists() {
        failed(&json)
    } else {
        vec![format!("no report: {}", text(&out))]
    };
    (out, failed)
}

fn passes(name: &str, out: &Output, failed: &[String]) {
    let printed = text(out);
    assert!(out.status.success(), "{name}: {printed}");
    assert_eq!(failed, Vec::<String>::new(), "{name}: {printed}");
    assert!(printed.contains("score: "), "{printed}");
}

#[test]
fn mbpoll_as_an_rtu_master_passes_with_nothing_reported() {
    let pair = PtyPair::new(&folder("check-master", "mbpoll-rtu"));
    let device = pair.a.to_str().unwrap();
    let _mbpoll = Master::start(
        "mbpoll",
        &[
            "-m", "rtu", "-a", "1", "-b", "115200", "-P", "none", "-t", "4", "-r", "1", "-c", "4",
            device,
        ],
    );
    let (out, failed) = check_master(
        "mbpoll-rtu",
        pair.b.to_str().unwrap(),
        "modbus-rtu-master",
        &[],
    );
    passes("mbpoll", &out, &failed);
    // mbpoll reads four holding registers; the map has three: said, not graded.
    let printed = text(&out);
    assert!(printed.contains("got exception 02"), "{printed}");
    super::held_to_the_book(
        "check::master_modbus's mbpoll_as_an_rtu_master",
        &printed.replace(pair.b.to_str().unwrap(), "/tmp/ttyV1"),
    );
}

#[test]
fn a_pymodbus_client_as_an_rtu_master_passes_with_nothing_reported() {
    let pair = PtyPair::new(&folder("check-master", "pymodbus-rtu"));
    let _client = Master::start(
        "python3",
        &[
            &peer("pymodbus_polling_master.py"),
            "rtu",
            pair.a.to_str().unwrap(),
        ],
    );
    let (out, failed) = check_master(
        "pymodbus-rtu",
        pair.b.to_str().unwrap(),
        "modbus-rtu-master",
        &[],
    );
    passes("pymodbus", &out, &failed);
}

const WELL_FORMED: &str = "polls every slave with well-formed requests, one at a time";
const SLOW: &str =
    "waits for a slow reply (300 ms, within the timeout) and sends nothing before it";
const SILENT: &str = "gives up on a slave that does not answer, and polls the others meanwhile";

#[test]
fn a_students_rtu_master_passes_and_each_planted_bug_is_found_and_nothing_else() {
    let cases: [(Option<&str>, &[&str]); 4] = [
        (None, &[]),
        (Some("crc-swapped"), &[WELL_FORMED]),
        (Some("never-times-out"), &[SILENT]),
        (Some("floods"), &[WELL_FORMED, SLOW]),
    ];
    std::thread::scope(|scope| {
        for (bug, expected) in cases {
            scope.spawn(move || {
                let name = format!("student-rtu-{}", bug.unwrap_or("correct"));
                let pair = PtyPair::new(&folder("check-master", &name));
                let mut args = vec![
                    peer("modbus_student_master.py"),
                    pair.a.to_str().unwrap().to_string(),
                    "--id".into(),
                    "1,2".into(),
                ];
                if let Some(bug) = bug {
                    args.extend(["--bug".to_string(), bug.to_string()]);
                }
                let args: Vec<&str> = args.iter().map(String::as_str).collect();
                let _student = Master::start("python3", &args);
                let (out, failed) = check_master(
                    &name,
                    pair.b.to_str().unwrap(),
                    "modbus-rtu-master",
                    &["--id", "1,2"],
                );
                let printed = text(&out);
                assert_eq!(
                    out.status.success(),
                    expected.is_empty(),
                    "{name}: {printed}"
                );
                assert_eq!(failed, expected, "{name}: {printed}");
            });
        }
    });
}

#[test]
fn mbpoll_and_pymodbus_as_tcp_masters_pass_with_nothing_reported() {
    std::thread::scope(|scope| {
        for who in ["mbpoll", "pymodbus"] {
            scope.spawn(move || {
                let json = scratch("check-master", &format!("{who}-tcp.json"));
                let _ = std::fs::remove_file(&json);
                // The check listens on a port of its own and says which.
                let mut check = Command::new(env!("CARGO_BIN_EXE_twin"))
                    .args(["check", "master", "tcp://127.0.0.1:0"])
                    .args(["--suite", "modbus-tcp-master", "--json"])
                    .arg(&json)
                    .stdout(Stdio::piped())
                    .stderr(Stdio::piped())
                    .spawn()
                    .expect("twin runs");
                let mut stderr = BufReader::new(check.stderr.take().unwrap());
                let mut said = String::new();
                let port = loop {
                    let mut line = String::new();
                    assert!(stderr.read_line(&mut line).unwrap() > 0, "{said}");
                    said.push_str(&line);
                    if let Some(link) = line.trim().rsplit(' ').next()
                        && link.starts_with("tcp://")
                    {
                        break host_port(link).rsplit(':').next().unwrap().to_string();
                    }
                };
                let _master = if who == "mbpoll" {
                    Master::start(
                        "mbpoll",
                        &[
                            "-m",
                            "tcp",
                            "-a",
                            "1",
                            "-t",
                            "3",
                            "-r",
                            "1",
                            "-c",
                            "4",
                            "-p",
                            &port,
                            "127.0.0.1",
                        ],
                    )
                } else {
                    let script = peer("pymodbus_polling_master.py");
                    Master::start("python3", &[&script, "tcp", "127.0.0.1", &port])
                };
                let out = check.wait_with_output().unwrap();
                let mut rest = String::new();
                let _ = stderr.read_to_string(&mut rest);
                let printed = format!("{}{said}{rest}", String::from_utf8_lossy(&out.stdout));
                assert!(out.status.success(), "{who}: {printed}");
                assert_eq!(failed(&json), Vec::<String>::new(), "{who}: {printed}");
            });
        }
    });
}

/// The master's end of `pair`, held open: the Controller_network master
/// closes its end after every transaction, and holding it here too keeps
/// socat from seeing a hang-up (a real port has no such problem).
fn hold_open(path: &Path) -> std::fs::File {
    std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(OFlags::NOCTTY.bits() as i32)
        .open(path)
        .expect("open the master's end")
}

#[test]
fn the_controller_network_master_passes_the_eight_byte_suite_and_its_planted_bugs_are_found() {
    let cases: [(Option<&str>, &[&str]); 3] = [
        (None, &[]),
        (
            Some("crc-low-first"),
            &["polls both nodes with well-formed 8-byte requests, one at a time"],
        ),
        (
            Some("wrong-function"),
            &["polls both nodes with well-formed 8-byte requests, one at a time"],
        ),
    ];
    std::thread::scope(|scope| {
        for (bug, expected) in cases {
            scope.spawn(move || {
                let name = format!("controller-network-{}", bug.unwrap_or("correct"));
                let pair = PtyPair::new(&folder("check-master", &name));
                let _held = hold_open(&pair.a);
                let mut args = vec![
                    peer("controller_network_master.py"),
                    pair.a.to_str().unwrap().to_string(),
                    "100000".into(),
                    "30".into(),
                ];
                if let Some(bug) = bug {
                    args.push(bug.to_string());
                }
                let args: Vec<&str> = args.iter().map(String::as_str).collect();
                let _master = Master::start("python3", &args);
                let (out, failed) =
                    check_master(&name, pair.b.to_str().unwrap(), "modbus8-master", &[]);
                let printed = text(&out);
                assert_eq!(
                    out.status.success(),
                    expected.is_empty(),
                    "{name}: {printed}"
                );
                assert_eq!(failed, expected, "{name}: {printed}");
                // By design it blocks until a reply comes: the suite says so.
                assert!(!printed.contains("does not answer"), "{printed}");
            });
        }
    });
}
