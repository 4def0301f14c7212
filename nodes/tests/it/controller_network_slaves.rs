//! The Controller_network project's motor and light-sensor nodes as slaves: every register and
//! exception case of `docs/protocols/modbus8.md`, the request vectors of
//! `tests/vectors/modbus8.jsonl` answered with the captured replies, and
//! the firmware's encoder window and light-sensor blend against hand results.

use nodes::controller_network::{LightNode, MotorConfig, MotorNode, MotorState, PortConfig};
use nodes::node::{Firmware, Node};
use protocols::modbus8::{CrcOrder, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};
use serde::Deserialize;

const VECTORS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/vectors/modbus8.jsonl");

#[derive(Debug, Deserialize)]
struct Vector {
    frame_hex: String,
    valid: bool,
    valid_standard_order: bool,
    note: String,
}

fn hex(s: &str) -> [u8; 8] {
    let mut out = [0u8; 8];
    assert_eq!(s.len(), 16, "{s}");
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = u8::from_str_radix(&s[2 * i..2 * i + 2], 16).unwrap();
    }
    out
}

fn vectors() -> Vec<Vector> {
    let text = std::fs::read_to_string(VECTORS).expect("read modbus8.jsonl");
    let v: Vec<Vector> = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert!(v.len() >= 15);
    v
}

fn vector(note_start: &str) -> [u8; 8] {
    let v = vectors()
        .into_iter()
        .find(|v| v.note.starts_with(note_start))
        .unwrap_or_else(|| panic!("no vector {note_start}"));
    hex(&v.frame_hex)
}

/// Sends `request` to `node` at `now`; the reply, if it answers.
fn exchange(node: &mut impl Node, now: SimTime, request: &[u8]) -> Option<[u8; 8]> {
    node.handle_bytes(now, request);
    let mut buf = [0u8; 16];
    let n = node.poll_transmit(now, &mut buf)?;
    assert_eq!(n, 8);
    assert_eq!(
        node.poll_transmit(now, &mut buf),
        None,
        "one reply per request"
    );
    Some(buf[..8].try_into().unwrap())
}

fn req(id: u8, function: u8, addr: u16, value: u16) -> [u8; 8] {
    Modbus8Repr {
        id,
        function,
        addr,
        value,
    }
    .to_bytes(CrcOrder::HighFirst)
}

fn reply(bytes: [u8; 8]) -> Modbus8Repr {
    Modbus8Repr::parse(&bytes, CrcOrder::HighFirst).expect("reply CRC")
}

fn ms(t: u64) -> SimTime {
    SimTime::ZERO + SimDuration::from_millis(t)
}

fn sensors_with_encoder(count: i64) -> plant::Sensors {
    let mut s = plant::Sensors::default();
    s.shaft.encoder_count = count;
    s
}

#[test]
fn motor_answers_the_captured_request_vectors() {
    let mut motor = MotorNode::default();
    let t = ms(1);
    // Boots pre-operational; writing 0x80 is echoed.
    assert_eq!(motor.state(), MotorState::PreOperational);
    let write_80 = vector("request: motor, write control state 0x80");
    assert_eq!(exchange(&mut motor, t, &write_80), Some(write_80));
    let read_state = vector("request: motor, read control state");
    assert_eq!(
        reply(exchange(&mut motor, t, &read_state).unwrap()).value,
        0x80
    );
    // Operational: the read gives the captured reply byte for byte.
    exchange(&mut motor, t, &req(1, 6, 1, 1)).unwrap();
    assert_eq!(
        exchange(&mut motor, t, &read_state),
        Some(vector("reply: control state 0x01"))
    );
    // Set-point writes are echoed.
    for note in [
        "request and echo: set speed 5000",
        "request and echo: set speed 10000",
    ] {
        let frame = vector(note);
        assert_eq!(exchange(&mut motor, t, &frame), Some(frame));
    }
    assert_eq!(motor.set_point(), 10_000);
}

