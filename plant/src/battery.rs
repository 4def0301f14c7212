//! The EV module's battery pack: an equivalent circuit (OCV(SOC) in series with R0 and N RC pairs),
//! the BMS that opens the pack's output on a fault, and the AC/DC charger (CC/CV).
//!
//! Pack current is positive when discharging. Each RC pair is advanced with the exact solution of
//! `C dv/dt = i - v/R` for a current held constant over the step, so results do not depend on the
//! step size (10 us .. 10 ms) and nothing goes unstable when `dt` exceeds a time constant; the
//! internal loss of a step is the exact integral of `R0 i^2 + sum v_rc^2 / R_rc` over it.
//!
//! Parameters come from files, so [`Battery::new`] never panics on nonsense (it clamps it to
//! something finite); [`Battery::try_new`] rejects it with a [`BatteryConfigError`] instead.

use serde::{Deserialize, Serialize};

/// Largest load current `step` takes seriously (A). A dead short is ~OCV/R0 (~500 A for the default
/// pack); the clamp keeps an infinite demand from turning the state into NaN.
const MAX_LOAD_CURRENT_A: f64 = 1.0e6;

/// Slack on trip/release delays (s): 3200 steps of 100 us sum to 0.31999999999998, and a 320 ms
/// delay must still count as elapsed on the 3200th step.
const DELAY_TOLERANCE_S: f64 = 1.0e-9;

/// One point of the open-circuit-voltage curve.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OcvPoint {
    /// State of charge, 0..=1.
    pub soc: f64,
    /// Pack open-circuit voltage at that SOC (V).
    pub volts: f64,
}

impl OcvPoint {
    /// The point (`soc`, `volts`).
    pub const fn new(soc: f64, volts: f64) -> Self {
        Self { soc, volts }
    }
}

/// One parallel RC pair of the equivalent circuit (charge-transfer and diffusion polarisation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RcPair {
    /// Resistance (ohm).
    pub r_ohm: f64,
    /// Capacitance (F).
    pub c_farad: f64,
}

impl RcPair {
    /// The pair `r_ohm` || `c_farad`.
    pub const fn new(r_ohm: f64, c_farad: f64) -> Self {
        Self { r_ohm, c_farad }
    }

    /// Time constant R*C (s).
    pub fn time_constant(&self) -> f64 {
        self.r_ohm * self.c_farad
    }
}

/// Equivalent-circuit parameters of the pack. Default = the EV module's 36 V pack (vemodule preset).
///
/// The M3CVME paper names the module's batteries but gives no pack data, so the default is an
/// assumption: a 36 V nominal 10s4p pack of 2.5 Ah 18650 NMC cells (Samsung INR18650-25R class),
/// the usual supply of the e-bike hub motors such lab modules are built around.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BatteryParams {
    /// Usable capacity (Ah). 10: four 2.5 Ah cells in parallel (25R datasheet nominal capacity).
    pub capacity_ah: f64,
    /// Pack OCV over SOC, SOC strictly increasing; interpolated linearly, clamped at the ends.
    /// Default: a typical low-rate NMC cell curve (3.0 V empty .. 4.2 V full) times 10 cells.
    pub ocv_table: Vec<OcvPoint>,
    /// Ohmic series resistance (ohm). 0.08: 10 x 20 mOhm (25R DC resistance) / 4 in parallel, plus
    /// ~30 mOhm for the BMS MOSFETs, nickel strip and leads (estimate).
    pub r0_ohm: f64,
    /// Polarisation RC pairs. Default two, scaled x10/4 from typical two-RC fits of 18650 NMC cells
    /// in the literature (~12 mOhm / 15 s and ~16 mOhm / 400 s per cell).
    pub rc_pairs: Vec<RcPair>,
    /// SOC at start, 0..=1. 0.9: a pack charged before the lab session (assumption).
    pub initial_soc: f64,
}

/// Default OCV curve, (SOC, volts per cell); the pack has 10 cells in series.
const NMC_CELL_OCV: [(f64, f64); 12] = [
    (0.00, 3.00),
    (0.05, 3.28),
    (0.10, 3.40),
    (0.20, 3.53),
    (0.30, 3.60),
    (0.40, 3.65),
    (0.50, 3.70),
    (0.60, 3.77),
    (0.70, 3.86),
    (0.80, 3.96),
    (0.90, 4.07),
    (1.00, 4.20),
];

impl Default for BatteryParams {
    fn default() -> Self {
        Self {
            capacity_ah: 10.0,
            ocv_table: NMC_CELL_OCV
                .iter()
                .map(|&(soc, cell_volts)| OcvPoint::new(soc, 10.0 * cell_volts))
                .collect(),
            r0_ohm: 0.08,
            rc_pairs: vec![RcPair::new(0.03, 500.0), RcPair::new(0.04, 10_000.0)],
            initial_soc: 0.9,
        }
    }
}

impl BatteryParams {
    /// The Controller_network bench: a 12 V lab supply as a stiff, flat source. The OCV is 12 V at
    /// every SOC, the capacity so large (1e6 Ah) that the SOC does not visibly move, and there are
    /// no RC pairs (a regulated supply does not sag slowly). R0 = 20 mOhm: output impedance plus
    /// ~1 m of leads.
    pub fn bench_supply_12v() -> Self {
        Self {
            capacity_ah: 1.0e6,
            ocv_table: vec![OcvPoint::new(0.0, 12.0), OcvPoint::new(1.0, 12.0)],
            r0_ohm: 0.02,
            rc_pairs: Vec::new(),
            initial_soc: 1.0,
        }
    }

    /// Open-circuit voltage at `soc` (V): linear in the table, clamped at its ends; 0 if empty.
    pub fn ocv_at(&self, soc: f64) -> f64 {
        interpolate_ocv(&self.ocv_table, soc)
    }

