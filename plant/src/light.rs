//! The wheel's light sensor: a paper flag on the wheel passes between a lamp and a CdS photoresistor
//! (GL5528-like) once per turn; the photoresistor sits on top of a divider whose output an ADC reads.
//!
//! # State variable
//! A CdS cell's steady resistance follows a power law in illuminance, `R = R10 (E / 10 lx)^-gamma`
//! (capped at the dark resistance), and its response to a change of light is close to exponential in
//! log-resistance. The state is therefore the log-conductance `x = -ln(R / 1 ohm)`: its steady value
//! `x_ss(E) = max(-ln R10 + gamma ln(E / 10 lx), -ln R_dark)` is affine in `ln E`, and it relaxes as
//! `dx/dt = (x_ss - x) / tau`, with `tau = tau_rise` while the resistance rises (light -> dark, `x` falls)
//! and `tau = tau_fall` while it falls. Within a step the flag edges are located on the linearly
//! interpolated angle and each piece of constant light gets the exact update
//! `x <- x_ss + (x - x_ss) exp(-h / tau)`, so the state does not depend on the step size. Whole turns
//! inside one step are folded into one affine map `x <- A x + B` raised to the number of turns. A
//! flickering lamp is held constant on a fixed grid of absolute time (cells of `min(1 ms, period / 8)`,
//! light taken at the cell's middle), which keeps that case step-size independent too.
//!
//! Limits of the model: a real CdS cell is slower in dim light and after long darkness (the datasheet
//! times are taken at 10 lx); one pair of time constants is used at every level, and the lamp and the
//! ambient light are lumped into the lit and shaded illuminances.
//!
//! # Fastest speed a fixed threshold sees ([`fixed_threshold_max_rpm`])
//! The flag blocks the beam for `t_d = (arc / 360) * 60 / n` at `n` wheel rpm. Before it arrives the lamp
//! has shone for `(360 - arc) / arc` = 11 (30 deg flag) or 5 (60 deg) times as long: at least `10 tau_fall` at the
//! fixed-threshold limits below, so the cell starts from its lit state `x_l` (to within `e^-10`; where it
//! has not fully recovered the dip is only deeper, so the limit is conservative). In the shadow
//! `x(t) = x_d + (x_l - x_d) exp(-t / tau_rise)`. The divider voltage `V = Vs / (1 + e^-x / Rf)` rises
//! monotonically with `x`, so `V` falls below `V_th` exactly when `x` falls below
//! `x_th = -ln(Rf (Vs / V_th - 1))`. The dip therefore reaches the threshold only if
//!
//! `t_d >= tau_rise ln((x_l - x_d) / (x_th - x_d))`, i.e. `n_max = (arc / 360) 60 / (tau_rise ln((x_l - x_d) / (x_th - x_d)))`.
//!
//! Above `n_max` the detector sees no dip at all: the derived rpm falls to 0 (or n/2, n/3 when only some
//! dips graze the threshold) rather than sagging.
//!
//! # Numbers for the presets' flags (tau_rise 30 ms; tests check every number below)
//! | preset | lit V | shaded V | fixed threshold | adaptive, 20 % of swing | adaptive, 5 sigma dip |
//! |---|---|---|---|---|---|
//! | [`LightParams::controller_network`] (60 deg flag, 39 kOhm, 10-bit) | 4.700 | 1.975 | 3.0 V: **248 rpm** | 4.16 V: 734 rpm | 25 mV: 12 200 rpm |
//! | [`LightParams::default`] vemodule (30 deg flag, 10 kOhm, 12-bit) | 4.005 | 0.717 | mid-way 2.36 V: **260 rpm** | 3.35 V: 685 rpm | 10 mV: 42 000 rpm |
//!
//! An adaptive detector tracks the recent maximum and minimum and calls a dip once the signal falls a set
//! amount below the maximum. Measured against the full lit-shaded swing (20 %) it is the same formula
//! with `V_th = V_lit - 0.2 (V_lit - V_shaded)`, a few hundred rpm. Measured against the swing it
//! actually sees (so only noise limits it), the dip needed is a few noise sigmas ([`adaptive_dip_max_rpm`]):
//! for short shadows the dip is `(x_l - x_d) t_d / tau_rise`, linear in `1 / n`, so the sensor itself
//! allows thousands to tens of thousands of rpm. Past `1 / tau_fall` (about 3 000 rpm) the dips of
//! successive turns merge into a ripple of about the same size on a lowered mean, so the practical
//! limit becomes the sampling: at least two samples per turn, `n < 30 / T_s` (1 500 rpm at the
//! Controller_network project's 20 ms sampling) -- a few thousand rpm.

use std::f64::consts::TAU;

use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};

/// Longest piece of constant lamp light when the lamp flickers (s).
const FLICKER_CELL_MAX_S: f64 = 1e-3;