#[test]
fn motor_rpm_reply_matches_the_capture_after_23_pulses_in_20_ms() {
    let mut motor = MotorNode::default();
    motor.loop_tick(ms(0), &sensors_with_encoder(0));
    for t in (2..=20).step_by(2) {
        // 23 pulses spread over the window; only the latch at 20 ms counts.
        let count = (23 * t / 20) as i64;
        motor.loop_tick(ms(t), &sensors_with_encoder(count));
    }
    assert_eq!(motor.latched_rpm(), 9857);
    let read_rpm = vector("request: motor, read rpm");
    assert_eq!(
        exchange(&mut motor, ms(21), &read_rpm),
        Some(vector("reply: motor rpm 9857"))
    );
}

#[test]
fn motor_rpm_is_latched_every_20_ms_in_428_rpm_steps_and_signed() {
    let mut motor = MotorNode::default();
    motor.loop_tick(ms(0), &sensors_with_encoder(1000));
    let mut count = 1000i64;
    for (window, pulses) in [24i64, 1, 0, -23, 29].into_iter().enumerate() {
        let start = 20 * window as u64;
        for t in (start + 2..=start + 20).step_by(2) {
            if t == start + 10 {
                count += pulses;
            }
            motor.loop_tick(ms(t), &sensors_with_encoder(count));
        }
        let expected = (pulses as f64 * 3000.0 / 7.0) as i16;
        assert_eq!(motor.latched_rpm(), expected, "window {window}");
        let got = reply(exchange(&mut motor, ms(start + 21), &req(1, 3, 5, 0)).unwrap());
        assert_eq!(got.value, expected as u16, "two's complement on the wire");
    }
    // Steps of 428.57: 24 pulses -> 10285, 1 -> 428, -23 -> -9857.
    assert_eq!((24.0f64 * 3000.0 / 7.0) as i16, 10285);
}

#[test]
fn motor_exceptions_in_the_specified_order() {
    let mut motor = MotorNode::default();
    let t = ms(0);
    let ask = |motor: &mut MotorNode, f: u8, a: u16, v: u16| {
        reply(exchange(motor, t, &req(1, f, a, v)).unwrap())
    };
    // Captured exception replies, byte for byte.
    assert_eq!(
        exchange(&mut motor, t, &req(1, 6, 1, 0x78)),
        Some(vector("reply: exception 03 illegal data"))
    );
    assert_eq!(
        exchange(&mut motor, t, &req(1, 6, 2, 0)),
        Some(vector("reply: exception 02 illegal address"))
    );
    assert_eq!(
        exchange(&mut motor, t, &req(1, 4, 1, 0)),
        Some(vector("reply: exception 01 illegal function"))
    );
    // Address before function: an unknown function at an unknown address is 02.
    assert_eq!(ask(&mut motor, 4, 2, 0).value, 2);
    assert_eq!(ask(&mut motor, 4, 2, 0).function, 0x84);
    // Function before value: writing the read-only rpm is 01 whatever the value.
    let f = ask(&mut motor, 6, 5, 0xffff);
    assert_eq!((f.function, f.value), (0x86, 1));
    // Reading the write-only set speed is 01.
    let f = ask(&mut motor, 3, 9, 0);
    assert_eq!((f.function, f.value), (0x83, 1));
    // Set speed: 21..=12499 decimal, else 03 and the set point is kept.
    for (value, ok) in [
        (20u16, false),
        (21, true),
        (12_499, true),
        (12_500, false),
        (0, false),
    ] {
        let f = ask(&mut motor, 6, 9, value);
        if ok {
            assert_eq!((f.function, f.value), (6, value));
            assert_eq!(motor.set_point(), value);
        } else {
            assert_eq!((f.function, f.value), (0x86, 3), "set speed {value}");
            assert_ne!(motor.set_point(), value);
        }
    }
    // Control state: only 01 02 80 81 82.
    for value in [0u16, 3, 0x7f, 0x83, 0x100, 0x8001] {
        let f = ask(&mut motor, 6, 1, value);
        assert_eq!((f.function, f.value), (0x86, 3), "state {value:#x}");
    }
    assert_eq!(motor.state(), MotorState::PreOperational);
}