    /// Checks that every value is usable by the model.
    pub fn validate(&self) -> Result<(), BatteryConfigError> {
        positive("capacity_ah", self.capacity_ah)?;
        not_negative("r0_ohm", self.r0_ohm)?;
        if !(0.0..=1.0).contains(&self.initial_soc) {
            return Err(out_of_range("initial_soc", self.initial_soc, "in 0..=1"));
        }
        if self.ocv_table.is_empty() {
            return Err(BatteryConfigError::EmptyOcvTable);
        }
        let mut previous_soc = f64::NEG_INFINITY;
        for (index, p) in self.ocv_table.iter().enumerate() {
            if !(p.soc.is_finite() && p.soc > previous_soc && p.volts.is_finite() && p.volts >= 0.0)
            {
                return Err(BatteryConfigError::BadOcvPoint { index });
            }
            previous_soc = p.soc;
        }
        for (index, p) in self.rc_pairs.iter().enumerate() {
            if ![p.r_ohm, p.c_farad]
                .iter()
                .all(|x| x.is_finite() && *x >= 0.0)
            {
                return Err(BatteryConfigError::BadRcPair { index });
            }
        }
        Ok(())
    }
}

/// BMS protection thresholds. Default = a 10s BMS for the default pack; the delays are settings of
/// the TI bq76940 monitor (UV/OV 1 s, OCD 320 ms, SCD 200 us), a common e-bike BMS front end.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BmsParams {
    /// Under-voltage trip on the terminal voltage (V). 30: 3.0 V per cell, the OCV table's empty point.
    pub uv_trip_volts: f64,
    /// Under-voltage release (V), above the trip. 31: 3.1 V per cell, so a pack that only sagged under
    /// load recovers at rest, while an empty one needs the charger.
    pub uv_release_volts: f64,
    /// Time below the UV trip before the BMS opens (s). 1 (bq76940).
    pub uv_delay_s: f64,
    /// Over-voltage trip on the terminal voltage (V). 42.5: 4.25 V per cell, the usual NMC limit.
    pub ov_trip_volts: f64,
    /// Over-voltage release (V), below the trip. 42.2: above the full pack's 42.0 V OCV, because
    /// this BMS opens the whole output on OV, so the pack can only release by resting.
    pub ov_release_volts: f64,
    /// Time above the OV trip before the BMS opens (s). 1 (bq76940).
    pub ov_delay_s: f64,
    /// Discharge over-current trip (A). 30: a 20 A continuous e-bike BMS with 50 % margin (assumption).
    pub oc_trip_amps: f64,
    /// Time above the OC trip before the BMS opens (s). 0.32 (a bq76940 OCD delay setting).
    pub oc_delay_s: f64,
    /// Short-circuit trip (A). 120: four times OC, well below the ~500 A of a dead short (OCV / R0).
    pub sc_trip_amps: f64,
    /// Time above the SC trip before the BMS opens (s). 200e-6 (a bq76940 SCD delay setting).
    pub sc_delay_s: f64,
    /// Time back inside the release threshold before a UV/OV trip clears (s). 1 (assumption): keeps
    /// a pack that recovers at rest from chattering with its load.
    pub release_delay_s: f64,
}

impl Default for BmsParams {
    fn default() -> Self {
        Self {
            uv_trip_volts: 30.0,
            uv_release_volts: 31.0,
            uv_delay_s: 1.0,
            ov_trip_volts: 42.5,
            ov_release_volts: 42.2,
            ov_delay_s: 1.0,
            oc_trip_amps: 30.0,
            oc_delay_s: 0.32,
            sc_trip_amps: 120.0,
            sc_delay_s: 200e-6,
            release_delay_s: 1.0,
        }
    }
}

impl BmsParams {
    /// The Controller_network bench supply's own limits: a 5 A current limit in trip (OCP) mode
    /// after 50 ms, a hard trip at 15 A after 100 us, OVP at 13.2 V (110 % of 12 V). A supply has
    /// no under-voltage cut-off: the UV trip sits at 0 V, which only a shorted output (SC first)
    /// reaches.
    pub fn bench_supply_12v() -> Self {
        Self {
            uv_trip_volts: 0.0,
            uv_release_volts: 1.0,
            uv_delay_s: 1.0,
            ov_trip_volts: 13.2,
            ov_release_volts: 12.6,
            ov_delay_s: 0.01,
            oc_trip_amps: 5.0,
            oc_delay_s: 0.05,
            sc_trip_amps: 15.0,
            sc_delay_s: 100e-6,
            release_delay_s: 0.1,
        }
    }

    /// Checks that every value is usable and each release threshold is on the safe side of its trip.
    pub fn validate(&self) -> Result<(), BatteryConfigError> {
        for (field, value) in [
            ("uv_trip_volts", self.uv_trip_volts),
            ("uv_release_volts", self.uv_release_volts),
            ("uv_delay_s", self.uv_delay_s),
            ("ov_trip_volts", self.ov_trip_volts),
            ("ov_release_volts", self.ov_release_volts),
            ("ov_delay_s", self.ov_delay_s),
            ("oc_trip_amps", self.oc_trip_amps),
            ("oc_delay_s", self.oc_delay_s),
            ("sc_trip_amps", self.sc_trip_amps),
            ("sc_delay_s", self.sc_delay_s),
            ("release_delay_s", self.release_delay_s),
        ] {
            not_negative(field, value)?;
        }
        if self.uv_release_volts <= self.uv_trip_volts {
            return Err(out_of_range(
                "uv_release_volts",
                self.uv_release_volts,
                "above uv_trip_volts",
            ));
        }
        if self.ov_release_volts >= self.ov_trip_volts {
            return Err(out_of_range(
                "ov_release_volts",
                self.ov_release_volts,
                "below ov_trip_volts",
            ));
        }
        Ok(())
    }
}

/// The AC/DC charger. Default = a 42 V 2 A e-bike charger for the default pack.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChargerParams {
    /// Constant-current phase current (A). 2: the common 42 V 2 A charger (C/5 for 10 Ah).
    pub cc_amps: f64,
    /// Constant-voltage set point at the pack terminals (V). 42: 4.2 V per cell.
    pub cv_volts: f64,
    /// The charger stops once its CV current falls below this (A). 0.2: C/50 (assumption).
    pub termination_amps: f64,
}

impl Default for ChargerParams {
    fn default() -> Self {
        Self {
            cc_amps: 2.0,
            cv_volts: 42.0,
            termination_amps: 0.2,
        }
    }
}

impl ChargerParams {
    /// For the Controller_network bench supply, which has no charger: a 12 V 1 A set that stays
    /// consistent with the supply's OVP and never pushes current into a supply sitting at its own
    /// 12 V.
    pub fn bench_supply_12v() -> Self {
        Self {
            cc_amps: 1.0,
            cv_volts: 12.0,
            termination_amps: 0.1,
        }
    }