/// Everything between the lamp and the ADC count. Default = the EV module (vemodule): 12-bit ADC, 0-5 V.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LightParams {
    /// Angle the flag covers on the wheel (deg). 30: the lab's paper flag (NOTES.md).
    pub flag_arc_deg: f64,
    /// Flags on the wheel, evenly spaced, each `flag_arc_deg` wide (1 on the lab's
    /// wheels; the Controller_network bench's log shows three marks a turn).
    pub flags: u32,
    /// Wheel angle at which the (first) flag's middle is in the beam (deg). 180 (argument): a wheel resting at
    /// angle 0 leaves the cell lit, matching the lit state a new sensor starts in.
    pub flag_center_deg: f64,
    /// Illuminance on the cell with the beam clear (lx). 200 (argument): a small lamp a few cm from a
    /// shrouded cell; with the shading below it puts the controller network's 3.0 V threshold at the
    /// ~125 rpm limit noted in NOTES.md.
    pub lit_lux: f64,
    /// Illuminance on the cell behind the flag (lx). 1 (argument): an opaque paper flag leaves only
    /// stray light on a shrouded cell.
    pub shaded_lux: f64,
    /// Lamp flicker depth, (max - min) / (max + min), 0..=1. 0 (argument): DC lamp; a mains incandescent
    /// bulb is about 0.1.
    pub flicker_depth: f64,
    /// Mains frequency (Hz); the lamp flickers at twice this. 50: the lab is in Europe (the
    /// Controller_network project).
    pub mains_hz: f64,
    /// Cell resistance at 10 lx (ohm). 15 k: middle of the GL5528 datasheet range 10-20 k.
    pub ldr_ohm_at_10_lux: f64,
    /// Power-law exponent, log10(R10 / R100). 0.6: GL5528 datasheet.
    pub ldr_gamma: f64,
    /// Dark resistance, the ceiling of the power law (ohm). 1 M: GL5528 datasheet minimum.
    pub ldr_dark_ohm: f64,
    /// Time constant while the resistance rises, light -> dark (s). 0.030: GL5528 datasheet decay time.
    pub tau_resistance_rise_s: f64,
    /// Time constant while the resistance falls, dark -> light (s). 0.020: GL5528 datasheet rise time.
    pub tau_resistance_fall_s: f64,
    /// Fixed divider resistor from the output to ground, under the cell (ohm). 10 k (argument): the usual
    /// pull-down for a GL5528; lit and shaded then sit near 4.0 V and 0.7 V.
    pub divider_fixed_ohm: f64,
    /// Supply on top of the cell (V). 5: the module's 5 V rail.
    pub supply_volts: f64,
    /// ADC resolution (bits, 1..=16). 12: the vemodule's analog inputs (meb.md).
    pub adc_bits: u8,
    /// ADC full-scale reference (V). 5: the vemodule reads 0-5 V (meb.md).
    pub adc_reference_volts: f64,
    /// RMS noise on the divider output (V). 0.002 (argument): rail ripple and pickup, ~1.6 LSB at 12 bits.
    pub noise_rms_volts: f64,
}

impl Default for LightParams {
    fn default() -> Self {
        Self {
            flag_arc_deg: 30.0,
            flags: 1,
            flag_center_deg: 180.0,
            lit_lux: 200.0,
            shaded_lux: 1.0,
            flicker_depth: 0.0,
            mains_hz: 50.0,
            ldr_ohm_at_10_lux: 15e3,
            ldr_gamma: 0.6,
            ldr_dark_ohm: 1e6,
            tau_resistance_rise_s: 0.030,
            tau_resistance_fall_s: 0.020,
            divider_fixed_ohm: 10e3,
            supply_volts: 5.0,
            adc_bits: 12,
            adc_reference_volts: 5.0,
            noise_rms_volts: 0.002,
        }
    }
}

/// A [`LightParams`] field outside its physical range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("light sensor parameter `{field}` must be {requirement}, got {value}")]
pub struct LightParamsError {
    /// Field name as in the config file.
    pub field: &'static str,
    /// What the field must satisfy.
    pub requirement: &'static str,
    /// The value found.
    pub value: f64,
}

impl LightParams {
    /// The Controller_network project's light-sensor Nano: 10-bit ADC on a 5 V reference, "dark
    /// below 3.0 V". A 39 kOhm pull-down (E12) puts the lit level at 4.70 V and the shaded level at
    /// 1.98 V, both well clear of 3.0 V.
    pub fn controller_network() -> Self {
        Self {
            // The Controller_network project's log shows the light node reading
            // a steady ≈ 98 rpm with 20 ms sampling. A 30° flag shades the cell
            // for 50 ms at 100 rpm, of which only ~10 ms fall below 3.0 V, so
            // most passes would slip between samples; the project's marker must
            // have been wider. 60° (a 34 mm paper strip on the 65 mm wheel)
            // keeps the signal below 3.0 V for about 60 ms per turn at 100 rpm.
            flag_arc_deg: 60.0,
            // The bench's log: the light reading steps every 0.205 s while the
            // motor reads 9850 rpm (the wheel turns in 0.609 s), and it settles
            // at the motor's value: three marks a turn, which the firmware
            // divides by.
            flags: 3,
            divider_fixed_ohm: 39e3,
            adc_bits: 10,
            // Argument: about 1 LSB of the Arduino's 10-bit ADC, referenced to a USB-fed 5 V rail.
            noise_rms_volts: 0.005,
            ..Self::default()
        }
    }

    /// Checks every field against its physical range; a loader calls this on parameters from a file.
    /// [`LightSensor`] never panics or hangs on unchecked values, but their output is meaningless.
    pub fn validate(&self) -> Result<(), LightParamsError> {
        let check = |field, value: f64, ok: bool, requirement| {
            let error = LightParamsError {
                field,
                requirement,
                value,
            };
            if ok { Ok(()) } else { Err(error) }
        };
        for (field, value) in [
            ("mains_hz", self.mains_hz),
            ("ldr_ohm_at_10_lux", self.ldr_ohm_at_10_lux),
            ("ldr_gamma", self.ldr_gamma),
            ("ldr_dark_ohm", self.ldr_dark_ohm),
            ("tau_resistance_rise_s", self.tau_resistance_rise_s),
            ("tau_resistance_fall_s", self.tau_resistance_fall_s),
            ("divider_fixed_ohm", self.divider_fixed_ohm),
            ("supply_volts", self.supply_volts),
            ("adc_reference_volts", self.adc_reference_volts),
        ] {
            check(field, value, positive(value), "finite and > 0")?;
        }
        for (field, value) in [
            ("lit_lux", self.lit_lux),
            ("shaded_lux", self.shaded_lux),
            ("noise_rms_volts", self.noise_rms_volts),
        ] {
            check(
                field,
                value,
                value >= 0.0 && value.is_finite(),
                "finite and >= 0",
            )?;
        }
        let (arc, centre, depth) = (self.flag_arc_deg, self.flag_center_deg, self.flicker_depth);
        check(
            "flag_arc_deg",
            arc,
            (0.0..=360.0).contains(&arc),
            "in 0..=360",
        )?;
        check("flag_center_deg", centre, centre.is_finite(), "finite")?;
        check(
            "flags",
            f64::from(self.flags),
            self.flags >= 1 && f64::from(self.flags) * arc <= 360.0,
            "at least 1, and flags x flag_arc_deg at most 360",
        )?;
        check(
            "flicker_depth",
            depth,
            (0.0..=1.0).contains(&depth),
            "in 0..=1",
        )?;
        let bits = self.adc_bits;
        check(
            "adc_bits",
            f64::from(bits),
            (1..=16).contains(&bits),
            "in 1..=16",
        )
    }

