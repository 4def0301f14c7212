//! Simulated time, as every node and codec sees it.
//!
//! Nodes never read a clock: the engine hands them `now`. One tick is 1/72 GHz,
//! chosen so that the bit time of every standard baud rate up to 921 600
//! (2¹²·3²·5² Hz) and the period of a 150 MHz capture counter (2⁶·3·5⁸ Hz) are
//! whole numbers of ticks: 72·10⁹ = 2¹²·3²·5⁹. A `u64` of ticks lasts 8 years.

use core::ops::{Add, AddAssign, Sub};

/// Ticks per second.
pub const TICKS_PER_SECOND: u64 = 72_000_000_000;

/// A point in simulated time, in ticks since the start of the run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SimTime(pub u64);

/// A span of simulated time, in ticks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SimDuration(pub u64);

impl SimTime {
    pub const ZERO: SimTime = SimTime(0);

    /// Seconds since the start of the run (for display and for the plant).
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 / TICKS_PER_SECOND as f64
    }

    /// Time elapsed since `earlier`, zero if `earlier` is later.
    pub fn saturating_since(self, earlier: SimTime) -> SimDuration {
        SimDuration(self.0.saturating_sub(earlier.0))
    }
}

impl SimDuration {
    pub const ZERO: SimDuration = SimDuration(0);

    pub const fn from_secs(s: u64) -> Self {
        SimDuration(s * TICKS_PER_SECOND)
    }
    pub const fn from_millis(ms: u64) -> Self {
        SimDuration(ms * (TICKS_PER_SECOND / 1_000))
    }
    pub const fn from_micros(us: u64) -> Self {
        SimDuration(us * (TICKS_PER_SECOND / 1_000_000))
    }
    pub const fn from_nanos(ns: u64) -> Self {
        SimDuration(ns * (TICKS_PER_SECOND / 1_000_000_000))
    }
    /// The nearest whole tick to `s` seconds (negative and NaN give zero).
    pub fn from_secs_f64(s: f64) -> Self {
        SimDuration((s * TICKS_PER_SECOND as f64).round().max(0.0) as u64)
    }
    /// The duration of `bits` bit times at `baud`; exact when `baud` divides 72 GHz.
    pub const fn bit_times(bits: u64, baud: u32) -> Self {
        SimDuration(bits * TICKS_PER_SECOND / baud as u64)
    }
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 / TICKS_PER_SECOND as f64
    }
}

impl Add<SimDuration> for SimTime {
    type Output = SimTime;
    fn add(self, d: SimDuration) -> SimTime {
        SimTime(self.0.saturating_add(d.0))
    }
}

impl AddAssign<SimDuration> for SimTime {
    fn add_assign(&mut self, d: SimDuration) {
        self.0 = self.0.saturating_add(d.0);
    }
}

impl Sub<SimTime> for SimTime {
    type Output = SimDuration;
    /// Saturates at zero: time never runs backwards for a node.
    fn sub(self, earlier: SimTime) -> SimDuration {
        self.saturating_since(earlier)
    }
}

impl Add for SimDuration {
    type Output = SimDuration;
    fn add(self, d: SimDuration) -> SimDuration {
        SimDuration(self.0.saturating_add(d.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bit_times_are_exact_for_lab_baud_rates() {
        for baud in [
            9600u32, 19200, 38400, 57600, 115200, 230400, 460800, 921600, 1_000_000,
        ] {
            assert_eq!(TICKS_PER_SECOND % baud as u64, 0, "{baud} baud");
        }
        assert_eq!(TICKS_PER_SECOND % 150_000_000, 0);
        // One 8N1 byte at 115200 baud lasts 86.805… µs.
        let byte = SimDuration::bit_times(10, 115_200);
        assert_eq!(byte.0 * 115_200, 10 * TICKS_PER_SECOND);
    }
}
