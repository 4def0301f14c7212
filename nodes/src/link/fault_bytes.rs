//! What a fault does to a reply's bytes, shared by the simulated slaves
//! ([`super::FaultyNode`]) and `twin serve`'s links, so a master sees the
//! same bytes from either: a reply re-addressed as another slave's (its
//! check made good again, so only the id is wrong), junk bytes next to a
//! reply, and where a reply is split in two.

use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

use super::CheckKind;
use protocols::crc::crc16_modbus;

/// Most junk bytes sent with one reply.
pub const MAX_JUNK: usize = 32;

const HEX_UPPER: &[u8; 16] = b"0123456789ABCDEF";

/// The highest slave id the protocol can carry: MEB's two decimal digits,
/// Modbus's 247 (the 8-byte Modbus keeps the standard's range).
pub fn max_id(kind: CheckKind) -> u8 {
    match kind {
        CheckKind::Meb => 99,
        CheckKind::Modbus8 | CheckKind::ModbusRtu => 247,
    }
}

/// The id `frame` carries, if it is shaped like `kind`.
pub fn frame_id(kind: CheckKind, frame: &[u8]) -> Option<u8> {
    match kind {
        CheckKind::Meb => match frame {
            [b'@', t, u, ..] if t.is_ascii_digit() && u.is_ascii_digit() => {
                Some((t - b'0') * 10 + (u - b'0'))
            }
            _ => None,
        },
        CheckKind::Modbus8 | CheckKind::ModbusRtu => frame.first().copied(),
    }
}

/// The id a wrong-id reply carries when none is chosen: the slave's own
/// plus one, or minus one at the top of the range.
pub fn other_id(kind: CheckKind, own: u8) -> u8 {
    if own >= max_id(kind) {
        own.saturating_sub(1)
    } else {
        own + 1
    }
}

/// Rewrites the id of `frame` as `id` and makes its check good again: a
/// well-formed reply from another slave. False (the frame left as it was)
/// if the frame is not shaped like `kind` or `id` does not fit it.
pub fn set_id(kind: CheckKind, frame: &mut [u8], id: u8) -> bool {
    if id > max_id(kind) {
        return false;
    }
    match kind {
        CheckKind::Meb => {
            let body = if frame.ends_with(b"*\r\n") {
                frame.len().saturating_sub(3)
            } else if frame.ends_with(b"*\n") {
                frame.len().saturating_sub(2)
            } else {
                return false;
            };
            // `@`, ID, CMD, ADDR, CNT, then the two FCS characters.
            if body < 11 || frame_id(kind, frame).is_none() {
                return false;
            }
            frame[1] = b'0' + id / 10;
            frame[2] = b'0' + id % 10;
            let fcs_at = body - 2;
            let fcs = frame[..fcs_at].iter().fold(0, |acc, b| acc ^ b);
            frame[fcs_at] = HEX_UPPER[usize::from(fcs >> 4)];
            frame[fcs_at + 1] = HEX_UPPER[usize::from(fcs & 0x0F)];
            true
        }
        CheckKind::Modbus8 => {
            if frame.len() != 8 {
                return false;
            }
            frame[0] = id;
            let crc = crc16_modbus(&frame[..6]).to_be_bytes();
            frame[6..].copy_from_slice(&crc);
            true
        }
        CheckKind::ModbusRtu => {
            let len = frame.len();
            if len < 4 {
                return false;
            }
            frame[0] = id;
            let [l, h] = crc16_modbus(&frame[..len - 2]).to_le_bytes();
            frame[len - 2] = l;
            frame[len - 1] = h;
            true
        }
    }
}

/// Where a reply of `len` bytes is split: after `first` bytes (kept to at
/// least one byte on each side), or in its middle. `None` for a reply too
/// short to split.
pub fn split_point(len: usize, first: Option<u16>) -> Option<usize> {
    (len >= 2).then(|| first.map_or(len / 2, usize::from).clamp(1, len - 1))
}

/// The bytes of a junk fault: chosen ones, or a count drawn at random (from
/// a seeded generator: a scenario's seed in the simulation).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JunkBytes {
    /// These bytes (the first `len` of `bytes`).
    Given { bytes: [u8; MAX_JUNK], len: u8 },
    /// This many bytes, drawn afresh for every reply.
    Random(u8),
}

impl JunkBytes {
    /// The bytes given, or `None` if there are none or more than [`MAX_JUNK`].
    pub fn given(given: &[u8]) -> Option<Self> {
        let len = u8::try_from(given.len())
            .ok()
            .filter(|&n| n > 0 && usize::from(n) <= MAX_JUNK)?;
        let mut bytes = [0; MAX_JUNK];
        bytes[..given.len()].copy_from_slice(given);
        Some(JunkBytes::Given { bytes, len })
    }

    /// `count` random bytes, or `None` if `count` is 0 or more than [`MAX_JUNK`].
    pub fn random(count: usize) -> Option<Self> {
        let count = u8::try_from(count)
            .ok()
            .filter(|&n| n > 0 && usize::from(n) <= MAX_JUNK)?;
        Some(JunkBytes::Random(count))
    }

    /// How many bytes go out with each reply.
    pub fn len(&self) -> usize {
        match *self {
            JunkBytes::Given { len, .. } => usize::from(len),
            JunkBytes::Random(n) => usize::from(n),
        }
    }

    /// Never true: there is always at least one byte.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Whether junk goes out just before a reply, or just after it (so it lies
/// between the reply and the master's next request).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JunkPlace {
    Before,
    After,
}

/// Junk bytes sent with every reply, in the same write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Junk {
    pub bytes: JunkBytes,
    pub place: JunkPlace,
}

impl std::fmt::Display for Junk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.bytes {
            JunkBytes::Given { bytes, len } => {
                f.write_str("junk")?;
                for b in &bytes[..usize::from(len)] {
                    write!(f, " {b:02x}")?;
                }
            }
            JunkBytes::Random(n) => write!(f, "junk of {n} random byte(s)")?,
        }
        match self.place {
            JunkPlace::Before => f.write_str(" before each reply"),
            JunkPlace::After => f.write_str(" after each reply"),
        }
    }
}

/// Writes junk next to replies; random junk comes from its seeded generator.
#[derive(Debug, Clone)]
pub struct JunkSource {
    rng: Pcg64,
}

/// Seeded with 0: `twin serve`'s links, where nothing asks for a seed.
impl Default for JunkSource {
    fn default() -> Self {
        JunkSource::new(0)
    }
}

impl JunkSource {
    /// A source whose random bytes follow from `seed`.
    pub fn new(seed: u64) -> Self {
        JunkSource {
            rng: Pcg64::seed_from_u64(seed),
        }
    }

    /// Puts `junk` before or after the reply held in the first `len` bytes
    /// of `buf`, in place; returns the new length. Junk that would not fit
    /// `buf` is cut short.
    pub fn apply(&mut self, junk: &Junk, buf: &mut [u8], len: usize) -> usize {
        let len = len.min(buf.len());
        let n = junk.bytes.len().min(buf.len() - len);
        let at = match junk.place {
            JunkPlace::Before => {
                buf.copy_within(..len, n);
                0
            }
            JunkPlace::After => len,
        };
        let slot = &mut buf[at..at + n];
        match junk.bytes {
            JunkBytes::Given { bytes, .. } => slot.copy_from_slice(&bytes[..n]),
            JunkBytes::Random(_) => slot.iter_mut().for_each(|b| *b = self.rng.random()),
        }
        len + n
    }
}
