//! Two firmware nodes on two cores, and firmware bytes on the wire at their
//! own times: the Controller_network Nanos give the same recording to the
//! byte whether each core runs ahead on a thread of its own or all run on
//! the engine's thread; the EV sketch's replies reach the supervisor when
//! their last stop bit ends, so it polls as often as with the Rust controller.

use crate::common;

use std::path::PathBuf;

use twin_sim::scenario::Scenario;
use twin_sim::virtual_run;

fn crate_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn out(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name)
}

/// A shipped scenario with its sketches built here.
fn shipped(file: &str, sketches: &[&str], duration_s: f64) -> Scenario {
    let build = common::make("cores", "", sketches);
    let text = std::fs::read_to_string(crate_dir().join("scenarios").join(file))
        .expect("scenario")
        .replace("twin/avr/firmware/build/", &format!("{}/", build.display()));
    let mut s = Scenario::parse(&text, file).expect("parses");
    s.duration_s = duration_s;
    s
}

/// The cycles a firmware node's core ran, from the end-of-run summary.
fn firmware_cycles(o: &virtual_run::RunOutcome, node: &str) -> u64 {
    let (_, t) = o
        .telemetry
        .iter()
        .find(|(n, _)| n == node)
        .unwrap_or_else(|| panic!("node {node} reports"));
    t["firmware_cycles"].as_u64().unwrap_or(0)
}

#[test]
fn two_nanos_on_their_own_threads_record_what_one_thread_records() {
    use twin_avr::stepper::Mode;
    twin_avr::register();
    // The Nanos boot for 1.065 s and the master starts at 1.165 s: a
    // second and a half of traffic after.
    let seconds = 2.5;
    let scenario = shipped(
        "controller-network-avr.toml",
        &["motor-nano", "light-nano"],
        seconds,
    );
    let booted = scenario.boards_booted_s();
    assert!(booted > 0.0, "the Nanos boot");
    // Threaded twice, then the same split points on one thread, then no
    // core ever run ahead: a horizon that let the light Nano's core run past
    // a byte or a tick for it would make the last differ from the others.
    let modes = [
        Mode::Threaded,
        Mode::Threaded,
        Mode::OneThread,
        Mode::NoRunAhead,
    ];
    let mut runs = Vec::new();
    for (i, mode) in modes.into_iter().enumerate() {
        twin_avr::stepper::set_mode(mode);
        let path = out(&format!("cores-{i}.mcap"));
        let outcome = virtual_run::run(&scenario, &path, |_| {}).expect("runs");
        runs.push(std::fs::read(&outcome.recording).expect("recording"));
        let _ = std::fs::remove_file(&outcome.recording);
        // Every core ends at the run's end, not a horizon past it: the
        // time since its boot at 16 MHz, to the cycle (the motor Nano's
        // core stops on the instruction boundary at or after it).
        let exact = ((seconds - booted) * 16e6).round() as u64;
        for node in ["motor", "sensor"] {
            let cycles = firmware_cycles(&outcome, node);
            assert!(
                (exact..exact + 4).contains(&cycles),
                "{mode:?}: {node} ran {cycles} cycles in {seconds} s, {exact} expected"
            );
        }
    }
    twin_avr::stepper::set_mode(Mode::Threaded);
    assert!(runs[0].len() > 10_000, "{} bytes", runs[0].len());
    assert!(runs[0] == runs[1], "two threaded runs differ");
    assert!(
        runs[0] == runs[2],
        "threaded and one-thread runs differ ({} and {} bytes)",
        runs[0].len(),
        runs[2].len()
    );
    assert!(
        runs[0] == runs[3],
        "runs with and without cores running ahead differ ({} and {} bytes)",
        runs[0].len(),
        runs[3].len()
    );
}

fn requests(o: &virtual_run::RunOutcome) -> f64 {
    let (_, t) = o
        .telemetry
        .iter()
        .find(|(n, _)| n == "supervisor")
        .expect("the supervisor reports");
    t["loops"][0]["requests"].as_f64().unwrap_or(f64::NAN)
}

#[test]
fn the_supervisor_polls_the_sketch_as_often_as_the_rust_controller() {
    twin_avr::register();
    let seconds = 3.0;
    let sketch = shipped("ev-meb-avr.toml", &["ev-controller"], seconds);
    let mut model = Scenario::load("ev-meb").expect("ev-meb");
    model.duration_s = seconds;
    let a = virtual_run::run(&sketch, &out("polls-avr.mcap"), |_| {}).expect("sketch");
    let b = virtual_run::run(&model, &out("polls-rust.mcap"), |_| {}).expect("model");
    let _ = std::fs::remove_file(&a.recording);
    let _ = std::fs::remove_file(&b.recording);
    let (sketch_polls, model_polls) = (requests(&a) / seconds, requests(&b) / seconds);
    println!("polls per second: sketch {sketch_polls:.1}, Rust controller {model_polls:.1}");
    assert!(
        (sketch_polls / model_polls - 1.0).abs() < 0.03,
        "the supervisor polled the sketch {sketch_polls:.1} times a second, the Rust controller {model_polls:.1}"
    );
}

#[test]
fn a_supervisor_at_another_baud_than_the_sketch_gets_no_answer_and_framing_errors_are_counted() {
    twin_avr::register();
    let mut scenario = shipped("ev-meb-avr.toml", &["ev-controller"], 0.6);
    // The supervisor at 57600; the sketch keeps its own 117 647 (UBRR0 16, U2X0).
    scenario.buses[0].baud = 57_600;
    let o = virtual_run::run(&scenario, &out("baud-mismatch.mcap"), |_| {}).expect("runs");
    let _ = std::fs::remove_file(&o.recording);
    let (_, sketch) = o
        .telemetry
        .iter()
        .find(|(n, _)| n == "ev1")
        .expect("sketch");
    let framing = sketch["framing_errors_in"].as_u64().unwrap_or(0);
    let bytes_in = sketch["bytes_in"].as_u64().unwrap_or(0);
    println!("the sketch took {bytes_in} bytes, {framing} with a framing error");
    assert!(framing > 0 && framing < bytes_in, "{sketch}");
    assert_eq!(o.events.get("framing").copied(), Some(1), "{:?}", o.events);
    let (_, sup) = o
        .telemetry
        .iter()
        .find(|(n, _)| n == "supervisor")
        .expect("supervisor");
    assert_eq!(sup["loops"][0]["replies"].as_u64(), Some(0), "{sup}");
    assert!(
        o.events.get("timeout").copied().unwrap_or(0) > 2,
        "{:?}",
        o.events
    );
}