    /// Checks that every value is usable and the charger can reach termination.
    pub fn validate(&self) -> Result<(), BatteryConfigError> {
        positive("cc_amps", self.cc_amps)?;
        positive("cv_volts", self.cv_volts)?;
        not_negative("termination_amps", self.termination_amps)?;
        if self.termination_amps >= self.cc_amps {
            return Err(out_of_range(
                "termination_amps",
                self.termination_amps,
                "below cc_amps",
            ));
        }
        Ok(())
    }
}

/// A parameter set the model cannot run with.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BatteryConfigError {
    /// The parameter `field` holds `value`, which is not `expected`.
    #[error("`{field}` = {value} must be {expected}")]
    OutOfRange {
        /// Parameter name.
        field: &'static str,
        /// The rejected value.
        value: f64,
        /// What the value must be.
        expected: &'static str,
    },
    /// The OCV table has no points.
    #[error("`ocv_table` is empty")]
    EmptyOcvTable,
    /// OCV point `index` has a non-finite value, negative volts or a SOC not above its predecessor's.
    #[error(
        "`ocv_table[{index}]`: SOC must be finite and above the previous one, volts finite and >= 0"
    )]
    BadOcvPoint {
        /// Position in the table.
        index: usize,
    },
    /// RC pair `index` has a negative or non-finite value.
    #[error("`rc_pairs[{index}]`: r_ohm and c_farad must be finite and >= 0")]
    BadRcPair {
        /// Position in the list.
        index: usize,
    },
    /// A full pack rests above the OV release, so an OV trip could never clear.
    #[error("BMS `ov_release_volts` must be above the full pack's OCV of {full_ocv} V")]
    OvReleaseBelowFullOcv {
        /// Highest OCV in the table (V).
        full_ocv: f64,
    },
    /// The charger's CV set point reaches the BMS OV trip, so a normal charge would trip it.
    #[error("charger `cv_volts` must be below the BMS `ov_trip_volts`")]
    ChargerAboveOvTrip,
}

fn out_of_range(field: &'static str, value: f64, expected: &'static str) -> BatteryConfigError {
    BatteryConfigError::OutOfRange {
        field,
        value,
        expected,
    }
}

fn positive(field: &'static str, value: f64) -> Result<(), BatteryConfigError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(out_of_range(field, value, "finite and > 0"))
    }
}

fn not_negative(field: &'static str, value: f64) -> Result<(), BatteryConfigError> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        Err(out_of_range(field, value, "finite and >= 0"))
    }
}

/// `value` if finite and positive, else 0: how `Battery::new` defuses nonsense from files.
fn positive_or_zero(value: f64) -> f64 {
    if value.is_finite() && value > 0.0 {
        value
    } else {
        0.0
    }
}

fn interpolate_ocv(table: &[OcvPoint], soc: f64) -> f64 {
    let (Some(first), Some(last)) = (table.first(), table.last()) else {
        return 0.0;
    };
    if soc <= first.soc {
        return first.volts;
    }
    for segment in table.windows(2) {
        if let [a, b] = segment
            && soc <= b.soc
        {
            let span = b.soc - a.soc;
            if span > 0.0 {
                return a.volts + (b.volts - a.volts) * (soc - a.soc) / span;
            }
            return b.volts;
        }
    }
    last.volts
}

/// Why the BMS opened the pack's output.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum BmsTrip {
    /// Terminal voltage below the UV trip for the UV delay; clears itself above the UV release.
    UnderVoltage,
    /// Terminal voltage above the OV trip for the OV delay; clears itself below the OV release.
    OverVoltage,
    /// Discharge current above the OC trip for the OC delay; latched until [`Battery::reset_trip`].
    OverCurrent,
    /// Discharge current above the SC trip for the SC delay; latched until [`Battery::reset_trip`].
    ShortCircuit,
}

impl std::fmt::Display for BmsTrip {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            BmsTrip::UnderVoltage => "under-voltage",
            BmsTrip::OverVoltage => "over-voltage",
            BmsTrip::OverCurrent => "over-current",
            BmsTrip::ShortCircuit => "short circuit",
        })
    }
}

/// What one step did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BatteryStep {
    /// Terminal voltage during the step, as the load saw it: source_voltage() - r0 * net current (at step start).
    pub terminal_voltage: f64,
    /// Charger current into the pack (A, >= 0).
    pub charger_current: f64,
    /// Net pack current, positive when discharging (load - charger) (A).
    pub net_current: f64,
    /// Heat in R0 and the RC resistors during the step (J).
    pub internal_loss: f64,
}

/// How long each BMS condition has held without a break (s).
#[derive(Debug, Clone, Copy, Default)]
struct ConditionTimers {
    under_voltage: f64,
    over_voltage: f64,
    over_current: f64,
    short_circuit: f64,
    release: f64,
}

fn persisted(timer: f64, holds: bool, dt: f64) -> f64 {
    if holds { timer + dt } else { 0.0 }
}

fn elapsed(timer: f64, delay: f64) -> bool {
    timer > 0.0 && timer >= delay - DELAY_TOLERANCE_S
}

/// The pack: equivalent circuit, BMS and charger, stepped by the plant.
#[derive(Debug, Clone)]
pub struct Battery {
    ocv_table: Vec<OcvPoint>,
    r0_ohm: f64,
    rc_pairs: Vec<RcPair>,
    /// Voltage across each RC pair (V), as `rc_pairs`; positive while discharging.
    rc_volts: Vec<f64>,
    /// 1 / (3600 * capacity_ah).
    soc_per_coulomb: f64,
    /// Coulomb counter with Neumaier compensation: at 10 us steps each increment is ~1e-11 of the
    /// SOC, and a plain sum loses a measurable share of every one of them to rounding.
    soc: f64,
    soc_rounding: f64,
    bms: BmsParams,
    charger: ChargerParams,
    trip: Option<BmsTrip>,
    timers: ConditionTimers,
    /// The charger reached termination; it stays off until unplugged.
    charge_terminated: bool,
    /// The current the load asked for in the last step, even while the output was open.
    load_demand: f64,
    last_step: BatteryStep,
    terminal_after_step: f64,
}

