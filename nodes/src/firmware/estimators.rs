//! The two wheel-speed estimates the firmware computes, as a microcontroller
//! with an input-capture unit and an ADC would: from hall-edge timestamps
//! ([`HallRpm`]) and from the photoresistor's dips ([`LightRpm`]).
//!
//! Neither looks at the plant's true speed or flag position: the hall estimate
//! sees only edge counts and the capture time of the latest edge, the light
//! estimate only the ADC samples taken at loop ticks, so both miss what the
//! real sensors miss.

use plant::shaft::ShaftReading;

use protocols::time::{SimDuration, SimTime};

/// Hall-edge speed estimator: edges counted between captured edges.
///
/// At every loop tick where the hall edge count moved, the capture unit holds
/// the timestamp of the latest edge, so each such tick gives an exact pair
/// (edge time, cumulative count). Once per `RPM_WIN` window the estimate is
/// the edges between the first and the last capture of the window divided by
/// the time between them; the last capture of a window is the first of the
/// next, so no edge interval is lost and a steady speed is measured exactly.
#[derive(Debug, Clone)]
pub struct HallRpm {
    /// Hall edges per wheel turn: 6 per electrical turn × pole pairs × gear ratio.
    edges_per_wheel_turn: f64,
    /// No edge for this long and the wheel counts as stopped (s).
    timeout_s: f64,
    /// Edge count seen at the previous tick.
    last_count: u64,
    /// The latest capture: (edge time s, cumulative edge count).
    last_capture: Option<(f64, u64)>,
    /// The capture the current window measures from.
    window_first: Option<(f64, u64)>,
    window_end: Option<SimTime>,
    rpm: f64,
}

impl HallRpm {
    /// An estimator for a motor with `pole_pairs` behind a `gear_ratio`
    /// (motor turns per wheel turn), reading 0 after `timeout` without an edge.
    pub fn new(pole_pairs: u32, gear_ratio: f64, timeout: SimDuration) -> Self {
        let edges = 6.0 * f64::from(pole_pairs.max(1)) * gear_ratio.abs();
        Self {
            edges_per_wheel_turn: if edges > 0.0 { edges } else { 6.0 },
            timeout_s: timeout.as_secs_f64(),
            last_count: 0,
            last_capture: None,
            window_first: None,
            window_end: None,
            rpm: 0.0,
        }
    }

    /// One loop pass: take the capture if an edge came, close the window if
    /// it is over, and return the wheel rpm (magnitude).
    pub fn tick(&mut self, now: SimTime, window: SimDuration, shaft: &ShaftReading) -> f64 {
        let now_s = now.as_secs_f64();
        if shaft.hall_edges != self.last_count && shaft.last_hall_edge_at.is_finite() {
            let capture = (shaft.last_hall_edge_at, shaft.hall_edges);
            self.window_first.get_or_insert(capture);
            self.last_capture = Some(capture);
        }
        self.last_count = shaft.hall_edges;

        let window_end = *self.window_end.get_or_insert(now + window);
        if now >= window_end {
            if let (Some((t0, n0)), Some((t1, n1))) = (self.window_first, self.last_capture)
                && n1 > n0
                && t1 > t0
            {
                let edges_per_s = (n1 - n0) as f64 / (t1 - t0);
                self.rpm = edges_per_s * 60.0 / self.edges_per_wheel_turn;
            }
            self.window_first = self.last_capture;
            self.window_end = Some(now + window);
        }

        match self.last_capture {
            Some((t, _)) if now_s - t <= self.timeout_s => {
                // While no edge comes the wheel turns slower than one edge in
                // the time since the last: a decelerating wheel reads lower at
                // once instead of holding the last window's value. At a steady
                // speed the time since the last edge is under one edge period,
                // so this never lowers the estimate.
                let since = now_s - t;
                if since > 0.0 {
                    let bound = 60.0 / (self.edges_per_wheel_turn * since);
                    self.rpm.min(bound)
                } else {
                    self.rpm
                }
            }
            _ => {
                // Stopped: forget the old captures so that the first edges after
                // a restart are not measured against an edge from before the stop.
                self.rpm = 0.0;
                self.last_capture = None;
                self.window_first = None;
                0.0
            }
        }
    }
}

