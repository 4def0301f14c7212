//! The PWM-capture paper's figures (`docs/protocols/pwmcap.md`): Table 2's
//! transfer times, bit-recognition reliability against added line impedance,
//! and the longest clean cable — all computed from the coding in
//! `protocols::pwmcap` and the line model in `nodes::link::pwmline`.

use nodes::link::pwmline::{PwmCalibration, PwmLine, PwmLineError, PwmLineParams, PwmTestValues};
use protocols::pwmcap::PwmCoding;

/// What a bit-recognition true/false positive is in this model; printed with
/// the figures and repeated in `docs/protocols/pwmcap-line.md`.
pub const BIT_RECOGNITION_DEFINITION: &str = "\
a test signal is one frame: start symbol + 4 data symbols, each a uniformly drawn 8-bit value;
each of the 32 data bits is one recognition: sent 1 read 1 = TP, sent 0 read 1 = FP,
sent 1 read 0 = FN, sent 0 read 0 = TN. A symbol the receiver gets no valid value for
(pulse lost, pulses merged, width out of range) reads as 0 (nothing captured); after a
lost pulse the receiver's symbol index runs one ahead, as on the bench.";

/// The paper's Table 2 and the model's numbers for it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Table2 {
    /// 8 bytes × 8 data bits at 1 Mbit/s, µs.
    pub modbus_data_us: f64,
    /// 8 bytes × 11.5 bit times (start, 8 data, parity, 1.5 stop) at 1 Mbit/s, µs.
    pub modbus_with_start_us: f64,
    /// 8 bare symbols of 256 ticks at 150 MHz, µs.
    pub pwm_bare_us: f64,
    /// The same plus one 100-tick start symbol, µs.
    pub pwm_with_start_us: f64,
    /// `modbus_data_us / pwm_bare_us`.
    pub speedup_data: f64,
    /// `modbus_with_start_us / pwm_with_start_us`.
    pub speedup_with_start: f64,
    /// The twin's real frame, start + 8 symbols of `S + C_max`, Table 2's coding, µs.
    pub twin_table2_coding_us: f64,
    /// The same with the paper's 10-bit coding and 200-tick start, µs.
    pub twin_paper_coding_us: f64,
}

/// Bytes (Modbus) or symbols (PWM) in Table 2's frame.
const TABLE2_SYMBOLS: u32 = 8;
/// Modbus bit rate in Table 2.
const MODBUS_BAUD: f64 = 1e6;

fn ticks_us(coding: &PwmCoding, ticks: u64) -> f64 {
    ticks as f64 / f64::from(coding.clock_hz()) * 1e6
}

/// Table 2 from the codings' own arithmetic.
pub fn table2() -> Table2 {
    let bytes = f64::from(TABLE2_SYMBOLS);
    let modbus_data_us = bytes * 8.0 / MODBUS_BAUD * 1e6;
    let modbus_with_start_us = bytes * 11.5 / MODBUS_BAUD * 1e6;
    let t2 = PwmCoding::TABLE2;
    let pwm_bare_us = ticks_us(&t2, t2.table2_bare_ticks(TABLE2_SYMBOLS));
    let pwm_with_start_us = ticks_us(&t2, t2.table2_with_start_ticks(TABLE2_SYMBOLS));
    let paper = PwmCoding::PAPER;
    Table2 {
        modbus_data_us,
        modbus_with_start_us,
        pwm_bare_us,
        pwm_with_start_us,
        speedup_data: modbus_data_us / pwm_bare_us,
        speedup_with_start: modbus_with_start_us / pwm_with_start_us,
        twin_table2_coding_us: ticks_us(&t2, t2.frame_ticks(TABLE2_SYMBOLS + 1)),
        twin_paper_coding_us: ticks_us(&paper, paper.frame_ticks(TABLE2_SYMBOLS + 1)),
    }
}

/// A confusion matrix of bit recognitions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Confusion {
    /// Sent 1, read 1.
    pub true_positive: u32,
    /// Sent 0, read 1.
    pub false_positive: u32,
    /// Sent 1, read 0.
    pub false_negative: u32,
    /// Sent 0, read 0.
    pub true_negative: u32,
}

impl Confusion {
    fn record(&mut self, sent: u16, read: u16, bits: u8) {
        for bit in 0..bits {
            let (s, r) = ((sent >> bit) & 1 == 1, (read >> bit) & 1 == 1);
            match (s, r) {
                (true, true) => self.true_positive += 1,
                (false, true) => self.false_positive += 1,
                (true, false) => self.false_negative += 1,
                (false, false) => self.true_negative += 1,
            }
        }
    }

    fn total(&self) -> u32 {
        self.true_positive + self.false_positive + self.false_negative + self.true_negative
    }

