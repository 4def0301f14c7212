//! PWM-capture symbols (`docs/protocols/pwmcap.md`): values sent as pulse widths.
//!
//! The sender's PWM timer makes a pulse whose ON width, in counter ticks, carries
//! the value; the receiver's capture unit measures it back. This module is the
//! coding only — value ↔ width, frames ↔ width sequences (a checked view over
//! captured widths, [`PwmFrame`], and a value, [`PwmRepr`]), and the frame times of
//! the paper's Table 2; the line (RC low-pass, comparator, noise) is modelled
//! elsewhere.
//!
//! The coding, in counter ticks:
//! - a value of `b` data bits plus `d` dummy bits spans `C_max = 2^(b+d)` ticks;
//! - every frame opens with a start symbol of width `S`;
//! - a data symbol's ON width is `S + (value << d)`, its period `S + C_max`;
//! - the receiver subtracts the start width it *measured*, so a delay the line adds
//!   to every pulse cancels, then drops the `d` dummy bits with rounding, so noise
//!   under half a dummy step cancels too.
//!
//! No function here panics or allocates, whatever the widths captured.

use crate::time::{SimDuration, TICKS_PER_SECOND};

use super::words::FixedWords;
use core::fmt;

/// The most data symbols a broadcast or designated frame carries in the twin.
pub const PWM_MAX_DATA: usize = 16;
/// The most symbols of any frame, start symbol included.
pub const PWM_MAX_SYMBOLS: usize = 2 + PWM_MAX_DATA;

/// The data values of one frame.
pub type PwmData = FixedWords<PWM_MAX_DATA>;

/// Why a value, a width or a frame cannot be coded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, thiserror::Error)]
pub enum PwmError {
    /// The coding's parameters are out of the supported range (see [`PwmCoding::new`]).
    #[error("PWM coding parameters out of range")]
    InvalidCoding,
    /// A value does not fit its field (the data bits, or a 4-bit nibble of the status).
    #[error("value {value} above the field's maximum {max}")]
    ValueOutOfRange {
        /// The value given.
        value: u16,
        /// The largest the field holds.
        max: u16,
    },
    /// A captured width is shorter than the measured start width by more than the rounding.
    #[error("captured width {width} below the start width {start}")]
    WidthBelowStart {
        /// The captured width, in ticks.
        width: u32,
        /// The start width measured in the same frame.
        start: u32,
    },
    /// A captured width is longer than the largest value allows.
    #[error("captured width {width} above the range for start width {start}")]
    WidthAboveRange {
        /// The captured width, in ticks.
        width: u32,
        /// The start width measured in the same frame.
        start: u32,
    },
    /// The output slice is shorter than the frame.
    #[error("output too small: the frame needs {needed} symbols")]
    BufferTooSmall {
        /// Symbols in the frame, start included.
        needed: usize,
    },
    /// The number of captured symbols does not fit the frame kind.
    #[error("{got} symbols do not make a {kind} frame")]
    SymbolCount {
        /// The frame kind expected.
        kind: PwmFrameKind,
        /// Symbols captured, start included.
        got: usize,
    },
    /// A status or function code symbol is wider than 8 bits.
    #[error("symbol value {0} does not fit 8 bits")]
    NotAByte(u16),
    /// The status' command-type nibble names no command type.
    #[error("unknown command type {0}")]
    UnknownCommandType(u8),
}

/// The counter clock and the bit layout of a symbol.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PwmCoding {
    clock_hz: u32,
    data_bits: u8,
    dummy_bits: u8,
    start_ticks: u32,
}

impl PwmCoding {
    /// The paper's coding: 150 MHz counter, 8 data + 2 dummy bits (1024 ticks),
    /// and Fig. 10's 200-tick start symbol.
    pub const PAPER: PwmCoding = PwmCoding {
        clock_hz: 150_000_000,
        data_bits: 8,
        dummy_bits: 2,
        start_ticks: 200,
    };

