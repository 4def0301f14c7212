//! Tick lateness (actual − scheduled tick time) as an HDR histogram made
//! once: no allocation per tick, percentiles to the microsecond below 2 ms
//! (three significant digits: exact below 2048 µs, 0.1 % above).

use hdrhistogram::Histogram;
use serde::Serialize;

/// Lateness beyond this (µs) counts as this: a stall this long slips the
/// clock instead, and a wider range would only cost memory per session.
const HIGHEST_US: u64 = 100_000;

/// Lateness of a run of ticks.
#[derive(Debug, Clone)]
pub struct Lateness {
    /// Each tick's lateness in whole microseconds, rounded up, so a
    /// quantile is the upper edge of the microsecond it falls in.
    histogram: Histogram<u32>,
    ticks: u64,
    max_ns: u64,
    sum_ns: u128,
    /// Ticks more than one period late: the loop caught up a burst.
    pub overruns: u64,
    /// Times the clock slipped (the loop was further behind than it
    /// catches up), and by how much in all.
    slips: u64,
    slipped_ns: u64,
}

/// A summary of [`Lateness`], as printed and recorded.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct LatenessSummary {
    pub ticks: u64,
    pub p50_us: f64,
    pub p99_us: f64,
    pub p999_us: f64,
    pub max_us: f64,
    pub mean_us: f64,
    pub overruns: u64,
    /// Times the session's clock slipped, and the time lost in all (ms):
    /// the machine stopped the twin longer than it could catch up.
    pub slips: u64,
    pub slipped_ms: f64,
}

impl LatenessSummary {
    /// The real time the session lost, in words, if it lost any.
    pub fn slip_line(&self) -> Option<String> {
        (self.slips > 0).then(|| {
            format!(
                "real time lost: {:.0} ms in {} slip{} (the machine stopped the twin or was too \
                 busy; its clock slipped rather than run the lost time in a burst)",
                self.slipped_ms,
                self.slips,
                if self.slips == 1 { "" } else { "s" }
            )
        })
    }
}

impl Default for Lateness {
    fn default() -> Self {
        Self::new()
    }
}

impl Lateness {
    pub fn new() -> Self {
        Self {
            histogram: Histogram::new_with_bounds(1, HIGHEST_US, 3)
                .expect("constant bounds within hdrhistogram's limits"),
            ticks: 0,
            max_ns: 0,
            sum_ns: 0,
            overruns: 0,
            slips: 0,
            slipped_ns: 0,
        }
    }

    /// One tick, `late_ns` after its scheduled time.
    pub fn record(&mut self, late_ns: u64) {
        self.histogram.saturating_record(late_ns.div_ceil(1_000));
        self.ticks += 1;
        self.max_ns = self.max_ns.max(late_ns);
        self.sum_ns += u128::from(late_ns);
    }

    /// Forget everything (the per-second window).
    pub fn clear(&mut self) {
        self.histogram.reset();
        self.ticks = 0;
        self.max_ns = 0;
        self.sum_ns = 0;
        self.overruns = 0;
        self.slips = 0;
        self.slipped_ns = 0;
    }

    /// The clock slipped `count` times, by `ns` in all.
    pub fn slipped(&mut self, count: u64, ns: u64) {
        self.slips += count;
        self.slipped_ns = self.slipped_ns.saturating_add(ns);
    }

    pub fn ticks(&self) -> u64 {
        self.ticks
    }

    /// The lateness (µs, the upper edge of its bucket) below which `q` of
    /// the ticks fall.
    pub fn quantile_us(&self, q: f64) -> f64 {
        if self.ticks == 0 {
            return 0.0;
        }
        let upper = self.histogram.value_at_quantile(q) as f64;
        upper.min(self.max_ns as f64 / 1e3)
    }

    pub fn summary(&self) -> LatenessSummary {
        LatenessSummary {
            ticks: self.ticks,
            p50_us: self.quantile_us(0.5),
            p99_us: self.quantile_us(0.99),
            p999_us: self.quantile_us(0.999),
            max_us: self.max_ns as f64 / 1e3,
            mean_us: if self.ticks == 0 {
                0.0
            } else {
                self.sum_ns as f64 / self.ticks as f64 / 1e3
            },
            overruns: self.overruns,
            slips: self.slips,
            // To the microsecond: no floating-point noise in the file.
            slipped_ms: (self.slipped_ns as f64 / 1e3).round() / 1e3,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_come_from_the_histogram() {
        let mut l = Lateness::new();
        for i in 0..1000u64 {
            l.record(i * 1_000 + 500); // 0.5 µs .. 999.5 µs
        }
        let s = l.summary();
        assert_eq!(s.ticks, 1000);
        assert_eq!(s.p50_us, 500.0);
        assert_eq!(s.p99_us, 990.0);
        assert!((s.max_us - 999.5).abs() < 1e-9);
        assert!((s.mean_us - 500.0).abs() < 1e-9);
        l.record(50_000_000);
        assert_eq!(l.summary().max_us, 50_000.0);
        // Above 2048 µs, to 0.1 %: the upper edge of a 2 µs bucket here.
        let mut far = Lateness::new();
        far.record(3_000_500);
        far.record(3_001_000);
        assert_eq!(far.summary().p50_us, 3_001.0);
        assert_eq!(far.summary().p99_us, 3_001.0);
        // Beyond the histogram's range a quantile is still no more than the max.
        far.record(400_000_000);
        far.record(400_000_000);
        assert_eq!(far.summary().p99_us, 100_031.0);
        l.slipped(1, 250_000_400);
        l.slipped(1, 62_000_000);
        assert_eq!((l.summary().slips, l.summary().slipped_ms), (2, 312.0));
        l.clear();
        assert_eq!(l.summary(), LatenessSummary::default());
    }
}
