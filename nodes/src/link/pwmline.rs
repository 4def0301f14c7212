//! The PWM-capture line (`docs/protocols/pwmcap.md`, the PWM-capture paper): sender edges
//! in, capture widths out.
//!
//! The physical chain, from the master's PWM pin to the slave's capture unit:
//!
//! ```text
//!  driver (R_drv) ── cable (r·L, c·L) ── added series R ──┬── comparator (V_th, noise) ── capture
//!                                                  shunt C ┴ + input C
//! ```
//!
//! is lumped into one RC low-pass, `τ = (R_drv + r·L + R_add)·(c·L + C_add + C_in)`.
//! Between two sender edges the input is constant, so the comparator input is
//! exactly `v(t) = u + (v₀ − u)·e^{−(t−t₀)/τ}` and each threshold crossing time
//! is solved in closed form; no time stepping.
//!
//! Noise is the comparator's input-referred noise, taken as constant over the
//! few nanoseconds of one decision: when the comparator starts waiting for its
//! next transition, one Gaussian sample `n` is drawn and the transition happens
//! where `v(t) + n` reaches `V_th`, i.e. where `v(t) = V_th − n`.
//!
//! The capture unit runs in time-difference mode on a free counter of the
//! coding's clock whose phase against the sender is drawn per transmission:
//! a pulse's captured width is the number of counter ticks between its rising
//! and falling comparator edges. A pulse that never reaches the threshold, or
//! that merges with the next one because the line has not fallen back below it,
//! is simply not there for the capture unit, as on the bench.
//!
//! Nothing here reads a clock, allocates per transmission, or panics.

use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

use protocols::pwmcap::{PwmCoding, PwmError};

/// Why a line cannot be built or a transmission made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum PwmLineError {
    /// A parameter is not finite or out of its physical range; names which.
    #[error("PWM line parameter out of range: {0}")]
    InvalidParameter(&'static str),
    /// A width is not shorter than the symbol period, so the pulse never ends.
    #[error("pulse width {width} ticks not below the period {period} ticks")]
    WidthNotBelowPeriod {
        /// The ON width, in counter ticks.
        width: u32,
        /// The symbol period, in counter ticks.
        period: u32,
    },
    /// The coding could not build or read a symbol.
    #[error(transparent)]
    Coding(#[from] PwmError),
}

/// The physical parameters of one master→slave line. All SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PwmLineParams {
    /// Output resistance of the sender's line driver, Ω.
    pub driver_ohm: f64,
    /// Loop resistance of the cable (signal and return conductor), Ω per metre.
    pub cable_ohm_per_m: f64,
    /// Capacitance between the pair's conductors, F per metre.
    pub cable_farad_per_m: f64,
    /// Cable length, m.
    pub cable_length_m: f64,
    /// Series resistance added to the line (the paper's "+R"), Ω.
    pub added_series_ohm: f64,
    /// Shunt capacitance added across the line (the paper's "+C"), F.
    pub added_shunt_farad: f64,
    /// Input capacitance of the receiving comparator, F.
    pub receiver_input_farad: f64,
    /// The driver's high level, V (low is 0 V).
    pub drive_volts: f64,
    /// The comparator's threshold, V.
    pub threshold_volts: f64,
    /// RMS input-referred noise of the comparator, V.
    pub noise_volts_rms: f64,
    /// How the cable's own R and C enter the line's time constant.
    pub cable_model: CableModel,
}

/// How the cable's resistance and capacitance make the one pole of the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CableModel {
    /// Everything in one lump: `τ = (R_drv + r·L + R_add)·(c·L + C_add + C_in)`.
    /// Pessimistic for a long cable: every resistance charges every capacitance.
    #[default]
    Lumped,
    /// The cable as a distributed RC line, reduced to the single pole with the
    /// same Elmore delay (first moment of its impulse response): every
    /// resistance charges only the capacitance downstream of it,
    /// `τ = R_drv·(c·L + C_l) + r·L·(c·L/2 + C_l) + R_add·C_l`, `C_l = C_add + C_in`.
    /// The cable's own `r·c·L²` counts half, and the added series R (after
    /// the cable, at the receiver) does not charge the cable.
    Elmore,
}