    /// Table 2's accounting: 150 MHz, bare 8-bit symbols of 256 ticks, a 100-tick start.
    pub const TABLE2: PwmCoding = PwmCoding {
        clock_hz: 150_000_000,
        data_bits: 8,
        dummy_bits: 0,
        start_ticks: 100,
    };

    /// A coding with a `clock_hz` counter, `data_bits` (1–16) of value,
    /// `dummy_bits` below them (at most 24 bits in all) and a start symbol of
    /// `start_ticks` (at least 1).
    pub const fn new(
        clock_hz: u32,
        data_bits: u8,
        dummy_bits: u8,
        start_ticks: u32,
    ) -> Result<Self, PwmError> {
        let total_bits = data_bits as u32 + dummy_bits as u32;
        // 24 bits keep every width and period far inside a u32.
        if clock_hz == 0 || data_bits == 0 || data_bits > 16 || total_bits > 24 {
            return Err(PwmError::InvalidCoding);
        }
        if start_ticks == 0 || start_ticks > u32::MAX - (1 << 24) {
            return Err(PwmError::InvalidCoding);
        }
        Ok(PwmCoding {
            clock_hz,
            data_bits,
            dummy_bits,
            start_ticks,
        })
    }

    /// The counter clock, in hertz.
    pub const fn clock_hz(&self) -> u32 {
        self.clock_hz
    }

    /// Bits of value per symbol.
    pub const fn data_bits(&self) -> u8 {
        self.data_bits
    }

    /// Low bits the receiver drops to cancel noise.
    pub const fn dummy_bits(&self) -> u8 {
        self.dummy_bits
    }

    /// The start symbol's ON width, in ticks.
    pub const fn start_ticks(&self) -> u32 {
        self.start_ticks
    }

    /// `C_max = 2^(b+d)`: the ticks a value spans (paper eq. 5).
    pub const fn c_max(&self) -> u32 {
        1 << (self.data_bits + self.dummy_bits)
    }

    /// The largest value a symbol carries, `2^b − 1`.
    pub const fn max_value(&self) -> u16 {
        ((1u32 << self.data_bits) - 1) as u16
    }

    /// The period of every symbol in the twin, start included: `S + C_max` ticks.
    pub const fn symbol_period_ticks(&self) -> u32 {
        self.start_ticks + self.c_max()
    }

    /// The ON width that carries `value`: `S + (value << d)` ticks.
    pub const fn encode_width(&self, value: u16) -> Result<u32, PwmError> {
        if value > self.max_value() {
            return Err(PwmError::ValueOutOfRange {
                value,
                max: self.max_value(),
            });
        }
        Ok(self.start_ticks + ((value as u32) << self.dummy_bits))
    }

    /// The value carried by a captured `width`, given the start width measured
    /// in the same frame. The dummy bits are dropped with rounding to nearest
    /// (a tie rounds up), so any error in `[−2^(d−1), 2^(d−1))` ticks cancels.
    pub const fn decode_width(&self, width: u32, measured_start: u32) -> Result<u16, PwmError> {
        let half_step = (1i64 << self.dummy_bits) >> 1;
        let rounded = width as i64 - measured_start as i64 + half_step;
        if rounded < 0 {
            return Err(PwmError::WidthBelowStart {
                width,
                start: measured_start,
            });
        }
        let value = rounded >> self.dummy_bits;
        if value > self.max_value() as i64 {
            return Err(PwmError::WidthAboveRange {
                width,
                start: measured_start,
            });
        }
        Ok(value as u16)
    }

    /// `ticks` of the counter as simulated time (exact when the clock divides
    /// 72 GHz, as 150 MHz does: 480 simulation ticks per counter tick).
    pub const fn ticks_to_duration(&self, ticks: u64) -> SimDuration {
        let clock = self.clock_hz as u128;
        let sim_ticks = (ticks as u128 * TICKS_PER_SECOND as u128 + clock / 2) / clock;
        SimDuration(if sim_ticks > u64::MAX as u128 {
            u64::MAX
        } else {
            sim_ticks as u64
        })
    }

