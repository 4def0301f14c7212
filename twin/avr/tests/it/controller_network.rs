//! The Controller_network project's two Nanos as real sketches (our
//! `motor-nano` and `light-nano`, written from the 8-byte Modbus protocol
//! page) in simavr, held against the twin's Rust motor and light nodes on
//! the same bench and master; and the motor sketch's encoder count held to
//! the plant's own edges, one by one.

use crate::common;

use std::path::PathBuf;
use std::process::Command;
use std::sync::OnceLock;

use nodes::node::{Firmware, Node};
use plant::{Actuators, EvModule, PlantParams};
use protocols::time::{SimDuration, SimTime};
use twin_avr::node::Board;
use twin_avr::{AvrNode, Wiring};
use twin_sim::scenario::Scenario;
use twin_sim::virtual_run;

fn crate_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn build_dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| common::make("nanos", "", &["motor-nano", "light-nano"]))
}

fn out(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name)
}

fn master_reads(o: &virtual_run::RunOutcome) -> (f64, f64) {
    let (_, t) = o
        .telemetry
        .iter()
        .find(|(n, _)| n == "rpi")
        .expect("the master reports");
    (
        t["motor_rpm"].as_f64().unwrap_or(f64::NAN),
        t["sensor_value"].as_f64().unwrap_or(f64::NAN),
    )
}

#[test]
fn the_nano_sketches_run_the_bench_as_the_rust_motor_and_light_nodes_do() {
    twin_avr::register();
    let seconds = 8.0;
    let text = std::fs::read_to_string(crate_dir().join("scenarios/controller-network-avr.toml"))
        .expect("scenario")
        .replace(
            "twin/avr/firmware/build/",
            &format!("{}/", build_dir().display()),
        );
    let mut sketches = Scenario::parse(&text, "controller-network-avr.toml").expect("parses");
    // Its master starts once the Nanos have booted: both are compared the
    // same time after their master's start.
    sketches.duration_s = seconds + sketches.masters_start_s();
    let mut model = Scenario::load("controller-network").expect("controller-network");
    model.duration_s = seconds;
    let a = virtual_run::run(&sketches, &out("cn-avr.mcap"), |_| {}).expect("runs the sketches");
    let b = virtual_run::run(&model, &out("cn-rust.mcap"), |_| {}).expect("runs the Rust nodes");
    let (a_motor, a_sensor) = master_reads(&a);
    let (b_motor, b_sensor) = master_reads(&b);
    let (a_bench, b_bench) = (&a.modules[0].1, &b.modules[0].1);
    println!(
        "at {seconds} s, set point 10000 rpm: motor {:.0} rpm (sketches) vs {:.0} rpm (Rust nodes), \
         wheel {:.1} vs {:.1} rpm; the master read motor {a_motor} vs {b_motor}, sensor {a_sensor} vs {b_sensor}",
        a_bench.motor_rpm, b_bench.motor_rpm, a_bench.wheel_rpm, b_bench.wheel_rpm
    );
    // Both loops settled within 2 % of the set point, the plant's own speed.
    for (who, rpm) in [
        ("sketches", a_bench.motor_rpm),
        ("Rust nodes", b_bench.motor_rpm),
    ] {
        assert!(
            (rpm - 10_000.0).abs() <= 200.0,
            "the motor under the {who} runs at {rpm:.0} rpm, not within 2 % of 10000"
        );
    }
    // What the master read: one 20 ms window of encoder edges, in steps of
    // 428.57 rpm, so within two steps.
    for (who, rpm) in [("sketch", a_motor), ("Rust node", b_motor)] {
        assert!(
            (rpm - 10_000.0).abs() <= 2.0 * 428.6,
            "the {who} read {rpm} rpm"
        );
    }
    // The light sketch times the same marker as the Rust node: rpm x 100.
    assert!(
        (a_sensor / b_sensor - 1.0).abs() < 0.03,
        "sensor {a_sensor} vs {b_sensor}"
    );
    // The Nanos booted before the master's first request: none unanswered.
    assert_eq!(
        a.events.get("timeout").copied().unwrap_or(0),
        0,
        "{:?}",
        a.events
    );
}

/// The address of a global of the sketch in its data space (`avr-nm`).
fn symbol(elf: &std::path::Path, name: &str) -> u16 {
    let out = Command::new("avr-nm")
        .arg(elf)
        .output()
        .expect("avr-nm runs (gcc-avr's binutils)");
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find(|l| l.ends_with(&format!(" {name}")))
        .unwrap_or_else(|| panic!("{name} not in {}", elf.display()));
    let addr = u32::from_str_radix(line.split_whitespace().next().unwrap(), 16).unwrap();
    (addr & 0xFFFF) as u16
}

#[test]
fn the_motor_sketch_counts_every_rising_edge_of_the_plants_encoder() {
    let elf = build_dir().join("motor-nano.elf");
    let count_at = symbol(&elf, "_ZL13encoder_count");
    let params = PlantParams::preset("controller-network").expect("preset");
    let mut node = AvrNode::start(
        Board {
            name: "motor",
            elf: &elf,
            mcu: "atmega328p",
            clock_hz: 16_000_000,
            bus_baud: 115_200,
            bus_bits: 10,
        },
        Wiring::load("motor-nano").expect("map"),
        params.sensing.clone(),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let mut plant = EvModule::new(&params, 7);
    // The driver enabled at 60 % throttle: the motor spins up through a
    // range of edge rates.
    let drive = Actuators {
        vel_volts: 3.0,
        enable: true,
        ..Actuators::default()
    };
    let step = SimDuration::from_micros(100);
    let mut t = SimTime::ZERO;
    let mut rising = 0i64;
    let mut a = plant.sensors().shaft.encoder_a;
    let end = SimTime::ZERO + SimDuration::from_millis(1500);
    while t < end {
        t += step;
        let sensors = *plant.step(step.as_secs_f64(), &drive);
        if sensors.shaft.encoder_a && !a {
            rising += 1;
        }
        a = sensors.shaft.encoder_a;
        node.loop_tick(t, &sensors);
        if node.poll_timeout().is_some_and(|d| d <= t) {
            node.handle_timeout(t);
        }
    }
    let bytes: [u8; 4] = std::array::from_fn(|i| node.ram(count_at + i as u16));
    let counted = i32::from_le_bytes(bytes);
    println!(
        "1.5 s spinning up to {:.0} rpm: the plant's encoder A rose {rising} times, the sketch counted {counted}",
        plant.sensors().motor_rpm
    );
    assert!(rising > 500, "the motor barely turned: {rising} edges");
    assert_eq!(i64::from(counted), rising);
}

/// Each Nano sketch folder carries its own copy of the protocol header, so
/// it opens alone in the Arduino IDE; the copies must not drift apart.
#[test]
fn both_nanos_speak_the_same_modbus8() {
    let firmware = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("firmware");
    let read = |sketch: &str| {
        std::fs::read_to_string(firmware.join(sketch).join("modbus8.h"))
            .unwrap_or_else(|e| panic!("{sketch}/modbus8.h: {e}"))
    };
    assert_eq!(read("motor-nano"), read("light-nano"));
}
