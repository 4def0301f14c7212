//! The Controller_network project's nodes (`docs/protocols/modbus8.md`) through the
//! virtual-time engine: the Raspberry Pi master's handshake with the motor
//! node, the motor's 428.57-rpm reading steps against the plant's true speed,
//! and the light sensor's register against its smoothing rule, all read from
//! the 8-byte frames on the wire.

use e2e::{Capture, WireFrame, at, run_captured};
use protocols::modbus8::{self, CrcOrder, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};
use twin_sim::scenario::Scenario;

/// The embedded scenario, read from its file so the test follows the file.
const CONTROLLER_NETWORK: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../recordings/scenarios/controller-network.toml"
));

/// Frames copied from the Controller_network project's own terminal output.
const VECTORS: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../nodes/tests/vectors/modbus8.jsonl"
);

/// Wire rpm step of the motor node: one encoder pulse per 20 ms window is
/// 50 / 7 × 60 rpm.
const RPM_STEP: f64 = 3000.0 / 7.0;

/// An 8-byte frame's fields.
trait Decoded {
    fn decoded(&self) -> Modbus8Repr;
}

impl Decoded for WireFrame {
    fn decoded(&self) -> Modbus8Repr {
        Modbus8Repr::parse(&self.bytes, CrcOrder::HighFirst)
            .unwrap_or_else(|e| panic!("{} sent {:02x?}: {e}", self.from, self.bytes))
    }
}

/// The network run for `seconds`, and the light node's final state.
fn run_network(seconds: f64) -> (Capture, serde_json::Value) {
    let scenario = Scenario::parse(CONTROLLER_NETWORK, "controller-network.toml")
        .expect("controller-network parses");
    let (capture, mut engine) = run_captured(&scenario, seconds);
    let light = engine
        .nodes
        .iter_mut()
        .find(|n| n.name == "sensor")
        .and_then(|n| n.node.final_state())
        .expect("the light node reports its state");
    (capture, light)
}

/// The bytes of the vector frame whose note is `note`.
fn vector(note: &str) -> Vec<u8> {
    let text = std::fs::read_to_string(VECTORS).expect("modbus8 vectors");
    let line = text
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).expect("vector line is JSON"))
        .find(|v| v["note"] == note)
        .unwrap_or_else(|| panic!("no vector `{note}`"));
    let hex = line["frame_hex"].as_str().expect("frame_hex");
    (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).expect("hex"))
        .collect()
}

/// Each master request with the reply that followed it.
fn exchanges(frames: &[WireFrame]) -> Vec<(&WireFrame, &WireFrame)> {
    frames
        .windows(2)
        .filter(|pair| pair[0].from == "rpi" && pair[1].from != "rpi")
        .map(|pair| (&pair[0], &pair[1]))
        .collect()
}

#[test]
fn handshake_takes_the_motor_from_pre_operational_to_operational() {
    let (capture, _) = run_network(2.0);
    let frames = &capture.frames;
    assert!(frames.len() >= 10, "{} frames in 2 s", frames.len());
    let read_state = vector("request: motor, read control state");
    // Read the state: pre-operational (0x80) after boot.
    assert_eq!(frames[0].from, "rpi");
    assert_eq!(frames[0].bytes, read_state);
    assert_eq!(frames[1].from, "motor");
    let booted = frames[1].decoded();
    assert_eq!(
        (booted.id, booted.function, booted.addr),
        (1, modbus8::READ, 1)
    );
    assert_eq!(booted.reply(), Ok(0x80));
    // Write operational: 01 06 0001 0001, echoed by the motor.
    assert_eq!(frames[2].from, "rpi");
    assert_eq!(&frames[2].bytes[..6], &[0x01, 0x06, 0x00, 0x01, 0x00, 0x01]);
    assert_eq!(
        frames[2].decoded(),
        Modbus8Repr {
            id: 1,
            function: modbus8::WRITE,
            addr: 1,
            value: 1
        }
    );
    assert_eq!(frames[3].from, "motor");
    assert_eq!(frames[3].bytes, frames[2].bytes, "a write is echoed");
    // Read again: operational, then the loop starts with the rpm read.
    assert_eq!(frames[4].bytes, read_state);
    assert_eq!(
        frames[5].bytes,
        vector("reply: control state 0x01 (operational)")
    );
    assert_eq!(frames[6].bytes, vector("request: motor, read rpm"));
    assert_eq!(frames[8].bytes, vector("request: light sensor, read value"));
    assert_eq!(frames[9].from, "sensor");
    let state_writes = frames
        .iter()
        .filter(|f| f.from == "rpi" && f.decoded().function == modbus8::WRITE)
        .filter(|f| f.decoded().addr == 1)
        .count();
    assert_eq!(state_writes, 1, "one handshake");
    assert!(
        capture.events.iter().any(|(node, e)| node == "motor"
            && e.kind == "state"
            && e.detail.ends_with("-> 0x01 (operational)")),
        "the motor reports its move to operational"
    );
}

