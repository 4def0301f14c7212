//! Buck-boost DC-DC converter between the battery (V1) and the inverter's DC bus
//! (V2), the bus capacitor and the discharge bleeder (`DES`).
//!
//! The model is *averaged and quasi-static*: the converter switches at tens of
//! kHz, far above anything the plant or the firmware resolve, so only its
//! cycle-averaged behaviour matters:
//!
//! - **Pass-through** (`PRO` off): the converter's high-side switch is held on,
//!   so the bus hangs on the battery through the switch resistance. Current
//!   flows both ways (regenerated energy goes back into the pack).
//! - **Regulated** (`PRO` on): a voltage-mode buck-boost regulating V2 to
//!   `regulated_bus_volts`. Its closed loop is represented by a Thévenin source
//!   (`regulated_bus_volts` behind `regulation_droop_ohm`, sourcing only, current
//!   limited): a control abstraction, not a resistor, so it dissipates nothing.
//!   The power it draws from the battery is the bus power divided by the
//!   efficiency, so the converter loss is `P_bus·(1/η − 1)`.
//!
//! The bus voltage obeys `C·dV2/dt = i_out − i_inverter − V2/R_bleed`, linear in
//! V2 for a constant inverter current, and is advanced with its exact
//! exponential solution so the step size never matters for stability. The
//! energy integrals (switch losses, bleeder heat) are integrated in closed form
//! over the same exponential, so the energy balance closes to rounding.

use serde::{Deserialize, Serialize};

/// Parameters of the DC-DC stage and the DC bus.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ConverterParams {
    /// Bus voltage regulated when `PRO` enables the boost (V). 48 V: the usual
    /// bus of a 36 V e-bike-class drive boosted one voltage class up.
    pub regulated_bus_volts: f64,
    /// Output impedance of the regulator's closed loop (Ω): 1 % droop at 10 A,
    /// typical of a voltage-mode converter without integral action on the droop.
    pub regulation_droop_ohm: f64,
    /// Largest current the converter delivers to the bus when regulating (A);
    /// its inductor's saturation-limited rating.
    pub max_output_amps: f64,
    /// Efficiency when regulating: 0.92 is typical of a 300 W hard-switched
    /// buck-boost at this voltage.
    pub efficiency: f64,
    /// On-resistance of the high-side switch in pass-through (Ω): two 10 mΩ
    /// MOSFETs and the inductor's copper.
    pub pass_through_ohm: f64,
    /// DC-bus capacitance (F): 1000 µF electrolytic, the common value on
    /// 36–48 V controller boards.
    pub bus_capacitance_farad: f64,
    /// Bleeder resistor switched across the bus by `DES` (Ω): 100 Ω gives
    /// τ = R·C = 0.1 s, a bus discharged in half a second.
    pub bleeder_ohm: f64,
    /// The module's precharge circuit has brought the bus up to the battery
    /// voltage before the pack's contactor closes. Without it, closing onto an
    /// empty 1000 µF bus draws a ~200 A inrush (and trips a real BMS).
    pub precharged: bool,
}

impl Default for ConverterParams {
    fn default() -> Self {
        Self {
            regulated_bus_volts: 48.0,
            regulation_droop_ohm: 0.05,
            max_output_amps: 25.0,
            efficiency: 0.92,
            pass_through_ohm: 0.03,
            bus_capacitance_farad: 1.0e-3,
            bleeder_ohm: 100.0,
            precharged: true,
        }
    }
}

/// What the converter did over one step; energies in joules.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ConverterStep {
    /// Current drawn from the battery terminals (A, negative when charging it).
    pub battery_current: f64,
    /// Terminal voltage the battery showed under that current (V).
    pub battery_terminal_volts: f64,
    /// Bus voltage averaged over the step (V): what the inverter saw.
    pub mean_bus_volts: f64,
    /// Energy taken from (positive) or returned to the battery terminals.
    pub battery_energy: f64,
    /// Energy lost in the converter: switch resistance or `P·(1/η − 1)`.
    pub converter_loss: f64,
    /// Heat in the bleeder resistor.
    pub bleeder_loss: f64,
    /// Energy delivered to the inverter.
    pub inverter_energy: f64,
}

/// The converter and the DC bus it feeds.
#[derive(Debug, Clone)]
pub struct Converter {
    params: ConverterParams,
    bus_volts: f64,
}

/// Closed-form integrals of `v(t) = a + b·e^{−t/τ}` over `[0, h]`.
struct ExpSegment {
    a: f64,
    b: f64,
    h: f64,
    /// ∫ e^{−t/τ} dt
    i1: f64,
    /// ∫ e^{−2t/τ} dt
    i2: f64,
    end: f64,
}

