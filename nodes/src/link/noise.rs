//! Line noise: independent bit flips at a fixed bit-error rate.
//!
//! Drawing one random number per bit would cost eight draws per byte for an
//! event that, at the rates worth simulating (1e-6 … 1e-2), almost never
//! happens. Instead the gap to the next flipped bit is drawn from the geometric
//! distribution once per error, so a clean byte costs one comparison.

use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

/// Data bits per character that noise can flip. Start, parity and stop bits are
/// assumed received correctly: a flipped stop bit is a framing error the UART
/// would report, which the lab's firmware does not look at.
const DATA_BITS: u64 = 8;

/// A seeded source of bit flips, consumed byte by byte in delivery order.
#[derive(Debug, Clone)]
pub(crate) struct BitNoise {
    rng: Pcg64,
    /// `ln(1 - p)`, or `None` when `p` is 0 (no error ever) or 1 (every bit).
    ln_keep: Option<f64>,
    /// Every bit flips (`p == 1`).
    always: bool,
    /// Data bits still to pass before the next flipped one.
    gap: u64,
}

impl BitNoise {
    /// Noise flipping each bit with probability `rate` (0 ≤ rate ≤ 1, checked
    /// by the caller).
    pub(crate) fn new(rate: f64, seed: u64) -> Self {
        let always = rate >= 1.0;
        let ln_keep = (rate > 0.0 && !always).then(|| (-rate).ln_1p());
        let mut noise = BitNoise {
            rng: Pcg64::seed_from_u64(seed),
            ln_keep,
            always,
            gap: 0,
        };
        noise.gap = noise.draw_gap();
        noise
    }

    /// Clean bits before the next flip: geometric with success probability `p`.
    fn draw_gap(&mut self) -> u64 {
        if self.always {
            return 0;
        }
        let Some(ln_keep) = self.ln_keep else {
            return u64::MAX;
        };
        // 1 - U lies in (0, 1], so its log is finite and ≤ 0.
        let u = 1.0 - self.rng.random::<f64>();
        let gap = (u.ln() / ln_keep).floor();
        // `as` saturates: a gap beyond u64 means "never" anyway.
        gap as u64
    }

    /// The XOR mask of the data bits flipped in the next byte (0 if clean).
    pub(crate) fn next_byte_mask(&mut self) -> u8 {
        if self.gap >= DATA_BITS {
            self.gap -= DATA_BITS;
            return 0;
        }
        let mut mask = 0u8;
        let mut position = self.gap;
        while position < DATA_BITS {
            mask |= 1 << position;
            position = position.saturating_add(1).saturating_add(self.draw_gap());
        }
        self.gap = position - DATA_BITS;
        mask
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_rate_never_flips_and_one_flips_everything() {
        let mut clean = BitNoise::new(0.0, 7);
        assert!((0..10_000).all(|_| clean.next_byte_mask() == 0));
        let mut dirty = BitNoise::new(1.0, 7);
        assert!((0..100).all(|_| dirty.next_byte_mask() == 0xFF));
    }

    #[test]
    fn flipped_bit_count_matches_the_rate() {
        // 8e6 bits at p = 1e-2: mean 80 000 flips, sigma ≈ 281.
        let mut noise = BitNoise::new(1e-2, 42);
        let flips: u64 = (0..1_000_000)
            .map(|_| u64::from(noise.next_byte_mask().count_ones()))
            .sum();
        let mean = 8e6 * 1e-2;
        let sigma = (8e6_f64 * 1e-2 * (1.0 - 1e-2)).sqrt();
        assert!(
            (flips as f64 - mean).abs() < 5.0 * sigma,
            "{flips} flips, expected {mean} ± {sigma}"
        );
    }
}