#[test]
fn slaves_stay_silent_on_bad_crc_other_ids_and_partial_frames() {
    let mut motor = MotorNode::default();
    let mut light = LightNode::default();
    let mut t = 0;
    for v in vectors().iter().filter(|v| !v.valid) {
        let bytes = hex(&v.frame_hex);
        assert_eq!(exchange(&mut motor, ms(t), &bytes), None, "{}", v.note);
        assert_eq!(exchange(&mut light, ms(t), &bytes), None, "{}", v.note);
        // Let the discard after a bad CRC end.
        motor.handle_timeout(ms(t + 10));
        light.handle_timeout(ms(t + 10));
        t += 20;
    }
    assert!(t > 0);
    assert_eq!(motor.state(), MotorState::PreOperational);
    // Requests for the other slave or an unknown id.
    assert_eq!(exchange(&mut motor, ms(t + 20), &req(2, 3, 6, 0)), None);
    assert_eq!(exchange(&mut light, ms(t + 20), &req(1, 3, 1, 0)), None);
    assert_eq!(exchange(&mut light, ms(t + 20), &req(3, 3, 6, 0)), None);
    // Seven bytes, then silence: dropped; the next full frame is answered.
    let read_state = req(1, 3, 1, 0);
    assert_eq!(exchange(&mut motor, ms(t + 30), &read_state[..7]), None);
    motor.handle_timeout(ms(t + 40));
    assert!(exchange(&mut motor, ms(t + 50), &read_state).is_some());
}

#[test]
fn the_crc_order_is_a_setting() {
    let standard = vectors()
        .into_iter()
        .find(|v| v.valid_standard_order && !v.valid)
        .unwrap();
    let bytes = hex(&standard.frame_hex);
    let port = PortConfig {
        crc_order: CrcOrder::LowFirst,
        ..PortConfig::default()
    };
    let mut motor = MotorNode::new(MotorConfig {
        port,
        ..MotorConfig::default()
    });
    // The standard-order write of 0x80 is echoed in standard order.
    assert_eq!(exchange(&mut motor, ms(0), &bytes), Some(bytes));
    let mut default_motor = MotorNode::default();
    assert_eq!(exchange(&mut default_motor, ms(0), &bytes), None);
}

#[test]
fn injected_reply_crc_fault_adds_one_as_the_project_did() {
    let mut motor = MotorNode::default();
    motor.set_corrupt_reply_crc(true);
    let write_80 = vector("request: motor, write control state 0x80");
    let bad = exchange(&mut motor, ms(0), &write_80).unwrap();
    assert_eq!(bad, vector("bad CRC: must be ignored by a slave"));
}