    /// Bit errors (FP + FN).
    pub fn errors(&self) -> u32 {
        self.false_positive + self.false_negative
    }

    /// (TP + TN) / all (paper eq. 6).
    pub fn accuracy(&self) -> f64 {
        ratio(self.true_positive + self.true_negative, self.total())
    }

    /// TP / (TP + FP) (paper eq. 7).
    pub fn precision(&self) -> f64 {
        ratio(self.true_positive, self.true_positive + self.false_positive)
    }

    /// TP / (TP + FN) (paper eq. 8).
    pub fn recall(&self) -> f64 {
        ratio(self.true_positive, self.true_positive + self.false_negative)
    }

    /// Harmonic mean of precision and recall (paper eq. 9).
    pub fn f1(&self) -> f64 {
        let (p, r) = (self.precision(), self.recall());
        if p + r > 0.0 {
            2.0 * p * r / (p + r)
        } else {
            0.0
        }
    }
}

fn ratio(numerator: u32, denominator: u32) -> f64 {
    if denominator == 0 {
        f64::NAN
    } else {
        f64::from(numerator) / f64::from(denominator)
    }
}

/// The experiment's set-up; [`ReliabilitySetup::DEFAULT`] is what the CLI runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReliabilitySetup {
    /// The line before anything is added.
    pub line: PwmLineParams,
    /// The coding the master starts with.
    pub coding: PwmCoding,
    /// Shunt capacitance added in every impedance row, F.
    pub added_shunt_farad: f64,
    /// Test signals per row.
    pub signals: u32,
    /// Seed of everything random (values, noise, counter phase).
    pub seed: u64,
}

/// Added series resistances of the paper's three rows, Ω.
pub const IMPEDANCE_ROWS_OHM: [f64; 3] = [1.0, 5.0, 20.0];
/// Data symbols per test signal (the experiment frame's four).
pub const VALUES_PER_SIGNAL: usize = 4;

impl ReliabilitySetup {
    /// 10 m of Cat5 (the paper's short-line case), the paper's 20 nF added in
    /// every row (it names no other value), 200 test signals, the paper's
    /// coding (10 bits, 200-tick start).
    pub const DEFAULT: ReliabilitySetup = ReliabilitySetup {
        line: PwmLineParams::DEFAULT,
        coding: PwmCoding::PAPER,
        added_shunt_farad: 20e-9,
        signals: 200,
        seed: 3,
    };
}

/// One row of the reliability figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReliabilityRow {
    /// Added series resistance, Ω.
    pub added_series_ohm: f64,
    /// The line's τ, counter ticks.
    pub tau_ticks: f64,
    /// Bit recognitions with the initial coding.
    pub uncalibrated: Confusion,
    /// Start width and guard after calibration, `None` if none was found.
    pub calibration: Option<PwmCalibration>,
    /// Bit recognitions with the calibrated coding (all errors if none found).
    pub calibrated: Confusion,
}