impl PwmLineParams {
    /// The twin's line, every value fixed from a datasheet before any
    /// reliability figure was computed (arguments in `docs/protocols/pwmcap-line.md`):
    /// - driver 23 Ω: a 3.3 V 74LVC1G125-class buffer, V_OL 0.55 V at 24 mA;
    /// - cable 0.188 Ω/m loop (2 × 0.094 Ω/m, 24 AWG Cat5 conductor) and
    ///   50 pF/m mutual capacitance (Cat5 / RS-485 twisted pair, ≤ 52 pF/m);
    /// - 10 m of cable, nothing added (the paper's "less than 10 m", Fig. 22(b));
    /// - receiver 5 pF input capacitance, threshold at mid-supply 1.65 V;
    /// - comparator noise 0.5 mV rms: 20 nV/√Hz over a 300 MHz noise bandwidth
    ///   (a 7 ns comparator), √(300 MHz · π/2) · 20 nV ≈ 0.43 mV, rounded up.
    pub const DEFAULT: PwmLineParams = PwmLineParams {
        driver_ohm: 23.0,
        cable_ohm_per_m: 0.188,
        cable_farad_per_m: 50e-12,
        cable_length_m: 10.0,
        added_series_ohm: 0.0,
        added_shunt_farad: 0.0,
        receiver_input_farad: 5e-12,
        drive_volts: 3.3,
        threshold_volts: 1.65,
        noise_volts_rms: 0.5e-3,
        cable_model: CableModel::Lumped,
    };

    /// Total series resistance of the lumped RC, Ω.
    pub fn series_ohm(&self) -> f64 {
        self.driver_ohm + self.cable_ohm_per_m * self.cable_length_m + self.added_series_ohm
    }

    /// Total shunt capacitance of the lumped RC, F.
    pub fn shunt_farad(&self) -> f64 {
        self.cable_farad_per_m * self.cable_length_m
            + self.added_shunt_farad
            + self.receiver_input_farad
    }

    /// The line's time constant, s: `τ = R·C` lumped, or the Elmore delay
    /// of the distributed cable (see [`CableModel`]).
    pub fn time_constant_s(&self) -> f64 {
        match self.cable_model {
            CableModel::Lumped => self.series_ohm() * self.shunt_farad(),
            CableModel::Elmore => {
                let cable_c = self.cable_farad_per_m * self.cable_length_m;
                let cable_r = self.cable_ohm_per_m * self.cable_length_m;
                let load_c = self.added_shunt_farad + self.receiver_input_farad;
                self.driver_ohm * (cable_c + load_c)
                    + cable_r * (cable_c / 2.0 + load_c)
                    + self.added_series_ohm * load_c
            }
        }
    }

    /// Checks every parameter is finite and physical.
    pub fn validate(&self) -> Result<(), PwmLineError> {
        let non_negative = [
            (self.driver_ohm, "driver_ohm"),
            (self.cable_ohm_per_m, "cable_ohm_per_m"),
            (self.cable_farad_per_m, "cable_farad_per_m"),
            (self.cable_length_m, "cable_length_m"),
            (self.added_series_ohm, "added_series_ohm"),
            (self.added_shunt_farad, "added_shunt_farad"),
            (self.receiver_input_farad, "receiver_input_farad"),
            (self.noise_volts_rms, "noise_volts_rms"),
        ];
        for (value, name) in non_negative {
            if !(value.is_finite() && value >= 0.0) {
                return Err(PwmLineError::InvalidParameter(name));
            }
        }
        if !(self.drive_volts.is_finite() && self.drive_volts > 0.0) {
            return Err(PwmLineError::InvalidParameter("drive_volts"));
        }
        if !(self.threshold_volts > 0.0 && self.threshold_volts < self.drive_volts) {
            return Err(PwmLineError::InvalidParameter("threshold_volts"));
        }
        let tau = self.time_constant_s();
        if !(tau.is_finite() && tau > 0.0) {
            return Err(PwmLineError::InvalidParameter(
                "time constant (R·C must be > 0)",
            ));
        }
        Ok(())
    }
}

/// One pulse as the capture unit measured it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PwmCapture {
    /// The captured ON width, counter ticks.
    pub width: u32,
    /// When its falling edge crossed the threshold, counter ticks after the
    /// sender's first rising edge.
    pub fall_at_ticks: f64,
}