    /// Table 2's frame of `symbols` bare symbols of `C_max` ticks each, no start symbol.
    pub const fn table2_bare_ticks(&self, symbols: u32) -> u64 {
        symbols as u64 * self.c_max() as u64
    }

    /// Table 2's frame of `symbols` bare symbols plus one start symbol of `S` ticks.
    pub const fn table2_with_start_ticks(&self, symbols: u32) -> u64 {
        self.table2_bare_ticks(symbols) + self.start_ticks as u64
    }

    /// The twin's own frame time for `symbols` symbols, start included: every
    /// symbol takes a full period of `S + C_max` ticks.
    pub const fn frame_ticks(&self, symbols: u32) -> u64 {
        symbols as u64 * self.symbol_period_ticks() as u64
    }
}

/// The kind of command a status symbol's low nibble classifies (paper: I, R, P, V).
/// The nibble codes are the twin's choice; the paper does not give them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PwmCommandType {
    /// Current reference (I).
    Current = 0,
    /// Resistance reference (R).
    Resistance = 1,
    /// Power reference (P).
    Power = 2,
    /// Voltage reference (V).
    Voltage = 3,
}

impl PwmCommandType {
    /// The type coded by a nibble, or `None` for the unused codes 4–15.
    pub const fn from_nibble(nibble: u8) -> Option<Self> {
        Some(match nibble {
            0 => PwmCommandType::Current,
            1 => PwmCommandType::Resistance,
            2 => PwmCommandType::Power,
            3 => PwmCommandType::Voltage,
            _ => return None,
        })
    }
}

/// A status symbol: upper 4 bits `high`, lower 4 bits the command type. In the
/// broadcast and experiment frames `high` is the operation status (run/stop…);
/// in the designated frame it is the slave id (so 16 slaves at most).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PwmStatus {
    /// Upper nibble, 0–15.
    pub high: u8,
    /// Lower nibble.
    pub command: PwmCommandType,
}

impl PwmStatus {
    const fn to_symbol(self) -> Result<u16, PwmError> {
        if self.high > 0x0F {
            return Err(PwmError::ValueOutOfRange {
                value: self.high as u16,
                max: 0x0F,
            });
        }
        Ok(((self.high as u16) << 4) | self.command as u16)
    }

    const fn from_symbol(symbol: u16) -> Result<Self, PwmError> {
        if symbol > 0xFF {
            return Err(PwmError::NotAByte(symbol));
        }
        let nibble = (symbol & 0x0F) as u8;
        match PwmCommandType::from_nibble(nibble) {
            Some(command) => Ok(PwmStatus {
                high: (symbol >> 4) as u8,
                command,
            }),
            None => Err(PwmError::UnknownCommandType(nibble)),
        }
    }
}

/// Which layout a receiver expects; the widths alone do not say.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PwmFrameKind {
    /// Start, status, data…: the same reference for every slave.
    Broadcast,
    /// Start, status with the slave id, data… for that slave.
    Designated,
    /// The experiment frame (paper Fig. 15): start, function code, status, reference 1, reference 2.
    Experiment,
}

impl fmt::Display for PwmFrameKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            PwmFrameKind::Broadcast => "broadcast",
            PwmFrameKind::Designated => "designated",
            PwmFrameKind::Experiment => "experiment",
        })
    }
}

/// A checked view over the ON widths a receiver captured for one frame, start
/// symbol first.
///
/// Widths do not say which layout they carry, so the receiver names the
/// [`PwmFrameKind`] it expects and the [`PwmCoding`] it listens with.
/// [`PwmFrame::new_checked`] checks the symbol count and decodes every symbol
/// once, so each accessor reads a well-formed frame; the accessors decode the
/// symbols they read again, against the start width measured in this frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PwmFrame<T: AsRef<[u32]>> {
    widths: T,
    kind: PwmFrameKind,
    coding: PwmCoding,
}