impl Battery {
    /// The pack at rest (RC pairs discharged) at `battery.initial_soc`. Never panics: values
    /// [`Battery::try_new`] would reject are clamped to something finite (a capacity <= 0 freezes
    /// the SOC, an empty OCV table reads 0 V, a NaN threshold never trips).
    pub fn new(battery: &BatteryParams, bms: &BmsParams, charger: &ChargerParams) -> Self {
        let capacity_ah = positive_or_zero(battery.capacity_ah);
        let rc_pairs: Vec<RcPair> = (battery.rc_pairs.iter())
            .map(|p| RcPair::new(positive_or_zero(p.r_ohm), positive_or_zero(p.c_farad)))
            .collect();
        let mut pack = Self {
            ocv_table: battery.ocv_table.clone(),
            r0_ohm: positive_or_zero(battery.r0_ohm),
            rc_volts: vec![0.0; rc_pairs.len()],
            rc_pairs,
            soc_per_coulomb: if capacity_ah > 0.0 {
                1.0 / (3600.0 * capacity_ah)
            } else {
                0.0
            },
            soc: positive_or_zero(battery.initial_soc).min(1.0),
            soc_rounding: 0.0,
            bms: bms.clone(),
            charger: ChargerParams {
                cc_amps: positive_or_zero(charger.cc_amps),
                ..charger.clone()
            },
            trip: None,
            timers: ConditionTimers::default(),
            charge_terminated: false,
            load_demand: 0.0,
            last_step: BatteryStep::default(),
            terminal_after_step: 0.0,
        };
        pack.terminal_after_step = pack.source_voltage();
        pack.last_step.terminal_voltage = pack.terminal_after_step;
        pack
    }

    /// Like [`Battery::new`], after validating the three parameter sets and how they fit together.
    pub fn try_new(
        battery: &BatteryParams,
        bms: &BmsParams,
        charger: &ChargerParams,
    ) -> Result<Self, BatteryConfigError> {
        battery.validate()?;
        bms.validate()?;
        charger.validate()?;
        let full_ocv = (battery.ocv_table.iter()).fold(f64::NEG_INFINITY, |v, p| v.max(p.volts));
        if bms.ov_release_volts <= full_ocv {
            return Err(BatteryConfigError::OvReleaseBelowFullOcv { full_ocv });
        }
        if charger.cv_volts >= bms.ov_trip_volts {
            return Err(BatteryConfigError::ChargerAboveOvTrip);
        }
        Ok(Self::new(battery, bms, charger))
    }

    /// EMF the load sees this step: OCV(SOC) minus the RC-pair voltages (V).
    pub fn source_voltage(&self) -> f64 {
        self.open_circuit_voltage() - self.rc_volts.iter().sum::<f64>()
    }

    /// OCV at the present SOC (V): what the terminals read after a long rest.
    pub fn open_circuit_voltage(&self) -> f64 {
        interpolate_ocv(&self.ocv_table, self.soc())
    }

    /// Voltage across each RC pair (V), in parameter order; positive while discharging.
    pub fn rc_voltages(&self) -> &[f64] {
        &self.rc_volts
    }

    /// R0 (ohm). The load solves its own current against source_voltage() and this resistance.
    pub fn series_resistance(&self) -> f64 {
        self.r0_ohm
    }

    /// Whether the BMS holds the output closed (false while tripped).
    pub fn output_closed(&self) -> bool {
        self.trip.is_none()
    }

    /// Advance by `dt` s with `load_current` A drawn at the terminals (>= 0; treated as 0 while the output is open),
    /// `charger_connected` = the AC/DC charger is plugged in (CHG active). Charger current (CC/CV) is computed here.
    ///
    /// A negative `load_current` is current pushed back into the pack (the DC bus feeding it) and
    /// is counted like charge; NaN counts as 0. While the output is open, keep passing what the
    /// load would draw: [`Battery::reset_trip`] judges from it whether an over-current is gone.
    /// A non-finite or non-positive `dt` counts as 0: no time passes.
    pub fn step(&mut self, dt: f64, load_current: f64, charger_connected: bool) -> BatteryStep {
        let dt = positive_or_zero(dt);
        self.load_demand = if load_current.is_nan() {
            0.0
        } else {
            load_current.clamp(-MAX_LOAD_CURRENT_A, MAX_LOAD_CURRENT_A)
        };
        let load = if self.output_closed() {
            self.load_demand
        } else {
            0.0
        };
        let source = self.source_voltage();
        let charger_current = self.charger_current(charger_connected, load, source);
        let net = load - charger_current;
        let terminal = source - self.r0_ohm * net;

        let mut internal_loss = self.r0_ohm * net * net * dt;
        for (pair, v) in self.rc_pairs.iter().zip(self.rc_volts.iter_mut()) {
            internal_loss += advance_rc_pair(pair, v, net, dt);
        }
        self.count_coulombs(net * dt);
        self.update_bms(dt, terminal, net);

        self.terminal_after_step = self.source_voltage() - self.r0_ohm * net;
        self.last_step = BatteryStep {
            terminal_voltage: terminal,
            charger_current,
            net_current: net,
            internal_loss,
        };
        self.last_step
    }

    /// State of charge, 0..=1.
    pub fn soc(&self) -> f64 {
        (self.soc + self.soc_rounding).clamp(0.0, 1.0)
    }

    /// SOC in 0.1 % counts, as MEB flag word FA0 carries it (0..=1000).
    pub fn soc_permille(&self) -> u16 {
        (self.soc() * 1000.0).round() as u16
    }

    /// Terminal voltage after the last step (open-circuit-ish when no current flows): the state at
    /// the end of the step with the step's net current still flowing through R0.
    pub fn terminal_voltage(&self) -> f64 {
        self.terminal_after_step
    }

    /// What the last step did (before the first: zeros and the open-circuit terminal voltage).
    pub fn last_step(&self) -> BatteryStep {
        self.last_step
    }

    /// The trip holding the output open, if any.
    pub fn trip(&self) -> Option<BmsTrip> {
        self.trip
    }

    /// Whether the charger is pushing current into the pack.
    pub fn charging(&self) -> bool {
        self.last_step.charger_current > 0.0
    }