#[test]
fn control_states_and_what_they_drive() {
    let mut motor = MotorNode::default();
    let idle = plant::Sensors::default();
    let drive = motor.loop_tick(ms(0), &idle);
    assert!(!drive.enable, "pre-operational at boot: driver asleep");
    exchange(&mut motor, ms(1), &req(1, 6, 1, 1)).unwrap();
    assert_eq!(motor.state(), MotorState::Operational);
    assert!(motor.loop_tick(ms(2), &idle).enable);
    exchange(&mut motor, ms(3), &req(1, 6, 1, 2)).unwrap();
    assert!(!motor.loop_tick(ms(4), &idle).enable);
    assert_eq!(motor.state(), MotorState::Stopped);
    // Init reads 0x81 until the next loop pass, then falls to 0x80.
    exchange(&mut motor, ms(5), &req(1, 6, 1, 0x81)).unwrap();
    assert_eq!(
        reply(exchange(&mut motor, ms(5), &req(1, 3, 1, 0)).unwrap()).value,
        0x81
    );
    motor.loop_tick(ms(6), &idle);
    assert_eq!(
        reply(exchange(&mut motor, ms(7), &req(1, 3, 1, 0)).unwrap()).value,
        0x80
    );
    // Reset communication: the write is echoed, the next loop pass closes
    // the port for 3 ms and goes to init, the one after to pre-operational.
    assert!(exchange(&mut motor, ms(8), &req(1, 6, 1, 0x82)).is_some());
    assert_eq!(motor.state(), MotorState::ResetCommunication);
    motor.loop_tick(ms(10), &idle);
    assert_eq!(motor.state(), MotorState::Init);
    assert_eq!(
        exchange(&mut motor, ms(12), &req(1, 3, 1, 0)),
        None,
        "port closed"
    );
    let answer = exchange(&mut motor, ms(14), &req(1, 3, 1, 0)).unwrap();
    assert_eq!(reply(answer).value, 0x81);
    motor.loop_tick(ms(14), &idle);
    assert_eq!(motor.state(), MotorState::PreOperational);
}

#[test]
fn encoder_fault_held_low_over_5_ms_stops_the_motor() {
    let mut motor = MotorNode::default();
    let idle = plant::Sensors::default();
    exchange(&mut motor, ms(0), &req(1, 6, 1, 1)).unwrap();
    motor.set_encoder_fault(ms(0), true);
    for t in (0..=4).step_by(2) {
        motor.loop_tick(ms(t), &idle);
    }
    assert_eq!(motor.state(), MotorState::Operational, "4 ms is not enough");
    motor.loop_tick(ms(6), &idle);
    assert_eq!(motor.state(), MotorState::Stopped);
}

#[test]
fn pi_runs_every_100_ms_only_in_operational() {
    let mut motor = MotorNode::default();
    motor.loop_tick(ms(0), &sensors_with_encoder(0));
    // Pre-operational for 200 ms: no PI, duty stays 0.
    for t in (2..=200).step_by(2) {
        motor.loop_tick(ms(t), &sensors_with_encoder(0));
    }
    assert_eq!(motor.duty(), 0.0);
    exchange(&mut motor, ms(201), &req(1, 6, 1, 1)).unwrap();
    // The pending 100 ms flag runs the PI at the first operational pass:
    // e = 10000, integral = 1000, output = 0.27 (10000 + 1000/0.41) = 3358.5;
    // duty = trunc(33.585 %) = 33 %.
    let drive = motor.loop_tick(ms(202), &sensors_with_encoder(0));
    assert_eq!(motor.duty(), 0.33);
    assert!((drive.vel_volts - 1.65).abs() < 1e-12);
    // Nothing changes until the next 100 ms mark.
    for t in (204..300).step_by(2) {
        motor.loop_tick(ms(t), &sensors_with_encoder(0));
        assert_eq!(motor.duty(), 0.33);
    }
    // Second run: integral 2000, output 0.27 (10000 + 2000/0.41) = 4017.07 -> 40 %.
    motor.loop_tick(ms(300), &sensors_with_encoder(0));
    assert_eq!(motor.duty(), 0.40);
}

/// Light-sensor ADC counts: dark below 3.0 V is below 613.8 counts.
const LIT: u16 = 900;
const DARK: u16 = 613;

fn light_sample(light: &mut LightNode, t: u64, counts: u16) {
    let s = plant::Sensors {
        ldr_counts: counts,
        ..Default::default()
    };
    light.loop_tick(ms(t), &s);
}

#[test]
fn light_threshold_is_3_volts() {
    let mut light = LightNode::default();
    light_sample(&mut light, 0, 614); // 3.0009 V: light
    light_sample(&mut light, 20, 613); // 2.996 V: dark, first edge
    assert_eq!(light.edges(), 1);
    light_sample(&mut light, 40, 614);
    light_sample(&mut light, 60, 613);
    assert_eq!(light.edges(), 2);
    assert_eq!(light.raw_rpm(), 60_000.0 / 40.0);
}

