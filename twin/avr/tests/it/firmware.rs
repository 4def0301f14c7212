//! Real compiled firmware in simavr, no mocks: the sketches are built from
//! source with gcc-avr, avr-libc and the Arduino core (the crate's
//! Makefile), loaded into the twin's AVR node and held to what the bench
//! would show.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use nodes::node::{Firmware, Node};
use plant::{EvModule, PlantParams, Sensors};
use protocols::time::{SimDuration, SimTime};
use twin_avr::node::Board;
use twin_avr::{AvrNode, Wiring};

fn crate_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Builds the sketches once per test binary into the target folder (with
/// `defines`, into a folder of their own) and returns where.
fn build(defines: &str) -> PathBuf {
    let tag = if defines.is_empty() {
        "plain".to_string()
    } else {
        defines.replace(['-', '='], "")
    };
    common::make(&tag, defines, &[])
}

fn firmware(name: &str) -> PathBuf {
    static PLAIN: OnceLock<PathBuf> = OnceLock::new();
    PLAIN.get_or_init(|| build("")).join(format!("{name}.elf"))
}

fn ms(v: u64) -> SimTime {
    SimTime::ZERO + SimDuration::from_millis(v)
}

fn start(elf: &Path, wiring: &str, bus_baud: u32) -> AvrNode {
    let wiring = Wiring::parse(wiring, "test map").expect("map");
    AvrNode::start(
        board(elf, bus_baud),
        wiring,
        PlantParams::vemodule().sensing,
    )
    .unwrap_or_else(|e| panic!("{e}"))
}

fn board(elf: &Path, bus_baud: u32) -> Board<'_> {
    Board {
        name: "board",
        elf,
        mcu: "atmega328p",
        clock_hz: 16_000_000,
        bus_baud,
        bus_bits: 10,
    }
}

/// Runs the node to `until` in loop ticks with `sensors`, collecting every
/// frame it sends.
fn run(node: &mut AvrNode, from: SimTime, until: SimTime, sensors: &Sensors, out: &mut Vec<u8>) {
    let mut t = from;
    let mut buf = [0u8; 600];
    while t < until {
        let tick = t + node.loop_period();
        let next = node
            .poll_timeout()
            .filter(|d| *d < tick)
            .unwrap_or(tick)
            .min(until);
        t = next;
        if node.poll_timeout().is_some_and(|d| d <= t) {
            node.handle_timeout(t);
        }
        node.loop_tick(t, sensors);
        while let Some(n) = node.poll_transmit(t, &mut buf) {
            out.extend_from_slice(&buf[..n]);
        }
    }
}

/// Sends `bytes` as a master on a bus at `baud` would: one byte each
/// character time, from `at`; returns when the last stop bit ended.
fn send(node: &mut AvrNode, at: SimTime, bytes: &[u8], baud: u32, sensors: &Sensors) -> SimTime {
    let char_time = SimDuration::bit_times(10, baud);
    let mut t = at;
    let mut ignored = Vec::new();
    for b in bytes {
        run(node, t, t + char_time, sensors, &mut ignored);
        t += char_time;
        node.handle_bytes(t, &[*b]);
    }
    t
}

/// What a freshly started node writes when `request` reaches it at `baud`
/// 5 ms after power-up, up to `wait_ms` after the request's last byte.
fn ask(node: &mut AvrNode, request: &[u8], baud: u32, sensors: &Sensors, wait_ms: u64) -> Vec<u8> {
    let mut out = Vec::new();
    run(node, SimTime::ZERO, ms(5), sensors, &mut out);
    let end = send(node, ms(5), request, baud, sensors);
    let until = end + SimDuration::from_millis(wait_ms);
    run(node, end, until, sensors, &mut out);
    out
}

const SERIAL_ONLY: &str = "[board]\ntick_us = 100\n";

#[test]
fn the_echo_sketch_answers_every_byte_at_115200_and_at_9600() {
    let text = b"MEB @01EA000643*\n";
    let at_9600 = build("-DECHO_BAUD=9600").join("echo.elf");
    for (elf, baud, expected_baud) in [
        (firmware("echo"), 115_200, 117_647.0),
        (at_9600, 9600, 9615.0),
    ] {
        let mut node = start(&elf, SERIAL_ONLY, baud);
        let sensors = Sensors::default();
        let out = ask(&mut node, text, baud, &sensors, 40);
        assert_eq!(
            String::from_utf8_lossy(&out),
            String::from_utf8_lossy(text),
            "at {baud} baud"
        );
        // The firmware's own registers set its baud: UBRR0 and U2X0.
        let got = node.uart().baud;
        assert!((got - expected_baud).abs() < 1.0, "{got} baud at {baud}");
    }
}

