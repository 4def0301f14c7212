//! What the plant's own model says a slave's outputs should do and its
//! inputs should read, from the plant's parameters alone (as the bench's
//! panel serves them): the steady speed a VEL gives, how fast the wheel
//! coasts, and the counts each analog input has for a plant value. The
//! check runs no plant: these are the model's closed forms, so a slave is
//! held to the physics the twin simulates, not to a figure guessed here.

use plant::PlantParams;
use plant::motor::PwmDecay;

const RPM_PER_RAD_S: f64 = 60.0 / std::f64::consts::TAU;

/// The MEB page's default scaling: VEL is a 12-bit DAC count, 0-5 V.
pub const DAC_MAX: u16 = 4095;
pub const DAC_FULL_VOLTS: f64 = 5.0;

/// The DAC's output for a VEL.
pub fn vel_volts(vel: u16) -> f64 {
    f64::from(vel.min(DAC_MAX)) / f64::from(DAC_MAX) * DAC_FULL_VOLTS
}

/// The wheel's and the reflected rotor's inertia, at the wheel (kg·m²).
fn inertia(p: &PlantParams) -> f64 {
    let n = p.gearbox.ratio;
    p.wheel.inertia() + p.motor.rotor_inertia * n * n
}

/// The motor's steady speed (rpm, positive) for a `vel` written on a bus
/// of `bus_volts`: where the drive's torque meets the bearings' friction
/// (Coulomb and viscous). Below the stiction it is 0.
pub fn steady_rpm(p: &PlantParams, vel: u16, bus_volts: f64) -> f64 {
    let duty = p.motor.throttle.duty(vel_volts(vel));
    let (r, k, n) = (
        p.motor.resistance_ohm,
        p.motor.torque_constant,
        p.gearbox.ratio,
    );
    let (tc, b) = (p.wheel.coulomb_friction_nm, p.wheel.viscous_friction_nms);
    // Motor speed w: the wheel turns at w / n and needs tc + b·w/n.
    let w = match p.motor.pwm_decay {
        // The motor sees duty × bus: d·V = R·i + k·w, and k·i·n = tc + b·w/n.
        PwmDecay::Slow => (duty * bus_volts - r * tc / (k * n)) / (k + r * b / (k * n * n)),
        // Current only while a pulse is on: d·k·n·(V − k·w)/R = tc + b·w/n.
        PwmDecay::Fast => {
            let denominator = duty * k * k * n / r + b / n;
            if denominator <= 0.0 {
                0.0
            } else {
                (duty * k * n * bus_volts / r - tc) / denominator
            }
        }
    };
    if w.is_finite() {
        w.max(0.0) * RPM_PER_RAD_S
    } else {
        0.0
    }
}

/// How far the steady speed moves for one DAC count either side of
/// `vel` (rpm): the resolution VEL is written with, so the tolerance a
/// speed is held to.
pub fn rpm_per_count(p: &PlantParams, vel: u16, bus_volts: f64) -> f64 {
    let up = steady_rpm(p, vel.saturating_add(1).min(DAC_MAX), bus_volts);
    let down = steady_rpm(p, vel.saturating_sub(1), bus_volts);
    ((up - down) / 2.0).abs()
}

/// The motor's speed (rpm, same sign) after coasting `seconds` from
/// `rpm`: J·dω/dt = −tc − b·ω, undriven and unbraked, until it stops.
pub fn coasted_rpm(p: &PlantParams, rpm: f64, seconds: f64) -> f64 {
    let n = p.gearbox.ratio;
    let j = inertia(p);
    let (tc, b) = (p.wheel.coulomb_friction_nm, p.wheel.viscous_friction_nms);
    let w0 = rpm.abs() / RPM_PER_RAD_S / n;
    let w = if b > 0.0 {
        (w0 + tc / b) * (-b * seconds / j).exp() - tc / b
    } else {
        w0 - tc / j * seconds
    };
    (w.max(0.0) * n * RPM_PER_RAD_S).copysign(rpm)
}

/// An analog input as the controller's ADC gives it for a plant value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Analog {
    /// Battery voltage through its divider.
    V1,
    /// DC-bus voltage through its divider.
    V2,
    /// Inverter input current through the hall sensor.
    I,
}

/// The counts of `input` for `value` (V or A).
pub fn counts(p: &PlantParams, input: Analog, value: f64) -> u16 {
    let s = &p.sensing;
    match input {
        Analog::V1 => s.counts(value / s.battery_divider),
        Analog::V2 => s.counts(value / s.bus_divider),
        Analog::I => s.counts(s.current_zero_volts + value * s.current_volts_per_amp),
    }
}

/// How far the photoresistor's reading wanders between two samples of a
/// still plant (counts): five standard deviations of the divider's noise
/// (one reading in about two million goes further).
pub fn ldr_noise_counts(p: &PlantParams) -> f64 {
    let l = &p.light;
    let volts_per_count = l.adc_reference_volts / f64::from(1u32 << l.adc_bits.clamp(1, 16));
    5.0 * l.noise_rms_volts / volts_per_count
}

/// Hall edges per wheel turn: six per electrical turn.
pub fn hall_edges_per_wheel_turn(p: &PlantParams) -> f64 {
    6.0 * f64::from(p.motor.pole_pairs) * p.gearbox.ratio
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_vel_on_the_ev_module_turns_near_half_the_rated_speed() {
        let p = PlantParams::vemodule();
        // 36 V at 4000 rpm: half of a 48 V bus is 24 V, about 2670 rpm
        // before friction.
        let rpm = steady_rpm(&p, 2048, 48.0);
        assert!((2500.0..2670.0).contains(&rpm), "{rpm}");
        assert_eq!(steady_rpm(&p, 0, 48.0), 0.0);
        let per = rpm_per_count(&p, 2048, 48.0);
        assert!((1.0..1.5).contains(&per), "{per}");
    }

    #[test]
    fn coasting_slows_and_stops() {
        let p = PlantParams::vemodule();
        let later = coasted_rpm(&p, 2000.0, 0.5);
        assert!(later < 2000.0 && later > 1900.0, "{later}");
        assert_eq!(coasted_rpm(&p, -2000.0, 1e6), 0.0);
        assert!(coasted_rpm(&p, -2000.0, 0.5) < -1900.0);
    }

    #[test]
    fn inputs_count_as_the_plant_does() {
        let p = PlantParams::vemodule();
        assert_eq!(counts(&p, Analog::I, 0.0), 2048);
        assert_eq!(counts(&p, Analog::V1, 36.0), p.sensing.counts(3.6));
        assert_eq!(hall_edges_per_wheel_turn(&p), 24.0);
        // 2 mV of noise on a 12-bit, 5 V converter: 1.6 counts, times 5.
        assert!((ldr_noise_counts(&p) - 8.19).abs() < 0.01);
    }
}