#[test]
fn an_8_byte_exchange_takes_160_bit_times_plus_the_turnaround() {
    let (capture, _) = run_network(5.0);
    let wire = SimDuration::bit_times(160, 115_200);
    assert!((wire.as_secs_f64() - 1.389e-3).abs() < 0.5e-6);
    let turnaround = SimDuration::from_millis(1);
    let pairs = exchanges(&capture.frames);
    assert!(pairs.len() >= 10, "{} exchanges in 5 s", pairs.len());
    for (request, reply) in pairs {
        assert_eq!((request.bytes.len(), reply.bytes.len()), (8, 8));
        assert_eq!(reply.start - request.end, turnaround);
        assert_eq!(reply.end - request.start, wire + turnaround);
    }
}

/// Stretches where the master's set point has been 10000 rpm (the motor's
/// default, then every other toggle) for at least `settle_s`: the motor's own
/// PI holds it steady there (at 5000 rpm it hunts by several percent).
fn steady_at_10000(frames: &[WireFrame], settle_s: f64, end_s: f64) -> Vec<(SimTime, SimTime)> {
    let mut changes = vec![(SimTime::ZERO, 10_000)];
    for f in frames.iter().filter(|f| f.from == "rpi") {
        let frame = f.decoded();
        if frame.function == modbus8::WRITE && frame.addr == 9 {
            changes.push((f.end, frame.value));
        }
    }
    let mut stretches = Vec::new();
    for (i, &(from, value)) in changes.iter().enumerate() {
        let until = changes.get(i + 1).map_or(at(end_s), |next| next.0);
        let from = from + SimDuration::from_secs_f64(settle_s);
        if value == 10_000 && from < until {
            stretches.push((from, until));
        }
    }
    stretches
}