#[test]
fn a_master_at_another_baud_sees_garbled_bytes() {
    // The sketch runs at 115200; the bus at 9600.
    let mut node = start(&firmware("echo"), SERIAL_ONLY, 9600);
    let sensors = Sensors::default();
    let out = ask(&mut node, b"hello", 9600, &sensors, 40);
    assert_ne!(
        out, b"hello",
        "no byte should survive a 12x baud mismatch intact"
    );
}

#[test]
fn the_adc_sketch_reads_v1_within_one_count_of_the_plant() {
    let params = PlantParams::vemodule();
    let mut plant = EvModule::new(&params, 7);
    let sensors = *plant.step(0.001, &plant::Actuators::default());
    let mut node = start(&firmware("adc"), "[analog]\nA2 = \"v1\"\n", 115_200);
    let out = ask(&mut node, b"r", 115_200, &sensors, 20);
    let line = String::from_utf8_lossy(&out).to_string();
    let count: f64 = line
        .trim()
        .strip_prefix("V1 ")
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("the sketch said {line:?}"));
    // The pin: V1 through the 10:1 divider; the ATmega's ADC: 1024 steps of AVcc = 5 V.
    let pin = sensors.battery_volts / params.sensing.battery_divider;
    let expected = pin / 5.0 * 1024.0;
    assert!(
        (count - expected).abs() <= 1.0,
        "ADC {count}, plant {expected:.2} ({pin:.4} V)"
    );
}

/// A sketch that writes port B at every pass of `loop()` (digitalWrite on
/// D8, a whole-port write, a pinMode) while Timer1 drives D9 at half duty:
/// the module's VEL input reads half of 5 V, as on the bench. simavr drove
/// D9 from PORTB at each of those writes, cutting every pulse short: VEL
/// read 0.09-0.22 V (a duty of 3.6 % in a VCD trace), and a student's
/// motor turned slower in the twin alone.
#[test]
fn writes_to_port_b_leave_d9_s_pwm_alone() {
    let sensors = Sensors::default();
    let mut node = start(
        &firmware("pwm-port-writes"),
        "[pwm]\nD9 = \"vel\"\n[board]\ntick_us = 100\npwm_filter_ms = 1.0\n",
        115_200,
    );
    let mut t = SimTime::ZERO;
    let mut vel = Vec::new();
    while t < ms(200) {
        t += node.loop_period();
        let actuators = node.loop_tick(t, &sensors);
        if t >= ms(100) {
            vel.push(actuators.vel_volts);
        }
    }
    let (low, high) = vel
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    // OCR1A = 512 of 1024: 2.5 V, the RC's ripple aside.
    assert!(
        (2.4..=2.6).contains(&low) && (2.4..=2.6).contains(&high),
        "VEL between {low:.3} and {high:.3} V over the last 100 ms"
    );
}

#[test]
fn the_ev_sketch_answers_the_meb_slave_vectors() {
    let vectors =
        std::fs::read_to_string(crate_dir().join("../../nodes/tests/vectors/meb_slave.jsonl"))
            .expect("the MEB slave vectors");
    let params = PlantParams::vemodule();
    let mut plant = EvModule::new(&params, 1);
    let sensors = *plant.step(0.001, &plant::Actuators::default());
    let wiring = include_str!("../../wiring/ev-controller.toml");
    let mut checked = 0;
    for line in vectors.lines().filter(|l| !l.trim().is_empty()) {
        let v: serde_json::Value = serde_json::from_str(line).expect("JSON");
        let request = v["request"].as_str().expect("request");
        // A freshly started slave for each, as the vectors say.
        let mut node = start(&firmware("ev-controller"), wiring, 115_200);
        let out = ask(&mut node, request.as_bytes(), 115_200, &sensors, 30);
        let reply = String::from_utf8_lossy(&out).to_string();
        let note = v["note"].as_str().unwrap_or("");
        if let Some(shape) = v.get("reply_shape") {
            let cmd = shape["cmd"].as_str().unwrap();
            let cnt = shape["cnt"].as_u64().unwrap() as usize;
            assert!(
                reply.starts_with(&format!("@01{cmd}")),
                "{note}: {request:?} -> {reply:?}"
            );
            assert_eq!(
                reply.len(),
                9 + 4 * cnt + 4,
                "{note}: {request:?} -> {reply:?}"
            );
        } else if v["reply"].is_null() {
            assert_eq!(reply, "", "{note}: {request:?} must be met with silence");
        } else {
            assert_eq!(reply, v["reply"].as_str().unwrap(), "{note}: {request:?}");
        }
        checked += 1;
    }
    assert!(checked >= 30, "{checked} vectors");
}