impl<T: AsRef<[u32]>> PwmFrame<T> {
    /// Checks `widths` as one whole frame of `kind` coded with `coding`: the
    /// number of symbols, then every symbol's value (its width within the
    /// coding's range, the status' command type, a function code of 8 bits).
    pub fn new_checked(
        widths: T,
        kind: PwmFrameKind,
        coding: &PwmCoding,
    ) -> Result<Self, PwmError> {
        check(widths.as_ref(), kind, coding)?;
        Ok(PwmFrame {
            widths,
            kind,
            coding: *coding,
        })
    }

    /// The layout the frame was checked against.
    pub fn kind(&self) -> PwmFrameKind {
        self.kind
    }

    /// The start symbol's width as measured: every other symbol is read against it.
    pub fn start_width(&self) -> u32 {
        self.widths.as_ref().first().copied().unwrap_or(0)
    }

    /// The status symbol (the second symbol of a broadcast or designated frame,
    /// the third of an experiment frame).
    pub fn status(&self) -> PwmStatus {
        let at = match self.kind {
            PwmFrameKind::Experiment => 2,
            PwmFrameKind::Broadcast | PwmFrameKind::Designated => 1,
        };
        PwmStatus::from_symbol(self.value(at)).unwrap_or(PwmStatus {
            high: 0,
            command: PwmCommandType::Current,
        })
    }

    /// The data values of a broadcast or designated frame; none in an experiment frame.
    pub fn data(&self) -> PwmData {
        let mut data = PwmData::new();
        if self.kind != PwmFrameKind::Experiment {
            for at in 2..self.widths.as_ref().len() {
                // The check bounded the count by PWM_MAX_DATA, so every value fits.
                let _ = data.push(self.value(at));
            }
        }
        data
    }

    /// The function code of an experiment frame.
    pub fn function_code(&self) -> Option<u8> {
        (self.kind == PwmFrameKind::Experiment).then(|| u8::try_from(self.value(1)).unwrap_or(0))
    }

    /// The two control references of an experiment frame.
    pub fn references(&self) -> Option<(u16, u16)> {
        (self.kind == PwmFrameKind::Experiment).then(|| (self.value(3), self.value(4)))
    }

    /// The widths, as captured.
    pub fn as_widths(&self) -> &[u32] {
        self.widths.as_ref()
    }

    /// Gives the widths back.
    pub fn into_inner(self) -> T {
        self.widths
    }

    /// The value of symbol `at` (1 is the first after the start); 0 where the
    /// check would have failed, which it did not.
    fn value(&self, at: usize) -> u16 {
        let width = self.widths.as_ref().get(at).copied().unwrap_or(0);
        self.coding
            .decode_width(width, self.start_width())
            .unwrap_or(0)
    }
}

/// Checks captured widths as a frame of `kind`, as [`PwmFrame::new_checked`] says.
fn check(widths: &[u32], kind: PwmFrameKind, coding: &PwmCoding) -> Result<(), PwmError> {
    let count_error = PwmError::SymbolCount {
        kind,
        got: widths.len(),
    };
    let Some((&start, symbols)) = widths.split_first() else {
        return Err(count_error);
    };
    let value = |width: u32| coding.decode_width(width, start);
    match (kind, symbols) {
        (PwmFrameKind::Experiment, &[function_code, status, reference_1, reference_2]) => {
            let function_code = value(function_code)?;
            u8::try_from(function_code).map_err(|_| PwmError::NotAByte(function_code))?;
            PwmStatus::from_symbol(value(status)?)?;
            value(reference_1)?;
            value(reference_2)?;
            Ok(())
        }
        (PwmFrameKind::Broadcast | PwmFrameKind::Designated, [status, data @ ..])
            if data.len() <= PWM_MAX_DATA =>
        {
            PwmStatus::from_symbol(value(*status)?)?;
            for &width in data {
                value(width)?;
            }
            Ok(())
        }
        _ => Err(count_error),
    }
}

