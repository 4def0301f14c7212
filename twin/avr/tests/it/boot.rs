//! Boards that boot before their master: the motor Nano's pinout with the
//! naive receive routine of many student sketches (`motor-nano-naive`:
//! eight bytes with `Serial.readBytes` and its 1 s timeout, no
//! resynchronisation on a gap) answers the shipped Controller_network
//! scenario, whose Nanos boot (`boot_ms`) before the Pi's program starts;
//! started at 0 s instead, with a retry shorter than that timeout, its
//! first request reaches the UART before `Serial.begin` and every later
//! frame is read two bytes out of step, so it never answers.

use crate::common;

use std::path::PathBuf;
use std::sync::OnceLock;

use twin_sim::scenario::{NodeSpec, Scenario};
use twin_sim::virtual_run::{self, RunOutcome};

fn build_dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| common::make("boot", "", &["motor-nano-naive", "light-nano"]))
}

/// The shipped scenario with the naive motor sketch in place of ours.
fn shipped_with_the_naive_sketch(seconds: f64) -> Scenario {
    let text = std::fs::read_to_string(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenarios/controller-network-avr.toml"),
    )
    .expect("scenario")
    .replace("build/motor-nano.elf", "build/motor-nano-naive.elf")
    .replace(
        "twin/avr/firmware/build/",
        &format!("{}/", build_dir().display()),
    );
    assert!(text.contains("motor-nano-naive.elf"), "{text}");
    let mut scenario = Scenario::parse(&text, "controller-network-avr.toml").expect("parses");
    scenario.duration_s = seconds;
    scenario
}

fn run(scenario: &Scenario, name: &str) -> RunOutcome {
    twin_avr::register();
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    virtual_run::run(scenario, &out, |_| {}).expect("runs")
}

/// A node's end-of-run state.
fn state<'a>(o: &'a RunOutcome, node: &str) -> &'a serde_json::Value {
    &o.telemetry
        .iter()
        .find(|(n, _)| n == node)
        .unwrap_or_else(|| panic!("no {node} among {:?}", o.telemetry))
        .1
}

/// Replies the motor sketch sent: its UART's bytes, eight a frame.
fn motor_replies(o: &RunOutcome) -> u64 {
    state(o, "motor")["bytes_out"].as_u64().expect("bytes_out") / 8
}

/// The master's start and reply wait, and both boards' boot.
fn set(scenario: &mut Scenario, start_s: f64, retry_ms: Option<f64>, boot: f64) {
    for node in &mut scenario.nodes {
        match node {
            NodeSpec::ControllerNetworkMaster {
                start_s: s,
                reply_timeout_ms,
                ..
            } => {
                *s = Some(start_s);
                *reply_timeout_ms = retry_ms;
            }
            NodeSpec::Firmware { boot_ms, .. } => *boot_ms = boot,
            _ => {}
        }
    }
}

#[test]
fn the_shipped_scenario_starts_its_master_once_the_nanos_have_booted() {
    let scenario = shipped_with_the_naive_sketch(1.0);
    assert_eq!(scenario.boards_booted_s(), 1.065);
    for node in &scenario.nodes {
        if let NodeSpec::ControllerNetworkMaster {
            start_s,
            reply_timeout_ms,
            ..
        } = node
        {
            assert_eq!(
                *start_s,
                Some(1.165),
                "the Pi starts after the Nanos and their setup()"
            );
            assert_eq!(
                *reply_timeout_ms, None,
                "the Pi program as shipped: no retry"
            );
        }
    }
}

#[test]
fn the_naive_sketch_answers_when_its_board_boots_before_the_master_and_slips_when_not() {
    let seconds = 6.0;
    let booted = run(&shipped_with_the_naive_sketch(seconds), "naive-booted.mcap");
    let rpi = state(&booted, "rpi");
    println!(
        "boards boot first: the sketch sent {} replies; the master {rpi}",
        motor_replies(&booted)
    );
    // Every request answered: the master has no timeout, so one lost
    // reply would have stopped it for good.
    assert_eq!(rpi["timeouts"], 0, "{rpi}");
    assert_eq!(rpi["crc_errors"], 0, "{rpi}");
    // The Pi's program is slow (a handshake, then a cycle of set point,
    // rpm and light about every half second): ten replies in its 4.8 s.
    assert_eq!(rpi["phase"], "running", "{rpi}");
    assert!(motor_replies(&booted) >= 8, "{}", motor_replies(&booted));
    // The sketch drove the motor: the master read it near its set point.
    let rpm = rpi["motor_rpm"].as_f64().expect("a reading");
    assert!(rpm > 3000.0, "the master read {rpm} rpm");

    // The cause: the same sketch, its board started at 0 s with the master,
    // which asks again after 300 ms (within the sketch's 1 s timeout).
    let mut early = shipped_with_the_naive_sketch(seconds);
    set(&mut early, 0.0, Some(300.0), 0.0);
    let stuck = run(&early, "naive-at-zero.mcap");
    let rpi = state(&stuck, "rpi");
    let motor = state(&stuck, "motor");
    println!(
        "master at 0 s, retry 300 ms: the sketch heard {} bytes and sent {} replies; the master {rpi}",
        motor["bytes_in"],
        motor_replies(&stuck)
    );
    assert!(
        motor_replies(&stuck) <= 1,
        "a slipped sketch answered {} times",
        motor_replies(&stuck)
    );
    // It heard the master all along: the requests reached it, misaligned.
    assert!(motor["bytes_in"].as_u64().unwrap_or(0) > 100, "{motor}");
    assert!(rpi["timeouts"].as_u64().unwrap_or(0) > 10, "{rpi}");

    // Not the retry: with the boards booted first, the same 300 ms retry
    // is answered as well.
    let mut retrying = shipped_with_the_naive_sketch(seconds);
    set(&mut retrying, 1.165, Some(300.0), 1065.0);
    let fine = run(&retrying, "naive-booted-retry.mcap");
    println!(
        "boards boot first, retry 300 ms: the sketch sent {} replies",
        motor_replies(&fine)
    );
    assert_eq!(state(&fine, "rpi")["timeouts"], 0);
    assert!(motor_replies(&fine) >= 8, "{}", motor_replies(&fine));
}

#[test]
fn a_board_in_boot_hears_nothing_and_its_sketch_starts_after() {
    // The naive sketch's board booting for 1.065 s while the master asks
    // from 0 s with a 300 ms retry: the requests before the sketch runs are
    // lost (counted), and the first after it is read whole, since the
    // sketch's receiver starts between two of the master's frames.
    let mut scenario = shipped_with_the_naive_sketch(3.0);
    set(&mut scenario, 0.0, Some(300.0), 1065.0);
    let o = run(&scenario, "naive-boot-deaf.mcap");
    let motor = state(&o, "motor");
    println!("booting board, master from 0 s: {motor}");
    assert_eq!(motor["boot_s"], 1.065, "{motor}");
    // Four requests (0, 0.3, 0.6, 0.9 s) of eight bytes before 1.065 s.
    assert_eq!(motor["bytes_before_boot"], 32, "{motor}");
    assert!(motor_replies(&o) >= 3, "{}", motor_replies(&o));
}