/// How the light detector decides that the flag darkens the cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightDetectorConfig {
    /// Dark threshold at power-up (`VA0` `LDR_TH`, ADC counts): dark below it.
    pub threshold_counts: u16,
    /// Counts above the threshold the signal must climb back before the next
    /// dip counts, so noise around the threshold gives one edge, not several.
    pub hysteresis_counts: u16,
    /// Adaptive detector at power-up (`VD0` bit 0).
    pub adaptive: bool,
    /// Adaptive: a dip is a fall of this fraction of the tracked swing below the tracked maximum.
    pub adaptive_dip_fraction: f64,
    /// Adaptive: below this tracked swing (counts) there is no flag to see, only noise.
    pub adaptive_min_swing_counts: u16,
    /// Adaptive: time constant with which the tracked maximum and minimum forget old extremes.
    pub tracker_memory: SimDuration,
    /// No dip for this long and the wheel reads 0.
    pub no_dip_timeout: SimDuration,
}

impl LightDetectorConfig {
    /// The detector for a light sensor: threshold midway between its lit and
    /// shaded ADC counts, fixed-threshold mode.
    pub fn for_sensor(light: &plant::light::LightParams) -> Self {
        let lit = light.adc_counts_for(light.lit_volts());
        let shaded = light.adc_counts_for(light.shaded_volts());
        // Both are at most 65535, so their mean is too.
        let midway = ((u32::from(lit) + u32::from(shaded)) / 2) as u16;
        Self {
            threshold_counts: midway,
            // About 12 mV: six noise sigmas of the module's divider.
            hysteresis_counts: 10,
            adaptive: false,
            adaptive_dip_fraction: 0.2,
            // About 0.25 V, far above the noise, far below a flag's dip.
            adaptive_min_swing_counts: 200,
            tracker_memory: SimDuration::from_secs(2),
            no_dip_timeout: SimDuration::from_secs(2),
        }
    }
}

impl LightDetectorConfig {
    /// Volts per ADC count of `light`'s converter.
    fn volts_per_count(light: &plant::light::LightParams) -> f64 {
        light.adc_reference_volts / f64::from(1u32 << light.adc_bits.clamp(1, 16))
    }

    /// The detector in the lab's words: `fixed 2.36 V`, `adaptive (swing ≥ 0.244 V)`.
    pub fn describe(&self, light: &plant::light::LightParams) -> String {
        let lsb = Self::volts_per_count(light);
        if self.adaptive {
            let swing = f64::from(self.adaptive_min_swing_counts) * lsb;
            format!("adaptive (swing ≥ {swing:.3} V)")
        } else {
            let threshold = f64::from(self.threshold_counts) * lsb;
            format!("fixed {threshold:.2} V")
        }
    }

    /// The fastest wheel speed (rpm) at which this detector still sees the
    /// flag on the sensor `light`, by the formulas of `plant/src/light.rs`.
    /// A fixed threshold: where the dip stops reaching it. Adaptive: in
    /// steady running the trackers span the swing the detector sees, so what
    /// limits it is the smallest swing it accepts.
    pub fn max_rpm(&self, light: &plant::light::LightParams) -> f64 {
        let lsb = Self::volts_per_count(light);
        if self.adaptive {
            let swing = f64::from(self.adaptive_min_swing_counts) * lsb;
            plant::light::adaptive_dip_max_rpm(light, swing)
        } else {
            let threshold = f64::from(self.threshold_counts) * lsb;
            plant::light::fixed_threshold_max_rpm(light, threshold)
        }
    }
}

impl Default for LightDetectorConfig {
    /// The EV module's sensor ([`plant::light::LightParams::default`]): lit
    /// 4.005 V and shaded 0.717 V on a 12-bit 5 V ADC, threshold midway
    /// (1933 counts, 2.36 V).
    fn default() -> Self {
        Self::for_sensor(&plant::light::LightParams::default())
    }
}