/// A seeded master→slave PWM-capture line.
#[derive(Debug, Clone)]
pub struct PwmLine {
    params: PwmLineParams,
    /// τ in counter ticks.
    tau_ticks: f64,
    rng: Pcg64,
}

/// What the comparator is waiting for, with the noise-shifted level it acts at.
#[derive(Debug, Clone, Copy)]
struct Pending {
    rising: bool,
    level: f64,
}

impl PwmLine {
    /// A line with `params`, capture counter at `clock_hz`, noise and counter
    /// phase drawn from `seed`.
    pub fn new(params: PwmLineParams, clock_hz: u32, seed: u64) -> Result<Self, PwmLineError> {
        params.validate()?;
        if clock_hz == 0 {
            return Err(PwmLineError::InvalidParameter("clock_hz"));
        }
        let tau_ticks = params.time_constant_s() * f64::from(clock_hz);
        if !(tau_ticks.is_finite() && tau_ticks > 0.0) {
            return Err(PwmLineError::InvalidParameter("time constant in ticks"));
        }
        Ok(PwmLine {
            params,
            tau_ticks,
            rng: Pcg64::seed_from_u64(seed),
        })
    }

    /// The same line with its noise and counter phase drawn from `seed`.
    pub fn reseeded(&self, seed: u64) -> Self {
        PwmLine {
            rng: Pcg64::seed_from_u64(seed),
            ..self.clone()
        }
    }

    /// The line's parameters.
    pub fn params(&self) -> &PwmLineParams {
        &self.params
    }

    /// τ in ticks of the capture counter.
    pub fn tau_ticks(&self) -> f64 {
        self.tau_ticks
    }

    /// One standard normal sample (Box–Muller; `rand` is built without `rand_distr`).
    fn gaussian(&mut self) -> f64 {
        // 1 − U lies in (0, 1], so the log is finite.
        let u1 = 1.0 - self.rng.random::<f64>();
        let u2 = self.rng.random::<f64>();
        (-2.0 * u1.ln()).sqrt() * (core::f64::consts::TAU * u2).cos()
    }

    fn pending(&mut self, rising: bool) -> Pending {
        let noise = self.params.noise_volts_rms * self.gaussian();
        Pending {
            rising,
            level: self.params.threshold_volts - noise,
        }
    }

    /// Sends pulses of ON `widths` (counter ticks), one every `period` ticks,
    /// from an idle (settled low) line, and writes the ON widths the capture
    /// unit measures, in order, to `captured`. Returns how many it measured:
    /// fewer than sent when pulses were lost or merged; extra ones beyond
    /// `captured.len()` are dropped, as a full capture buffer would.
    pub fn transmit(
        &mut self,
        widths: &[u32],
        period: u32,
        captured: &mut [u32],
    ) -> Result<usize, PwmLineError> {
        let mut count = 0usize;
        self.transmit_with(widths, period, |width, _| {
            if let Some(slot) = captured.get_mut(count) {
                *slot = width;
                count += 1;
            }
        })?;
        Ok(count)
    }

    /// As [`PwmLine::transmit`], and also says when each captured pulse's
    /// falling edge reached the capture unit (the instant its width is known),
    /// in counter ticks from the first rising edge sent: what a receiver's
    /// capture interrupt sees, for a medium that delivers pulses in time.
    pub fn transmit_timed(
        &mut self,
        widths: &[u32],
        period: u32,
        captured: &mut [PwmCapture],
    ) -> Result<usize, PwmLineError> {
        let mut count = 0usize;
        self.transmit_with(widths, period, |width, fall_at_ticks| {
            if let Some(slot) = captured.get_mut(count) {
                *slot = PwmCapture {
                    width,
                    fall_at_ticks,
                };
                count += 1;
            }
        })?;
        Ok(count)
    }

