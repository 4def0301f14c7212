//! The bench against analytic results: each test could fail.

use plant::{Actuators, EvModule, PlantParams, Sensors};
use std::f64::consts::TAU;

const DT: f64 = 1e-3;

fn run(module: &mut EvModule, seconds: f64, act: &Actuators) -> Sensors {
    let steps = (seconds / DT).round() as usize;
    for _ in 0..steps {
        module.step(DT, act);
    }
    *module.sensors()
}

fn driving(vel_volts: f64) -> Actuators {
    Actuators {
        enable: true,
        vel_volts,
        ..Default::default()
    }
}

/// Steady state of a DC motor on bus `v2` at duty `d` against Coulomb `tc` and
/// viscous `b` friction at the wheel: `k·ω·N = d·V2 − R·i`, `k·N·i = tc + b·ω`.
/// With fast decay each pulse applies the whole bus and the mean current is
/// `i = d·(V2 − k·N·ω)/R`.
fn analytic_wheel_speed(p: &PlantParams, duty: f64, v2: f64) -> f64 {
    let (k, r, n) = (
        p.motor.torque_constant,
        p.motor.resistance_ohm,
        p.gearbox.ratio,
    );
    let (tc, b) = (p.wheel.coulomb_friction_nm, p.wheel.viscous_friction_nms);
    let kn = k * n;
    match p.motor.pwm_decay {
        plant::motor::PwmDecay::Slow => (duty * v2 - r * tc / kn) / (kn + r * b / kn),
        plant::motor::PwmDecay::Fast => (duty * kn * v2 / r - tc) / (duty * kn * kn / r + b),
    }
}

#[test]
fn steady_state_speed_matches_the_dc_motor_at_three_duties() {
    for preset in ["vemodule", "controller-network"] {
        let p = PlantParams::preset(preset).unwrap();
        for duty in [0.3, 0.6, 0.9] {
            let mut m = EvModule::new(&p, 7);
            let s = run(&mut m, 6.0, &driving(5.0 * duty));
            let expected = analytic_wheel_speed(&p, duty, s.bus_volts) * 60.0 / TAU;
            let err = (s.wheel_rpm - expected).abs() / expected;
            assert!(
                err < 0.02,
                "{preset} duty {duty}: {} rpm vs analytic {expected} rpm",
                s.wheel_rpm
            );
        }
    }
}

#[test]
fn current_limited_start_accelerates_as_the_limit_says() {
    let p = PlantParams::vemodule();
    let mut m = EvModule::new(&p, 7);
    let limit = p.motor.current_limit_amps;
    // J·dω/dt = k·I_lim − T_c − b·ω from rest.
    let j = p.wheel.inertia() + p.motor.rotor_inertia;
    let (tc, b) = (p.wheel.coulomb_friction_nm, p.wheel.viscous_friction_nms);
    let drive = p.motor.torque_constant * limit - tc;
    let t = 0.4;
    let s = run(&mut m, t, &driving(5.0));
    assert!(
        (s.motor_current - limit).abs() < 1e-6,
        "held at the limit: {}",
        s.motor_current
    );
    let expected = drive / b * (1.0 - (-b * t / j).exp()) * 60.0 / TAU;
    let err = (s.wheel_rpm - expected).abs() / expected;
    assert!(err < 0.02, "{} rpm vs {expected} rpm", s.wheel_rpm);
}

#[test]
fn energy_balances_over_ten_seconds_with_every_loss_from_its_own_model() {
    let p = PlantParams::vemodule();
    let mut m = EvModule::new(&p, 7);
    let mut act = driving(0.0);
    for k in 0..10_000 {
        let t = k as f64 * DT;
        act.vel_volts = if t < 1.0 {
            0.0
        } else if t < 4.0 {
            3.5
        } else {
            2.0
        };
        act.boost = (3.0..6.0).contains(&t);
        act.brake = t >= 8.0;
        act.enable = t < 7.5;
        act.discharge = t >= 9.0;
        m.step(DT, &act);
    }
    let e = m.sensors().energy;
    let residual = e.residual(m.initial_stored_energy());
    for (name, v) in [
        ("converter", e.converter_loss),
        ("bleeder", e.bleeder_loss),
        ("copper", e.copper_loss),
        ("friction", e.friction_loss),
        ("brake", e.brake_loss),
    ] {
        assert!(v > 1e-3, "{name} loss should be exercised: {v} J");
    }
    assert!(
        residual.abs() < 0.01 * e.battery_out,
        "residual {residual} J of {} J battery energy: {e:?}",
        e.battery_out
    );
}