/// One frame as a value, start symbol implied.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PwmRepr {
    /// Start, status (operation status, command type), data.
    Broadcast {
        /// Operation status and command type.
        status: PwmStatus,
        /// The command data, same for every slave.
        data: PwmData,
    },
    /// Start, status (slave id, command type), data.
    Designated {
        /// `high` is the designated slave's id, 0–15.
        status: PwmStatus,
        /// The command data for that slave.
        data: PwmData,
    },
    /// Start, function code, status, reference 1, reference 2.
    Experiment {
        /// The function code the slave answers.
        function_code: u8,
        /// Operation status and command type.
        status: PwmStatus,
        /// First control reference.
        reference_1: u16,
        /// Second control reference.
        reference_2: u16,
    },
}

impl PwmRepr {
    /// Checks captured ON widths, start symbol first, as a frame of `kind` and
    /// reads its values.
    pub fn parse(kind: PwmFrameKind, coding: &PwmCoding, widths: &[u32]) -> Result<Self, PwmError> {
        PwmFrame::new_checked(widths, kind, coding).map(|frame| Self::from_frame(&frame))
    }

    /// The value of a checked frame.
    pub fn from_frame<T: AsRef<[u32]>>(frame: &PwmFrame<T>) -> Self {
        let status = frame.status();
        match (frame.function_code(), frame.references()) {
            (Some(function_code), Some((reference_1, reference_2))) => PwmRepr::Experiment {
                function_code,
                status,
                reference_1,
                reference_2,
            },
            _ if frame.kind() == PwmFrameKind::Designated => PwmRepr::Designated {
                status,
                data: frame.data(),
            },
            _ => PwmRepr::Broadcast {
                status,
                data: frame.data(),
            },
        }
    }

    /// The frame's layout.
    pub const fn kind(&self) -> PwmFrameKind {
        match self {
            PwmRepr::Broadcast { .. } => PwmFrameKind::Broadcast,
            PwmRepr::Designated { .. } => PwmFrameKind::Designated,
            PwmRepr::Experiment { .. } => PwmFrameKind::Experiment,
        }
    }

    /// Symbols on the wire, start symbol included.
    pub fn symbol_count(&self) -> usize {
        match self {
            PwmRepr::Broadcast { data, .. } | PwmRepr::Designated { data, .. } => 2 + data.len(),
            PwmRepr::Experiment { .. } => 5,
        }
    }

    /// Writes the ON widths of the frame's symbols, start first, to the start of
    /// `widths` and returns how many. Every symbol's period is
    /// [`PwmCoding::symbol_period_ticks`].
    pub fn emit(&self, coding: &PwmCoding, widths: &mut [u32]) -> Result<usize, PwmError> {
        let needed = self.symbol_count();
        let out = widths
            .get_mut(..needed)
            .ok_or(PwmError::BufferTooSmall { needed })?;
        // Start excluded; `data` holds at most PWM_MAX_DATA words, so it fits.
        let mut values = [0u16; PWM_MAX_SYMBOLS - 1];
        let count = match self {
            PwmRepr::Broadcast { status, data } | PwmRepr::Designated { status, data } => {
                values[0] = status.to_symbol()?;
                values[1..=data.len()].copy_from_slice(data);
                1 + data.len()
            }
            PwmRepr::Experiment {
                function_code,
                status,
                reference_1,
                reference_2,
            } => {
                let symbols = [
                    u16::from(*function_code),
                    status.to_symbol()?,
                    *reference_1,
                    *reference_2,
                ];
                values[..4].copy_from_slice(&symbols);
                4
            }
        };
        let (start, symbols) = out
            .split_first_mut()
            .ok_or(PwmError::BufferTooSmall { needed })?;
        *start = coding.start_ticks;
        for (width, value) in symbols.iter_mut().zip(&values[..count]) {
            *width = coding.encode_width(*value)?;
        }
        Ok(needed)
    }
}