    /// Steady cell resistance under `lux` (ohm): the power law, capped at the dark resistance.
    pub fn steady_resistance_ohm(&self, lux: f64) -> f64 {
        (-self.steady_log_conductance(lux)).exp()
    }

    /// Divider output for a cell resistance (V), noise-free.
    pub fn divider_volts(&self, ldr_ohm: f64) -> f64 {
        self.supply_volts * self.divider_fixed_ohm / (self.divider_fixed_ohm + ldr_ohm)
    }

    /// Divider output with the beam clear, steady state (V).
    pub fn lit_volts(&self) -> f64 {
        self.divider_volts(self.steady_resistance_ohm(self.lit_lux))
    }

    /// Divider output with the flag in the beam, steady state (V).
    pub fn shaded_volts(&self) -> f64 {
        self.divider_volts(self.steady_resistance_ohm(self.shaded_lux))
    }

    /// ADC reading of `volts`: `floor(V / Vref * 2^bits)`, clamped to `0..=2^bits - 1`.
    pub fn adc_counts_for(&self, volts: f64) -> u16 {
        let bits = self.adc_bits.clamp(1, 16);
        let full_scale = (1u32 << bits) - 1;
        let counts = (volts / self.adc_reference_volts * f64::from(1u32 << bits)).floor();
        if counts.is_nan() || counts <= 0.0 {
            0
        } else if counts >= f64::from(full_scale) {
            u16::try_from(full_scale).unwrap_or(u16::MAX)
        } else {
            // In range 0..65535 here, so the cast is exact.
            counts as u16
        }
    }

    /// Log-conductance `x = -ln(R / 1 ohm)` the cell settles to under `lux`.
    fn steady_log_conductance(&self, lux: f64) -> f64 {
        let floor = -self.ldr_dark_ohm.ln();
        if lux.is_nan() || lux <= 0.0 {
            return floor;
        }
        let power_law = -self.ldr_ohm_at_10_lux.ln() + self.ldr_gamma * (lux / 10.0).ln();
        // `max` keeps the finite side if the power law came out NaN.
        power_law.max(floor)
    }

    /// Log-conductance at which the divider reads `volts`; NaN outside `0 < volts < supply`.
    fn log_conductance_at_volts(&self, volts: f64) -> f64 {
        -(self.divider_fixed_ohm * (self.supply_volts / volts - 1.0)).ln()
    }
}

fn positive(value: f64) -> bool {
    value > 0.0 && value.is_finite()
}

/// Fastest wheel speed (rpm) at which the flag's dip still crosses below a fixed `threshold_volts`, from the flag
/// arc, time constants, divider and threshold (noise and flicker ignored). Derived in the module docs.
/// 0 when the threshold lies outside the lit-shaded range (no speed gives a crossing); infinite for an
/// instantaneous cell.
pub fn fixed_threshold_max_rpm(params: &LightParams, threshold_volts: f64) -> f64 {
    let x_lit = params.steady_log_conductance(params.lit_lux);
    let x_shaded = params.steady_log_conductance(params.shaded_lux);
    let x_threshold = params.log_conductance_at_volts(threshold_volts);
    // Written so that NaN anywhere also lands on 0.
    if !(x_shaded < x_threshold && x_threshold < x_lit) {
        return 0.0;
    }
    let shadow_s =
        params.tau_resistance_rise_s * ((x_lit - x_shaded) / (x_threshold - x_shaded)).ln();
    let shadow_per_rpm = params.flag_arc_deg / 360.0 * 60.0;
    if shadow_s > 0.0 {
        shadow_per_rpm / shadow_s
    } else {
        f64::INFINITY
    }
}

/// Fastest wheel speed (rpm) at which the dip from the lit level is at least `dip_volts` deep: the limit of
/// an adaptive detector that needs that dip (see the module docs).
pub fn adaptive_dip_max_rpm(params: &LightParams, dip_volts: f64) -> f64 {
    fixed_threshold_max_rpm(params, params.lit_volts() - dip_volts)
}

/// The light sensor's state.
#[derive(Debug, Clone)]
pub struct LightSensor {
    params: LightParams,
    /// Steady log-conductance with the beam clear / blocked, DC lamp.
    x_lit: f64,
    x_shaded: f64,
    /// Flag arc (clamped to a full turn) and the wheel angle of its middle, rad,
    /// both measured in "flag angle": the wheel angle times the number of
    /// flags, in which evenly spaced flags are one flag a turn.
    arc_rad: f64,
    centre_rad: f64,
    flags: f64,
    /// Lamp light is constant on cells of this length when it flickers (s); 0 for a DC lamp.
    flicker_cell_s: f64,
    /// Present log-conductance, `-ln(R / 1 ohm)`.
    log_conductance: f64,
    flag_in_beam: bool,
    noise_volts: f64,
    rng: Pcg64,
}