#[test]
fn halving_the_time_steps_changes_the_two_second_speed_by_under_half_a_percent() {
    for preset in ["vemodule", "controller-network"] {
        let coarse = PlantParams::preset(preset).unwrap();
        let mut fine = coarse.clone();
        fine.electrical_step_s /= 2.0;
        fine.wheel.step_s /= 2.0;
        let speed_at_2s = |p: &PlantParams, dt: f64| {
            let mut m = EvModule::new(p, 3);
            let mut act = driving(0.0);
            let n = (2.0 / dt).round() as usize;
            for k in 0..n {
                // The step lands mid-acceleration at 2 s on both benches.
                act.vel_volts = if k as f64 * dt >= 1.8 { 3.0 } else { 0.0 };
                m.step(dt, &act);
            }
            m.sensors().wheel_rpm
        };
        let a = speed_at_2s(&coarse, 1e-3);
        let b = speed_at_2s(&fine, 0.5e-3);
        assert!(a > 10.0, "{preset}: the wheel must be moving: {a}");
        assert!(
            (a - b).abs() / b < 0.005,
            "{preset}: {a} rpm vs {b} rpm with half the steps"
        );
    }
}

/// Wheel rpm from hall-edge timing, as firmware with input capture does:
/// edges counted between two captured edge times.
fn hall_rpm(p: &PlantParams, a: &Sensors, b: &Sensors) -> f64 {
    let edges = (b.shaft.hall_edges - a.shaft.hall_edges) as f64;
    let dt = b.shaft.last_hall_edge_at - a.shaft.last_hall_edge_at;
    edges / dt / f64::from(6 * p.motor.pole_pairs) * 60.0 / p.gearbox.ratio
}

#[test]
fn hall_edge_timing_gives_the_true_speed_within_one_percent_above_100_rpm() {
    for preset in ["vemodule", "controller-network"] {
        let p = PlantParams::preset(preset).unwrap();
        for vel in [0.5, 2.0, 4.5] {
            let mut m = EvModule::new(&p, 5);
            let act = driving(vel);
            run(&mut m, 4.0, &act);
            let a = *m.sensors();
            let b = run(&mut m, 0.1, &act);
            let truth = 0.5 * (a.wheel_rpm + b.wheel_rpm);
            if truth < 100.0 {
                continue;
            }
            let measured = hall_rpm(&p, &a, &b);
            assert!(
                (measured - truth).abs() / truth < 0.01,
                "{preset}: {measured} vs {truth}"
            );
        }
    }
}

#[test]
fn encoder_counts_seven_pulses_per_motor_turn_on_the_geared_bench() {
    let p = PlantParams::controller_network();
    let mut m = EvModule::new(&p, 5);
    let act = driving(5.0);
    run(&mut m, 3.0, &act);
    let a = *m.sensors();
    let b = run(&mut m, 1.0, &act);
    let motor_turns = (b.wheel_angle - a.wheel_angle) / TAU * p.gearbox.ratio;
    let counts = (b.shaft.encoder_count - a.shaft.encoder_count) as f64;
    assert!(
        (counts - 7.0 * motor_turns).abs() <= 1.0,
        "{counts} counts for {motor_turns} turns"
    );
    // ≈ 10 000 motor rpm ≈ 100 wheel rpm, as the Controller_network project's log shows.
    assert!((9000.0..12500.0).contains(&b.motor_rpm), "{}", b.motor_rpm);
    assert!((90.0..125.0).contains(&b.wheel_rpm), "{}", b.wheel_rpm);
}

#[test]
fn brake_stops_the_wheel_and_fr_reverses_it() {
    let p = PlantParams::vemodule();
    let mut m = EvModule::new(&p, 5);
    let s = run(&mut m, 2.0, &driving(3.0));
    assert!(s.wheel_rpm > 1000.0);
    let braking = Actuators {
        brake: true,
        ..Default::default()
    };
    let stopped = run(&mut m, 1.0, &braking);
    assert!(stopped.wheel_rpm.abs() < 0.01, "{}", stopped.wheel_rpm);
    let reverse = Actuators {
        reverse: true,
        ..driving(3.0)
    };
    let s = run(&mut m, 2.0, &reverse);
    assert!(s.wheel_rpm < -1000.0, "{}", s.wheel_rpm);
    assert!(
        s.shaft.encoder_count < stopped.shaft.encoder_count,
        "the encoder counts down"
    );
}

#[test]
fn enable_gates_the_inverter() {
    let p = PlantParams::vemodule();
    let mut m = EvModule::new(&p, 5);
    let s = run(
        &mut m,
        1.0,
        &Actuators {
            vel_volts: 5.0,
            ..Default::default()
        },
    );
    assert_eq!(s.wheel_rpm, 0.0);
    assert_eq!(s.motor_current, 0.0);
}

#[test]
fn two_runs_are_bit_identical() {
    let p = PlantParams::vemodule();
    let trace = || {
        let mut m = EvModule::new(&p, 42);
        let mut out = Vec::new();
        for k in 0..3000 {
            let s = m.step(DT, &driving(if k > 500 { 3.0 } else { 0.0 }));
            out.extend(
                [
                    s.wheel_rpm,
                    s.bus_volts,
                    s.ldr_volts,
                    s.motor_current,
                    s.soc,
                ]
                .map(f64::to_bits),
            );
            out.push(u64::from(s.ldr_counts));
        }
        out
    };
    assert_eq!(trace(), trace());
}
