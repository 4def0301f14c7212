//! Shaft-position sensors: the BLDC motor's three hall sensors and the
//! quadrature encoder, as the firmware's input-capture and counter units see
//! them.
//!
//! Both are functions of the motor shaft angle. The plant moves the angle
//! linearly across each sub-step, so the instant of every edge is found by
//! interpolation, exactly as an input-capture unit would timestamp it. The
//! firmware gets cumulative counts plus the time of the last edge, which is all
//! that either speed method (edge period or counts per window) needs.

use std::f64::consts::TAU;

/// Hall code for each 60° electrical sector, A in bit 0, B bit 1, C bit 2:
/// the standard 120°-spaced sequence 001, 011, 010, 110, 100, 101.
const HALL_SEQUENCE: [u8; 6] = [0b001, 0b011, 0b010, 0b110, 0b100, 0b101];

/// Edge counter for a sensor whose output changes every `1/edges_per_turn` of
/// a shaft turn.
#[derive(Debug, Clone)]
struct EdgeCounter {
    edges_per_turn: f64,
    /// Index of the sector the shaft is in (floor of angle × edges per turn / 2π).
    sector: i64,
    edges: u64,
    net_edges: i64,
    last_edge_at: f64,
}

impl EdgeCounter {
    fn new(edges_per_turn: u32, angle: f64) -> Self {
        let edges_per_turn = f64::from(edges_per_turn.max(1));
        Self {
            edges_per_turn,
            sector: (angle * edges_per_turn / TAU).floor() as i64,
            edges: 0,
            net_edges: 0,
            last_edge_at: f64::NAN,
        }
    }

    /// Shaft moved linearly from `a0` at `t0` to `a1` at `t0 + h`.
    fn advance(&mut self, t0: f64, h: f64, a0: f64, a1: f64) {
        let sector = (a1 * self.edges_per_turn / TAU).floor() as i64;
        // Saturating: a runaway shaft (parameters far outside a bench's)
        // gives meaningless counts, never an overflow.
        let crossed = sector.saturating_sub(self.sector);
        if crossed == 0 {
            return;
        }
        // The last boundary crossed: moving up it is the new sector's lower
        // edge, moving down the old sector's lower edge.
        let boundary = if crossed > 0 {
            sector
        } else {
            sector.saturating_add(1)
        };
        let boundary_angle = boundary as f64 * TAU / self.edges_per_turn;
        let span = a1 - a0;
        let frac = if span != 0.0 {
            ((boundary_angle - a0) / span).clamp(0.0, 1.0)
        } else {
            1.0
        };
        self.last_edge_at = t0 + frac * h;
        self.edges = self.edges.saturating_add(crossed.unsigned_abs());
        self.net_edges = self.net_edges.saturating_add(crossed);
        self.sector = sector;
    }
}

/// The motor's hall sensors and encoder.
#[derive(Debug, Clone)]
pub struct ShaftSensors {
    hall: EdgeCounter,
    /// Counts quadrature states: four per pulse (A rises, B rises, A falls, B falls).
    encoder: EdgeCounter,
}

/// What the shaft sensors show the firmware.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct ShaftReading {
    /// Hall code: bit 0 A, bit 1 B, bit 2 C.
    pub hall: u8,
    /// Hall edges seen since power-up (all three sensors, both directions).
    pub hall_edges: u64,
    /// Time of the latest hall edge (s), NaN before the first.
    pub last_hall_edge_at: f64,
    /// Encoder channel A level and channel B level (B lags A by 90° clockwise).
    pub encoder_a: bool,
    pub encoder_b: bool,
    /// Rising edges of channel A, counted down while B is high (turning
    /// counter-clockwise), as the Controller_network motor Nano's firmware counts
    /// them.
    pub encoder_count: i64,
    /// Time of the latest edge on either encoder channel (s), NaN before the first.
    pub last_encoder_edge_at: f64,
}

impl ShaftSensors {
    pub fn new(pole_pairs: u32, encoder_pulses_per_turn: u32, shaft_angle: f64) -> Self {
        Self {
            hall: EdgeCounter::new(6 * pole_pairs, shaft_angle),
            encoder: EdgeCounter::new(4 * encoder_pulses_per_turn, shaft_angle),
        }
    }

    /// The shaft turned linearly from `a0` (at `t0`) to `a1` (at `t0 + h`).
    pub fn advance(&mut self, t0: f64, h: f64, a0: f64, a1: f64) {
        self.hall.advance(t0, h, a0, a1);
        self.encoder.advance(t0, h, a0, a1);
    }

    pub fn reading(&self) -> ShaftReading {
        let hall = HALL_SEQUENCE[self.hall.sector.rem_euclid(6) as usize];
        // Quarter-period index: A is high in quarters 0 and 1, B (lagging A by
        // 90° when turning clockwise) in quarters 1 and 2.
        let quarter = self.encoder.sector.rem_euclid(4);
        let encoder_a = quarter < 2;
        let encoder_b = (1..=2).contains(&quarter);
        ShaftReading {
            hall,
            hall_edges: self.hall.edges,
            last_hall_edge_at: self.hall.last_edge_at,
            encoder_a,
            encoder_b,
            // Every fourth quadrature state change is a rising edge of A.
            encoder_count: self.encoder.net_edges / 4,
            last_encoder_edge_at: self.encoder.last_edge_at,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn six_edges_per_pole_pair_per_turn_with_interpolated_times() {
        let mut s = ShaftSensors::new(4, 7, 0.0);
        // One turn in 1 s, stepped at 7 ms so edges fall inside steps.
        let omega = TAU;
        let h = 0.007;
        let mut t = 0.0;
        while t < 1.0 - 1e-12 {
            s.advance(t, h, omega * t, omega * (t + h));
            t += h;
        }
        let r = s.reading();
        assert_eq!(r.hall_edges, 24);
        // The 24th edge is at exactly one turn.
        assert!(
            (r.last_hall_edge_at - 1.0).abs() < 1e-9,
            "{}",
            r.last_hall_edge_at
        );
        assert_eq!(r.encoder_count, 7);
    }

    #[test]
    fn hall_sequence_changes_one_bit_per_edge() {
        for w in 0..6 {
            let diff = HALL_SEQUENCE[w] ^ HALL_SEQUENCE[(w + 1) % 6];
            assert_eq!(diff.count_ones(), 1);
        }
    }

    #[test]
    fn reverse_rotation_counts_encoder_down() {
        let mut s = ShaftSensors::new(1, 7, 0.0);
        s.advance(0.0, 1.0, 0.0, -2.0 * TAU);
        assert_eq!(s.reading().encoder_count, -14);
        assert_eq!(s.reading().hall_edges, 12);
    }
}
