//! `twin-avr serve` with sketches in real time, against real masters in
//! processes of their own: the Controller_network Nanos (motor-nano and
//! light-nano, both in one server) answering a master that behaves like
//! that project's Raspberry Pi (write 8 bytes, wait 100 ms, read once) over
//! a crossed pair of pseudo-terminals; a sketch that never answers marked
//! dead while the other board (the twin's own motor node) goes on; the
//! motor Nano's naive-receive test sketch answering a master started after
//! `ready`; the EV sketch over TCP answering
//! every request of a client that sends ten at once, in order.

use crate::common;

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use serde_json::Value;

/// Two sketches in real time take most of a core: one test at a time.
pub(crate) static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

pub(crate) fn sketches() -> PathBuf {
    common::make(
        "serve-boards",
        "",
        &[
            "motor-nano",
            "motor-nano-naive",
            "light-nano",
            "mute",
            "ev-controller",
        ],
    )
}

pub(crate) fn scratch(name: &str) -> PathBuf {
    let dir =
        PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn twin_avr(args: &[&str]) -> Child {
    twin_avr_with(args, Stdio::null())
}

/// `twin-avr ARGS` whose console reads `stdin`.
fn twin_avr_with(args: &[&str], stdin: Stdio) -> Child {
    Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args(args)
        .stdin(stdin)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("twin-avr starts")
}

/// Reads `child`'s stdout up to its `ready` line; the lines before it.
pub(crate) fn wait_ready(child: &mut Child) -> (BufReader<std::process::ChildStdout>, String) {
    let mut out = BufReader::new(child.stdout.take().expect("stdout"));
    let mut seen = String::new();
    let mut line = String::new();
    while out.read_line(&mut line).expect("reads") > 0 {
        if line.trim() == "ready" {
            return (out, seen);
        }
        seen.push_str(&line);
        line.clear();
    }
    let mut err = String::new();
    let _ = child.stderr.take().map(|mut e| e.read_to_string(&mut err));
    panic!("no `ready` line: {seen}{err}");
}

fn wait_for(path: &Path) {
    let until = Instant::now() + Duration::from_secs(10);
    while !path.exists() {
        assert!(Instant::now() < until, "{} never appeared", path.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Stops `child` with SIGINT (it finishes its recording) and returns the
/// rest of its stdout.
pub(crate) fn stop(mut child: Child, mut out: BufReader<std::process::ChildStdout>) -> String {
    let _ = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status();
    let mut rest = String::new();
    let _ = out.read_to_string(&mut rest);
    let _ = child.wait();
    rest
}

/// The Controller_network master of `twin`'s peer tests: for every
/// transaction it opens the port, writes 8 bytes, waits WAIT_MS, reads once.
pub(crate) fn controller_network_master(device: &Path, cycles: u32, wait_ms: u32) -> Value {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../cli/tests/peers/controller_network_master.py");
    let out: Output = Command::new("python3")
        .arg(script)
        .arg(device)
        .args([cycles.to_string(), wait_ms.to_string()])
        .output()
        .expect("python3 runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "the master failed: {stderr}");
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {stderr}"))
}

/// A vsp pair and `serve --modbus8` on one end with the sketches `boards`
/// (`motor=FILE`, `light=FILE`), recording to `out`.
pub(crate) fn serve_nanos(dir: &Path, boards: &[String], out: &Path) -> (Vsp, Child, String) {
    serve_nanos_with(dir, boards, out, Stdio::null())
}

/// [`serve_nanos`], its console reading `stdin`.
fn serve_nanos_with(
    dir: &Path,
    boards: &[String],
    out: &Path,
    stdin: Stdio,
) -> (Vsp, Child, String) {
    let (a, b) = (dir.join("ttyV0"), dir.join("ttyV1"));
    let mut vsp = twin_avr(&["vsp", &a.display().to_string(), &b.display().to_string()]);
    // Its stdout stays open: it prints as the master opens and closes its end.
    let (vsp_out, _) = wait_ready(&mut vsp);
    let vsp = Vsp {
        child: vsp,
        _out: vsp_out,
    };
    wait_for(&b);
    let mut args = vec![
        "serve".to_string(),
        "--modbus8".into(),
        b.display().to_string(),
        "--duration".into(),
        "60".into(),
        "--out".into(),
        out.display().to_string(),
        "--quiet".into(),
        "--status-every".into(),
        "0".into(),
    ];
    for board in boards {
        args.push("--firmware".into());
        args.push(board.clone());
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let serve = twin_avr_with(&args, stdin);
    (vsp, serve, a.display().to_string())
}

/// The vsp process and its stdout, kept open while it runs.
pub(crate) struct Vsp {
    child: Child,
    /// Held open, never read.
    _out: BufReader<std::process::ChildStdout>,
}

impl Vsp {
    pub(crate) fn kill(&mut self) -> std::io::Result<()> {
        self.child.kill()
    }

    pub(crate) fn wait(&mut self) -> std::io::Result<std::process::ExitStatus> {
        self.child.wait()
    }
}

/// A transaction that went wrong only because a reply came after the
/// master's 2 s (two cores shared by far more work than they have): none
/// in time, another's in this read, or two whole replies in one read.
fn late_symptom(t: &Value) -> bool {
    let p = t["problem"].as_str().unwrap_or("");
    let reply = t["reply"].as_str().unwrap_or("");
    p.starts_with("no reply")
        || p == "reply to another request"
        || (p.ends_with("bytes in the one read")
            && reply.len() > 16
            && reply.len().is_multiple_of(16))
}

fn ints(v: &Value) -> Vec<Option<i64>> {
    v.as_array().unwrap().iter().map(Value::as_i64).collect()
}

// Both sketches are held to every request: a board marked dead (the
// watchdog) fails the test. This once failed one run in four, from two
// faults now fixed: the sketches' receiver cut a frame whenever their loop
// was busy longer than 3.5 characters (the light Nano's sample, once the
// wheel turns), and the watchdog counted a reply still being written as
// none.
#[test]
fn the_nano_sketches_answer_a_controller_network_master_over_a_pty() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let fw = sketches();
    let dir = scratch("nanos");
    let (mut vsp, mut serve, master_end) = serve_nanos(
        &dir,
        &[
            format!("motor={}", fw.join("motor-nano.elf").display()),
            format!("light={}", fw.join("light-nano.elf").display()),
        ],
        &dir.join("nanos.mcap"),
    );
    let (out, head) = wait_ready(&mut serve);
    assert!(head.contains("motor: the sketch"), "{head}");
    assert!(
        head.contains("light-nano.elf (wiring light-nano)"),
        "{head}"
    );
    assert!(!head.contains("light detector"), "{head}");
    let seen = controller_network_master(Path::new(&master_end), 20, 100);
    let rest = stop(serve, out);
    let _ = vsp.kill();
    let _ = vsp.wait();
    println!("{seen}\n{rest}");
    let log = seen["log"].as_array().unwrap();
    let problems: Vec<&Value> = log.iter().filter(|t| !t["problem"].is_null()).collect();
    let late = log.iter().filter(|t| t["late"] == true).count();
    eprintln!(
        "{} of {} transactions failed, {late} answered after the 100 ms wait",
        problems.len(),
        log.len()
    );
    // Every reply whole and valid. Two sketches take most of a core: on a
    // machine loaded far beyond its cores the server's ticks lag by seconds
    // and a reply can come after the master's 2 s (then in its next read,
    // as on a bench whose board is that slow); a few, never most.
    assert!(
        problems.iter().all(|t| late_symptom(t)) && problems.len() * 4 <= log.len(),
        "{} of {} transactions failed: {problems:#?}",
        problems.len(),
        log.len()
    );
    let states = ints(&seen["states"]);
    assert!(
        states.contains(&Some(0x80)),
        "boots pre-operational: {states:?}"
    );
    assert_eq!(states.last(), Some(&Some(0x01)), "goes operational");
    // The motor sketch counts the plant's encoder in 20 ms windows: rpm =
    // pulses × 50 / 7 × 60, truncated, so a whole number of pulses.
    let rpms: Vec<i64> = ints(&seen["rpms"]).into_iter().flatten().collect();
    for &r in &rpms {
        let pulses = (r as f64 * 7.0 / 3000.0).round() as i64;
        assert_eq!(pulses * 3000 / 7, r, "{r} rpm is no whole count of pulses");
    }
    assert!(
        rpms.iter().any(|&r| r >= 3000),
        "the motor turns once operational: {rpms:?}"
    );
    // The light sketch sees the flag go by once the wheel turns.
    let lights: Vec<i64> = ints(&seen["lights"]).into_iter().flatten().collect();
    assert!(lights.iter().any(|&l| l > 0), "{lights:?}");
    assert!(!rest.contains("marked dead"), "{rest}");
    firmware_channels_hold_the_session(&dir.join("nanos.mcap"), log);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The driver's fault forced from the console reaches the motor Nano's D4,
/// its fault line (active low, as the driver's): the Controller_network
/// sketch stops the motor after 5 ms of it, as on the bench, and the master
/// reads the stopped state; released, the sketch can be started again.
#[test]
fn a_driver_fault_forced_from_the_console_stops_the_motor_sketch() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let fw = sketches();
    let dir = scratch("driver-fault");
    let (mut vsp, mut serve, master_end) = serve_nanos_with(
        &dir,
        &[
            format!("motor={}", fw.join("motor-nano.elf").display()),
            format!("light={}", fw.join("light-nano.elf").display()),
        ],
        &dir.join("fault.mcap"),
        Stdio::piped(),
    );
    let mut console = serve.stdin.take().expect("the console's pipe");
    let (out, _) = wait_ready(&mut serve);
    let healthy = controller_network_master(Path::new(&master_end), 12, 100);
    let states = ints(&healthy["states"]);
    assert_eq!(states.last(), Some(&Some(0x01)), "operational: {states:?}");
    assert!(
        !states.contains(&Some(0x02)),
        "stopped while healthy: {states:?}"
    );

    writeln!(console, "force driver_fault on").unwrap();
    console.flush().unwrap();
    let faulted = controller_network_master(Path::new(&master_end), 12, 100);
    writeln!(console, "release driver_fault").unwrap();
    console.flush().unwrap();
    let released = controller_network_master(Path::new(&master_end), 12, 100);
    let rest = stop(serve, out);
    let _ = vsp.kill();
    let _ = vsp.wait();
    let states = ints(&faulted["states"]);
    // The master starts a stopped board again (81, then 01); the fault
    // stops it again each time it comes up.
    assert!(
        states.contains(&Some(0x02)),
        "never stopped: {states:?}\n{rest}"
    );
    let rpms: Vec<i64> = ints(&faulted["rpms"]).into_iter().flatten().collect();
    assert!(
        rpms.iter().rev().take(3).all(|&r| r == 0),
        "still turning: {rpms:?}"
    );
    let states = ints(&released["states"]);
    assert_eq!(
        states.last(),
        Some(&Some(0x01)),
        "operational again: {states:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The naive receive routine (`Serial.readBytes` of eight bytes, no
/// resynchronisation) answers a master that starts after `ready`, as the
/// sketch's board has set itself up by then: every request answered
/// whole, and the motor driven to the set point.
#[test]
fn the_naive_motor_sketch_answers_a_master_started_after_ready() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let fw = sketches();
    let dir = scratch("naive");
    let (mut vsp, mut serve, master_end) = serve_nanos(
        &dir,
        &[format!(
            "motor={}",
            fw.join("motor-nano-naive.elf").display()
        )],
        &dir.join("naive.mcap"),
    );
    let (out, head) = wait_ready(&mut serve);
    assert!(
        head.contains("motor-nano-naive.elf (wiring motor-nano)"),
        "{head}"
    );
    let seen = controller_network_master(Path::new(&master_end), 12, 100);
    let rest = stop(serve, out);
    let _ = vsp.kill();
    let _ = vsp.wait();
    println!("{seen}\n{rest}");
    let log = seen["log"].as_array().unwrap();
    let problems: Vec<&Value> = log.iter().filter(|t| !t["problem"].is_null()).collect();
    // As for our own sketches: only a reply a loaded machine made late.
    assert!(
        problems.iter().all(|t| late_symptom(t)) && problems.len() * 4 <= log.len(),
        "{} of {} transactions failed: {problems:#?}",
        problems.len(),
        log.len()
    );
    let states = ints(&seen["states"]);
    assert_eq!(
        states.last(),
        Some(&Some(0x01)),
        "goes operational: {states:?}"
    );
    let rpms: Vec<i64> = ints(&seen["rpms"]).into_iter().flatten().collect();
    assert!(
        rpms.iter().any(|&r| r >= 3000),
        "the motor turns once operational: {rpms:?}"
    );
    assert!(!rest.contains("marked dead"), "{rest}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The session's recording holds the sketches' own channels, as a virtual
/// run's does: the motor Nano's pins and cycles every 10 ms, its software
/// PWM on D9 as Timer1 makes it, the light Nano's A0 as its ADC reads it,
/// and the bytes each UART sent, the master's replies among them.
fn firmware_channels_hold_the_session(recording: &Path, log: &[Value]) {
    const HZ: f64 = 16e6;
    let (mut io, mut light_adc, mut bursts) = (Vec::new(), Vec::new(), Vec::new());
    twin_recording::Recording::scan(recording, |m| {
        match m.topic {
            "/firmware/motor/io" => io.push((m.time_s(), m.value()?)),
            "/firmware/sensor/io" => light_adc.push(m.value()?["adc"][0].clone()),
            "/firmware/motor/uart" | "/firmware/sensor/uart" => bursts.push(m.value()?),
            _ => {}
        }
        Ok(())
    })
    .expect("the recording reads");
    assert!(io.len() > 100, "{} samples of the motor's pins", io.len());
    // The first sample may be the one at 0 s, before the core ran a cycle.
    let mut last = None;
    for (t, sample) in &io {
        let cycles = sample["cycles"].as_u64().expect("cycles");
        // The core has run at least to the sample's instant, on and on.
        assert!(cycles as f64 >= (t * HZ).floor() - 1.0, "{cycles} at {t} s");
        assert!(last.is_none_or(|l| cycles > l), "{cycles} after {last:?}");
        last = Some(cycles);
    }
    // Timer1 steps the software PWM every 1600 cycles, 100 steps a period:
    // 10 ms, at the duty the PI loop sets, never fully on or off. A duty
    // raised while the step counter lies between the old and the new duty
    // switches D9 on a second time in that period, as on the real board:
    // that sample's rises are a whole number of 100 µs steps apart, fewer
    // than 100. Most samples see the plain 10 ms period.
    let d9: Vec<&Value> = io
        .iter()
        .filter_map(|(_, s)| s["pins"].as_array()?.iter().find(|p| p["pin"] == "D9"))
        .filter(|p| p["edges"].as_u64().unwrap_or(0) >= 2)
        .collect();
    assert!(d9.len() > 50, "D9 switching in {} samples", d9.len());
    let mut plain = 0;
    for p in &d9 {
        assert_eq!(p["signal"], "vel", "{p}");
        let duty = p["duty"].as_f64().unwrap();
        assert!(duty > 0.0 && duty < 1.0, "{p}");
        let period = p["period_us"].as_f64().unwrap();
        assert!(period <= 10_100.0, "{p}");
        if period == 0.0 || (period - 10_000.0).abs() < 100.0 {
            plain += 1;
        }
    }
    assert!(
        plain * 10 >= d9.len() * 9,
        "{plain} of {} samples at 10 ms",
        d9.len()
    );
    // The light Nano's A0: the photoresistor's divider, as the 10-bit
    // converter reads it at AVcc = 5 V.
    assert!(light_adc.len() > 100, "{}", light_adc.len());
    for a in &light_adc {
        assert_eq!(a["pin"], "A0", "{a}");
        let mv = a["millivolts"].as_u64().unwrap();
        assert!(mv <= 5000, "{a}");
        assert_eq!(a["counts"].as_u64().unwrap(), (mv * 1024 / 5000).min(1023));
    }
    // Each reply the master read whole left a sketch's UART as one burst,
    // each byte with the cycle it started at.
    for t in log.iter().filter(|t| t["problem"].is_null()) {
        let reply = t["reply"].as_str().unwrap();
        let burst = bursts
            .iter()
            .find(|b| b["dir"] == "tx" && b["hex"] == reply)
            .unwrap_or_else(|| panic!("no burst {reply}"));
        let cycles = burst["cycles"].as_array().unwrap();
        assert_eq!(cycles.len(), 8, "{burst}");
        assert!(
            cycles.windows(2).all(|w| w[0].as_u64() < w[1].as_u64()),
            "{burst}"
        );
    }
}

#[test]
fn a_sketch_that_never_answers_is_marked_dead_and_the_other_board_goes_on() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let fw = sketches();
    let dir = scratch("mute");
    let recording = dir.join("mute.mcap");
    // The motor is the twin's own node here: one sketch's core is half the
    // work, and the server must go on serving whatever else it serves.
    let (mut vsp, mut serve, master_end) = serve_nanos(
        &dir,
        &[format!("light={}", fw.join("mute.elf").display())],
        &recording,
    );
    let (out, _) = wait_ready(&mut serve);
    let seen = controller_network_master(Path::new(&master_end), 3, 100);
    let rest = stop(serve, out);
    let _ = vsp.kill();
    let _ = vsp.wait();
    println!("{seen}\n{rest}");
    // The master sees the mute board time out, as on the bench, and the
    // motor's answers throughout (some late, on a loaded machine).
    let log = seen["log"].as_array().unwrap();
    let mut motor_ok = 0;
    for t in log {
        let request = t["request"].as_str().unwrap();
        let reply = t["reply"].as_str().unwrap();
        assert!(
            (0..reply.len() / 16).all(|k| !reply[k * 16..].starts_with("02")),
            "the mute board wrote a reply: {t}"
        );
        if request.starts_with("02") {
            assert!(!t["problem"].is_null(), "{t}");
        } else if t["problem"].is_null() {
            motor_ok += 1;
        } else {
            assert!(late_symptom(t), "{t}");
        }
    }
    let motor_asked = log
        .iter()
        .filter(|t| t["request"].as_str().unwrap().starts_with("01"))
        .count();
    assert!(
        motor_ok * 2 > motor_asked,
        "{motor_ok} of {motor_asked}: {seen}"
    );
    assert_eq!(ints(&seen["states"]).last(), Some(&Some(0x01)));
    let dead = rest
        .lines()
        .find(|l| l.contains("marked dead"))
        .unwrap_or_else(|| panic!("no word of the mute board: {rest}"));
    assert!(dead.contains("mute.elf"), "{dead}");
    assert!(dead.contains("answered none of the"), "{dead}");
    assert!(dead.contains("at PC 0x"), "{dead}");
    assert!(dead.contains(" s simulated"), "{dead}");
    // The recording is kept, the board's end in it.
    let events = twin_recording::read::Recording::read(&recording)
        .expect("the recording reads")
        .events()
        .expect("its events");
    assert!(
        events
            .iter()
            .any(|e| e.node == "sensor" && e.kind == "trip" && e.detail.contains("marked dead")),
        "{events:?}"
    );
    // The sketch that ran is in the session's file, whole, as in a run's.
    let meta = &twin_recording::Recording::read(&recording)
        .expect("the recording reads")
        .metadata[&twin_recording::topics::firmware_metadata("sensor")];
    let elf = std::fs::read(fw.join("mute.elf")).expect("the sketch");
    assert_eq!(meta["bytes"], elf.len().to_string(), "{meta:?}");
    let stored = twin_recording::attachment::read(&recording).expect("its attachments");
    assert_eq!(
        stored.get(&meta["attachment"]).map(|a| a.data.as_slice()),
        Some(elf.as_slice()),
        "the ELF stored whole"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn over_tcp_the_ev_sketch_answers_every_request_in_order() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let elf = sketches().join("ev-controller.elf");
    let mut serve = twin_avr(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--firmware",
        &elf.display().to_string(),
        "--duration",
        "60",
        "--no-record",
        "--quiet",
        "--status-every",
        "0",
    ]);
    let (out, head) = wait_ready(&mut serve);
    let address = head
        .lines()
        .find_map(|l| l.trim().strip_prefix("meb tcp://"))
        .and_then(|rest| rest.split_whitespace().next())
        .unwrap_or_else(|| panic!("no TCP link in {head}"))
        .to_string();
    let (host, port) = address.rsplit_once(':').unwrap();
    // Ten requests in one write, ten times: every reply, each to its request.
    let burst = Command::new("python3")
        .arg(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/meb_burst.py"))
        .args([host, port, "10", "10"])
        .output()
        .expect("python3 runs");
    assert!(
        burst.status.success(),
        "{}",
        String::from_utf8_lossy(&burst.stderr)
    );
    let seen: Value = serde_json::from_slice(&burst.stdout).unwrap();
    println!("{seen}");
    // The supervisor's loop over TCP, one request at a time.
    let supervise = Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args([
            "supervise",
            "--meb",
            &format!("tcp://{address}"),
            "--set-point",
            "1000",
            "--duration",
            "4",
            "--no-record",
            "--quiet",
            "--no-server",
        ])
        .output()
        .expect("supervise runs");
    let rest = stop(serve, out);
    println!("{rest}");
    assert_eq!(seen["requests"], 100, "{seen}");
    assert_eq!(seen["replies"], 100, "{seen}");
    assert_eq!(seen["wrong"], 0, "{seen}");
    let text = String::from_utf8_lossy(&supervise.stdout);
    let last = text
        .lines()
        .rfind(|l| l.contains("slave 01:"))
        .unwrap_or_else(|| panic!("{text}"));
    println!("{last}");
    let count = |what: &str| -> u64 {
        let at = last.find(what).unwrap_or_else(|| panic!("{what}: {last}"));
        last[..at]
            .split_whitespace()
            .next_back()
            .and_then(|w| w.trim_start_matches(',').parse().ok())
            .unwrap_or_else(|| panic!("{what}: {last}"))
    };
    let (requests, replies, timeouts) = (count(" requests"), count(" replies"), count(" timeouts"));
    assert!(requests > 100, "{last}");
    // Every request answered, but for the few a stall of this loaded
    // machine let time out (a late tick holds the sketch), as on the bench.
    assert!(timeouts <= requests / 100 + 1, "{last}");
    assert!(replies + timeouts + 2 >= requests, "{last}");
}

/// The EV sketch over TCP, polled one request at a time, recorded: the
/// sketch's UART hears each request when it came on the link (not at the
/// engine's last tick, up to a millisecond early, as before), and each
/// reply leaves the link once the sketch has written it and its line has
/// gone quiet, never earlier. Read from the recording, so a loaded machine
/// only makes it late, which is allowed.
#[test]
fn the_ev_sketch_hears_each_request_when_it_came_and_answers_once_written() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let elf = sketches().join("ev-controller.elf");
    let dir = scratch("reply-times");
    let recording = dir.join("replies.mcap");
    let mut serve = twin_avr(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--firmware",
        &elf.display().to_string(),
        "--duration",
        "60",
        "--out",
        &recording.display().to_string(),
        "--quiet",
        "--status-every",
        "0",
    ]);
    let (out, head) = wait_ready(&mut serve);
    let address = head
        .lines()
        .find_map(|l| l.trim().strip_prefix("meb tcp://"))
        .and_then(|rest| rest.split_whitespace().next())
        .unwrap_or_else(|| panic!("no TCP link in {head}"))
        .to_string();
    let (host, port) = address.rsplit_once(':').unwrap();
    let timed = Command::new("python3")
        .arg(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/peers/meb_latency.py"))
        .args([host, port, "60"])
        .output()
        .expect("python3 runs");
    assert!(
        timed.status.success(),
        "{}",
        String::from_utf8_lossy(&timed.stderr)
    );
    let seen: Value = serde_json::from_slice(&timed.stdout).unwrap();
    let rest = stop(serve, out);
    println!("{seen}\n{rest}");
    assert_eq!(seen["replies"], 60, "{seen}");
    assert_eq!(seen["wrong"], 0, "{seen}");

    // The link's frames (start, from the client?) and the sketch's UART
    // bursts (dir, start, end, baud), in order.
    let (mut link, mut uart) = (Vec::new(), Vec::new());
    twin_recording::Recording::scan(&recording, |m| {
        if m.topic.starts_with("/link/") && m.topic.ends_with("/frames") {
            let v = m.value()?;
            link.push((
                v["start_s"].as_f64().unwrap_or(m.time_s()),
                v["from"] != "twin",
            ));
        } else if m.topic.starts_with("/firmware/") && m.topic.ends_with("/uart") {
            let v = m.value()?;
            uart.push((
                v["dir"] == "rx",
                v["start_s"].as_f64().unwrap_or(f64::NAN),
                v["end_s"].as_f64().unwrap_or(f64::NAN),
                v["baud"].as_f64().unwrap_or(f64::NAN),
            ));
        }
        Ok(())
    })
    .expect("the recording reads");
    let requests: Vec<f64> = link.iter().filter(|l| l.1).map(|l| l.0).collect();
    let replies: Vec<f64> = link.iter().filter(|l| !l.1).map(|l| l.0).collect();
    let heard: Vec<f64> = uart.iter().filter(|u| u.0).map(|u| u.2).collect();
    let written: Vec<(f64, f64)> = uart.iter().filter(|u| !u.0).map(|u| (u.2, u.3)).collect();
    assert_eq!(requests.len(), 60, "{} requests recorded", requests.len());
    assert_eq!(heard.len(), 60, "{} requests heard", heard.len());
    assert_eq!(written.len(), 60, "{} replies written", written.len());
    // Recorded to the nanosecond, in floating point.
    const EPS: f64 = 2e-9;
    for (n, (came, got)) in requests.iter().zip(&heard).enumerate() {
        assert!(
            got + EPS >= *came,
            "request {n} came at {came:.6} s, its last byte reached the sketch at {got:.6} s"
        );
    }
    for (n, (sent, (end, baud))) in replies.iter().zip(&written).enumerate() {
        // A frame ends when the line has been quiet for two characters.
        let due = end + 20.0 / baud;
        assert!(
            sent + EPS >= due,
            "reply {n} left at {sent:.6} s, before the sketch's line went quiet at {due:.6} s"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
