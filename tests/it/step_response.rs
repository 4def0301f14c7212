//! The step-response experiment and the light-sensor sweep on the whole
//! bench: the closed loop's figures against what the loop and the sensors
//! must give, and the speed where the light sensor stops seeing the flag
//! against the limit derived in plant/src/light.rs.

use plant::PlantParams;
use std::path::PathBuf;
use twin_lab::instruments;
use twin_lab::step::{self, StepConfig, StepDrive};
use twin_lab::sweep::{self, SweepConfig, TRACKING_TOLERANCE};
use twin_sim::scenario::Scenario;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twin-step-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("scratch folder");
    dir.join(name)
}

#[test]
fn closed_loop_step_figures_of_both_sensors() {
    let config = StepConfig {
        drive: StepDrive::ClosedLoop {
            scenario: Box::new(Scenario::load("ev-meb").expect("embedded")),
            on_light: false,
        },
        from: 100.0,
        to: 200.0,
        step_at_s: 2.0,
        duration_s: 6.0,
        seed: 1,
    };
    let recording = scratch("closed.mcap");
    let report = step::run(&config, &recording, |_| {}).expect("step runs");
    let figures = |name: &str| {
        report
            .signals
            .iter()
            .find(|s| s.signal.starts_with(name))
            .unwrap_or_else(|| panic!("no {name} row"))
    };
    let wheel = figures("wheel").metrics.expect("wheel figures");
    let hall = figures("motor");
    let light = figures("light");
    let (hall_m, light_m) = (hall.metrics.expect("hall"), light.metrics.expect("light"));
    // The loop is tuned not to overshoot and to settle within 2 % in about a second.
    assert!(wheel.overshoot_pct < 5.0, "{wheel:?}");
    let settle = wheel.settling_time_s.expect("wheel settles");
    assert!(settle < 2.0, "{wheel:?}");
    assert!((wheel.initial - 100.0).abs() < 2.0, "{wheel:?}");
    // The PI closes on the hall rpm, so that ends on the set point.
    assert!(hall_m.steady_state_error.expect("closed loop").abs() < 2.0);
    assert!(light_m.steady_state_error.expect("closed loop").abs() < 4.0);
    // The hall estimate averages 100 ms windows; the light sensor one turn
    // (0.3 s at 200 rpm, 0.6 s at 100 rpm): it lags more.
    let hall_delay = hall.delay_s.expect("hall delay");
    let light_delay = light.delay_s.expect("light delay");
    assert!((0.04..0.2).contains(&hall_delay), "hall delay {hall_delay}");
    assert!(
        (0.2..0.9).contains(&light_delay),
        "light delay {light_delay}"
    );
    assert!(light_m.rise_time_s.expect("rises") > hall_m.rise_time_s.expect("rises"));

    // The recording holds what the figures were computed from.
    let bytes = std::fs::read(&recording).expect("recording");
    let samples = mcap::MessageStream::new(&bytes)
        .expect("mcap opens")
        .filter_map(|m| m.ok())
        .filter(|m| m.channel.topic == "/experiment/step")
        .count();
    assert_eq!(samples, report.trace.time_s.len());
    assert!(samples > 2000, "{samples} samples");
}

/// Mean light rpm over true rpm at `fraction` × the detector's limit.
fn light_ratio_at(params: &PlantParams, preset: &str, adaptive: bool, fraction: f64) -> f64 {
    let (_, limit) = instruments::light_limit(params, preset, adaptive);
    let config = SweepConfig {
        params: params.clone(),
        preset: preset.into(),
        adaptive,
        target_rpm: vec![fraction * limit],
        settle_s: 3.0,
        measure_s: 3.0,
        seed: 1,
    };
    let report = sweep::run(&config, None, |_| {}).expect("sweep runs");
    assert_eq!(report.light_limit_rpm, limit);
    let p = report.points[0];
    assert!(
        (p.wheel_rpm / (fraction * limit) - 1.0).abs() < 0.03,
        "asked for {} rpm, ran at {}",
        fraction * limit,
        p.wheel_rpm
    );
    p.light_ratio
}

#[test]
fn ev_module_light_sensor_fails_where_plant_says_for_both_detectors() {
    let p = PlantParams::vemodule();
    for adaptive in [false, true] {
        let (name, limit) = instruments::light_limit(&p, "vemodule", adaptive);
        let below = light_ratio_at(&p, "vemodule", adaptive, 0.9);
        let above = light_ratio_at(&p, "vemodule", adaptive, 1.1);
        assert!(
            (below - 1.0).abs() <= TRACKING_TOLERANCE,
            "{name}: at 0.9 × {limit:.0} rpm the light reads {below} × the true speed"
        );
        assert!(
            above < 0.9,
            "{name}: at 1.1 × {limit:.0} rpm the light still reads {above} × the true speed"
        );
    }
    // The numbers the module docs of plant/src/light.rs give for the fixed threshold.
    let (_, fixed) = instruments::light_limit(&p, "vemodule", false);
    assert!((fixed - 260.0).abs() < 2.0, "{fixed}");
}