    /// Whether the reason for the present trip is still there: for UV/OV until the BMS releases by
    /// itself; for OC/SC while the load still asks for more than the OC trip current.
    pub fn trip_cause_persists(&self) -> bool {
        match self.trip {
            None => false,
            Some(BmsTrip::UnderVoltage | BmsTrip::OverVoltage) => true,
            Some(BmsTrip::OverCurrent | BmsTrip::ShortCircuit) => {
                self.load_demand > self.bms.oc_trip_amps
            }
        }
    }

    /// Clears a latched OC/SC trip if its cause is gone (see [`Battery::trip_cause_persists`]).
    /// UV/OV trips are not latched, they clear by hysteresis: this leaves them alone.
    pub fn reset_trip(&mut self) {
        let latched = matches!(
            self.trip,
            Some(BmsTrip::OverCurrent | BmsTrip::ShortCircuit)
        );
        if latched && !self.trip_cause_persists() {
            self.trip = None;
            self.timers = ConditionTimers::default();
        }
    }

    /// CC/CV: the current that holds the terminals at CV, limited to 0..=CC. The charger sits on the
    /// pack terminals next to the load, so holding CV takes the load current on top.
    fn charger_current(&mut self, connected: bool, load: f64, source: f64) -> f64 {
        if !connected {
            // Unplugging re-arms a charger that had terminated.
            self.charge_terminated = false;
            return 0.0;
        }
        // A UV-tripped pack recovers through the charger; any other trip blocks it.
        let allowed = matches!(self.trip, None | Some(BmsTrip::UnderVoltage));
        if self.charge_terminated || !allowed {
            return 0.0;
        }
        let headroom = self.charger.cv_volts - source;
        let holds_cv = if self.r0_ohm > 0.0 {
            load + headroom / self.r0_ohm
        } else if headroom > 0.0 {
            // Without R0 the charger cannot move the terminals: CC until the source reaches CV.
            f64::INFINITY
        } else {
            load
        };
        // max/min rather than clamp: a NaN (a NaN OCV table) becomes 0 instead of a panic.
        let current = holds_cv.max(0.0).min(self.charger.cc_amps);
        if current < self.charger.termination_amps {
            self.charge_terminated = true;
            return 0.0;
        }
        current
    }

    fn count_coulombs(&mut self, discharged_coulombs: f64) {
        let delta = -discharged_coulombs * self.soc_per_coulomb;
        let sum = self.soc + delta;
        self.soc_rounding += if self.soc.abs() >= delta.abs() {
            (self.soc - sum) + delta
        } else {
            (delta - sum) + self.soc
        };
        self.soc = sum;
        // Charge beyond full or empty goes into side reactions this model does not carry.
        let total = self.soc + self.soc_rounding;
        if !(0.0..=1.0).contains(&total) {
            self.soc = total.clamp(0.0, 1.0);
            self.soc_rounding = 0.0;
        }
    }

    /// Conditions are judged on the step's terminal voltage and net current; a trip opens the
    /// output from the next step on, as the MOSFETs open after the detection delay.
    fn update_bms(&mut self, dt: f64, terminal: f64, net: f64) {
        let (p, t) = (&self.bms, &mut self.timers);
        let next = match self.trip {
            None => {
                t.short_circuit = persisted(t.short_circuit, net > p.sc_trip_amps, dt);
                t.over_current = persisted(t.over_current, net > p.oc_trip_amps, dt);
                t.over_voltage = persisted(t.over_voltage, terminal > p.ov_trip_volts, dt);
                t.under_voltage = persisted(t.under_voltage, terminal < p.uv_trip_volts, dt);
                [
                    (t.short_circuit, p.sc_delay_s, BmsTrip::ShortCircuit),
                    (t.over_current, p.oc_delay_s, BmsTrip::OverCurrent),
                    (t.over_voltage, p.ov_delay_s, BmsTrip::OverVoltage),
                    (t.under_voltage, p.uv_delay_s, BmsTrip::UnderVoltage),
                ]
                .into_iter()
                .find(|&(timer, delay, _)| elapsed(timer, delay))
                .map(|(_, _, trip)| trip)
            }
            Some(BmsTrip::UnderVoltage) => {
                // The charger still runs during a UV trip, so a faulty one can push the pack into OV.
                t.over_voltage = persisted(t.over_voltage, terminal > p.ov_trip_volts, dt);
                t.release = persisted(t.release, terminal > p.uv_release_volts, dt);
                if elapsed(t.over_voltage, p.ov_delay_s) {
                    Some(BmsTrip::OverVoltage)
                } else if elapsed(t.release, p.release_delay_s) {
                    None
                } else {
                    self.trip
                }
            }
            Some(BmsTrip::OverVoltage) => {
                t.release = persisted(t.release, terminal < p.ov_release_volts, dt);
                (!elapsed(t.release, p.release_delay_s)).then_some(BmsTrip::OverVoltage)
            }
            latched @ Some(BmsTrip::OverCurrent | BmsTrip::ShortCircuit) => latched,
        };
        if next != self.trip {
            self.trip = next;
            self.timers = ConditionTimers::default();
        }
    }
}