/// Photoresistor speed estimator: the period between successive light-to-dark
/// edges of the sampled divider signal.
///
/// The edge time is the loop tick at which the sample first reads dark, so
/// the period is quantised to the loop period. A dip too short or too shallow
/// for the detector (the cell is slow: above
/// [`plant::light::fixed_threshold_max_rpm`] it never reaches the threshold)
/// is missed, and the estimate falls to 0 or to a sub-multiple of the speed.
/// Between dips it never reads faster than one turn in the time since the
/// last dip, so a slowing wheel reads slower at once.
#[derive(Debug, Clone)]
pub struct LightRpm {
    config: LightDetectorConfig,
    /// Fraction of the distance to a sample the trackers move per tick.
    tracker_step: f64,
    dark: bool,
    last_dip_at: Option<SimTime>,
    /// Tracked maximum and minimum (counts); `None` before the first sample.
    tracked: Option<(f64, f64)>,
    rpm: f64,
}

impl LightRpm {
    /// A detector sampled every `loop_period`.
    pub fn new(config: LightDetectorConfig, loop_period: SimDuration) -> Self {
        let memory = config.tracker_memory.as_secs_f64();
        let tracker_step = if memory > 0.0 {
            (loop_period.as_secs_f64() / memory).clamp(0.0, 1.0)
        } else {
            1.0
        };
        Self {
            config,
            tracker_step,
            dark: false,
            last_dip_at: None,
            tracked: None,
            rpm: 0.0,
        }
    }

    /// Whether the detector currently sees the flag (ED0 bit 3).
    pub fn dark(&self) -> bool {
        self.dark
    }