#[test]
fn motor_readings_alternate_between_neighbouring_steps_and_track_the_true_speed() {
    // Two stretches at 10000 rpm: boot to the first toggle (~13.7 s) and the
    // second toggle (~27.9 s) to the third (~42 s).
    let end_s = 42.0;
    let (capture, _) = run_network(end_s);
    let stretches = steady_at_10000(&capture.frames, 7.0, end_s);
    assert_eq!(stretches.len(), 2, "{stretches:?}");
    let inside = |t: SimTime| stretches.iter().any(|&(a, b)| t >= a && t < b);

    let true_rpm: Vec<f64> = capture
        .plant
        .iter()
        .filter(|(t, _)| inside(*t))
        .map(|(_, s)| s.motor_rpm)
        .collect();
    let true_mean = true_rpm.iter().sum::<f64>() / true_rpm.len() as f64;
    for rpm in &true_rpm {
        assert!(
            (rpm / true_mean - 1.0).abs() < 0.03,
            "not steady: {rpm:.0} rpm against a mean of {true_mean:.0}"
        );
    }

    // Each reading with the request it answers: the motor node latches the
    // pulses of its last whole 20 ms window, so the reading counts the
    // motor's speed at some point of the 40 ms before the request ended.
    let readings: Vec<(SimTime, i16)> = exchanges(&capture.frames)
        .into_iter()
        .filter(|(request, reply)| inside(request.end) && reply.from == "motor")
        .map(|(request, reply)| (request.end, reply.decoded()))
        .filter(|(_, f)| f.function == modbus8::READ && f.addr == 5)
        .map(|(t, f)| (t, f.value as i16))
        .collect();
    assert!(readings.len() >= 15, "{} readings", readings.len());
    // Every reading is a whole number of pulses per window, truncated as the
    // firmware does: the step at or just below the true speed of its window,
    // or the one above when the window caught one pulse more.
    let window = SimDuration::from_millis(40);
    for &(t, r) in &readings {
        let speeds: Vec<f64> = capture
            .plant
            .iter()
            .filter(|(at, _)| *at + window >= t && *at <= t)
            .map(|(_, s)| s.motor_rpm)
            .collect();
        let lo = speeds.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = speeds.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let steps = f64::from(r) / RPM_STEP;
        assert!(
            (steps - steps.round()).abs() < 0.01,
            "reading {r} rpm is not a whole number of {RPM_STEP:.2}-rpm steps"
        );
        assert!(
            steps.round() >= (lo / RPM_STEP).floor()
                && steps.round() <= (hi / RPM_STEP).floor() + 1.0,
            "reading {r} rpm at {:.3} s: the motor turned at {lo:.0}-{hi:.0} rpm in the window",
            t.as_secs_f64()
        );
    }
    let readings: Vec<i16> = readings.into_iter().map(|(_, r)| r).collect();
    let distinct: std::collections::BTreeSet<i16> = readings.iter().copied().collect();
    assert!(
        distinct.len() >= 2,
        "the readings {readings:?} never alternate between neighbouring steps"
    );
    let reading_mean = readings.iter().map(|&r| f64::from(r)).sum::<f64>() / readings.len() as f64;
    println!(
        "{} readings {readings:?}: mean {reading_mean:.0} rpm, true {true_mean:.0} rpm",
        readings.len()
    );
    assert!(
        (reading_mean / true_mean - 1.0).abs() < 0.02,
        "readings average {reading_mean:.0} rpm, the motor turns at {true_mean:.0} rpm"
    );
}

/// The light sensor's rpm as `docs/protocols/modbus8.md` defines it, replayed from the
/// photoresistor counts the plant showed at each of the node's 20 ms samples.
#[derive(Debug)]
struct LightModel {
    /// Marks on the wheel (the preset's `light.flags`): rpm = 60000 / (marks × Δt).
    marks: f64,
    dark: bool,
    last_edge_ms: Option<u64>,
    timeout_from_ms: u64,
    rpm: f64,
    raw_rpm: f64,
    ring: [f64; 5],
    ring_filled: usize,
    ring_next: usize,
}

impl LightModel {
    /// At reset, as the firmware's `lastRoundTime = 0`: a first edge within
    /// 5 s is timed from reset.
    fn new(marks: u32) -> Self {
        LightModel {
            marks: f64::from(marks),
            dark: false,
            last_edge_ms: Some(0),
            timeout_from_ms: 0,
            rpm: 0.0,
            raw_rpm: 0.0,
            ring: [0.0; 5],
            ring_filled: 0,
            ring_next: 0,
        }
    }

    fn sample(&mut self, now_ms: u64, ldr_counts: u16) {
        // 10-bit ADC on a 5 V reference; below 3.0 V is dark.
        let dark = f64::from(ldr_counts) * 5.0 / 1023.0 < 3.0;
        if dark && !self.dark {
            if let Some(last) = self.last_edge_ms {
                let interval = now_ms - last;
                assert_eq!(interval % 20, 0, "edges fall on the 20 ms grid");
                self.raw_rpm = 60_000.0 / (self.marks * interval as f64);
                self.rpm = self.raw_rpm;
            }
            self.last_edge_ms = Some(now_ms);
            self.timeout_from_ms = now_ms;
        }
        self.dark = dark;
        if now_ms - self.timeout_from_ms >= 5_000 {
            self.rpm = 0.0;
            self.raw_rpm = 0.0;
            self.last_edge_ms = None;
        }
        self.ring[self.ring_next] = self.rpm;
        self.ring_next = (self.ring_next + 1) % 5;
        self.ring_filled = (self.ring_filled + 1).min(5);
        if self.ring_filled == 5 {
            let mean = self.ring.iter().sum::<f64>() / 5.0;
            self.rpm = 0.3 * self.rpm + 0.7 * mean;
        }
    }