/// SplitMix64 step: independent seeds for each row and purpose from one seed.
fn derive_seed(seed: u64, stream: u64) -> u64 {
    let mut z = seed
        .wrapping_add(stream.wrapping_mul(0x9E37_79B9_7F4A_7C15))
        .wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Sends `signals` test signals over `line` and counts bit recognitions.
fn run_signals(
    line: &mut PwmLine,
    coding: &PwmCoding,
    guard_ticks: u32,
    signals: u32,
    values_seed: u64,
) -> Result<Confusion, PwmLineError> {
    let mut source = PwmTestValues::new(values_seed);
    let mut confusion = Confusion::default();
    let mut values = [0u16; VALUES_PER_SIGNAL];
    let mut decoded = [None; VALUES_PER_SIGNAL];
    for _ in 0..signals {
        source.fill(coding.max_value(), &mut values);
        line.send_values(coding, guard_ticks, &values, &mut decoded)?;
        for (&sent, read) in values.iter().zip(decoded) {
            confusion.record(sent, read.unwrap_or(0), coding.data_bits());
        }
    }
    Ok(confusion)
}

/// Sends the test signals over `params`, once with the initial coding and
/// once after calibration; `stream` keeps each call's randomness apart.
fn measure(
    setup: &ReliabilitySetup,
    params: PwmLineParams,
    stream: u64,
) -> Result<(f64, Confusion, Option<PwmCalibration>, Confusion), PwmLineError> {
    let clock = setup.coding.clock_hz();
    let values_seed = derive_seed(setup.seed, 4 * stream);
    let mut line = PwmLine::new(params, clock, derive_seed(setup.seed, 4 * stream + 1))?;
    let uncalibrated = run_signals(&mut line, &setup.coding, 0, setup.signals, values_seed)?;
    let mut training = PwmLine::new(params, clock, derive_seed(setup.seed, 4 * stream + 2))?;
    let calibration = PwmCalibration::find(&mut training, &setup.coding)?;
    let calibrated = match calibration {
        Some(found) => {
            let mut line = PwmLine::new(params, clock, derive_seed(setup.seed, 4 * stream + 3))?;
            run_signals(
                &mut line,
                &found.coding,
                found.guard_ticks,
                setup.signals,
                values_seed,
            )?
        }
        None => Confusion {
            // No usable start width: nothing is received, every 1 is missed.
            false_negative: uncalibrated.true_positive + uncalibrated.false_negative,
            true_negative: uncalibrated.true_negative + uncalibrated.false_positive,
            ..Confusion::default()
        },
    };
    Ok((line.tau_ticks(), uncalibrated, calibration, calibrated))
}

/// The reliability figures for [`IMPEDANCE_ROWS_OHM`].
pub fn reliability(setup: &ReliabilitySetup) -> Result<Vec<ReliabilityRow>, PwmLineError> {
    let mut rows = Vec::with_capacity(IMPEDANCE_ROWS_OHM.len());
    for (index, &added_series_ohm) in IMPEDANCE_ROWS_OHM.iter().enumerate() {
        let params = PwmLineParams {
            added_series_ohm,
            added_shunt_farad: setup.added_shunt_farad,
            ..setup.line
        };
        let (tau_ticks, uncalibrated, calibration, calibrated) =
            measure(setup, params, index as u64)?;
        rows.push(ReliabilityRow {
            added_series_ohm,
            tau_ticks,
            uncalibrated,
            calibration,
            calibrated,
        });
    }
    Ok(rows)
}

/// The longest cables, nothing added, that decode without a bit error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LongestCable {
    /// With the initial coding, m (every length up to it clean).
    pub uncalibrated_m: f64,
    /// With calibration at each length, m.
    pub calibrated_m: f64,
    /// Step of the search, m.
    pub step_m: f64,
    /// Longest length tried, m.
    pub limit_m: f64,
}

