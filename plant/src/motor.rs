//! Three-phase inverter and BLDC motor, averaged over the PWM period.
//!
//! With six-step commutation a BLDC motor seen from the DC bus is a DC motor:
//! two phases conduct at a time, so the equivalent circuit is the line-to-line
//! resistance and inductance in series with a back-EMF `k·ω`, and the torque is
//! `k·i`. The inverter applies `duty·V2` (sign set by `FR`). Its current
//! controller keeps `|i| ≤ current_limit` by lowering the applied voltage, as
//! the cycle-by-cycle limit of a real controller does; if the current still
//! exceeds `overcurrent_trip_amps` for `overcurrent_trip_s` (back-EMF above the
//! bus, a fault) the gates latch off until `EN` is released and applied again.
//!
//! The RL current is advanced with its exact exponential solution for a
//! constant applied voltage and speed over the sub-step, so the electrical time
//! constant (about 2 ms here) never limits the step.

use serde::{Deserialize, Serialize};

/// Throttle map: `VEL` pin volts to PWM duty, piecewise linear, clamped at the ends.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct ThrottleMap(pub Vec<[f64; 2]>);

impl ThrottleMap {
    /// Duty (0..=1) for a `VEL` voltage.
    pub fn duty(&self, volts: f64) -> f64 {
        let pts = &self.0;
        let Some(first) = pts.first() else { return 0.0 };
        if volts <= first[0] {
            return first[1].clamp(0.0, 1.0);
        }
        for w in pts.windows(2) {
            let ([x0, y0], [x1, y1]) = (w[0], w[1]);
            if volts <= x1 {
                let f = if x1 > x0 {
                    (volts - x0) / (x1 - x0)
                } else {
                    1.0
                };
                return (y0 + f * (y1 - y0)).clamp(0.0, 1.0);
            }
        }
        pts.last().map_or(0.0, |p| p[1].clamp(0.0, 1.0))
    }
}

/// Motor and inverter parameters (DC-equivalent, line to line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MotorParams {
    /// Line-to-line resistance including two conducting switches (Ω). Default:
    /// 57BLF-class 36 V, 4000 rpm, 0.3 N·m BLDC motor datasheets give 0.4–0.6 Ω.
    pub resistance_ohm: f64,
    /// Line-to-line inductance (H); same datasheets: 0.8–1.2 mH.
    pub inductance_henry: f64,
    /// Back-EMF and torque constant (V·s/rad = N·m/A): 36 V / 4000 rpm.
    pub torque_constant: f64,
    /// Pole pairs; six hall edges per electrical turn, so 6·p per mechanical turn.
    pub pole_pairs: u32,
    /// Encoder pulses (channel A periods) per motor turn: 7 on the Controller_network
    /// motor's magnetic encoder; the EV module has none, so it mirrors the halls.
    pub encoder_pulses_per_turn: u32,
    /// Rotor inertia (kg·m²), 57BLF datasheets: 1.2e-5.
    pub rotor_inertia: f64,
    /// Controller current limit (A).
    pub current_limit_amps: f64,
    /// Over-current trip threshold (A) and how long it must persist (s).
    pub overcurrent_trip_amps: f64,
    pub overcurrent_trip_s: f64,
    /// `VEL` volts to duty.
    pub throttle: ThrottleMap,
    /// What the drive does with the current between its PWM pulses.
    pub pwm_decay: PwmDecay,
}

/// What a drive does with the winding current between PWM pulses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PwmDecay {
    /// The current recirculates through the low-side switches (an inverter's
    /// synchronous rectification, a fast PWM): the motor sees duty × bus.
    #[default]
    Slow,
    /// The current decays into the supply and the motor coasts until the
    /// next pulse. With a PWM period far longer than L/R (the Controller_network
    /// Nano's 10 ms software PWM against about 0.75 ms) the current falls to
    /// zero in every period, so each pulse applies the whole bus: the mean
    /// torque is duty × k·(V − k·ω)/R, and a lightly loaded motor runs close
    /// to its no-load speed at any duty that overcomes its friction.
    Fast,
}

