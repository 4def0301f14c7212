//! Reference students as Arduino sketches, written outside the twin's own
//! code: `firmware/student-meb-slave` (an MEB slave of the EV module) and
//! `firmware/student-motor-nano` (the Controller_network motor node on the
//! 8-byte Modbus), each built correct and once per planted bug (`-DBUG_…`),
//! run in simavr by `twin-avr serve --firmware` on a pseudo-terminal and
//! checked there by `twin-avr check slave` (`twin check slave` itself) with
//! the built-in suite of its protocol. The correct builds pass every check;
//! each buggy build fails exactly the checks its bug explains, and nothing
//! else. The variants run three at a time, each in its own server.

use crate::common;
use crate::serve_boards::{ONE_AT_A_TIME, scratch, stop, wait_ready};

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// How many sketches are served and checked at once.
const AT_ONCE: usize = 3;
/// How long a sketch must stay silent where the suite requires silence.
const SILENCE_MS: u64 = 2000;
/// How long a reply is waited for: a loaded machine (two cores, a load of
/// 19) once ran a sketch's reply 1.5 s late.
const TIMEOUT_MS: u64 = 3000;
/// The same for a sketch whose every reply is wrong: each check with a
/// reply fails, late or not, and a failed check waits three times as long
/// again for a late reply.
const TIMEOUT_WRONG_REPLIES_MS: u64 = 1000;