impl LightSensor {
    /// A sensor at its lit steady state, flag out of the beam, no noise drawn yet.
    pub fn new(params: &LightParams, seed: u64) -> Self {
        let x_lit = params.steady_log_conductance(params.lit_lux);
        let flickers = params.flicker_depth > 0.0 && positive(params.mains_hz);
        let flicker_cell_s = if flickers {
            FLICKER_CELL_MAX_S.min(1.0 / (16.0 * params.mains_hz))
        } else {
            0.0
        };
        Self {
            params: params.clone(),
            x_lit,
            x_shaded: params.steady_log_conductance(params.shaded_lux),
            arc_rad: (params.flag_arc_deg.to_radians() * f64::from(params.flags.max(1)))
                .clamp(0.0, TAU),
            centre_rad: params.flag_center_deg.to_radians() * f64::from(params.flags.max(1)),
            flags: f64::from(params.flags.max(1)),
            flicker_cell_s,
            log_conductance: x_lit,
            flag_in_beam: false,
            noise_volts: 0.0,
            rng: Pcg64::seed_from_u64(seed),
        }
    }

    /// Advance from time `t` by `dt` s while the wheel angle moves LINEARLY from `angle_start` to `angle_end`
    /// (radians, unwrapped, either direction; may cover several turns in one step).
    pub fn step(&mut self, t: f64, dt: f64, angle_start: f64, angle_end: f64) {
        let (angle_start, angle_end) = (angle_start * self.flags, angle_end * self.flags);
        let travel = angle_end - angle_start;
        let has_edges = self.arc_rad > 0.0 && self.arc_rad < TAU;
        if dt > 0.0 && dt.is_finite() {
            if has_edges && travel != 0.0 && travel.is_finite() && angle_start.is_finite() {
                self.walk(t, dt, angle_start, travel);
            } else {
                let in_beam = self.beam_at(angle_end);
                self.hold(t, dt, in_beam);
                self.flag_in_beam = in_beam;
            }
        } else {
            self.flag_in_beam = self.beam_at(angle_end);
        }
        self.draw_noise();
    }

    /// Divider output at the end of the last step, with noise (V).
    pub fn divider_voltage(&self) -> f64 {
        self.clean_divider_voltage() + self.noise_volts
    }

    /// Divider output at the end of the last step, without noise (V).
    pub fn clean_divider_voltage(&self) -> f64 {
        self.params.divider_volts(self.ldr_resistance())
    }

    /// ADC reading of divider_voltage(), clamped to the ADC's range.
    pub fn adc_counts(&self) -> u16 {
        self.params.adc_counts_for(self.divider_voltage())
    }

    /// True geometry: the flag is between lamp and LDR at the end of the last step.
    pub fn flag_in_beam(&self) -> bool {
        self.flag_in_beam
    }

    /// Present LDR resistance (ohm).
    pub fn ldr_resistance(&self) -> f64 {
        (-self.log_conductance).exp()
    }

    /// The parameters this sensor was built with.
    pub fn params(&self) -> &LightParams {
        &self.params
    }

    /// Angle past the flag's leading edge, in `[0, 2 pi)`, for a flag whose middle is at `centre`.
    fn phase(&self, angle: f64, centre: f64) -> f64 {
        let phase = (angle - (centre - 0.5 * self.arc_rad)).rem_euclid(TAU);
        // rem_euclid may round up to exactly TAU for tiny negative inputs.
        if phase >= TAU { 0.0 } else { phase }
    }

    fn beam_at(&self, angle: f64) -> bool {
        if self.arc_rad >= TAU {
            return true;
        }
        self.phase(angle, self.centre_rad) < self.arc_rad
    }

    /// Splits the motion at the flag edges and applies each piece of constant shading exactly.
    fn walk(&mut self, t: f64, dt: f64, angle_start: f64, travel: f64) {
        // The flag is symmetric about its middle, so backward motion is forward motion of the mirrored wheel.
        let (start, centre) = if travel > 0.0 {
            (angle_start, self.centre_rad)
        } else {
            (-angle_start, -self.centre_rad)
        };
        let arc = self.arc_rad;
        let mut remaining = travel.abs();
        let rate = remaining / dt;
        let mut phase = self.phase(start, centre);
        let mut in_beam = phase < arc;
        let mut elapsed = 0.0;
        let mut turns_folded = false;
        loop {
            if in_beam && phase == 0.0 && remaining >= TAU && !turns_folded {
                turns_folded = true;
                let turns = (remaining / TAU).floor();
                if self.fold_turns(turns, arc / rate, (TAU - arc) / rate) {
                    elapsed += turns * TAU / rate;
                    remaining -= turns * TAU;
                }
            }
            let to_edge = if in_beam { arc - phase } else { TAU - phase };
            if to_edge >= remaining {
                self.hold(t + elapsed, (dt - elapsed).max(0.0), in_beam);
                break;
            }
            let piece_s = to_edge / rate;
            self.hold(t + elapsed, piece_s, in_beam);
            elapsed += piece_s;
            remaining -= to_edge;
            (phase, in_beam) = if in_beam { (arc, false) } else { (0.0, true) };
        }
        self.flag_in_beam = in_beam;
    }

