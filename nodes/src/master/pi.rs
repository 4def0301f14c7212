//! The supervisor's speed controller: a PI on rpm whose output is `VEL` counts.

/// Lowest `VEL` the DAC takes.
pub const VEL_MIN: f64 = 0.0;
/// Highest `VEL` the 12-bit DAC takes.
pub const VEL_MAX: f64 = 4095.0;

/// A PI controller from rpm error to `VEL` counts, with its integral clamped to
/// the DAC range so that a long saturation (set point out of reach, slave lost
/// for a while) does not leave a wound-up integral to unwind afterwards.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpeedPi {
    /// Proportional gain, counts per rpm of error.
    pub kp: f64,
    /// Integral gain, counts per rpm of error per second.
    pub ki: f64,
    /// The integral term, counts, always within `VEL_MIN..=VEL_MAX`.
    integral: f64,
}

impl SpeedPi {
    /// A controller with an empty integral.
    pub const fn new(kp: f64, ki: f64) -> Self {
        Self {
            kp,
            ki,
            integral: 0.0,
        }
    }

    /// The integral term, counts.
    pub fn integral(&self) -> f64 {
        self.integral
    }

    /// Forgets the integral (loop switched to open and back).
    pub fn reset(&mut self) {
        self.integral = 0.0;
    }

    /// Sets the integral to `counts` (clamped), so that closing the loop from a
    /// manual output starts where the output was instead of at zero.
    pub fn preload(&mut self, counts: f64) {
        if counts.is_finite() {
            self.integral = counts.clamp(VEL_MIN, VEL_MAX);
        }
    }

    /// One controller pass on a fresh measurement `dt_secs` after the previous
    /// one: returns the output in counts, within `VEL_MIN..=VEL_MAX`. Non-finite
    /// inputs leave the integral as it was, so a bad value cannot poison it.
    pub fn update(&mut self, set_point_rpm: f64, measured_rpm: f64, dt_secs: f64) -> f64 {
        let error = set_point_rpm - measured_rpm;
        let step = self.ki * error * dt_secs;
        if step.is_finite() {
            self.integral = (self.integral + step).clamp(VEL_MIN, VEL_MAX);
        }
        let output = self.kp * error + self.integral;
        if output.is_finite() {
            output.clamp(VEL_MIN, VEL_MAX)
        } else {
            self.integral
        }
    }
}
