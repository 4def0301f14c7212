//! The Controller_network project's slaves (`twin serve --modbus8`: motor id
//! 01, light sensor id 02 behind one port) against a master that behaves like
//! that network's Raspberry Pi (`peers/controller_network_master.py`): it
//! reopens the port for every transaction, waits a fixed 10 ms (its
//! step-response build) or 100 ms, reads once and has no timeout. Every
//! transaction must get a reply (none would hang the real master) and find it
//! whole and valid in that one read (a split or stray reply would misalign it).
//! Whether a reply came inside the fixed wait is printed, not asserted: on a
//! loaded machine the pty relay alone (socat; a bare echo behind it too)
//! sometimes takes longer than 10 ms.

use crate::peers;

use peers::{PtyPair, Serve, run_timeout, scratch, script};
use rustix::fs::OFlags;
use serde_json::Value;
use std::fs::OpenOptions;
use std::os::unix::fs::OpenOptionsExt;
use std::process::Command;
use std::time::Duration;

fn run_master(device: &str, cycles: u32, wait_ms: u32) -> Value {
    let out = run_timeout(
        Command::new("python3")
            .arg(script("controller_network_master.py"))
            .args([device, &cycles.to_string(), &wait_ms.to_string()]),
        Duration::from_secs(120),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "Controller_network master failed: {stderr}"
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {stderr}"))
}

/// The master's end of `pair`, held open: the master closes its end after
/// every transaction, and holding it here too keeps socat from seeing a
/// hang-up (a real port has no such problem).
fn hold_open(pair: &PtyPair) -> std::fs::File {
    OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(OFlags::NOCTTY.bits() as i32)
        .open(&pair.b)
        .expect("open the master's end")
}

fn assert_every_reply_whole(seen: &Value) {
    let log = seen["log"].as_array().unwrap();
    assert!(!log.is_empty());
    let late = log.iter().filter(|t| t["late"] == true).count();
    eprintln!("{late} of {} replies came after the fixed wait", log.len());
    let problems: Vec<&Value> = log.iter().filter(|t| !t["problem"].is_null()).collect();
    assert!(
        problems.is_empty(),
        "{} of {} transactions would have hung or misled the master: {problems:#?}",
        problems.len(),
        log.len()
    );
}

#[test]
fn controller_network_master_reopening_the_port_is_never_left_hanging() {
    let dir = scratch("modbus8");
    let pair = PtyPair::new(&dir);
    let serve = Serve::start(&["--quiet", "--modbus8", pair.a.to_str().unwrap()]);
    let ids: Vec<&str> = serve
        .links
        .iter()
        .filter(|l| l.protocol == "modbus8")
        .map(|l| l.id.as_str())
        .collect();
    assert!(!ids.is_empty(), "a modbus8 link: {:?}", serve.links);

    let _held = hold_open(&pair);

    let device = pair.b.to_str().unwrap();
    let fast = run_master(device, 45, 10);
    assert_every_reply_whole(&fast);
    let states = fast["states"].as_array().unwrap();
    assert_eq!(
        states.first().unwrap(),
        0x80,
        "boots pre-operational: {states:?}"
    );
    assert_eq!(states.last().unwrap(), 0x01, "goes operational: {states:?}");
    let rpms: Vec<i64> = fast["rpms"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_i64().unwrap())
        .collect();
    assert!(
        rpms.iter().any(|&r| r >= 428),
        "the motor turns once operational (steps of 428.57 rpm): {rpms:?}"
    );
    // rpm = pulses in 20 ms × 50 / 7 × 60, truncated: a whole number of steps.
    for &r in &rpms {
        let pulses = (r as f64 * 7.0 / 3000.0).round() as i64;
        assert_eq!(
            pulses * 3000 / 7,
            r,
            "{r} rpm is no whole count of encoder pulses"
        );
    }
    let lights = fast["lights"].as_array().unwrap();
    assert!(lights.iter().all(|v| v.is_i64()), "{lights:?}");

    // The production build's 100 ms wait: same answers, nothing left over
    // from the faster run to misalign it.
    let slow = run_master(device, 3, 100);
    assert_every_reply_whole(&slow);
    assert_eq!(slow["states"].as_array().unwrap().last().unwrap(), 0x01);
}

/// One encoder pulse in the motor node's 20 ms window: 50 / 7 × 60 rpm.
const PULSE_RPM: f64 = 3000.0 / 7.0;

/// The server stopped (SIGSTOP) for 300 ms every 2 s while the master
/// polls: each stall is longer than the engine catches up, so the session's
/// clock slips and the plant and the motor node step through every tick in
/// order. Every speed the node answered is within one encoder pulse of the
/// motor's speed over the 20 ms window it counted (read from the recording),
/// never a reading the bench could not give; the slips are counted and
/// recorded.
#[test]
fn a_stopped_server_slips_its_clock_and_reads_only_true_speeds() {
    let dir = scratch("modbus8-stall");
    let pair = PtyPair::new(&dir);
    let recording = dir.join("stall.mcap");
    let mut serve = Serve::start(&[
        "--quiet",
        "--modbus8",
        pair.a.to_str().unwrap(),
        "--out",
        recording.to_str().unwrap(),
    ]);
    let _held = hold_open(&pair);
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stopper = {
        let (done, pid) = (done.clone(), serve.pid().to_string());
        std::thread::spawn(move || {
            let mut stalls = 0;
            loop {
                std::thread::sleep(Duration::from_secs(2));
                if done.load(std::sync::atomic::Ordering::Relaxed) {
                    return stalls;
                }
                let _ = Command::new("kill").args(["-STOP", &pid]).status();
                std::thread::sleep(Duration::from_millis(300));
                let _ = Command::new("kill").args(["-CONT", &pid]).status();
                stalls += 1;
            }
        })
    };
    let seen = run_master(pair.b.to_str().unwrap(), 26, 100);
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    let stalls = stopper.join().expect("the stopper ran");
    serve.terminate();
    let said = serve.stdout();
    println!("{seen}\n{said}");
    assert!(stalls >= 3, "{stalls} stalls");

    let (mut motor, mut readings, mut slips, mut events) = (Vec::new(), Vec::new(), 0, 0);
    twin_recording::Recording::scan(&recording, |m| {
        let topic = m.topic;
        if topic.starts_with("/plant/") && topic.ends_with("/sensors") {
            if let Some(rpm) = m.value()?["motor_rpm"].as_f64() {
                motor.push((m.time_s(), rpm));
            }
        } else if topic.starts_with("/link/") {
            let v = m.value()?;
            let hex = v["hex"].as_str().unwrap_or("");
            // The motor's answer to a read of register 5, its speed.
            if v["from"] == "twin" && hex.len() == 16 && hex.starts_with("01030005") {
                let rpm = i64::from_str_radix(&hex[8..12], 16).unwrap_or(-1) as f64;
                readings.push((m.time_s(), rpm));
            }
        } else if topic == "/realtime/lateness" {
            slips = m.value()?["total"]["slips"].as_u64().unwrap_or(0);
        } else if topic == "/events" && m.value()?["kind"] == "slip" {
            events += 1;
        }
        Ok(())
    })
    .expect("the recording reads");
    assert!(readings.len() >= 20, "{} readings", readings.len());
    for &(t, rpm) in &readings {
        // The node counts in windows of exactly 20 ms, the last of which
        // ended at most 20 ms before the reply; the plant is sampled every
        // 10 ms.
        let window: Vec<f64> = motor
            .iter()
            .filter(|(s, _)| *s >= t - 0.045 && *s <= t + 0.001)
            .map(|(_, r)| *r)
            .collect();
        assert!(
            window.len() >= 3,
            "{} plant samples before {t} s",
            window.len()
        );
        let low = window.iter().copied().fold(f64::INFINITY, f64::min);
        let high = window.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        assert!(
            rpm >= low - PULSE_RPM - 1.0 && rpm <= high + PULSE_RPM + 1.0,
            "the node read {rpm} rpm at {t:.3} s while the motor turned at {low:.0}-{high:.0}"
        );
    }
    assert!(slips >= stalls, "{slips} slips for {stalls} stalls");
    assert!(events >= 1, "no slip event");
}