/// A built-in suite as shipped: the checks a planted bug may fail are
/// named from it.
fn suite(name: &str) -> toml::Table {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../check/suites/{name}.toml"));
    toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// The names of the suite's checks with a step that expects a reply (a
/// frame, an error reply or an exception) from a slave `from` accepts by
/// the id of the request it answers (MEB: `{id}`; 8-byte Modbus: `01`),
/// bench checks aside.
fn checks_with_a_reply(suite_name: &str, from: impl Fn(&str) -> bool) -> Vec<String> {
    suite(suite_name)["check"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| {
            let steps = c["steps"].as_array().unwrap();
            // A bench check is not applicable here (no --bench): never failed.
            if steps
                .iter()
                .any(|s| s.as_table().unwrap().contains_key("bench"))
            {
                return false;
            }
            let mut sent = String::new();
            steps.iter().any(|s| {
                let s = s.as_table().unwrap();
                if let Some(body) = s.get("send").and_then(|b| b.as_str()) {
                    sent = body.to_string();
                }
                (s.contains_key("expect") || s.contains_key("error") || s.contains_key("exception"))
                    && from(s.get("expect").and_then(|e| e.as_str()).unwrap_or(&sent))
            })
        })
        .map(|c| c["name"].as_str().unwrap().to_string())
        .collect()
}

fn twin_avr(args: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("twin-avr starts")
}

/// A process killed when the check is over, or when it panicked.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn wait_for(path: &Path) {
    let until = Instant::now() + Duration::from_secs(20);
    while !path.exists() {
        assert!(Instant::now() < until, "{} never appeared", path.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// What `twin-avr check slave` made of one sketch: the names of the checks
/// that failed, and its printed report.
struct Checked {
    failed: Vec<String>,
    report: String,
}

/// The built-in suite `name` with its silences lengthened from 150 ms to
/// SILENCE_MS, written into `dir`. A sketch in simavr on a loaded machine
/// runs behind the wall clock (the server's clock slips, and the sketch's
/// with it), so a buggy sketch's reply where silence is due may come after
/// the suite's 150 ms, unseen; every check and its verdict are the suite's
/// own.
fn patient_suite(name: &str, dir: &Path) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../check/suites/{name}.toml"));
    let text = std::fs::read_to_string(path).unwrap();
    assert!(
        text.contains("silence_ms = 150"),
        "{name}: its silences changed"
    );
    let file = dir.join(format!("{name}.toml"));
    std::fs::write(
        &file,
        text.replace("silence_ms = 150", &format!("silence_ms = {SILENCE_MS}")),
    )
    .unwrap();
    file
}

/// One sketch to check: served on `link` (`--meb`, `--modbus8`) with
/// `--firmware` `board` (`FILE`, `motor=FILE`) and the shipped sketches
/// `beside` on the same line (`light=light-nano`), checked with `suite`.
struct Student {
    tag: &'static str,
    sketch: &'static str,
    define: &'static str,
    link: &'static str,
    board: &'static str,
    beside: &'static [(&'static str, &'static str)],
    suite: &'static str,
    /// The checks its bug explains, in the suite's order.
    expected: Vec<String>,
    /// `--timeout-ms`.
    timeout_ms: u64,
}

/// The student's build served on one end of a vsp pair, checked on the
/// other end; the sketch given seconds to answer, and to stay silent (a
/// loaded test machine runs it late: what is checked here is its logic).
fn check(student: &Student, elf: &Path) -> Checked {
    let name = format!("{} {}", student.sketch, student.tag);
    let dir = scratch(&format!("{}-{}", student.sketch, student.tag));
    let (a, b) = (dir.join("ttyV0"), dir.join("ttyV1"));
    let (a_s, b_s) = (a.display().to_string(), b.display().to_string());
    let mut vsp = twin_avr(&["vsp", &a_s, &b_s]);
    // Its stdout stays open while it runs: it prints as the ends open and close.
    let (_vsp_out, _) = wait_ready(&mut vsp);
    let _vsp = Killed(vsp);
    wait_for(&b);
    let mut firmware = vec![format!("{}{}", student.board, elf.display())];
    let folder = elf.parent().unwrap();
    for (board, sketch) in student.beside {
        firmware.push(format!(
            "{board}={}",
            folder.join(format!("{sketch}.elf")).display()
        ));
    }
    let mut args = vec!["serve", student.link, &b_s];
    for f in &firmware {
        args.extend(["--firmware", f]);
    }
    let mut serve = twin_avr(
        &[
            args.as_slice(),
            &[
                "--duration",
                "120",
                "--no-record",
                "--quiet",
                "--status-every",
                "0",
            ],
        ]
        .concat(),
    );
    let (serve_out, head) = wait_ready(&mut serve);
    assert!(head.contains(&format!("{}.elf", student.sketch)), "{head}");
    let json = dir.join("run.json");
    let out = Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args(["check", "slave", &a_s, "--no-record"])
        .args(["--timeout-ms", &student.timeout_ms.to_string()])
        .arg("--suite")
        .arg(patient_suite(student.suite, &dir))
        .arg("--json")
        .arg(&json)
        .output()
        .expect("twin-avr check runs");
    let rest = stop(serve, serve_out);
    let report = format!(
        "{}{}\n(the server: {rest})",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let run: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&json)
            .unwrap_or_else(|e| panic!("{name}: no report: {e}\n{report}")),
    )
    .unwrap();
    let failed: Vec<String> = run["checks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["result"] == "fail")
        .map(|c| c["name"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(
        out.status.success(),
        failed.is_empty(),
        "{name}: exits 1 when a check fails\n{report}"
    );
    assert!(!rest.contains("marked dead"), "{name}: {rest}");
    let _ = std::fs::remove_dir_all(&dir);
    Checked { failed, report }
}

/// The student's sketch built with its define (none: correct), in a build
/// folder of its own.
fn build(student: &Student) -> PathBuf {
    let defines = if student.define.is_empty() {
        String::new()
    } else {
        format!("-D{}", student.define)
    };
    let mut sketches = vec![student.sketch];
    sketches.extend(student.beside.iter().map(|(_, sketch)| *sketch));
    common::make(
        &format!("{}-{}", student.sketch, student.tag),
        &defines,
        &sketches,
    )
    .join(format!("{}.elf", student.sketch))
}

fn meb(tag: &'static str, define: &'static str, expected: Vec<String>) -> Student {
    Student {
        tag,
        sketch: "student-meb-slave",
        define,
        link: "--meb",
        board: "",
        beside: &[],
        suite: "meb-slave",
        expected,
        timeout_ms: TIMEOUT_MS,
    }
}

fn motor(tag: &'static str, define: &'static str, expected: Vec<String>) -> Student {
    Student {
        tag,
        sketch: "student-motor-nano",
        define,
        link: "--modbus8",
        board: "motor=",
        // The project's own light Nano sketch is node 02 on the line, as
        // on the bench: the twin's own node would answer at once, before
        // a sketch run slower than real time answers a request sent
        // before its own (requests written at once, answered in order).
        beside: &[("light", "light-nano")],
        suite: "modbus8-slave",
        expected,
        timeout_ms: TIMEOUT_MS,
    }
}

fn names(names: &[&str]) -> Vec<String> {
    names.iter().map(|n| n.to_string()).collect()
}

#[test]
fn the_student_sketches_are_checked_and_each_planted_bug_is_found_alone() {
    // Each variant is one more core in real time: none of the other
    // real-time tests at once.
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let meb_replies = checks_with_a_reply("meb-slave", |_| true);
    assert_eq!(meb_replies.len(), 20, "{meb_replies:?}");
    let motor_replies = checks_with_a_reply("modbus8-slave", |b| b.starts_with("01"));
    assert_eq!(motor_replies.len(), 18, "{motor_replies:?}");
    let students = [
        meb("correct", "", vec![]),
        meb(
            "answers-bad-fcs",
            "BUG_ANSWERS_BAD_FCS",
            names(&["a bad FCS gets no reply, and the next good request is answered"]),
        ),
        meb(
            "answers-broadcast",
            "BUG_ANSWERS_BROADCAST",
            names(&[
                "a broadcast write (id 00) is not answered",
                "a broadcast read is not answered",
            ]),
        ),
        meb(
            "no-resync",
            "BUG_NO_RESYNC",
            names(&["a partial frame is dropped at the next @ and the new frame answered"]),
        ),
        meb(
            "wrong-error-code",
            "BUG_WRONG_ERROR_CODE",
            names(&[
                "an address outside the block gets error 02",
                "a range running past the block's end gets error 02",
            ]),
        ),
        // Every reply refused for its FCS; the silences still pass.
        Student {
            timeout_ms: TIMEOUT_WRONG_REPLIES_MS,
            ..meb("fcs-without-at", "BUG_FCS_WITHOUT_AT", meb_replies)
        },
        motor("correct", "", vec![]),
        // Every reply of the motor's refused for its CRC; the light
        // Nano's and the silences still pass.
        Student {
            timeout_ms: TIMEOUT_WRONG_REPLIES_MS,
            ..motor("crc-low-first", "BUG_CRC_LOW_FIRST", motor_replies)
        },
    ];
    // Built one after another (the builds would only share two cores).
    let built: Vec<PathBuf> = students.iter().map(build).collect();
    // Checked AT_ONCE at a time, the longest runs (a failed check waits
    // 3 s for a late reply) first: each sketch is a core run in real time,
    // and more of them than a loaded machine can run would answer later
    // than the checker waits.
    let mut order: Vec<usize> = (0..students.len()).collect();
    order.sort_by_key(|&i| std::cmp::Reverse(students[i].expected.len()));
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<Checked>>> =
        Mutex::new((0..students.len()).map(|_| None).collect());
    let started = Instant::now();
    std::thread::scope(|s| {
        for _ in 0..AT_ONCE {
            s.spawn(|| {
                while let Some(&i) = order.get(next.fetch_add(1, Ordering::SeqCst)) {
                    let run = check(&students[i], &built[i]);
                    results.lock().unwrap()[i] = Some(run);
                }
            });
        }
    });
    let checked: Vec<Checked> = results
        .into_inner()
        .unwrap()
        .into_iter()
        .map(|r| r.expect("every variant checked"))
        .collect();
    eprintln!(
        "{} sketches checked, {AT_ONCE} at once, in {:.1} s",
        checked.len(),
        started.elapsed().as_secs_f64()
    );
    for (student, run) in students.iter().zip(&checked) {
        assert_eq!(
            run.failed, student.expected,
            "{} {}:\n{}",
            student.sketch, student.tag, run.report
        );
    }
    let fcs = &checked[5];
    assert!(fcs.report.contains("its FCS is `"), "{}", fcs.report);
    let crc = &checked[7];
    assert!(
        crc.report.contains("the two bytes swapped"),
        "{}",
        crc.report
    );
}