impl ExpSegment {
    fn new(start: f64, asymptote: f64, tau: f64, h: f64) -> Self {
        let b = start - asymptote;
        let decay = (-h / tau).exp();
        // `-expm1` keeps precision when h ≪ τ.
        let i1 = tau * -(-h / tau).exp_m1();
        let i2 = 0.5 * tau * -(-2.0 * h / tau).exp_m1();
        Self {
            a: asymptote,
            b,
            h,
            i1,
            i2,
            end: asymptote + b * decay,
        }
    }
    fn integral(&self) -> f64 {
        self.a * self.h + self.b * self.i1
    }
    fn integral_of_square(&self) -> f64 {
        self.a * self.a * self.h + 2.0 * self.a * self.b * self.i1 + self.b * self.b * self.i2
    }
}

impl Converter {
    /// A converter whose bus starts at `initial_bus_volts`.
    pub fn new(params: &ConverterParams, initial_bus_volts: f64) -> Self {
        Self {
            params: params.clone(),
            bus_volts: initial_bus_volts,
        }
    }

    /// Present DC-bus voltage V2 (V).
    pub fn bus_volts(&self) -> f64 {
        self.bus_volts
    }

    /// Energy stored in the bus capacitor (J).
    pub fn stored_energy(&self) -> f64 {
        0.5 * self.params.bus_capacitance_farad * self.bus_volts * self.bus_volts
    }