#[test]
fn light_blend_matches_hand_calculation() {
    let mut light = LightNode::default();
    // Edges at 0 ms (starts timing) and 600 ms (100 rpm); dark one sample each.
    for t in (0..=600).step_by(20) {
        light_sample(
            &mut light,
            t,
            if t.is_multiple_of(600) { DARK } else { LIT },
        );
    }
    assert_eq!(light.raw_rpm(), 100.0);
    assert_eq!(light.last_interval_ms(), Some(600));
    // Ring before: zeros. rpm 100 enters: mean 20, rpm = 30 + 14 = 44.
    assert!((light.rpm() - 44.0).abs() < 1e-9, "{}", light.rpm());
    assert_eq!(light.register_value(), 4400);
    // Next sample: 44 enters, ring [0 0 0 100 44], mean 28.8:
    // rpm = 13.2 + 20.16 = 33.36 -> register 3336.
    light_sample(&mut light, 620, LIT);
    assert!((light.rpm() - 33.36).abs() < 1e-9);
    assert_eq!(light.register_value(), 3336);
    // The register is what a read returns.
    let got = reply(exchange(&mut light, ms(621), &req(2, 3, 6, 0)).unwrap());
    assert_eq!(got.value, 3336);
}

#[test]
fn light_steady_edges_settle_at_the_raw_rate() {
    let mut light = LightNode::default();
    for t in (0..=12_000).step_by(20) {
        light_sample(
            &mut light,
            t,
            if t.is_multiple_of(480) { DARK } else { LIT },
        );
    }
    // 480 ms per turn: 125 rpm; the blend converges to it.
    assert_eq!(light.raw_rpm(), 125.0);
    assert!((light.rpm() - 125.0).abs() < 0.5, "{}", light.rpm());
}

#[test]
fn light_times_out_after_5_s_and_restarts_timing() {
    let mut light = LightNode::default();
    let mut t = 0;
    while t <= 2_000 {
        light_sample(
            &mut light,
            t,
            if t.is_multiple_of(500) { DARK } else { LIT },
        );
        t += 20;
    }
    assert!(light.rpm() > 50.0);
    // Last edge at 2000 ms; none after.
    let mut zero_at = None;
    while t <= 7_200 {
        light_sample(&mut light, t, LIT);
        if zero_at.is_none() && light.register_value() == 0 {
            zero_at = Some(t);
        }
        t += 20;
    }
    let zero_at = zero_at.expect("register falls to 0");
    // Forced to 0 from 7000 ms; the ring empties in 5 samples.
    assert!((7_000..=7_080).contains(&zero_at), "{zero_at}");
    // The next edge only restarts timing; the one after gives a rate again.
    light_sample(&mut light, 7_220, DARK);
    assert_eq!(light.raw_rpm(), 0.0);
    light_sample(&mut light, 7_240, LIT);
    light_sample(&mut light, 7_820, DARK);
    assert_eq!(light.last_interval_ms(), Some(600));
    assert_eq!(light.raw_rpm(), 100.0);
}

#[test]
fn light_exceptions() {
    let mut light = LightNode::default();
    let f = reply(exchange(&mut light, ms(0), &req(2, 6, 6, 1)).unwrap());
    assert_eq!((f.function, f.value), (0x86, 1));
    let f = reply(exchange(&mut light, ms(0), &req(2, 3, 1, 0)).unwrap());
    assert_eq!((f.function, f.value), (0x83, 2));
    let f = reply(exchange(&mut light, ms(0), &req(2, 4, 6, 0)).unwrap());
    assert_eq!((f.function, f.value), (0x84, 1));
    assert_eq!(
        exchange(
            &mut light,
            ms(0),
            &vector("request: light sensor, read value")
        ),
        Some(req(2, 3, 6, 0)),
        "boot value 0"
    );
}