    /// What register `0006` holds: rpm × 100, truncated.
    fn register(&self) -> u16 {
        (self.rpm * 100.0) as u16
    }
}

#[test]
fn light_register_holds_the_smoothed_rpm_times_100() {
    let end_s = 30.0;
    let (capture, light) = run_network(end_s);
    // The node samples at 0, 20, 40 … ms; the plant is recorded every 5 ms
    // on the same instants, after the firmware's tick.
    let sample_period = SimDuration::from_millis(20);
    let mut model = LightModel::new(plant::PlantParams::controller_network().light.flags);
    // After each sample: when, the register, and the true wheel speed.
    let mut registers: Vec<(SimTime, u16, f64)> = Vec::new();
    for (t, sensors) in &capture.plant {
        if t.0 % sample_period.0 == 0 {
            let now_ms = t.0 / SimDuration::from_millis(1).0;
            model.sample(now_ms, sensors.ldr_counts);
            registers.push((*t, model.register(), sensors.wheel_rpm));
        }
    }
    assert_eq!(registers.len(), 1 + (end_s * 50.0) as usize);

    // The wheel's speed is steady (to about 1 %) once the motor has held
    // 10000 rpm for a while; the smoothing has long caught up by then.
    let steady_stretches = steady_at_10000(&capture.frames, 8.0, end_s);
    let mut compared = 0;
    let mut steady = Vec::new();
    for (request, reply) in exchanges(&capture.frames) {
        let frame = reply.decoded();
        if reply.from != "sensor" {
            continue;
        }
        assert_eq!(
            (frame.id, frame.function, frame.addr),
            (2, modbus8::READ, 6)
        );
        // The request is served when its last byte lands, before a firmware
        // tick at that same instant: the last sample strictly before.
        let (sampled_at, expected, wheel_rpm) = registers
            .iter()
            .rev()
            .find(|(t, _, _)| *t < request.end)
            .copied()
            .expect("a sample before the request");
        assert_eq!(
            frame.value,
            expected,
            "sensor read at {:.3} s (sample at {:.3} s)",
            request.end.as_secs_f64(),
            sampled_at.as_secs_f64()
        );
        compared += 1;
        if steady_stretches
            .iter()
            .any(|&(from, until)| request.end >= from && request.end < until)
        {
            steady.push((f64::from(frame.value) / 100.0, wheel_rpm));
        }
    }
    assert!(compared >= 35, "{compared} sensor reads compared");
    // The last unsmoothed value is 60000 / Δt on the sampling grid, and the
    // node agrees with the replay.
    let raw = light["raw_rpm"].as_f64().expect("raw_rpm");
    assert_eq!(raw, model.raw_rpm);
    let interval_ms = 60_000.0 / raw;
    assert!(
        (interval_ms / 20.0 - (interval_ms / 20.0).round()).abs() < 1e-9,
        "raw {raw} rpm is not 60000 / a multiple of 20 ms"
    );
    // At the steady 10000 motor rpm the sensor reads the wheel's speed
    // (about 99 rpm through the 100:1 gearbox) to within 2 %.
    assert!(steady.len() >= 6, "{} steady reads", steady.len());
    let n = steady.len() as f64;
    let sensed = steady.iter().map(|s| s.0).sum::<f64>() / n;
    let wheel = steady.iter().map(|s| s.1).sum::<f64>() / n;
    assert!(
        (sensed / wheel - 1.0).abs() < 0.02,
        "light sensor {sensed:.2} rpm, wheel {wheel:.2} rpm"
    );
}
