//! Reference students as Arduino sketches, written outside the twin's own
//! code: `firmware/student-meb-slave` (an MEB slave of the EV module) and
//! `firmware/student-motor-nano` (the Controller_network motor node on the
//! 8-byte Modbus), each built correct and once per planted bug (`-DBUG_…`),
//! run in simavr by `twin-avr serve --firmware` on a pseudo-terminal and
//! checked there by `twin-avr check slave` (`twin check slave` itself) with
//! the built-in suite of its protocol. The correct builds pass every check;
//! each buggy build fails exactly the checks its bug explains, and nothing
//! else. The variants run three at a time, each in its own server.
//!
//! The MEB slave is also checked on its bench (`serve --web`, `check
//! --bench` with an Arduino's 10-bit ADC and PWM): built correct it passes
//! the bench checks too, and a build whose frames are right but whose I/O
//! is wrong (FR on a pin the bench leaves unwired, V1 and V2 read from each
//! other's inputs) fails exactly the bench checks of that meaning.

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
    /// Checked on its bench: the server's panel given to `--bench`.
    bench: bool,
}

/// The panel's URL, as the server printed it before `ready`.
fn panel_of(head: &str) -> String {
    head.lines()
        .find_map(|l| l.strip_prefix("panel: "))
        .and_then(|l| l.split_whitespace().next())
        .unwrap_or_else(|| panic!("no panel line printed: {head}"))
        .to_string()
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
    if student.bench {
        args.extend(["--web", "127.0.0.1:0"]);
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
    // An Arduino's converters: its 10-bit ADC, and VEL on Timer1's 10-bit PWM.
    let bench = if student.bench {
        vec![
            "--bench".to_string(),
            panel_of(&head),
            "--adc-bits".into(),
            "10".into(),
            "--vel-bits".into(),
            "10".into(),
        ]
    } else {
        vec![]
    };
    let out = Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args(["check", "slave", &a_s, "--no-record"])
        .args(&bench)
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
    let with_result = |wanted: &str| -> Vec<String> {
        run["checks"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|c| c["result"] == wanted)
            .map(|c| c["name"].as_str().unwrap().to_string())
            .collect()
    };
    let failed = with_result("fail");
    if student.bench {
        // On its bench every check applies.
        assert_eq!(
            with_result("not applicable"),
            Vec::<String>::new(),
            "{name}:\n{report}"
        );
    }
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
        bench: false,
    }
}

/// The MEB slave on its bench.
fn meb_on_bench(tag: &'static str, define: &'static str, expected: Vec<String>) -> Student {
    Student {
        bench: true,
        ..meb(tag, define, expected)
    }
}

fn motor(tag: &'static str, define: &'static str, expected: Vec<String>) -> Student {
    Student {
        tag,
        sketch: "student-motor-nano",
        define,
        link: "--modbus8",
        board: "motor=",
        // The twin's own light node is node 02 on the line: it answers at
        // once, long before the sketch, which simavr runs slower than
        // real time, and the suite holds each node to the order of its
        // own requests alone.
        beside: &[],
        suite: "modbus8-slave",
        expected,
        timeout_ms: TIMEOUT_MS,
        bench: false,
    }
}

fn names(names: &[&str]) -> Vec<String> {
    names.iter().map(|n| n.to_string()).collect()
}

/// Builds the students one after another (the builds would only share two
/// cores), checks them AT_ONCE at a time, the longest runs first (a failed
/// check waits 3 s for a late reply): each sketch is a core run in real
/// time, and more of them than a loaded machine can run would answer later
/// than the checker waits.
fn check_all(students: &[Student]) -> Vec<Checked> {
    let built: Vec<PathBuf> = students.iter().map(build).collect();
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
    checked
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
    let checked = check_all(&students);
    let fcs = &checked[5];
    assert!(fcs.report.contains("its FCS is `"), "{}", fcs.report);
    let crc = &checked[7];
    assert!(
        crc.report.contains("the two bytes swapped"),
        "{}",
        crc.report
    );
}

#[test]
fn the_student_slave_on_its_bench_passes_and_each_meaning_bug_fails_its_bench_check_alone() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let students = [
        meb_on_bench("bench-correct", "", vec![]),
        // D10, FR's pin, left an input: the module's input pulls it up, so
        // the motor turns counter-clockwise whatever FR says. Every check
        // that turns it clockwise fails; the one that turns it
        // counter-clockwise passes.
        meb_on_bench(
            "fr-wrong-pin",
            "BUG_FR_WRONG_PIN",
            names(&[
                "VEL with EN on turns the motor clockwise at the plant's speed for it (SA 00, SD 00)",
                "EN off stops driving the motor: the wheel coasts (SD 00 bit 0)",
                "BRK brakes the wheel: it slows faster than coasting (SD 00 bit 1)",
                "RPM_M and RPM_L read the wheel's speed (EA 03-04, RPM_WIN 500 ms)",
            ]),
        ),
        meb_on_bench(
            "v1-v2-swapped",
            "BUG_V1_V2_SWAPPED",
            names(&[
                "the analog inputs read the plant within the ADC's resolution, the wheel braked at rest (EA 00-05)",
            ]),
        ),
    ];
    let checked = check_all(&students);
    let fr = &checked[1].report;
    assert!(
        fr.contains("the plant turns the motor counter-clockwise (FR as the plant sees it) where FR was written clockwise"),
        "{fr}"
    );
    let swapped = &checked[2].report;
    assert!(
        swapped.contains("V2 read ") && swapped.contains("; the bus at "),
        "{swapped}"
    );
    assert!(
        checked[0]
            .report
            .contains("(the slave's ADC 10 bits, VEL 10 bits)"),
        "{}",
        checked[0].report
    );
}
