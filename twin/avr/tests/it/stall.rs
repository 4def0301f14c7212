//! `twin-avr serve` stopped by the machine: the Controller_network Nanos in
//! real time, polled by that project's master over a pseudo-terminal, while
//! the server process is stopped (SIGSTOP) for 300 ms every 2 s. A stall is
//! longer than the engine catches up in a burst, so the session's clock
//! slips; every tick still runs in order, so the motor sketch counts every
//! encoder edge of its 20 ms windows and never reads a speed the motor did
//! not have.

use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use serde_json::Value;

use crate::serve_boards::{
    ONE_AT_A_TIME, controller_network_master, scratch, serve_nanos, sketches, stop, wait_ready,
};

/// One encoder pulse in the motor sketch's 20 ms window: 50 / 7 × 60 rpm.
const PULSE_RPM: f64 = 3000.0 / 7.0;

#[test]
fn a_stopped_server_slips_its_clock_and_the_motor_sketch_reads_only_true_speeds() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let fw = sketches();
    let dir = scratch("stall");
    let recording = dir.join("stall.mcap");
    let (mut vsp, mut serve, master_end) = serve_nanos(
        &dir,
        &[
            format!("motor={}", fw.join("motor-nano.elf").display()),
            format!("light={}", fw.join("light-nano.elf").display()),
        ],
        &recording,
    );
    let (out, _) = wait_ready(&mut serve);
    let done = Arc::new(AtomicBool::new(false));
    let stopper = {
        let (done, pid) = (done.clone(), serve.id().to_string());
        std::thread::spawn(move || {
            let mut stalls = 0;
            while !done.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_secs(2));
                if done.load(Ordering::Relaxed) {
                    break;
                }
                let _ = Command::new("kill").args(["-STOP", &pid]).status();
                std::thread::sleep(Duration::from_millis(300));
                let _ = Command::new("kill").args(["-CONT", &pid]).status();
                stalls += 1;
            }
            stalls
        })
    };
    let seen = controller_network_master(Path::new(&master_end), 26, 100);
    done.store(true, Ordering::Relaxed);
    let stalls = stopper.join().expect("the stopper ran");
    let rest = stop(serve, out);
    let _ = vsp.kill();
    let _ = vsp.wait();
    println!("{seen}\n{rest}");
    assert!(stalls >= 3, "{stalls} stalls");

    let ReadBack {
        motor,
        readings,
        slips,
        slip_events,
    } = read_back(&recording);
    // Every reading the sketch sent is within one pulse of the motor's
    // speed over the window it counted, that window stretched or shrunk by
    // up to 2 ms (10 %): `millis()` steps by 1.024 ms and the loop latches
    // when it next comes round. The window ended at most 22 ms before the
    // reply, so it lies within the last 45 ms.
    assert!(readings.len() >= 20, "{} readings", readings.len());
    let mut turning = 0;
    for &(t, rpm) in &readings {
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
            rpm >= low * 0.9 - PULSE_RPM && rpm <= high * 1.1 + PULSE_RPM,
            "the sketch read {rpm} rpm at {t:.3} s while the motor turned at {low:.0}-{high:.0}"
        );
        turning += usize::from(low > 3000.0);
    }
    assert!(
        turning * 2 >= readings.len(),
        "{turning} readings while turning"
    );

    // Each stall slipped the clock by about what it lost beyond the 50 ms
    // caught up; said in the recording and at the end.
    assert!(slips.0 >= stalls, "{} slips for {stalls} stalls", slips.0);
    assert!(
        slips.1 >= 200.0 * stalls as f64,
        "{} ms lost in {stalls} stalls",
        slips.1
    );
    assert!(!slip_events.is_empty(), "no slip event");
    assert!(slip_events.iter().all(|e| e.contains("real time lost")));
    assert!(rest.contains("real time lost:"), "{rest}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// What the session's recording says.
#[derive(Default)]
struct ReadBack {
    /// The motor's speed at each plant sample: (time, rpm).
    motor: Vec<(f64, f64)>,
    /// The motor sketch's rpm replies: (time, rpm).
    readings: Vec<(f64, f64)>,
    /// The slips of the last lateness record: count, ms lost.
    slips: (usize, f64),
    /// The details of the slip events.
    slip_events: Vec<String>,
}

fn read_back(recording: &Path) -> ReadBack {
    let mut back = ReadBack::default();
    twin_recording::Recording::scan(recording, |m| {
        let topic = m.topic;
        if topic.starts_with("/plant/") && topic.ends_with("/sensors") {
            let v = m.value()?;
            if let Some(rpm) = v["motor_rpm"].as_f64() {
                back.motor.push((m.time_s(), rpm));
            }
        } else if topic == "/firmware/motor/uart" {
            let v = m.value()?;
            let hex = v["hex"].as_str().unwrap_or("");
            // A read of register 5, the speed: 01 03 00 05 HH LL CRC.
            if v["dir"] == "tx" && hex.len() == 16 && hex.starts_with("01030005") {
                let rpm = i64::from_str_radix(&hex[8..12], 16).unwrap_or(-1) as f64;
                back.readings
                    .push((v["start_s"].as_f64().unwrap_or(m.time_s()), rpm));
            }
        } else if topic == "/realtime/lateness" {
            let v: Value = m.value()?;
            back.slips = (
                v["total"]["slips"].as_u64().unwrap_or(0) as usize,
                v["total"]["slipped_ms"].as_f64().unwrap_or(0.0),
            );
        } else if topic == "/events" {
            let v = m.value()?;
            if v["kind"] == "slip" {
                back.slip_events
                    .push(v["detail"].as_str().unwrap_or("").to_string());
            }
        }
        Ok(())
    })
    .expect("the recording reads");
    back
}