    /// One ADC sample at `now`; returns the wheel rpm.
    pub fn tick(&mut self, now: SimTime, counts: u16, threshold: u16, adaptive: bool) -> f64 {
        let x = f64::from(counts);
        let (high, low) = self.tracked.unwrap_or((x, x));
        let step = self.tracker_step;
        let high = if x > high {
            x
        } else {
            high + (x - high) * step
        };
        let low = if x < low { x } else { low + (x - low) * step };
        self.tracked = Some((high, low));

        let (enter_dark, leave_dark) = if adaptive {
            let swing = high - low;
            if swing < f64::from(self.config.adaptive_min_swing_counts) {
                (false, true)
            } else {
                let dip = self.config.adaptive_dip_fraction * swing;
                (x < high - dip, x > high - 0.5 * dip)
            }
        } else {
            let threshold = f64::from(threshold);
            (
                x < threshold,
                x >= threshold + f64::from(self.config.hysteresis_counts),
            )
        };

        if !self.dark && enter_dark {
            self.dark = true;
            if let Some(previous) = self.last_dip_at {
                let period = (now - previous).as_secs_f64();
                if period > 0.0 {
                    self.rpm = 60.0 / period;
                }
            }
            self.last_dip_at = Some(now);
        } else if self.dark && leave_dark {
            self.dark = false;
        }

        if let Some(previous) = self.last_dip_at
            && now - previous > self.config.no_dip_timeout
        {
            // The next dip only starts a new period: one from before the stop
            // would read as a crawl that never happened.
            self.last_dip_at = None;
            self.rpm = 0.0;
        }
        let Some(previous) = self.last_dip_at else {
            self.rpm = 0.0;
            return 0.0;
        };
        // No dip for longer than the last period: the wheel has slowed, and
        // turns at most once in the time since the last dip. Holding the last
        // period instead would read a stopping wheel as still turning until
        // the timeout, and a loop closed on RPM_L would stop the wheel dead.
        let since = (now - previous).as_secs_f64();
        if since > 0.0 {
            self.rpm.min(60.0 / since)
        } else {
            self.rpm
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reading(edges: u64, at: f64) -> ShaftReading {
        ShaftReading {
            hall_edges: edges,
            last_hall_edge_at: at,
            ..ShaftReading::default()
        }
    }

    #[test]
    fn hall_estimate_is_exact_for_a_steady_edge_rate() {
        // 24 edges per turn, 100 rpm: an edge every 25 ms, at 1.3 ms past each multiple.
        let mut hall = HallRpm::new(4, 1.0, SimDuration::from_millis(500));
        let window = SimDuration::from_millis(100);
        let mut rpm = 0.0;
        for ms in 0..1000u64 {
            let t = ms as f64 * 1e-3;
            let edges = ((t - 0.0013) / 0.025).floor().max(-1.0) as i64 + 1;
            let at = (edges - 1) as f64 * 0.025 + 0.0013;
            let edges = edges.max(0) as u64;
            let at = if edges == 0 { f64::NAN } else { at };
            rpm = hall.tick(
                SimTime::ZERO + SimDuration::from_millis(ms),
                window,
                &reading(edges, at),
            );
        }
        assert!((rpm - 100.0).abs() < 1e-6, "{rpm}");
    }

    #[test]
    fn hall_estimate_falls_to_zero_after_the_timeout() {
        let mut hall = HallRpm::new(1, 1.0, SimDuration::from_millis(200));
        let window = SimDuration::from_millis(10);
        let mut rpm = 0.0;
        // Six edges per turn at 1 turn/s, then nothing after t = 1 s.
        for ms in 0..1500u64 {
            let t = ms as f64 * 1e-3;
            let edges = ((t.min(1.0) * 6.0).floor()) as u64;
            let at = edges as f64 / 6.0;
            rpm = hall.tick(
                SimTime::ZERO + SimDuration::from_millis(ms),
                window,
                &reading(edges, at),
            );
            if ms == 999 {
                assert!((rpm - 60.0).abs() < 1e-6, "{rpm}");
            }
        }
        assert_eq!(rpm, 0.0);
    }

    #[test]
    fn light_period_between_dips() {
        let config = LightDetectorConfig::default();
        let mut light = LightRpm::new(config, SimDuration::from_millis(1));
        let mut rpm = 0.0;
        // 120 rpm: a 500 ms period with a 40 ms dark dip.
        for ms in 0..3000u64 {
            let dark = ms % 500 < 40;
            let counts = if dark { 600 } else { 3280 };
            rpm = light.tick(
                SimTime::ZERO + SimDuration::from_millis(ms),
                counts,
                config.threshold_counts,
                false,
            );
        }
        assert!((rpm - 120.0).abs() < 1e-9, "{rpm}");
        // The adaptive detector finds the same dips.
        let mut adaptive = LightRpm::new(config, SimDuration::from_millis(1));
        for ms in 0..3000u64 {
            let counts = if ms % 500 < 40 { 2500 } else { 3280 };
            rpm = adaptive.tick(
                SimTime::ZERO + SimDuration::from_millis(ms),
                counts,
                0,
                true,
            );
        }
        assert!((rpm - 120.0).abs() < 1e-9, "{rpm}");
        // Two seconds without a dip: 0.
        for ms in 3000..5100u64 {
            rpm = adaptive.tick(SimTime::ZERO + SimDuration::from_millis(ms), 3280, 0, true);
        }
        assert_eq!(rpm, 0.0);
    }

    #[test]
    fn a_slowing_wheel_reads_slower_between_dips() {
        let config = LightDetectorConfig::default();
        let mut light = LightRpm::new(config, SimDuration::from_millis(1));
        let at = |ms: u64| SimTime::ZERO + SimDuration::from_millis(ms);
        let mut tick = |ms: u64, dark: bool| {
            light.tick(
                at(ms),
                if dark { 600 } else { 3280 },
                config.threshold_counts,
                false,
            )
        };
        // Dips 500 ms apart (120 rpm), the last at 1000 ms; then the wheel stops.
        for ms in 0..=1000u64 {
            tick(ms, ms % 500 < 40);
        }
        // Within one period of the last dip, the last period stands...
        assert!((tick(1400, false) - 120.0).abs() < 1e-9);
        // ...past it, at most one turn in the time since the dip: 60 rpm at 1 s.
        assert!((tick(2000, false) - 60.0).abs() < 1e-9);
        assert!((tick(2500, false) - 40.0).abs() < 1e-9);
        // And 0 after the timeout, as before.
        assert_eq!(tick(3100, false), 0.0);
    }
}