    /// Applies `turns` whole turns, each starting as the flag enters the beam, as one affine map
    /// `x <- A x + B` raised to the power `turns`. DC lamp only; false (nothing done) otherwise or if the
    /// state lies outside the lit-shaded range, where the direction of change (and so tau) could differ.
    fn fold_turns(&mut self, turns: f64, shaded_s: f64, lit_s: f64) -> bool {
        let (x_lit, x_shaded, x) = (self.x_lit, self.x_shaded, self.log_conductance);
        let within = x_lit.min(x_shaded) <= x && x <= x_lit.max(x_shaded);
        if self.flicker_cell_s > 0.0 || !within {
            return false;
        }
        let log_shaded = -shaded_s / self.tau_towards(x_shaded, x_lit);
        let log_lit = -lit_s / self.tau_towards(x_lit, x_shaded);
        // One turn: x1 = x_s + (x - x_s) a, then x2 = x_l + (x1 - x_l) b, so A = a b and
        // B = b (1 - a) x_s + (1 - b) x_l; 1 - a is taken as -expm1 to stay accurate for short shadows.
        let offset = -log_lit.exp() * log_shaded.exp_m1() * x_shaded - log_lit.exp_m1() * x_lit;
        let log_gain = log_shaded + log_lit;
        // Geometric sum 1 + A + ... + A^(turns-1), accurate for A near 1.
        let sum = if log_gain == 0.0 {
            turns
        } else {
            (turns * log_gain).exp_m1() / log_gain.exp_m1()
        };
        self.log_conductance = (turns * log_gain).exp() * x + offset * sum;
        true
    }

    /// Time constant for moving towards `target` from the `from` side.
    fn tau_towards(&self, target: f64, from: f64) -> f64 {
        let tau = if target < from {
            self.params.tau_resistance_rise_s
        } else {
            self.params.tau_resistance_fall_s
        };
        tau.max(0.0)
    }

    /// Holds the shading constant for `duration` s from time `t`.
    fn hold(&mut self, t: f64, duration: f64, in_beam: bool) {
        let x_dc = if in_beam { self.x_shaded } else { self.x_lit };
        let cell = self.flicker_cell_s;
        if cell <= 0.0 {
            self.relax(x_dc, duration);
            return;
        }
        let first_cell = (t / cell).floor();
        // Times so large (or NaN) that the grid no longer resolves: take the light as steady.
        if !first_cell.is_finite() || first_cell + 1.0 == first_cell {
            self.relax(x_dc, duration);
            return;
        }
        let lux = if in_beam {
            self.params.shaded_lux
        } else {
            self.params.lit_lux
        };
        let flicker_rad_per_s = TAU * 2.0 * self.params.mains_hz;
        let end = t + duration;
        let (mut now, mut k) = (t, first_cell);
        while now < end {
            let cell_end = ((k + 1.0) * cell).min(end);
            if cell_end > now {
                let flicker =
                    1.0 + self.params.flicker_depth * (flicker_rad_per_s * (k + 0.5) * cell).sin();
                let target = self.params.steady_log_conductance(lux * flicker);
                self.relax(target, cell_end - now);
                now = cell_end;
            }
            k += 1.0;
        }
    }

    /// Exact first-order update towards `target` over `duration` s.
    fn relax(&mut self, target: f64, duration: f64) {
        if duration.is_nan() || duration <= 0.0 {
            return;
        }
        let x = self.log_conductance;
        let tau = self.tau_towards(target, x);
        self.log_conductance = target + (x - target) * (-duration / tau).exp();
    }