#[test]
fn a_crashing_sketch_is_reported_with_its_program_counter_and_time() {
    let why = failure_of("crash").expect("the crash is seen");
    println!("{why}");
    assert!(
        why.contains("crash.elf") && why.contains("crashed"),
        "{why}"
    );
    assert!(why.contains("at PC 0x"), "{why}");
    assert!(why.contains(" s simulated"), "{why}");
    let why = failure_of("sleepy").expect("the dead sleep is seen");
    println!("{why}");
    assert!(why.contains("sleep with interrupts off"), "{why}");
}

/// What the node says went wrong with `sketch` within 20 ms of its start.
fn failure_of(sketch: &str) -> Option<String> {
    let mut node = start(&firmware(sketch), SERIAL_ONLY, 115_200);
    run(
        &mut node,
        SimTime::ZERO,
        ms(20),
        &Sensors::default(),
        &mut Vec::new(),
    );
    twin_sim::engine::SimNode::failure(&node)
}

#[test]
fn a_sketch_for_another_mcu_is_refused_naming_the_file_and_field() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("avr-mega");
    std::fs::create_dir_all(&dir).unwrap();
    let src = dir.join("mega.c");
    std::fs::write(&src, "int main(void) { for (;;) {} }\n").unwrap();
    let elf = dir.join("mega.elf");
    let status = Command::new("avr-gcc")
        .args(["-mmcu=atmega2560", "-Os", "-o"])
        .arg(&elf)
        .arg(&src)
        .status()
        .expect("avr-gcc runs");
    assert!(status.success());
    let wiring = Wiring::parse(SERIAL_ONLY, "test map").unwrap();
    let err = AvrNode::start(
        board(&elf, 115_200),
        wiring,
        PlantParams::vemodule().sensing,
    )
    .expect_err("an ATmega2560 build is refused")
    .to_string();
    println!("{err}");
    assert!(err.contains("mega.elf"), "{err}");
    assert!(err.contains("e_flags"), "{err}");
    assert!(err.contains("avr6"), "{err}");
    assert!(err.contains("-mmcu=atmega328p"), "{err}");
}

#[test]
fn the_echo_sketch_runs_from_an_intel_hex_file_as_from_its_elf() {
    // What the Arduino IDE exports and avrdude flashes: flash only, the MCU
    // and clock given by the node.
    let hex = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("echo.hex");
    let status = Command::new("avr-objcopy")
        .args(["-O", "ihex", "-R", ".eeprom"])
        .arg(firmware("echo"))
        .arg(&hex)
        .status()
        .expect("avr-objcopy runs (gcc-avr's binutils)");
    assert!(status.success());
    let text = b"@01EA000643*\n";
    let mut node = start(&hex, SERIAL_ONLY, 115_200);
    let sensors = Sensors::default();
    let out = ask(&mut node, text, 115_200, &sensors, 20);
    assert_eq!(String::from_utf8_lossy(&out), String::from_utf8_lossy(text));
    assert_eq!(node.uart().baud.round(), 117_647.0);
}

/// MEB reads of the inputs, ten a second for 1.5 s, as a supervisor polls.
fn poll_for_a_second_and_a_half(node: &mut AvrNode) {
    let sensors = Sensors::default();
    let mut t = ms(100);
    run(node, SimTime::ZERO, t, &sensors, &mut Vec::new());
    for _ in 0..15 {
        let end = send(node, t, b"@01EA00*4C\r", 115_200, &sensors);
        t += SimDuration::from_millis(100);
        run(node, end, t, &sensors, &mut Vec::new());
    }
}

#[test]
fn a_sketch_that_hears_its_bus_and_never_answers_is_reported_with_its_pc() {
    let mut node = start(&firmware("mute"), SERIAL_ONLY, 115_200);
    poll_for_a_second_and_a_half(&mut node);
    let mut silent = Vec::new();
    while let Some(e) = node.poll_event() {
        if e.kind == "silent" {
            silent.push(e.detail);
        }
    }
    println!("{silent:?}");
    assert_eq!(silent.len(), 1, "reported once: {silent:?}");
    let said = &silent[0];
    assert!(said.contains("mute.elf"), "{said}");
    assert!(said.contains("answered none"), "{said}");
    assert!(said.contains("at PC 0x"), "{said}");
    assert!(said.contains("s simulated"), "{said}");
    // Only a running node is said to be silent: it is not marked dead.
    assert!(twin_sim::engine::SimNode::failure(&node).is_none());
}

#[test]
fn a_sketch_that_answers_is_never_said_to_be_silent() {
    let mut node = start(&firmware("echo"), SERIAL_ONLY, 115_200);
    poll_for_a_second_and_a_half(&mut node);
    while let Some(e) = node.poll_event() {
        assert_ne!(e.kind, "silent", "{}", e.detail);
    }
}
