//! The whole bench against the light sensor's analytic speed limit: the motor
//! drives the rapier wheel, the wheel carries the flag past the lamp, and the
//! photoresistor's dip crosses a fixed threshold below the formula's speed and
//! stops crossing it above.

use plant::light::fixed_threshold_max_rpm;
use plant::{Actuators, EvModule, PlantParams};

/// Lowest divider voltage over `turns` wheel turns after settling at the speed
/// that `vel_volts` gives, sampled every 0.1 ms, with the mean wheel rpm.
fn dip_at(params: &PlantParams, vel_volts: f64) -> (f64, f64) {
    let mut m = EvModule::new(params, 11);
    let act = Actuators {
        enable: true,
        vel_volts,
        ..Default::default()
    };
    for _ in 0..4000 {
        m.step(1e-3, &act);
    }
    let (mut lowest, mut rpm_sum, mut n) = (f64::INFINITY, 0.0, 0);
    for _ in 0..20_000 {
        let s = m.step(1e-4, &act);
        lowest = lowest.min(s.ldr_volts);
        rpm_sum += s.wheel_rpm;
        n += 1;
    }
    (lowest, rpm_sum / f64::from(n))
}

/// VEL volts for a wheel speed, from the DC-motor steady state (bus ≈ V1).
fn vel_for_rpm(p: &PlantParams, rpm: f64, bus_volts: f64) -> f64 {
    let omega = rpm * std::f64::consts::TAU / 60.0;
    let (k, r, n) = (
        p.motor.torque_constant,
        p.motor.resistance_ohm,
        p.gearbox.ratio,
    );
    let torque = p.wheel.coulomb_friction_nm + p.wheel.viscous_friction_nms * omega;
    let duty = (k * n * omega + r * torque / (k * n)) / bus_volts;
    5.0 * duty
}

#[test]
fn fixed_threshold_sees_the_flag_below_the_formulas_speed_and_not_above() {
    let mut p = PlantParams::vemodule();
    // Noise would blur a threshold test by its own few millivolts.
    p.light.noise_rms_volts = 0.0;
    let threshold = 0.5 * (p.light.lit_volts() + p.light.shaded_volts());
    let limit = fixed_threshold_max_rpm(&p.light, threshold);
    assert!((150.0..400.0).contains(&limit), "limit {limit} rpm");
    let bus = PlantParams::vemodule()
        .battery
        .ocv_at(p.battery.initial_soc);

    let (dip_slow, rpm_slow) = dip_at(&p, vel_for_rpm(&p, 0.9 * limit, bus));
    let (dip_fast, rpm_fast) = dip_at(&p, vel_for_rpm(&p, 1.1 * limit, bus));
    assert!(
        (rpm_slow / limit - 0.9).abs() < 0.03,
        "slow run at {rpm_slow} rpm, limit {limit}"
    );
    assert!(
        (rpm_fast / limit - 1.1).abs() < 0.03,
        "fast run at {rpm_fast} rpm, limit {limit}"
    );
    assert!(
        dip_slow < threshold,
        "at {rpm_slow:.0} rpm the dip reaches {dip_slow} V, above {threshold} V"
    );
    assert!(
        dip_fast > threshold,
        "at {rpm_fast:.0} rpm the dip reaches {dip_fast} V, below {threshold} V"
    );
}