impl Default for MotorParams {
    fn default() -> Self {
        Self {
            resistance_ohm: 0.5,
            inductance_henry: 1.0e-3,
            torque_constant: 36.0 / (4000.0 * std::f64::consts::TAU / 60.0),
            pole_pairs: 4,
            encoder_pulses_per_turn: 12,
            rotor_inertia: 1.2e-5,
            current_limit_amps: 10.0,
            overcurrent_trip_amps: 20.0,
            overcurrent_trip_s: 0.005,
            // The module's DAC drives the controller's speed input directly:
            // 0–5 V is 0–100 % duty.
            throttle: ThrottleMap(vec![[0.0, 0.0], [5.0, 1.0]]),
            pwm_decay: PwmDecay::Slow,
        }
    }
}

impl MotorParams {
    /// The Controller_network bench: a 12 V geared DC motor with a 7-pulse encoder
    /// (JGB37-520 class, ≈ 10 000 rpm at the motor before its 1:100 gearbox),
    /// driven by an H-bridge whose input the motor Nano switches with a 10 ms
    /// software PWM: fast decay, see [`PwmDecay::Fast`]. The motor constant,
    /// resistance and rotor inertia are fitted to the bench's step response
    /// by `twin calibrate` (`docs/models.md` has the table of where each
    /// value comes from); the rest is from datasheets or assumed.
    pub fn controller_network() -> Self {
        Self {
            // Fitted (datasheet class: 2 Ω).
            resistance_ohm: 1.326,
            inductance_henry: 1.5e-3,
            // Fitted: 12 V at 10 050 rpm (datasheet class: 12 V at ≈ 11 500 rpm).
            torque_constant: 0.0114,
            pole_pairs: 1,
            encoder_pulses_per_turn: 7,
            // Fitted (datasheet class: 5e-7 kg·m²).
            rotor_inertia: 2.81e-7,
            current_limit_amps: 6.0,
            overcurrent_trip_amps: 8.0,
            overcurrent_trip_s: 0.05,
            throttle: ThrottleMap(vec![[0.0, 0.0], [5.0, 1.0]]),
            pwm_decay: PwmDecay::Fast,
        }
    }
}

/// Inputs the inverter acts on during one sub-step.
#[derive(Debug, Clone, Copy)]
pub struct Drive {
    /// Gates enabled (`EN` active and no trip).
    pub enabled: bool,
    /// Duty from the throttle map, 0..=1.
    pub duty: f64,
    /// `FR`: counter-clockwise.
    pub reverse: bool,
    /// DC-bus voltage during the sub-step (V).
    pub bus_volts: f64,
    /// Motor shaft speed during the sub-step (rad/s).
    pub shaft_speed: f64,
}

/// What one sub-step did; energies in joules.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MotorStep {
    /// Mean motor current (A).
    pub mean_current: f64,
    /// Mean inverter input current drawn from the bus (A).
    pub bus_current: f64,
    /// ∫ k·i dt: angular impulse delivered to the shaft (N·m·s).
    pub torque_impulse: f64,
    /// Energy from the bus, copper heat, and energy converted to mechanical.
    pub electrical_energy: f64,
    pub copper_loss: f64,
    pub mechanical_energy: f64,
}

/// The inverter + motor's electrical state.
#[derive(Debug, Clone)]
pub struct Motor {
    params: MotorParams,
    /// The winding current; with fast decay, the current during a pulse.
    current: f64,
    /// The share of time the current flows: the duty with fast decay, else 1.
    conducting: f64,
    over_limit_for: f64,
    tripped: bool,
}

impl Motor {
    pub fn new(params: &MotorParams) -> Self {
        Self {
            params: params.clone(),
            current: 0.0,
            conducting: 1.0,
            over_limit_for: 0.0,
            tripped: false,
        }
    }

