//! The supervisor's PI alone, against a first-order plant simulated here: the
//! output is held between passes (zero-order hold), the plant integrated
//! exactly, `rpm(t + h) = K·u + (rpm(t) − K·u)·e^(−h/τ)`.

use nodes::master::{SpeedPi, VEL_MAX};

/// rpm per `VEL` count at steady state: full scale reaches about 10 200 rpm.
const GAIN: f64 = 2.5;
/// The wheel's time constant, s.
const TAU: f64 = 0.3;
/// One poll period, s.
const DT: f64 = 0.010;

struct Plant {
    rpm: f64,
}

impl Plant {
    fn hold(&mut self, vel: f64, seconds: f64) {
        let target = GAIN * vel;
        self.rpm = target + (self.rpm - target) * (-seconds / TAU).exp();
    }
}

/// Runs the loop from the current state for `seconds`, returning the rpm after
/// each pass and the outputs.
fn run(pi: &mut SpeedPi, plant: &mut Plant, set_point: f64, seconds: f64) -> Vec<(f64, f64)> {
    let steps = (seconds / DT).round() as usize;
    (0..steps)
        .map(|_| {
            let vel = pi.update(set_point, plant.rpm, DT);
            plant.hold(vel, DT);
            (plant.rpm, vel)
        })
        .collect()
}

#[test]
fn one_pass_is_kp_times_error_plus_the_integrated_error() {
    let mut pi = SpeedPi::new(0.2, 1.5);
    let first = pi.update(1000.0, 400.0, 0.02);
    assert!((first - (0.2 * 600.0 + 1.5 * 600.0 * 0.02)).abs() < 1e-9);
    assert!((pi.integral() - 18.0).abs() < 1e-9);
    let second = pi.update(1000.0, 900.0, 0.01);
    assert!((second - (0.2 * 100.0 + 18.0 + 1.5 * 100.0 * 0.01)).abs() < 1e-9);
}

#[test]
fn a_step_settles_within_two_percent() {
    let mut pi = SpeedPi::new(0.2, 1.0);
    let mut plant = Plant { rpm: 0.0 };
    let response = run(&mut pi, &mut plant, 3000.0, 4.0);
    // The proportional path alone would leave an offset of 1 / (1 + K·Kp) = 67 %;
    // the integral removes it.
    let settled = &response[(2.0 / DT) as usize..];
    for (rpm, _) in settled {
        assert!((rpm - 3000.0).abs() < 0.02 * 3000.0, "{rpm}");
    }
    let (last, vel) = response[response.len() - 1];
    assert!((last - 3000.0).abs() < 0.001 * 3000.0, "{last}");
    // At rest the integral holds exactly what the plant needs.
    assert!((vel - 3000.0 / GAIN).abs() < 1.0, "{vel}");
    assert!((pi.integral() - 3000.0 / GAIN).abs() < 1.0);
}

#[test]
fn the_integral_does_not_wind_up_while_the_output_saturates() {
    let mut pi = SpeedPi::new(0.2, 1.0);
    let mut plant = Plant { rpm: 0.0 };
    // 20 000 rpm is out of reach (full scale gives 10 237): the output pins
    // at full scale and so does the integral, no further.
    let saturated = run(&mut pi, &mut plant, 20_000.0, 5.0);
    assert!(
        saturated[saturated.len() / 2..]
            .iter()
            .all(|&(_, vel)| vel == VEL_MAX)
    );
    assert_eq!(pi.integral(), VEL_MAX);
    // An unclamped integral would hold 1.0 · ~10 000 rpm · 5 s = 50 000 counts
    // and take seconds to unwind; the clamped one comes back as fast as a
    // fresh step does.
    let recovery = run(&mut pi, &mut plant, 3000.0, 3.0);
    let settled = &recovery[(2.0 / DT) as usize..];
    for (rpm, _) in settled {
        assert!((rpm - 3000.0).abs() < 0.02 * 3000.0, "{rpm}");
    }
}

#[test]
fn the_output_stays_within_the_dac_range() {
    let mut pi = SpeedPi::new(5.0, 50.0);
    for (set_point, measured) in [(0.0, 5000.0), (10_000.0, 0.0), (-1.0, 1e9), (1e12, 0.0)] {
        let vel = pi.update(set_point, measured, DT);
        assert!((0.0..=VEL_MAX).contains(&vel), "{vel}");
        assert!((0.0..=VEL_MAX).contains(&pi.integral()));
    }
    // A non-finite measurement cannot poison the integral.
    let before = pi.integral();
    let vel = pi.update(1000.0, f64::NAN, DT);
    assert_eq!(pi.integral(), before);
    assert!((0.0..=VEL_MAX).contains(&vel));
}