    /// Advance by `h` seconds.
    ///
    /// `battery_emf` and `battery_r0` describe the pack as a Thévenin source
    /// (`None` when the BMS holds its output open); `inverter_current` is the
    /// inverter's mean input current over the step, `boost` is `PRO` active and
    /// `bleeder` is `DES` active.
    pub fn step(
        &mut self,
        h: f64,
        battery: Option<(f64, f64)>,
        inverter_current: f64,
        boost: bool,
        bleeder: bool,
    ) -> ConverterStep {
        let p = &self.params;
        let c = p.bus_capacitance_farad;
        let g_bleed = if bleeder { 1.0 / p.bleeder_ohm } else { 0.0 };
        let v0 = self.bus_volts;

        // Source feeding the bus: EMF and series resistance, or nothing.
        let source = match battery {
            Some((emf, r0)) if !boost => Some((emf, r0 + p.pass_through_ohm)),
            Some(_) => Some((p.regulated_bus_volts, p.regulation_droop_ohm)),
            None => None,
        };
        let mut result = ConverterStep::default();
        // The regulated source is one-way and current limited: decide which
        // regime holds at the start of the step; the step is short against the
        // bus time constant only when the source is off, where it does not matter.
        let (g_src, i_fixed) = match source {
            Some((e, r)) if boost => {
                let i_lin = (e - v0) / r;
                if i_lin <= 0.0 {
                    (0.0, 0.0)
                } else if i_lin >= p.max_output_amps {
                    (0.0, p.max_output_amps)
                } else {
                    (1.0 / r, e / r)
                }
            }
            Some((e, r)) => (1.0 / r, e / r),
            None => (0.0, 0.0),
        };
        // C dv/dt = i_fixed − g_src·v − i_inv − g_bleed·v
        let g_total = g_src + g_bleed;
        let drive = i_fixed - inverter_current;
        let seg = if g_total > 0.0 {
            ExpSegment::new(v0, drive / g_total, c / g_total, h)
        } else {
            // No conductance: the bus charges linearly; an exponential with an
            // enormous τ would lose precision, so integrate the ramp directly.
            let slope = drive / c;
            ExpSegment {
                a: v0,
                b: 0.0,
                h,
                i1: 0.0,
                i2: 0.0,
                end: v0 + slope * h,
            }
        };
        let (v_int, v_sq_int) = if g_total > 0.0 {
            (seg.integral(), seg.integral_of_square())
        } else {
            let v1 = seg.end;
            (0.5 * (v0 + v1) * h, h * (v0 * v0 + v0 * v1 + v1 * v1) / 3.0)
        };
        self.bus_volts = seg.end.max(0.0);
        result.mean_bus_volts = v_int / h;
        result.bleeder_loss = g_bleed * v_sq_int;
        result.inverter_energy = inverter_current * v_int;

        // Energy into the bus from the source: ∫ v·i_out dt.
        let i_out_int = i_fixed * h - g_src * v_int;
        let bus_energy_in = i_fixed * v_int - g_src * v_sq_int;
        let mean_out = i_out_int / h;
        match (battery, boost) {
            (Some((emf, r0)), false) => {
                // ∫ i² dt over i = i_fixed − g·v, exact.
                let i_sq_int = i_fixed * i_fixed * h - 2.0 * i_fixed * g_src * v_int
                    + g_src * g_src * v_sq_int;
                result.converter_loss = p.pass_through_ohm * i_sq_int;
                result.battery_energy = bus_energy_in + result.converter_loss;
                result.battery_current = mean_out;
                result.battery_terminal_volts = emf - r0 * mean_out;
            }
            (Some((emf, r0)), true) => {
                let input_energy = bus_energy_in / p.efficiency;
                result.converter_loss = input_energy - bus_energy_in;
                result.battery_energy = input_energy;
                // The pack delivers P = (E − R0·i)·i: take the smaller root.
                let power = input_energy / h;
                let disc = (emf * emf - 4.0 * r0 * power).max(0.0);
                let i = if r0 > 0.0 {
                    (emf - disc.sqrt()) / (2.0 * r0)
                } else {
                    power / emf.max(f64::MIN_POSITIVE)
                };
                result.battery_current = i;
                result.battery_terminal_volts = emf - r0 * i;
            }
            (None, _) => {}
        }
        result
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bleeder_alone_discharges_with_rc_time_constant_and_dissipates_half_cv_squared() {
        let p = ConverterParams::default();
        let tau = p.bleeder_ohm * p.bus_capacitance_farad;
        let mut conv = Converter::new(&p, 40.0);
        let stored = conv.stored_energy();
        let mut heat = 0.0;
        let h = 1e-3;
        for k in 1..=2000 {
            heat += conv.step(h, None, 0.0, false, true).bleeder_loss;
            if k == 100 {
                let expected = 40.0 * (-(k as f64) * h / tau).exp();
                assert!(
                    (conv.bus_volts() - expected).abs() < 1e-9,
                    "{}",
                    conv.bus_volts()
                );
            }
        }
        assert!(conv.bus_volts() < 40.0 * (-19.0f64).exp());
        assert!(
            (heat - stored).abs() < 1e-9 * stored,
            "heat {heat} vs ½CV² {stored}"
        );
    }

    #[test]
    fn pass_through_settles_at_battery_emf_minus_drop() {
        let p = ConverterParams::default();
        let mut conv = Converter::new(&p, 0.0);
        let mut last = ConverterStep::default();
        for _ in 0..100 {
            last = conv.step(1e-3, Some((37.0, 0.1)), 5.0, false, false);
        }
        let expected = 37.0 - 5.0 * (0.1 + p.pass_through_ohm);
        assert!((conv.bus_volts() - expected).abs() < 1e-9);
        assert!((last.battery_current - 5.0).abs() < 1e-9);
        assert!((last.battery_terminal_volts - (37.0 - 0.5)).abs() < 1e-9);
    }

    #[test]
    fn regulated_mode_holds_bus_and_draws_power_over_efficiency() {
        let p = ConverterParams::default();
        let mut conv = Converter::new(&p, 0.0);
        let mut last = ConverterStep::default();
        for _ in 0..200 {
            last = conv.step(1e-3, Some((36.0, 0.1)), 4.0, true, false);
        }
        let v = p.regulated_bus_volts - 4.0 * p.regulation_droop_ohm;
        assert!((conv.bus_volts() - v).abs() < 1e-6);
        let p_in = v * 4.0 / p.efficiency;
        assert!((last.battery_energy / 1e-3 - p_in).abs() < 1e-6 * p_in);
        let i = last.battery_current;
        assert!(((36.0 - 0.1 * i) * i - p_in).abs() < 1e-6 * p_in);
    }

    #[test]
    fn bus_energy_balance_closes_in_pass_through() {
        let p = ConverterParams::default();
        let mut conv = Converter::new(&p, 0.0);
        let (mut battery, mut losses, mut load) = (0.0, 0.0, 0.0);
        for k in 0..500 {
            let i_inv = if k < 250 { 8.0 } else { -2.0 };
            let s = conv.step(1e-3, Some((37.0, 0.12)), i_inv, false, k > 400);
            battery += s.battery_energy;
            losses += s.converter_loss + s.bleeder_loss;
            load += s.inverter_energy;
        }
        let balance = battery - losses - load - conv.stored_energy();
        assert!(
            balance.abs() < 1e-9 * battery,
            "residual {balance} J of {battery} J"
        );
    }
}