/// Walks the bare cable's length up in `step_m` steps to `limit_m` and
/// reports, for each mode, the last length before the first bit error.
pub fn longest_clean_cable(
    setup: &ReliabilitySetup,
    step_m: f64,
    limit_m: f64,
) -> Result<LongestCable, PwmLineError> {
    if !(step_m.is_finite() && step_m > 0.0 && limit_m.is_finite()) {
        return Err(PwmLineError::InvalidParameter("cable search step/limit"));
    }
    let mut result = LongestCable {
        uncalibrated_m: 0.0,
        calibrated_m: 0.0,
        step_m,
        limit_m,
    };
    let (mut raw_open, mut cal_open) = (true, true);
    let mut step = 1u64;
    while raw_open || cal_open {
        let length = step as f64 * step_m;
        if length > limit_m {
            break;
        }
        let params = PwmLineParams {
            cable_length_m: length,
            ..setup.line
        };
        let (_, uncalibrated, _, calibrated) = measure(setup, params, 1000 + step)?;
        if raw_open && uncalibrated.errors() == 0 {
            result.uncalibrated_m = length;
        } else {
            raw_open = false;
        }
        if cal_open && calibrated.errors() == 0 {
            result.calibrated_m = length;
        } else {
            cal_open = false;
        }
        step += 1;
    }
    Ok(result)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table2_timings_are_the_spec_targets_exactly() {
        let t = table2();
        assert_eq!(t.modbus_data_us, 64.0);
        assert_eq!(t.modbus_with_start_us, 92.0);
        // 2048 and 2148 ticks at 150 MHz.
        assert!((t.pwm_bare_us - 2048.0 / 150.0).abs() < 1e-12);
        assert!((t.pwm_with_start_us - 14.32).abs() < 1e-12);
        assert_eq!(format!("{:.3}", t.pwm_bare_us), "13.653");
        assert!((t.speedup_data - 64.0 * 150.0 / 2048.0).abs() < 1e-12);
        assert!((t.speedup_with_start - 92.0 / 14.32).abs() < 1e-12);
        // The twin's own frames: 9 × (100 + 256) and 9 × (200 + 1024) ticks.
        assert!((t.twin_table2_coding_us - 9.0 * 356.0 / 150.0).abs() < 1e-12);
        assert!((t.twin_paper_coding_us - 9.0 * 1224.0 / 150.0).abs() < 1e-12);
    }

    #[test]
    fn confusion_metrics_follow_the_paper_equations() {
        let c = Confusion {
            true_positive: 90,
            false_positive: 10,
            false_negative: 5,
            true_negative: 95,
        };
        assert!((c.accuracy() - 185.0 / 200.0).abs() < 1e-12);
        assert!((c.precision() - 0.9).abs() < 1e-12);
        assert!((c.recall() - 90.0 / 95.0).abs() < 1e-12);
        let f1 = 2.0 * 0.9 * (90.0 / 95.0) / (0.9 + 90.0 / 95.0);
        assert!((c.f1() - f1).abs() < 1e-12);
        let mut bits = Confusion::default();
        bits.record(0b1010_0000, 0b1000_0001, 8);
        assert_eq!(
            (
                bits.true_positive,
                bits.false_positive,
                bits.false_negative,
                bits.true_negative
            ),
            (1, 1, 1, 5)
        );
    }

    /// The default setup with the cable reduced to its Elmore-delay pole.
    fn distributed() -> ReliabilitySetup {
        let mut setup = ReliabilitySetup::DEFAULT;
        setup.line.cable_model = nodes::link::CableModel::Elmore;
        setup
    }

    #[test]
    fn reliability_falls_with_impedance_and_calibration_recovers_it() {
        check_trend(&ReliabilitySetup::DEFAULT);
    }

    #[test]
    fn the_trend_holds_with_the_cable_as_a_distributed_line() {
        let lumped = reliability(&ReliabilitySetup::DEFAULT).unwrap();
        let elmore = reliability(&distributed()).unwrap();
        // The distributed cable is faster: its own r·c counts half, and the
        // added R sits after it and does not charge it.
        for (l, e) in lumped.iter().zip(&elmore) {
            assert!(
                e.tau_ticks < l.tau_ticks,
                "{} vs {}",
                e.tau_ticks,
                l.tau_ticks
            );
        }
        check_trend(&distributed());
    }

    #[test]
    fn a_distributed_cable_reaches_at_least_as_far() {
        let lumped = longest_clean_cable(&ReliabilitySetup::DEFAULT, 10.0, 300.0).unwrap();
        let elmore = longest_clean_cable(&distributed(), 10.0, 300.0).unwrap();
        assert!(
            elmore.calibrated_m >= lumped.calibrated_m,
            "{elmore:?} vs {lumped:?}"
        );
        assert!(
            elmore.uncalibrated_m >= lumped.uncalibrated_m,
            "{elmore:?} vs {lumped:?}"
        );
    }

    fn check_trend(setup: &ReliabilitySetup) {
        let rows = reliability(setup).unwrap();
        assert_eq!(rows.len(), 3);
        assert!(rows[0].tau_ticks < rows[1].tau_ticks && rows[1].tau_ticks < rows[2].tau_ticks);
        let initial: Vec<f64> = rows.iter().map(|r| r.uncalibrated.accuracy()).collect();
        // Falling: every step up in R costs accuracy, 20 Ω clearly worst.
        assert!(
            initial[0] > initial[1] && initial[1] > initial[2],
            "{initial:?}"
        );
        assert!(initial[0] - initial[2] > 0.05, "{initial:?}");
        for row in &rows {
            assert!(row.calibration.is_some());
            assert!(row.calibrated.accuracy() >= 0.985, "{row:?}");
            assert!(row.calibrated.f1() > row.uncalibrated.f1(), "{row:?}");
        }
        // Calibration needs a longer start on a slower line.
        let starts: Vec<u32> = rows
            .iter()
            .filter_map(|r| r.calibration.map(|c| c.coding.start_ticks()))
            .collect();
        assert!(starts[0] < starts[2], "{starts:?}");
    }

    #[test]
    fn high_accuracy_at_low_impedance_without_added_capacitance() {
        let setup = ReliabilitySetup {
            added_shunt_farad: 0.0,
            ..ReliabilitySetup::DEFAULT
        };
        let rows = reliability(&setup).unwrap();
        assert!(rows[0].uncalibrated.accuracy() >= 0.985, "{:?}", rows[0]);
    }

    #[test]
    fn same_seed_same_figures() {
        let a = reliability(&ReliabilitySetup::DEFAULT).unwrap();
        let b = reliability(&ReliabilitySetup::DEFAULT).unwrap();
        assert_eq!(a, b);
        let other = ReliabilitySetup {
            seed: 4,
            ..ReliabilitySetup::DEFAULT
        };
        assert_ne!(a, reliability(&other).unwrap());
    }

    #[test]
    fn longer_start_reaches_further_than_the_initial_coding() {
        let cable = longest_clean_cable(&ReliabilitySetup::DEFAULT, 10.0, 400.0).unwrap();
        assert!(cable.uncalibrated_m >= 10.0, "{cable:?}");
        assert!(cable.calibrated_m > cable.uncalibrated_m, "{cable:?}");
    }
}