    pub fn params(&self) -> &MotorParams {
        &self.params
    }

    /// Motor current (A, signed: positive drives clockwise), the mean over
    /// a PWM period.
    pub fn current(&self) -> f64 {
        self.conducting * self.current
    }

    /// Magnetic energy in the winding inductance (J). With fast decay it goes
    /// back to the supply in every PWM period, so none is kept.
    pub fn stored_energy(&self) -> f64 {
        match self.params.pwm_decay {
            PwmDecay::Slow => 0.5 * self.params.inductance_henry * self.current * self.current,
            PwmDecay::Fast => 0.0,
        }
    }

    /// Whether the over-current protection holds the gates off.
    pub fn tripped(&self) -> bool {
        self.tripped
    }

    /// Clear the trip: the firmware does this when `EN` is released and applied.
    pub fn reset_trip(&mut self) {
        self.tripped = false;
        self.over_limit_for = 0.0;
    }

    /// Advance the winding current by `h` seconds.
    pub fn step(&mut self, h: f64, drive: &Drive) -> MotorStep {
        let p = &self.params;
        let (r, l, k) = (p.resistance_ohm, p.inductance_henry, p.torque_constant);
        let bus = drive.bus_volts.max(0.0);
        let emf = k * drive.shaft_speed;
        let gates_on = drive.enabled && !self.tripped;
        // With the gates off the terminals follow the back-EMF through the
        // freewheeling diodes; current flows only if the EMF exceeds the bus.
        let duty = drive.duty.clamp(0.0, 1.0);
        let fast = gates_on && p.pwm_decay == PwmDecay::Fast;
        // With fast decay the winding carries current only during pulses,
        // each applying the whole bus; what follows is scaled by the duty.
        self.conducting = if fast { duty } else { 1.0 };
        let requested = if gates_on {
            let sign = if drive.reverse { -1.0 } else { 1.0 };
            sign * if fast { bus } else { duty * bus }
        } else {
            emf.clamp(-bus, bus)
        };
        let limit = p.current_limit_amps;
        // The current controller may lower |V| down to zero, never reverse it,
        // and never exceed the bus: the applied voltage that holds the limit.
        let tau = l / r;
        let i0 = self.current;
        let (mut v_int_i, mut i_int, mut i_sq_int) = (0.0, 0.0, 0.0);
        let mut run = |v: f64, i_start: f64, dt: f64| -> f64 {
            // i(t) = a + b·e^{−t/τ}
            let a = (v - emf) / r;
            let b = i_start - a;
            let e1 = tau * -(-dt / tau).exp_m1();
            let e2 = 0.5 * tau * -(-2.0 * dt / tau).exp_m1();
            let int = a * dt + b * e1;
            i_int += int;
            v_int_i += v * int;
            i_sq_int += a * a * dt + 2.0 * a * b * e1 + b * b * e2;
            a + b * (-dt / tau).exp()
        };
        let free_end = {
            let a = (requested - emf) / r;
            a + (i0 - a) * (-h / tau).exp()
        };
        let i1 = if gates_on && free_end.abs() > limit && i0.abs() <= limit {
            // Runs free until the current reaches the limit, then is held there.
            let a = (requested - emf) / r;
            let target = limit * free_end.signum();
            let t_hit = (tau * ((i0 - a) / (target - a)).ln()).clamp(0.0, h);
            run(requested, i0, t_hit);
            let hold_v = (r * target + emf).clamp(-bus, bus);
            run(hold_v, target, h - t_hit)
        } else if gates_on && i0.abs() > limit {
            let target = limit * i0.signum();
            let hold_v = (r * target + emf).clamp(-bus, bus);
            run(hold_v, i0, h)
        } else {
            run(requested, i0, h)
        };
        self.current = i1;

        let peak = i0.abs().max(i1.abs());
        if peak > p.overcurrent_trip_amps {
            self.over_limit_for += h;
            if self.over_limit_for >= p.overcurrent_trip_s {
                self.tripped = true;
            }
        } else {
            self.over_limit_for = 0.0;
        }

        let share = self.conducting;
        let magnetic_change = share * 0.5 * l * (i1 * i1 - i0 * i0);
        let copper_loss = share * r * i_sq_int;
        // With fast decay the pulses' magnetic energy goes back to the supply.
        let electrical_energy = if fast {
            share * v_int_i - magnetic_change
        } else {
            v_int_i
        };
        let (i_int, magnetic_change) = if fast {
            (share * i_int, 0.0)
        } else {
            (i_int, magnetic_change)
        };
        MotorStep {
            mean_current: i_int / h,
            bus_current: if bus > 0.0 {
                electrical_energy / (bus * h)
            } else {
                0.0
            },
            torque_impulse: k * i_int,
            electrical_energy,
            copper_loss,
            // The exact solution satisfies v·i = R·i² + L·i·di/dt + k·ω·i.
            mechanical_energy: electrical_energy - copper_loss - magnetic_change,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn drive(duty: f64, speed: f64) -> Drive {
        Drive {
            enabled: true,
            duty,
            reverse: false,
            bus_volts: 36.0,
            shaft_speed: speed,
        }
    }

    #[test]
    fn throttle_map_interpolates_and_clamps() {
        let map = ThrottleMap(vec![[0.8, 0.0], [4.2, 1.0]]);
        assert_eq!(map.duty(0.0), 0.0);
        assert!((map.duty(2.5) - 0.5).abs() < 1e-12);
        assert_eq!(map.duty(5.0), 1.0);
        assert_eq!(ThrottleMap(vec![]).duty(3.0), 0.0);
    }

    #[test]
    fn winding_current_follows_rl_step_response_at_any_step() {
        let p = MotorParams {
            current_limit_amps: 1e9,
            overcurrent_trip_amps: 1e9,
            ..Default::default()
        };
        let tau = p.inductance_henry / p.resistance_ohm;
        let final_i = 0.1 * 36.0 / p.resistance_ohm;
        for h in [1e-5_f64, 1e-3] {
            let mut m = Motor::new(&p);
            let n = (4e-3 / h).round() as usize;
            for _ in 0..n {
                m.step(h, &drive(0.1, 0.0));
            }
            let expected = final_i * (1.0 - (-4e-3 / tau).exp());
            assert!(
                (m.current() - expected).abs() < 1e-9 * expected,
                "h={h}: {}",
                m.current()
            );
        }
    }

    #[test]
    fn current_limit_holds_the_current_at_the_limit() {
        let p = MotorParams::default();
        let mut m = Motor::new(&p);
        for _ in 0..50 {
            let s = m.step(1e-3, &drive(1.0, 0.0));
            assert!(s.mean_current <= p.current_limit_amps + 1e-9);
        }
        assert!((m.current() - p.current_limit_amps).abs() < 1e-9);
        assert!(!m.tripped());
    }

    #[test]
    fn energy_identity_holds_per_step() {
        let p = MotorParams::default();
        let mut m = Motor::new(&p);
        for k in 0..100 {
            let s = m.step(1e-3, &drive(0.6, 100.0 + k as f64));
            let mech = p.torque_constant * (100.0 + k as f64) * s.mean_current * 1e-3;
            assert!((s.mechanical_energy - mech).abs() < 1e-9 * (1.0 + mech.abs()));
        }
    }

    #[test]
    fn back_emf_above_bus_trips_the_gates() {
        let p = MotorParams::default();
        let mut m = Motor::new(&p);
        // Spun to twice its no-load speed by the load, with the bus at 36 V.
        let overspeed = 2.0 * 36.0 / p.torque_constant;
        for _ in 0..20 {
            m.step(1e-3, &drive(1.0, overspeed));
        }
        assert!(m.tripped());
        m.reset_trip();
        assert!(!m.tripped());
    }
}