    fn transmit_with(
        &mut self,
        widths: &[u32],
        period: u32,
        mut capture: impl FnMut(u32, f64),
    ) -> Result<(), PwmLineError> {
        if let Some(&width) = widths.iter().find(|&&w| w >= period) {
            return Err(PwmLineError::WidthNotBelowPeriod { width, period });
        }
        let high = self.params.drive_volts;
        let tau = self.tau_ticks;
        // The capture counter's phase against the sender's edges.
        let phase: f64 = self.rng.random::<f64>();
        let counter = |t: f64| (t - phase).floor();

        let mut volts = 0.0_f64;
        let mut pending = self.pending(true);
        let mut rise_at: Option<f64> = None;

        // Segments of constant input: [start, end) at level `input`.
        let last = widths.len().saturating_sub(1);
        for (index, &width) in widths.iter().enumerate() {
            let begin = index as f64 * f64::from(period);
            let fall = begin + f64::from(width);
            let end = if index == last {
                f64::INFINITY
            } else {
                begin + f64::from(period)
            };
            for (start, stop, input) in [(begin, fall, high), (fall, end, 0.0)] {
                let duration = stop - start;
                // The only transition this segment can make is in its direction.
                let toward_high = input > volts;
                if (pending.rising == toward_high || input == volts)
                    && let Some(dt) = crossing(volts, input, pending.level, tau)
                    && dt < duration
                {
                    let t = start + dt;
                    if pending.rising {
                        rise_at = Some(t);
                    } else if let Some(rise) = rise_at.take() {
                        let ticks = counter(t) - counter(rise);
                        // Non-negative and below 2^32 periods: fits.
                        capture(ticks.clamp(0.0, f64::from(u32::MAX)) as u32, t);
                    }
                    pending = self.pending(!pending.rising);
                }
                volts = if duration.is_finite() {
                    input + (volts - input) * (-duration / tau).exp()
                } else {
                    input
                };
            }
        }
        Ok(())
    }

    /// Sends `values` in one frame with `coding` (start symbol first, each
    /// value as `S + (value << d)`, period `S + C_max + guard`), and decodes
    /// what the capture unit measured: start-width compensation against the
    /// *measured* start, dummy bits dropped. `decoded[i]` is `None` when the
    /// receiver got no valid value for symbol `i` (lost, merged, out of range).
    /// The receiver takes captured widths in arrival order, so after a lost
    /// pulse the later ones land one slot early — as a real receiver's symbol
    /// index would.
    pub fn send_values(
        &mut self,
        coding: &PwmCoding,
        guard_ticks: u32,
        values: &[u16],
        decoded: &mut [Option<u16>],
    ) -> Result<(), PwmLineError> {
        let mut widths = [0u32; PWM_LINE_MAX_SYMBOLS];
        let mut captured = [0u32; PWM_LINE_MAX_SYMBOLS];
        let symbols = values.len() + 1;
        let sent = widths
            .get_mut(..symbols)
            .ok_or(PwmError::BufferTooSmall { needed: symbols })?;
        if let Some((start, rest)) = sent.split_first_mut() {
            *start = coding.start_ticks();
            for (width, &value) in rest.iter_mut().zip(values) {
                *width = coding.encode_width(value)?;
            }
        }
        let period = coding
            .symbol_period_ticks()
            .checked_add(guard_ticks)
            .ok_or(PwmLineError::InvalidParameter("guard_ticks"))?;
        let got = self.transmit(sent, period, &mut captured[..symbols])?;
        decode_captured(coding, &captured[..got], decoded);
        Ok(())
    }
}

/// The most symbols [`PwmLine::send_values`] sends in one frame, start included.
pub const PWM_LINE_MAX_SYMBOLS: usize = protocols::pwmcap::PWM_MAX_SYMBOLS;

/// Decodes captured widths (start first) into `decoded`, one slot per data
/// symbol; slots without a captured width or with an invalid one get `None`.
pub fn decode_captured(coding: &PwmCoding, captured: &[u32], decoded: &mut [Option<u16>]) {
    decoded.fill(None);
    let Some((&start, data)) = captured.split_first() else {
        return;
    };
    for (slot, &width) in decoded.iter_mut().zip(data) {
        *slot = coding.decode_width(width, start).ok();
    }
}

/// Time from a segment's start until `v(t) = u + (v₀ − u)e^{−t/τ}` reaches
/// `level`, or `None` if it never does (it moves monotonically toward `u`).
fn crossing(v0: f64, u: f64, level: f64, tau: f64) -> Option<f64> {
    let rising = u > v0;
    let already = if rising { v0 >= level } else { v0 <= level };
    if already {
        return Some(0.0);
    }
    let reaches = if rising { level < u } else { level > u };
    if !reaches {
        return None;
    }
    // Both differences have the same sign and (v0 − u) is the larger in size.
    Some(tau * ((v0 - u) / (level - u)).ln())
}