#[test]
fn controller_network_light_node_fails_below_the_formulas_speed_and_never_above() {
    // The geared bench tops out near 105 rpm; a 20:1 gearbox lets the wheel
    // pass the light sensor's limit.
    let mut p = PlantParams::controller_network();
    p.gearbox.ratio = 20.0;
    let (_, limit) = instruments::light_limit(&p, "controller-network", false);
    assert!((limit - 248.0).abs() < 2.0, "{limit}");
    // Its 20 ms sampling misses dips that spend less than a sample below
    // 3.0 V: every dip is caught below about 0.67 × the limit.
    let tracked = light_ratio_at(&p, "controller-network", false, 0.65);
    assert!(
        (tracked - 1.0).abs() <= TRACKING_TOLERANCE,
        "at 0.65 × the limit the light node reads {tracked} × the true speed"
    );
    let above = light_ratio_at(&p, "controller-network", false, 1.05);
    assert!(
        above < 0.5,
        "above the limit it reads {above} × the true speed"
    );
}

#[test]
fn pausing_a_run_to_sample_it_changes_nothing() {
    let mut scenario = Scenario::load("ev-meb").expect("embedded");
    scenario.duration_s = 3.0;
    let (plain, paused) = (scratch("plain.mcap"), scratch("paused.mcap"));
    twin_sim::virtual_run::run(&scenario, &plain, |_| {}).expect("plain run");
    let mut samples = 0;
    twin_sim::virtual_run::run_sampled(
        &scenario,
        &paused,
        |_| {},
        &Default::default(),
        Some(protocols::time::SimDuration::from_millis(2)),
        |_, _, _| {
            samples += 1;
            Ok(())
        },
    )
    .expect("paused run");
    assert_eq!(samples, 1501);
    let (a, b) = (
        std::fs::read(&plain).unwrap(),
        std::fs::read(&paused).unwrap(),
    );
    assert!(
        a == b,
        "recordings differ ({} and {} bytes)",
        a.len(),
        b.len()
    );
}

#[test]
fn the_controller_network_masters_own_step_with_both_sensors() {
    let config = StepConfig {
        drive: StepDrive::ClosedLoop {
            scenario: Box::new(Scenario::load("controller-network").expect("embedded")),
            on_light: false,
        },
        // Ignored: the Raspberry Pi master runs its own set points.
        from: f64::NAN,
        to: f64::NAN,
        step_at_s: 0.0,
        duration_s: 30.0,
        seed: 1,
    };
    let report =
        step::run(&config, &scratch("controller_network.mcap"), |_| {}).expect("step runs");
    // The master's handshake puts the motor node in operational at its
    // set point of 10000 motor rpm: 100 wheel rpm behind the 100:1 gearbox.
    assert_eq!((report.from, report.to), (0.0, 100.0));
    assert!(report.step_at_s < 1.0, "{}", report.step_at_s);
    // Measured until the master toggles to 5000 rpm (every 20th cycle).
    assert!((10.0..20.0).contains(&report.figures_until_s));
    let row = |name: &str| {
        report
            .signals
            .iter()
            .find(|s| s.signal.starts_with(name))
            .unwrap_or_else(|| panic!("no {name} row"))
    };
    assert_eq!(row("motor").signal, "motor (encoder)");
    let wheel = row("wheel").metrics.expect("wheel");
    let encoder = row("motor").metrics.expect("encoder");
    assert!((wheel.final_value - 100.0).abs() < 3.0, "{wheel:?}");
    assert!((encoder.final_value - wheel.final_value).abs() < 2.0);
    // The encoder's 20 ms windows lag a little; the light node's blend of
    // five samples and one reading per mark (three a turn: 0.2 s) lag far more.
    let (enc_delay, light_delay) = (
        row("motor").delay_s.expect("encoder delay"),
        row("light").delay_s.expect("light delay"),
    );
    assert!((0.005..0.05).contains(&enc_delay), "{enc_delay}");
    assert!(light_delay > 0.2, "{light_delay}");
}

#[test]
fn open_loop_wheel_step_is_the_dc_motors_first_order_lag() {
    // Wheel speed ω in the DC-motor model: J ω' = k n i - b ω - T_c with
    // i = (D V - k n ω) / R (the inductance's ms are negligible here), so a
    // step of the duty D is a first-order lag of τ = J / (b + (k n)² / R).
    let p = PlantParams::vemodule();
    let (k, r, n) = (
        p.motor.torque_constant,
        p.motor.resistance_ohm,
        p.gearbox.ratio,
    );
    let j = 0.5 * p.wheel.mass_kg * p.wheel.radius_m.powi(2) + p.motor.rotor_inertia * n * n;
    let tau = j / (p.wheel.viscous_friction_nms + (k * n).powi(2) / r);
    let config = StepConfig {
        drive: StepDrive::OpenLoop {
            params: Box::new(p),
            preset: "vemodule".into(),
            adaptive_light: false,
        },
        from: 0.025,
        to: 0.045,
        step_at_s: 2.0,
        duration_s: 2.0 + 12.0 * tau,
        seed: 1,
    };
    let report = step::run(&config, &scratch("open.mcap"), |_| {}).expect("step runs");
    let wheel = report.signals[0].metrics.expect("wheel figures");
    let rise = wheel.rise_time_s.expect("rises");
    let settle = wheel.settling_time_s.expect("settles");
    assert!(
        (rise / (9f64.ln() * tau) - 1.0).abs() < 0.03,
        "rise {rise} s, 2.197 τ = {} s",
        9f64.ln() * tau
    );
    assert!(
        (settle / (50f64.ln() * tau) - 1.0).abs() < 0.03,
        "settling {settle} s, 3.912 τ = {} s",
        50f64.ln() * tau
    );
    assert!(wheel.overshoot_pct < 0.5, "{wheel:?}");
}