/// Advances one RC pair over `dt` at constant `current`, exactly; returns the heat in its resistor (J).
///
/// With v_inf = I R and d = v0 - v_inf, v(t) = v_inf + d e^(-t/tau), so the integral of v^2 over
/// the step is v_inf^2 dt + 2 v_inf d tau (1 - e^(-dt/tau)) + d^2 tau/2 (1 - e^(-2 dt/tau)).
/// `exp_m1` keeps 1 - e^(-x) accurate when dt is a millionth of tau.
fn advance_rc_pair(pair: &RcPair, v: &mut f64, current: f64, dt: f64) -> f64 {
    let v_inf = current * pair.r_ohm;
    let tau = pair.time_constant();
    if pair.r_ohm <= 0.0 {
        *v = 0.0;
        return 0.0;
    }
    if tau <= 0.0 {
        // No capacitance: the pair is a plain resistor.
        *v = v_inf;
        return v_inf * v_inf / pair.r_ohm * dt;
    }
    let x = dt / tau;
    let settled = -(-x).exp_m1();
    let settled_twice = -(-2.0 * x).exp_m1();
    let d = *v - v_inf;
    let integral_v2 =
        v_inf * v_inf * dt + 2.0 * v_inf * d * tau * settled + d * d * 0.5 * tau * settled_twice;
    *v -= d * settled;
    integral_v2 / pair.r_ohm
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A BMS that stays out of the way of the physics tests.
    fn lenient_bms() -> BmsParams {
        BmsParams {
            uv_trip_volts: 0.0,
            ov_trip_volts: 1.0e3,
            oc_trip_amps: 1.0e3,
            sc_trip_amps: 1.0e4,
            ..BmsParams::default()
        }
    }

    /// A pack with a flat OCV, so the terminal voltage is pure circuit.
    fn flat_pack(volts: f64, r0_ohm: f64, rc_pairs: &[RcPair]) -> BatteryParams {
        BatteryParams {
            ocv_table: vec![OcvPoint::new(0.0, volts), OcvPoint::new(1.0, volts)],
            r0_ohm,
            rc_pairs: rc_pairs.to_vec(),
            ..BatteryParams::default()
        }
    }

    fn pack(battery: &BatteryParams, bms: &BmsParams) -> Battery {
        Battery::new(battery, bms, &ChargerParams::default())
    }

    fn relative_error(actual: f64, expected: f64) -> f64 {
        ((actual - expected) / expected).abs()
    }

    #[test]
    fn one_amp_for_one_hour_removes_one_over_capacity() {
        let params = BatteryParams::default();
        for dt in [1e-3_f64, 1e-2] {
            let mut pack = pack(&params, &lenient_bms());
            for _ in 0..(3600.0 / dt).round() as u64 {
                pack.step(dt, 1.0, false);
            }
            let drop = params.initial_soc - pack.soc();
            assert!(
                relative_error(drop, 1.0 / params.capacity_ah) < 1e-9,
                "{dt}: {drop}"
            );
            assert_eq!(pack.soc_permille(), 800);
        }
    }

    #[test]
    fn rc_pairs_follow_the_exact_step_response_at_any_dt() {
        let pairs = [RcPair::new(0.03, 0.02 / 0.03), RcPair::new(0.05, 10.0)];
        let params = flat_pack(12.0, 0.01, &pairs);
        let current = 4.0;
        for dt in [1e-3_f64, 1e-5] {
            let mut pack = pack(&params, &lenient_bms());
            let mut steps_done = 0_u64;
            for t in [0.005_f64, 0.02, 0.1, 1.0] {
                let steps = (t / dt).round() as u64;
                for _ in steps_done..steps {
                    pack.step(dt, current, false);
                }
                steps_done = steps;
                let t = steps as f64 * dt;
                for (pair, v) in pairs.iter().zip(pack.rc_voltages()) {
                    let expected = current * pair.r_ohm * (1.0 - (-t / pair.time_constant()).exp());
                    assert!(
                        relative_error(*v, expected) < 1e-9,
                        "dt {dt} t {t}: {v} vs {expected}"
                    );
                }
            }
        }
    }

    #[test]
    fn terminal_voltage_drops_by_r0_at_a_current_step() {
        let params = flat_pack(36.0, 0.08, &BatteryParams::default().rc_pairs);
        let mut battery = pack(&params, &lenient_bms());
        for _ in 0..10_000 {
            battery.step(1e-3, 10.0, false);
        }
        let rc_sum: f64 = (params.rc_pairs.iter())
            .map(|p| 10.0 * p.r_ohm * (1.0 - (-10.0 / p.time_constant()).exp()))
            .sum();
        let step = battery.step(1e-3, 20.0, false);
        assert!((step.terminal_voltage - (36.0 - 20.0 * 0.08 - rc_sum)).abs() < 1e-9);
        assert_eq!(step.net_current, 20.0);

        // Same on the real OCV curve, mid-discharge.
        let params = BatteryParams::default();
        let mut battery = pack(&params, &lenient_bms());
        for _ in 0..5_000 {
            battery.step(1e-3, 5.0, false);
        }
        let rc_sum: f64 = battery.rc_voltages().iter().sum();
        let expected = params.ocv_at(battery.soc()) - 25.0 * params.r0_ohm - rc_sum;
        assert!((battery.step(1e-3, 25.0, false).terminal_voltage - expected).abs() < 1e-9);
    }

    #[test]
    fn ocv_interpolates_linearly_and_clamps_at_the_ends() {
        let params = BatteryParams::default();
        assert!((params.ocv_at(0.25) - 35.65).abs() < 1e-12);
        assert!((params.ocv_at(0.10) - 34.0).abs() < 1e-12);
        assert_eq!(params.ocv_at(-0.5), 30.0);
        assert_eq!(params.ocv_at(1.5), 42.0);
        assert_eq!(interpolate_ocv(&[], 0.5), 0.0);
    }

    #[test]
    fn under_voltage_trips_after_its_delay_and_releases_with_hysteresis() {
        let params = BatteryParams {
            initial_soc: 0.08,
            ..BatteryParams::default()
        };
        let bms = BmsParams {
            uv_trip_volts: 32.0,
            uv_release_volts: 34.0,
            release_delay_s: 0.5,
            ..BmsParams::default()
        };
        let charger = ChargerParams {
            cc_amps: 10.0,
            ..ChargerParams::default()
        };
        let mut pack = Battery::new(&params, &bms, &charger);
        let dt = 1e-3;
        // 20 A sags the terminals below 32 V at once, but the output holds for the 1 s delay.
        for _ in 0..999 {
            assert!(pack.step(dt, 20.0, false).terminal_voltage < 32.0);
            assert!(pack.output_closed());
        }
        pack.step(dt, 20.0, false);
        assert_eq!(pack.trip(), Some(BmsTrip::UnderVoltage));
        // At rest the pack recovers above the trip but not above the release: it stays open.
        for _ in 0..5_000 {
            let step = pack.step(dt, 20.0, false);
            assert_eq!(step.net_current, 0.0);
            assert!(step.terminal_voltage > 32.0 && step.terminal_voltage < 34.0);
            assert!(!pack.output_closed());
        }
        // The charger may run during a UV trip; its current lifts the terminals over the release.
        for _ in 0..499 {
            let step = pack.step(dt, 20.0, true);
            assert_eq!(step.charger_current, 10.0);
            assert!(step.terminal_voltage > 34.0);
            assert!(!pack.output_closed());
        }
        pack.step(dt, 20.0, true);
        assert!(pack.output_closed());
        assert_eq!(pack.step(dt, 20.0, true).net_current, 10.0);
    }

    #[test]
    fn over_current_trips_after_its_delay_and_latches_until_reset() {
        let mut pack = pack(&BatteryParams::default(), &BmsParams::default());
        // 100 us steps sum to just under 0.32 s after 3200 of them: the delay tolerance matters.
        let dt = 1e-4;
        for _ in 0..3199 {
            assert_eq!(pack.step(dt, 35.0, false).net_current, 35.0);
        }
        assert!(pack.output_closed());
        pack.step(dt, 35.0, false);
        assert_eq!(pack.trip(), Some(BmsTrip::OverCurrent));
        for _ in 0..10_000 {
            assert_eq!(pack.step(dt, 0.0, false).net_current, 0.0);
        }
        assert_eq!(pack.trip(), Some(BmsTrip::OverCurrent));
        // The load still asks for 35 A: the cause persists and the reset is refused.
        pack.step(dt, 35.0, false);
        assert!(pack.trip_cause_persists());
        pack.reset_trip();
        assert_eq!(pack.trip(), Some(BmsTrip::OverCurrent));
        pack.step(dt, 0.0, false);
        pack.reset_trip();
        assert!(pack.output_closed());
        assert_eq!(pack.step(dt, 10.0, false).net_current, 10.0);
    }

    #[test]
    fn short_circuit_trips_long_before_the_over_current_delay() {
        let bms = BmsParams::default();
        let dt = 1e-5;
        let mut battery = pack(&BatteryParams::default(), &bms);
        for _ in 0..19 {
            battery.step(dt, 200.0, false);
            assert!(battery.output_closed());
        }
        battery.step(dt, 200.0, false);
        assert_eq!(battery.trip(), Some(BmsTrip::ShortCircuit));
        assert!(20.0 * dt < bms.oc_delay_s / 100.0);
        for _ in 0..1_000 {
            battery.step(dt, 0.0, false);
        }
        assert_eq!(battery.trip(), Some(BmsTrip::ShortCircuit));
        battery.reset_trip();
        assert!(battery.output_closed());
        // A 10 ms step is longer than the SC delay: one step suffices.
        let mut battery = pack(&BatteryParams::default(), &bms);
        battery.step(1e-2, 200.0, false);
        assert_eq!(battery.trip(), Some(BmsTrip::ShortCircuit));
    }

    #[test]
    fn charger_runs_cc_then_holds_cv_while_tapering_then_terminates() {
        let params = BatteryParams {
            initial_soc: 0.95,
            ..BatteryParams::default()
        };
        let charger = ChargerParams::default();
        let mut pack = Battery::try_new(&params, &BmsParams::default(), &charger).unwrap();
        let dt = 1e-2;
        let (mut cc_steps, mut cv_steps) = (0_u32, 0_u32);
        let (mut previous, mut last_charging) = (f64::INFINITY, 0.0);
        for _ in 0..2_000_000 {
            let step = pack.step(dt, 0.0, true);
            if !pack.charging() {
                break;
            }
            if step.charger_current == charger.cc_amps {
                cc_steps += 1;
                assert_eq!(cv_steps, 0, "CC after CV");
                assert!(step.terminal_voltage <= charger.cv_volts + 1e-12);
            } else {
                cv_steps += 1;
                assert!((step.terminal_voltage - charger.cv_volts).abs() < 1e-3);
                assert!((pack.terminal_voltage() - charger.cv_volts).abs() < 1e-3);
                assert!(step.charger_current <= previous + 1e-12, "current rose");
                assert!(step.charger_current >= charger.termination_amps);
            }
            (previous, last_charging) = (step.charger_current, step.charger_current);
        }
        assert!(
            cc_steps > 100 && cv_steps > 100,
            "{cc_steps} CC, {cv_steps} CV"
        );
        assert!(!pack.charging(), "never terminated");
        assert!(last_charging < 1.01 * charger.termination_amps);
        assert!(pack.soc() > 0.99);
        for _ in 0..1_000 {
            assert_eq!(pack.step(dt, 0.0, true).charger_current, 0.0);
        }
    }

    #[test]
    fn charger_holding_cv_feeds_the_load_too() {
        let params = BatteryParams {
            initial_soc: 0.99,
            ..BatteryParams::default()
        };
        let mut pack = pack(&params, &BmsParams::default());
        let first = pack.step(1e-3, 0.0, true);
        assert!(first.charger_current < 2.0, "starts in CV");
        let with_load = pack.step(1e-3, 0.3, true);
        assert!((with_load.terminal_voltage - 42.0).abs() < 1e-9);
        assert!((with_load.charger_current - 0.3 - first.charger_current).abs() < 1e-3);
    }

    #[test]
    fn over_voltage_blocks_the_charger_until_it_releases() {
        let params = BatteryParams {
            initial_soc: 0.99,
            ..BatteryParams::default()
        };
        let faulty = ChargerParams {
            cc_amps: 10.0,
            cv_volts: 43.0,
            ..ChargerParams::default()
        };
        let bms = BmsParams::default();
        let refused = Battery::try_new(&params, &bms, &faulty).unwrap_err();
        assert_eq!(refused, BatteryConfigError::ChargerAboveOvTrip);
        let mut pack = Battery::new(&params, &bms, &faulty);
        let dt = 1e-2;
        for _ in 0..1_000 {
            if pack.trip().is_some() {
                break;
            }
            pack.step(dt, 0.0, true);
        }
        assert_eq!(pack.trip(), Some(BmsTrip::OverVoltage));
        for _ in 0..10 {
            let step = pack.step(dt, 5.0, true);
            assert_eq!((step.charger_current, step.net_current), (0.0, 0.0));
        }
        // Unplugged, the pack relaxes below the release and closes after the release delay.
        let mut open_steps = 10;
        while pack.trip().is_some() && open_steps < 1_000_000 {
            pack.step(dt, 0.0, false);
            open_steps += 1;
        }
        assert!(pack.output_closed());
        assert!(pack.terminal_voltage() < bms.ov_release_volts);
        assert!(open_steps as f64 * dt >= bms.release_delay_s - 1e-9);
    }

    #[test]
    fn internal_loss_matches_the_analytic_integral() {
        let params = BatteryParams::default();
        let (current, duration) = (10.0, 100.0);
        let mut expected = params.r0_ohm * current * current * duration;
        for pair in &params.rc_pairs {
            let tau = pair.time_constant();
            let decay = |k: f64| 1.0 - (-k * duration / tau).exp();
            let v_inf = current * pair.r_ohm;
            expected +=
                v_inf * v_inf * (duration - 2.0 * tau * decay(1.0) + 0.5 * tau * decay(2.0))
                    / pair.r_ohm;
        }
        for dt in [1e-3_f64, 1e-2] {
            let mut pack = pack(&params, &lenient_bms());
            let steps = (duration / dt).round() as u64;
            let total: f64 = (0..steps)
                .map(|_| pack.step(dt, current, false).internal_loss)
                .sum();
            assert!(
                relative_error(total, expected) < 1e-6,
                "{total} vs {expected}"
            );
        }
    }

    #[test]
    fn bench_supply_is_stiff_and_flat_and_trips_on_its_current_limit() {
        let mut supply = Battery::try_new(
            &BatteryParams::bench_supply_12v(),
            &BmsParams::bench_supply_12v(),
            &ChargerParams::bench_supply_12v(),
        )
        .unwrap();
        for _ in 0..10_000 {
            let step = supply.step(1e-3, 4.0, false);
            assert!((step.terminal_voltage - (12.0 - 4.0 * 0.02)).abs() < 1e-12);
        }
        assert!(supply.soc() > 0.999_999);
        for _ in 0..49 {
            supply.step(1e-3, 6.0, false);
        }
        assert!(supply.output_closed());
        supply.step(1e-3, 6.0, false);
        assert_eq!(supply.trip(), Some(BmsTrip::OverCurrent));
    }

    #[test]
    fn defaults_validate_and_bad_values_are_named() {
        let (b, m, c) = (
            BatteryParams::default(),
            BmsParams::default(),
            ChargerParams::default(),
        );
        assert!(Battery::try_new(&b, &m, &c).is_ok());
        let refused = |b: &BatteryParams, m: &BmsParams, c: &ChargerParams| {
            Battery::try_new(b, m, c).unwrap_err().to_string()
        };
        let empty = BatteryParams {
            capacity_ah: 0.0,
            ..b.clone()
        };
        assert_eq!(
            refused(&empty, &m, &c),
            "`capacity_ah` = 0 must be finite and > 0"
        );
        let swapped = vec![b.ocv_table[1], b.ocv_table[0]];
        let unsorted = BatteryParams {
            ocv_table: swapped,
            ..b.clone()
        };
        assert!(refused(&unsorted, &m, &c).starts_with("`ocv_table[1]`"));
        let no_hysteresis = BmsParams {
            uv_release_volts: 29.0,
            ..m.clone()
        };
        assert!(refused(&b, &no_hysteresis, &c).contains("above uv_trip_volts"));
        let stuck_open = BmsParams {
            ov_release_volts: 41.0,
            ..m.clone()
        };
        assert!(refused(&b, &stuck_open, &c).contains("OCV of 42 V"));
        let endless = ChargerParams {
            termination_amps: 3.0,
            ..c.clone()
        };
        assert!(refused(&b, &m, &endless).contains("below cc_amps"));
    }

    #[test]
    fn params_load_from_toml_with_defaults_and_reject_unknown_fields() {
        let text = "capacity_ah = 5.0\nocv_table = [{ soc = 0.0, volts = 10.0 }, { soc = 1.0, volts = 14.0 }]";
        let params: BatteryParams = toml::from_str(text).unwrap();
        assert_eq!(params.capacity_ah, 5.0);
        assert_eq!(params.ocv_at(0.5), 12.0);
        assert_eq!(params.r0_ohm, BatteryParams::default().r0_ohm);
        let bms: BmsParams = toml::from_str("oc_trip_amps = 12.5").unwrap();
        assert_eq!(bms.oc_trip_amps, 12.5);
        assert_eq!(bms.sc_delay_s, BmsParams::default().sc_delay_s);
        assert!(toml::from_str::<BatteryParams>("capacity = 5.0").is_err());
        assert!(toml::from_str::<ChargerParams>("cc_amp = 1.0").is_err());
        assert!(toml::from_str::<BatteryParams>("rc_pairs = [{ r_ohm = 1.0 }]").is_err());
    }

    #[test]
    fn nonsense_parameters_and_inputs_neither_panic_nor_go_non_finite() {
        let garbage = BatteryParams {
            capacity_ah: 0.0,
            ocv_table: Vec::new(),
            r0_ohm: f64::NAN,
            rc_pairs: vec![
                RcPair::new(0.0, 0.0),
                RcPair::new(-1.0, f64::INFINITY),
                RcPair::new(0.1, 0.0),
            ],
            initial_soc: f64::NAN,
        };
        let bms = BmsParams {
            oc_delay_s: f64::NAN,
            ..BmsParams::default()
        };
        let charger = ChargerParams {
            cc_amps: -3.0,
            cv_volts: f64::NAN,
            ..ChargerParams::default()
        };
        assert!(Battery::try_new(&garbage, &bms, &charger).is_err());
        let mut pack = Battery::new(&garbage, &bms, &charger);
        for (dt, load) in [
            (f64::NAN, 1.0),
            (-1.0, 1.0),
            (1e-3, f64::NAN),
            (1e-3, -5.0),
            (1e-3, f64::INFINITY),
            (1e-3, f64::NEG_INFINITY),
            (f64::INFINITY, 1.0),
            (1e-3, 1.0),
        ] {
            let step = pack.step(dt, load, true);
            let outputs = [
                step.terminal_voltage,
                step.charger_current,
                step.net_current,
                step.internal_loss,
                pack.soc(),
                pack.terminal_voltage(),
                pack.source_voltage(),
            ];
            assert!(
                outputs.iter().all(|v| v.is_finite()),
                "dt {dt} load {load}: {step:?}"
            );
        }
    }

    #[test]
    fn current_pushed_back_into_the_pack_charges_it() {
        let params = BatteryParams::default();
        let mut pack = pack(&params, &lenient_bms());
        let step = pack.step(1.0, -3.6, false);
        assert_eq!(step.net_current, -3.6);
        assert!(step.terminal_voltage > params.ocv_at(params.initial_soc));
        assert!(relative_error(pack.soc() - params.initial_soc, 1e-4) < 1e-9);
    }
}