    /// One Gaussian draw per step (Box-Muller, cosine branch), so the stream depends only on the seed and
    /// the number of steps.
    fn draw_noise(&mut self) {
        let u1 = 1.0 - self.rng.random::<f64>();
        let u2 = self.rng.random::<f64>();
        let z = (-2.0 * u1.ln()).sqrt() * (TAU * u2).cos();
        self.noise_volts = self.params.noise_rms_volts * z;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quiet(params: LightParams) -> LightParams {
        LightParams {
            noise_rms_volts: 0.0,
            ..params
        }
    }

    /// Wheel angle that puts the flag's middle in the beam.
    fn flag_angle(params: &LightParams) -> f64 {
        params.flag_center_deg.to_radians()
    }

    fn rad_per_s(rpm: f64) -> f64 {
        rpm * TAU / 60.0
    }

    /// Turns the wheel at constant speed from `angle0` for `steps` steps of `dt`, calling `sample` after each.
    fn spin(
        sensor: &mut LightSensor,
        rpm: f64,
        angle0: f64,
        dt: f64,
        steps: usize,
        mut sample: impl FnMut(f64, &LightSensor),
    ) {
        let omega = rad_per_s(rpm);
        for k in 0..steps {
            let (t0, t1) = (k as f64 * dt, (k + 1) as f64 * dt);
            sensor.step(t0, dt, angle0 + omega * t0, angle0 + omega * t1);
            sample(t1, sensor);
        }
    }

    fn lowest_voltage(params: &LightParams, rpm: f64, turns: f64, dt: f64) -> f64 {
        let mut sensor = LightSensor::new(params, 1);
        let steps = (turns * 60.0 / rpm / dt).ceil() as usize;
        let mut lowest = f64::INFINITY;
        let start = flag_angle(params) + std::f64::consts::PI;
        spin(&mut sensor, rpm, start, dt, steps, |_, s| {
            lowest = lowest.min(s.divider_voltage())
        });
        lowest
    }

    fn log_conductance(sensor: &LightSensor) -> f64 {
        -sensor.ldr_resistance().ln()
    }

    #[test]
    fn static_levels_match_the_divider_formula() {
        for params in [
            quiet(LightParams::default()),
            quiet(LightParams::controller_network()),
        ] {
            let divider = |lux: f64| {
                let ldr = params.ldr_ohm_at_10_lux * (lux / 10.0).powf(-params.ldr_gamma);
                params.supply_volts * params.divider_fixed_ohm / (params.divider_fixed_ohm + ldr)
            };
            let mut sensor = LightSensor::new(&params, 7);
            sensor.step(0.0, 1.0, 0.0, 0.0);
            assert!(!sensor.flag_in_beam());
            assert!((sensor.divider_voltage() - divider(params.lit_lux)).abs() < 1e-12);
            let flag = flag_angle(&params);
            sensor.step(1.0, 2.0, flag, flag);
            assert!(sensor.flag_in_beam());
            assert!((sensor.divider_voltage() - divider(params.shaded_lux)).abs() < 1e-9);
            assert!((params.shaded_volts() - divider(params.shaded_lux)).abs() < 1e-12);
        }
        // The Controller_network light node: lit well above its 3.0 V threshold, shaded well below.
        let network = LightParams::controller_network();
        assert!(
            network.lit_volts() > 4.5 && network.shaded_volts() < 2.0,
            "{network:?}"
        );
    }

    #[test]
    fn shadow_follows_the_exponential_law_at_any_step() {
        let params = quiet(LightParams::default());
        let x_lit = params.steady_log_conductance(params.lit_lux);
        let x_shaded = params.steady_log_conductance(params.shaded_lux);
        let flag = flag_angle(&params);
        let (rise, fall) = (params.tau_resistance_rise_s, params.tau_resistance_fall_s);
        let checkpoints = [0.01, 0.02, 0.03, 0.05, 0.1];
        let mut runs = Vec::new();
        for dt in [1e-5_f64, 1e-2] {
            let mut sensor = LightSensor::new(&params, 3);
            let mut seen = Vec::new();
            let steps = (0.2 / dt).round() as usize;
            for k in 0..steps {
                let t = k as f64 * dt;
                // Shaded for 100 ms, then lit again.
                let angle = if t < 0.1 - 1e-12 { flag } else { 0.0 };
                sensor.step(t, dt, angle, angle);
                let t_end = (k + 1) as f64 * dt;
                let x = log_conductance(&sensor);
                if let Some(&c) = checkpoints.iter().find(|&&c| (c - t_end).abs() < 1e-9) {
                    let expected = x_shaded + (x_lit - x_shaded) * (-c / rise).exp();
                    assert!(
                        (x - expected).abs() < 1e-9,
                        "dt {dt} t {c}: {x} vs {expected}"
                    );
                    seen.push(x);
                }
                if (t_end - 0.15).abs() < 1e-9 || (t_end - 0.2).abs() < 1e-9 {
                    let x_100ms = x_shaded + (x_lit - x_shaded) * (-0.1 / rise).exp();
                    let expected = x_lit + (x_100ms - x_lit) * (-(t_end - 0.1) / fall).exp();
                    assert!(
                        (x - expected).abs() < 1e-9,
                        "dt {dt} t {t_end}: {x} vs {expected}"
                    );
                    seen.push(x);
                }
            }
            assert_eq!(seen.len(), checkpoints.len() + 2);
            runs.push(seen);
        }
        for (fine, coarse) in runs[0].iter().zip(&runs[1]) {
            assert!((fine - coarse).abs() < 1e-9);
        }
    }

    #[test]
    fn the_dip_does_not_depend_on_the_step() {
        let params = quiet(LightParams::default());
        let start = flag_angle(&params) - 0.5;
        let mut runs = Vec::new();
        for dt in [1e-5_f64, 1e-3, 2.5e-3, 1e-2] {
            let mut sensor = LightSensor::new(&params, 5);
            let mut every_10ms = Vec::new();
            let steps = (0.6 / dt).round() as usize;
            spin(&mut sensor, 200.0, start, dt, steps, |t, s| {
                let k = (t / 0.01).round();
                if (t - k * 0.01).abs() < 1e-9 {
                    every_10ms.push(s.divider_voltage());
                }
            });
            assert_eq!(every_10ms.len(), 60);
            runs.push(every_10ms);
        }
        // The samples must catch the dip for the comparison to mean anything.
        assert!(runs[0].iter().any(|&v| v < params.lit_volts() - 1.0));
        for run in &runs[1..] {
            for (a, b) in runs[0].iter().zip(run) {
                assert!((a - b).abs() < 1e-9, "{a} vs {b}");
            }
        }
    }

    #[test]
    fn fixed_threshold_limit_is_within_ten_percent() {
        let vemodule = quiet(LightParams::default());
        let mid_way = 0.5 * (vemodule.lit_volts() + vemodule.shaded_volts());
        // The formula assumes the cell recovers fully between dips: one flag.
        // (The geared bench's three marks leave 60° gaps, over which the cell
        // recovers to within a few mV of lit at the limit.)
        let one_mark = LightParams {
            flags: 1,
            ..LightParams::controller_network()
        };
        for (params, threshold) in [(quiet(one_mark), 3.0), (vemodule, mid_way)] {
            let limit = fixed_threshold_max_rpm(&params, threshold);
            assert!(limit > 50.0 && limit < 1000.0, "{limit}");
            let slower = lowest_voltage(&params, 0.9 * limit, 3.0, 2e-5);
            let faster = lowest_voltage(&params, 1.1 * limit, 3.0, 2e-5);
            assert!(
                slower < threshold,
                "0.9x: {slower} should cross {threshold}"
            );
            assert!(
                faster > threshold,
                "1.1x: {faster} should stay above {threshold}"
            );
        }
        // Thresholds outside the lit-shaded range can never be crossed by the dip.
        let params = LightParams::controller_network();
        assert_eq!(fixed_threshold_max_rpm(&params, 4.9), 0.0);
        assert_eq!(fixed_threshold_max_rpm(&params, 1.0), 0.0);
        assert_eq!(fixed_threshold_max_rpm(&params, f64::NAN), 0.0);
    }

    #[test]
    fn module_doc_numbers_hold() {
        let network = LightParams::controller_network();
        let vemodule = LightParams::default();
        let swing_20 = |p: &LightParams| p.lit_volts() - 0.2 * (p.lit_volts() - p.shaded_volts());
        let near =
            |value: f64, expected: f64, tolerance: f64| (value - expected).abs() <= tolerance;
        assert!(
            near(network.lit_volts(), 4.700, 5e-4) && near(network.shaded_volts(), 1.975, 5e-4)
        );
        assert!(
            near(vemodule.lit_volts(), 4.005, 5e-4) && near(vemodule.shaded_volts(), 0.717, 5e-4)
        );
        assert!(near(fixed_threshold_max_rpm(&network, 3.0), 248.0, 1.0));
        let mid_way = 0.5 * (vemodule.lit_volts() + vemodule.shaded_volts());
        assert!(near(mid_way, 2.36, 5e-3));
        assert!(near(
            fixed_threshold_max_rpm(&vemodule, mid_way),
            260.0,
            0.5
        ));
        assert!(near(swing_20(&network), 4.155, 5e-3) && near(swing_20(&vemodule), 3.35, 5e-3));
        assert!(near(
            fixed_threshold_max_rpm(&network, swing_20(&network)),
            734.0,
            1.0
        ));
        assert!(near(
            fixed_threshold_max_rpm(&vemodule, swing_20(&vemodule)),
            685.0,
            0.5
        ));
        assert!(near(
            adaptive_dip_max_rpm(&network, 5.0 * network.noise_rms_volts),
            12200.0,
            100.0
        ));
        assert!(near(
            adaptive_dip_max_rpm(&vemodule, 5.0 * vemodule.noise_rms_volts),
            42000.0,
            500.0
        ));
    }

    #[test]
    fn reverse_rotation_gives_the_same_dip() {
        let params = quiet(LightParams::default());
        // Mirror images: forward from 1 rad before the flag, backward from 1 rad after it.
        let mut traces = Vec::new();
        for rpm in [300.0_f64, -300.0] {
            let start = flag_angle(&params) - rpm.signum() * 1.0;
            let mut sensor = LightSensor::new(&params, 9);
            let mut trace = Vec::new();
            spin(&mut sensor, rpm, start, 1e-4, 4000, |_, s| {
                trace.push((s.divider_voltage(), s.flag_in_beam()))
            });
            traces.push(trace);
        }
        assert!(traces[0].iter().any(|&(v, _)| v < params.lit_volts() - 1.0));
        assert!(traces[0].iter().filter(|&&(_, in_beam)| in_beam).count() > 100);
        for (forward, backward) in traces[0].iter().zip(&traces[1]) {
            assert!((forward.0 - backward.0).abs() < 1e-9);
            assert_eq!(forward.1, backward.1);
        }
    }

    #[test]
    fn one_step_over_several_turns_matches_fine_steps() {
        let params = quiet(LightParams::default());
        let start = 0.3;
        for rpm in [600.0_f64, -600.0, 37.0] {
            let duration = 5.3 * 60.0 / rpm.abs();
            let omega = rad_per_s(rpm);
            let mut coarse = LightSensor::new(&params, 1);
            coarse.step(0.0, duration, start, start + omega * duration);
            let mut fine = LightSensor::new(&params, 1);
            let steps = (duration / 1e-5).round() as usize;
            spin(
                &mut fine,
                rpm,
                start,
                duration / steps as f64,
                steps,
                |_, _| {},
            );
            let (x_coarse, x_fine) = (log_conductance(&coarse), log_conductance(&fine));
            assert!(
                (x_coarse - x_fine).abs() < 1e-8,
                "{rpm} rpm: {x_coarse} vs {x_fine}"
            );
            assert_eq!(coarse.flag_in_beam(), fine.flag_in_beam());
        }
    }

    #[test]
    fn dark_time_is_summed_over_turns() {
        // A cell that never recovers in the light darkens by the total shadow time only.
        let params = LightParams {
            tau_resistance_fall_s: 1e15,
            ..quiet(LightParams::default())
        };
        let x_lit = params.steady_log_conductance(params.lit_lux);
        let x_shaded = params.steady_log_conductance(params.shaded_lux);
        let (rpm, turns) = (600.0, 7.0);
        let omega = rad_per_s(rpm);
        let start = flag_angle(&params) + std::f64::consts::PI;
        let duration = turns * TAU / omega;
        let shadow_s = turns * params.flag_arc_deg.to_radians() / omega;
        let expected =
            x_shaded + (x_lit - x_shaded) * (-shadow_s / params.tau_resistance_rise_s).exp();
        for pieces in [1, 3, 1000] {
            let mut sensor = LightSensor::new(&params, 2);
            let dt = duration / pieces as f64;
            spin(&mut sensor, rpm, start, dt, pieces, |_, _| {});
            let x = log_conductance(&sensor);
            assert!(
                (x - expected).abs() < 1e-9,
                "{pieces} pieces: {x} vs {expected}"
            );
        }
    }

    #[test]
    fn noise_is_seeded_and_gaussian() {
        let params = LightParams::default();
        let run = |seed: u64| {
            let mut sensor = LightSensor::new(&params, seed);
            let mut trace = Vec::new();
            spin(&mut sensor, 150.0, 0.0, 1e-3, 2000, |_, s| {
                trace.push((s.divider_voltage().to_bits(), s.adc_counts()));
            });
            trace
        };
        assert_eq!(run(42), run(42));
        assert_ne!(run(42), run(43));

        let mut sensor = LightSensor::new(&params, 11);
        let (mut sum, mut sum_sq, n) = (0.0, 0.0, 20_000);
        for k in 0..n {
            sensor.step(k as f64, 1.0, 0.0, 0.0);
            let noise = sensor.divider_voltage() - sensor.clean_divider_voltage();
            sum += noise;
            sum_sq += noise * noise;
        }
        let mean = sum / f64::from(n);
        let rms = (sum_sq / f64::from(n) - mean * mean).sqrt();
        assert!(
            mean.abs() < 4.0 * params.noise_rms_volts / f64::from(n).sqrt(),
            "{mean}"
        );
        assert!((rms / params.noise_rms_volts - 1.0).abs() < 0.03, "{rms}");
    }

    #[test]
    fn adc_quantises_and_clamps() {
        let vemodule = LightParams::default();
        assert_eq!(vemodule.adc_counts_for(2.5), 2048);
        assert_eq!(vemodule.adc_counts_for(4.9999), 4095);
        assert_eq!(vemodule.adc_counts_for(7.0), 4095);
        assert_eq!(vemodule.adc_counts_for(-0.3), 0);
        assert_eq!(vemodule.adc_counts_for(f64::NAN), 0);
        let network = LightParams::controller_network();
        assert_eq!(network.adc_counts_for(3.0), 614);
        assert_eq!(network.adc_counts_for(9.0), 1023);
        let sensor = LightSensor::new(&quiet(network.clone()), 0);
        assert_eq!(
            sensor.adc_counts(),
            network.adc_counts_for(network.lit_volts())
        );
    }

    #[test]
    fn flickering_lamp_ripples_at_twice_mains_whatever_the_step() {
        let depth = 0.1;
        let params = LightParams {
            flicker_depth: depth,
            ..quiet(LightParams::default())
        };
        let mut runs = Vec::new();
        for dt in [1e-5_f64, 1e-2] {
            let mut sensor = LightSensor::new(&params, 4);
            let (mut lowest, mut highest, mut at_10ms) =
                (f64::INFINITY, f64::NEG_INFINITY, Vec::new());
            let steps = (0.5 / dt).round() as usize;
            for k in 0..steps {
                sensor.step(k as f64 * dt, dt, 0.0, 0.0);
                let t_end = (k + 1) as f64 * dt;
                let x = log_conductance(&sensor);
                if t_end > 0.4 {
                    (lowest, highest) = (lowest.min(x), highest.max(x));
                }
                if ((t_end / 0.01).round() * 0.01 - t_end).abs() < 1e-9 {
                    at_10ms.push(x);
                }
            }
            runs.push((highest - lowest, at_10ms));
        }
        for (a, b) in runs[0].1.iter().zip(&runs[1].1) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        // Small-signal first-order filter of gamma * depth * sin(2 pi 100 t): the ripple lies between the
        // amplitudes for the slower and the faster time constant.
        let omega = TAU * 2.0 * params.mains_hz;
        let peak_to_peak =
            |tau: f64| 2.0 * params.ldr_gamma * depth / (1.0 + (omega * tau).powi(2)).sqrt();
        let ripple = runs[0].0;
        assert!(
            ripple > 0.9 * peak_to_peak(params.tau_resistance_rise_s),
            "{ripple}"
        );
        assert!(
            ripple < 1.1 * peak_to_peak(params.tau_resistance_fall_s),
            "{ripple}"
        );
    }

    #[test]
    fn flag_geometry_and_odd_inputs() {
        let params = quiet(LightParams::default());
        let mut sensor = LightSensor::new(&params, 0);
        let flag = flag_angle(&params);
        let half_arc = 0.5 * params.flag_arc_deg.to_radians();
        for (angle, expected) in [
            (flag, true),
            (flag + 0.9 * half_arc, true),
            (flag - 1.1 * half_arc, false),
        ] {
            for turns in [-3.0, 0.0, 2.0] {
                sensor.step(0.0, 1e-3, angle + turns * TAU, angle + turns * TAU);
                assert_eq!(sensor.flag_in_beam(), expected, "{angle} + {turns} turns");
            }
        }
        for (t, dt, a0, a1) in [
            (0.0, 0.0, 0.0, 1.0),
            (0.0, -1.0, 0.0, 1.0),
            (0.0, 1e-3, f64::NAN, 1.0),
            (0.0, 1e-3, 0.0, f64::INFINITY),
            (f64::NAN, 1e-3, 0.0, 1.0),
            (1e300, 1e-3, 0.0, 1e6),
        ] {
            sensor.step(t, dt, a0, a1);
            assert!(sensor.ldr_resistance().is_finite() && sensor.divider_voltage().is_finite());
        }
        let always = LightSensor::new(
            &LightParams {
                flag_arc_deg: 360.0,
                ..params.clone()
            },
            0,
        );
        let never = LightSensor::new(
            &LightParams {
                flag_arc_deg: 0.0,
                ..params.clone()
            },
            0,
        );
        for mut sensor in [always, never] {
            let full = sensor.params().flag_arc_deg >= 360.0;
            sensor.step(0.0, 0.05, 0.0, 3.0);
            assert_eq!(sensor.flag_in_beam(), full);
            assert_eq!(sensor.divider_voltage() < params.lit_volts() - 0.5, full);
        }
    }

    #[test]
    fn params_load_from_toml_and_validate() {
        let loaded: LightParams =
            toml::from_str(
                "flag_arc_deg = 60.0\nflags = 3\nadc_bits = 10\ndivider_fixed_ohm = 39000.0\nnoise_rms_volts = 0.005",
            )
                .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(loaded, LightParams::controller_network());
        assert!(toml::from_str::<LightParams>("flag_arc = 30.0").is_err());
        assert_eq!(LightParams::default().validate(), Ok(()));
        assert_eq!(LightParams::controller_network().validate(), Ok(()));
        let bad = LightParams {
            tau_resistance_rise_s: -0.03,
            ..LightParams::default()
        };
        assert_eq!(
            bad.validate().map_err(|e| e.field),
            Err("tau_resistance_rise_s")
        );
        let bad = LightParams {
            adc_bits: 17,
            ..LightParams::default()
        };
        assert_eq!(bad.validate().map_err(|e| e.field), Err("adc_bits"));
    }
}
