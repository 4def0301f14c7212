//! The supervisor's speed loop closed over MEB through the real EV
//! controller sketch in simavr, held against the same loop through the
//! twin's Rust model of that controller; and the same seed giving the same
//! recording, byte for byte.

use crate::common;

use std::path::PathBuf;
use std::sync::OnceLock;

use twin_sim::scenario::Scenario;
use twin_sim::virtual_run;

fn elf() -> &'static PathBuf {
    static ELF: OnceLock<PathBuf> = OnceLock::new();
    ELF.get_or_init(|| common::make("ev", "", &["ev-controller"]).join("ev-controller.elf"))
}

/// The shipped scenario, with the sketch built here and `duration_s`.
fn with_sketch(duration_s: f64) -> Scenario {
    let text = std::fs::read_to_string(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenarios/ev-meb-avr.toml"),
    )
    .expect("scenario");
    let text = text.replace(
        "twin/avr/firmware/build/ev-controller.elf",
        &elf().display().to_string(),
    );
    let mut s = Scenario::parse(&text, "ev-meb-avr.toml").expect("scenario parses");
    s.duration_s = duration_s;
    s
}

fn out(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name)
}

#[test]
fn the_supervisor_closes_the_loop_through_the_sketch_as_through_the_rust_controller() {
    twin_avr::register();
    let sketch = with_sketch(3.0);
    let mut model = Scenario::load("ev-meb").expect("ev-meb");
    model.duration_s = 3.0;
    let a =
        virtual_run::run(&sketch, &out("ev-meb-avr.mcap"), |_| {}).expect("runs with the sketch");
    let b =
        virtual_run::run(&model, &out("ev-meb-rust.mcap"), |_| {}).expect("runs with the model");
    let wheel = |o: &virtual_run::RunOutcome| o.modules[0].1.wheel_rpm;
    let (sketch_rpm, model_rpm) = (wheel(&a), wheel(&b));
    println!(
        "wheel at 3 s, set point 1000 rpm: sketch {sketch_rpm:.1} rpm, Rust controller {model_rpm:.1} rpm, {:+.2} % apart; V1 {:.3} V vs {:.3} V",
        (sketch_rpm / model_rpm - 1.0) * 100.0,
        a.modules[0].1.battery_volts,
        b.modules[0].1.battery_volts
    );
    for (who, rpm) in [("sketch", sketch_rpm), ("Rust controller", model_rpm)] {
        assert!(
            (rpm - 1000.0).abs() <= 20.0,
            "the loop through the {who} settled at {rpm:.1} rpm, not within 2 % of 1000"
        );
    }
    // The supervisor polled the sketch all along. Its first write, at power-up,
    // comes while the board is still starting (the Arduino core's init and
    // Serial.begin): that one may time out, as on the bench, and none after.
    assert!(
        a.events.get("timeout").copied().unwrap_or(0) <= 1,
        "{:?}",
        a.events
    );
    assert!(a.frames > 500, "{} frames", a.frames);
}

#[test]
fn the_same_seed_and_firmware_give_the_same_recording_bytes() {
    twin_avr::register();
    let scenario = with_sketch(0.8);
    let first = virtual_run::run(&scenario, &out("same-1.mcap"), |_| {}).expect("run 1");
    let second = virtual_run::run(&scenario, &out("same-2.mcap"), |_| {}).expect("run 2");
    let a = std::fs::read(first.recording).unwrap();
    let b = std::fs::read(second.recording).unwrap();
    assert!(a.len() > 10_000, "{} bytes", a.len());
    assert!(
        a == b,
        "two runs of one seed differ ({} and {} bytes)",
        a.len(),
        b.len()
    );
}

#[test]
fn twin_without_the_avr_builder_says_where_to_run_firmware() {
    // This test binary registers the builder in other tests; the message
    // itself comes from twin-sim, which `twin` uses alone.
    let scenario = with_sketch(0.1);
    let spec = scenario.nodes.iter().find(|n| n.name() == "ev1").unwrap();
    let err = twin_sim::external::unavailable::<()>(spec)
        .unwrap_err()
        .to_string();
    assert!(err.contains("twin-avr run"), "{err}");
}