/// The start width the line needs, found at initialisation by sending
/// training frames through the line itself (the paper's "automatic
/// initialisation setting sequence of the start bit").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PwmCalibration {
    /// The coding with the lengthened start symbol.
    pub coding: PwmCoding,
    /// Extra OFF ticks appended to every symbol period.
    pub guard_ticks: u32,
    /// Training frames sent to find it.
    pub frames_sent: u32,
}

impl PwmCalibration {
    /// Training frames that must all decode exactly at one allowance.
    pub const CLEAN_FRAMES: u32 = 8;
    /// Allowance step, ticks.
    pub const STEP_TICKS: u32 = 20;
    /// Largest allowance tried, ticks.
    pub const MAX_ALLOWANCE_TICKS: u32 = 20_000;

    /// Raises one allowance `a` in steps of [`Self::STEP_TICKS`] from 0 until
    /// [`Self::CLEAN_FRAMES`] training frames (values 0, max, max, 0, mid:
    /// every long/short neighbour pair) come through with margin, then uses
    /// `S + a` as start width and `a` as extra OFF time. One allowance covers
    /// both ways a slow line breaks the coding: a short start pulse shrinks
    /// more than long data pulses (the pulse must rise past the threshold)
    /// and a short OFF gap merges pulses (the line must fall back below it).
    ///
    /// "With margin": the receiver knows the training values, so it checks
    /// every captured width minus the captured start against the sent
    /// difference and accepts an error of at most a quarter of a dummy step
    /// (half of what the rounding absorbs), so that noise and the neighbours'
    /// residue left after calibration do not sit on the rounding edge.
    /// `None` if no allowance up to the maximum works.
    pub fn find(line: &mut PwmLine, base: &PwmCoding) -> Result<Option<Self>, PwmLineError> {
        let max = base.max_value();
        let training = [0, max, max, 0, max / 2 + 1];
        let margin = i64::from((1u32 << base.dummy_bits()) >> 2);
        let mut widths = [0u32; 6];
        let mut captured = [0u32; 6];
        let mut frames_sent = 0u32;
        let mut allowance = 0u32;
        while allowance <= Self::MAX_ALLOWANCE_TICKS {
            let coding = PwmCoding::new(
                base.clock_hz(),
                base.data_bits(),
                base.dummy_bits(),
                base.start_ticks() + allowance,
            )?;
            let (start, rest) = widths.split_at_mut(1);
            start.fill(coding.start_ticks());
            for (width, &value) in rest.iter_mut().zip(&training) {
                *width = coding.encode_width(value)?;
            }
            let period = coding.symbol_period_ticks() + allowance;
            let mut clean = true;
            for _ in 0..Self::CLEAN_FRAMES {
                let got = line.transmit(&widths, period, &mut captured)?;
                frames_sent += 1;
                let within = |(&sent, &seen): (&u32, &u32)| {
                    let sent_diff = i64::from(sent) - i64::from(coding.start_ticks());
                    let seen_diff = i64::from(seen) - i64::from(captured[0]);
                    (seen_diff - sent_diff).abs() <= margin
                };
                if got != widths.len() || !widths.iter().zip(&captured).skip(1).all(within) {
                    clean = false;
                    break;
                }
            }
            if clean {
                return Ok(Some(PwmCalibration {
                    coding,
                    guard_ticks: allowance,
                    frames_sent,
                }));
            }
            allowance += Self::STEP_TICKS;
        }
        Ok(None)
    }
}

/// A seeded source of test values for reliability experiments, kept apart
/// from the line's own noise so that changing the line does not change the
/// values sent.
#[derive(Debug, Clone)]
pub struct PwmTestValues {
    rng: Pcg64,
}

impl PwmTestValues {
    /// A source seeded with `seed`.
    pub fn new(seed: u64) -> Self {
        PwmTestValues {
            rng: Pcg64::seed_from_u64(seed),
        }
    }

    /// Fills `values` with values drawn uniformly from `0..=max`.
    pub fn fill(&mut self, max: u16, values: &mut [u16]) {
        for value in values {
            *value = self.rng.random_range(0..=max);
        }
    }
}
