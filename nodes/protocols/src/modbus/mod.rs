//! Standard Modbus: the PDU (function codes 01, 02, 03, 04, 05, 06, 15, 16 and
//! exception replies) and its three framings, RTU, ASCII and TCP.
//!
//! Written here rather than taken from rmodbus: rmodbus processes frames against
//! its own register context and has no stream decoder with the silence rule or
//! drop accounting, which a node on a simulated multi-drop bus needs.
//!
//! # Shape
//!
//! - [`pdu`]: [`Request`] and [`Response`] values with `parse`/`emit`, fixed-size
//!   storage ([`Bits`], [`Registers`]); a reply parses to
//!   `Result<Result<Response, ExceptionResponse>, PduError>`: an exception is a
//!   valid reply, a malformed PDU is an error.
//! - [`rtu`], [`ascii`], [`tcp`]: one frame per framing as a checked view over
//!   its bytes ([`rtu::RtuFrame`], [`ascii::AsciiFrame`], [`tcp::TcpFrame`]:
//!   `new_checked`, then `pdu()` and what they share as an [`Adu`]: `unit()`,
//!   `function()`, `request()`, `response()`, and on a serial line
//!   ([`SerialAdu`]) `is_for()`, `is_broadcast()`) and as a
//!   small value ([`rtu::RtuRepr`], [`ascii::AsciiRepr`], [`tcp::TcpRepr`]:
//!   `parse`, `from_frame`, `emit`), following smoltcp's `wire` split of
//!   `Packet` and `Repr`, as MEB does; and a stream decoder per framing that is
//!   fed byte chunks and yields checked views one at a time.
//!
//! - [`serial`]: the silence rule shared by RTU and the 8-byte variant
//!   ([`crate::modbus8`]), and the silences to configure it with.
//!
//! A slave checks a frame's `unit()` before it parses the PDU, so frames for
//! other slaves on the same line cost one byte compare. The decoders still
//! frame them, since a frame's end must be found to find the next one's start.
//!
//! # No panics
//!
//! Every parse takes untrusted bytes and returns a typed error on any input;
//! nothing on the parse, emit or decode path allocates.

mod adu;
pub mod ascii;
mod data;
pub mod pdu;
mod request;
mod response;
pub mod rtu;
pub mod serial;
pub mod tcp;

pub use adu::{Adu, SerialAdu};
pub use pdu::{
    Bits, EncodePdu, Exception, ExceptionResponse, PduError, Registers, Request, Response,
};

use thiserror::Error;

/// The longest PDU: function code plus 252 data bytes (Modbus application
/// protocol 1.1b3, section 4.1, from the 256-byte RTU ADU).
pub const MAX_PDU_LEN: usize = 253;

/// The output buffer was too small for the frame; nothing useful was written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[error("output buffer holds {available} bytes, the frame needs {needed}")]
pub struct BufferTooSmall {
    /// Bytes the frame needs.
    pub needed: usize,
    /// Bytes the buffer had.
    pub available: usize,
}

/// Why a Modbus ADU (RTU, ASCII or TCP framing) was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum FrameError {
    /// Fewer bytes than the smallest frame of this framing.
    #[error("frame of {len} bytes is shorter than the minimum {min}")]
    TooShort {
        /// Bytes received.
        len: usize,
        /// Smallest legal frame.
        min: usize,
    },
    /// More bytes than the longest frame of this framing.
    #[error("frame of {len} bytes is longer than the maximum {max}")]
    TooLong {
        /// Bytes received.
        len: usize,
        /// Longest legal frame.
        max: usize,
    },
    /// RTU CRC mismatch; both values as numbers (sent low byte first).
    #[error("CRC error: received {received:#06x}, calculated {calculated:#06x}")]
    BadCrc {
        /// CRC carried by the frame.
        received: u16,
        /// CRC computed over the frame.
        calculated: u16,
    },
    /// ASCII LRC mismatch.
    #[error("LRC error: received {received:#04x}, calculated {calculated:#04x}")]
    BadLrc {
        /// LRC carried by the frame.
        received: u8,
        /// LRC computed over the frame.
        calculated: u8,
    },
    /// ASCII frame not starting with `:`.
    #[error("ASCII frame does not start with ':'")]
    MissingStart,
    /// ASCII frame not ending with CR LF.
    #[error("ASCII frame does not end with CR LF")]
    MissingEnd,
    /// ASCII frame with a character that is not a hex digit at `position`.
    #[error("ASCII frame has a non-hex character {byte:#04x} at {position}")]
    NotHex {
        /// The offending byte.
        byte: u8,
        /// Its offset in the frame.
        position: usize,
    },
    /// ASCII frame with an odd number of hex digits.
    #[error("ASCII frame has an odd number of hex digits")]
    OddHexLength,
    /// TCP MBAP header with a protocol id other than 0.
    #[error("MBAP protocol id {0:#06x} is not Modbus (0)")]
    ProtocolId(u16),
    /// TCP MBAP length field outside 2..=254.
    #[error("MBAP length {0} is outside 2..=254")]
    MbapLength(u16),
    /// TCP frame whose size disagrees with its MBAP length field.
    #[error("MBAP length says {expected} bytes follow, frame has {actual}")]
    LengthMismatch {
        /// Bytes the MBAP length announces after the length field.
        expected: usize,
        /// Bytes actually there.
        actual: usize,
    },
}

/// A count of one kind of drop: how many times it happened and how many bytes it
/// threw away.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Tally {
    /// Occurrences.
    pub events: u64,
    /// Bytes thrown away.
    pub bytes: u64,
}

impl Tally {
    pub(crate) fn add(&mut self, bytes: usize) {
        self.events += 1;
        self.bytes += bytes as u64;
    }
}

/// What a stream decoder threw away, by reason. Every byte that went in and did
/// not come out in a frame is in exactly one of these.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Drops {
    /// Partial frames cut off by a silence (serial) before they were complete.
    pub timed_out: Tally,
    /// Complete frames whose CRC or LRC failed (also yielded as errors).
    pub bad_check: Tally,
    /// Bytes that arrived after a bad frame (failed check, unknown function,
    /// oversize), thrown away up to the next silence.
    pub after_bad_frame: Tally,
    /// Frames whose header cannot start a legal frame (unknown function where
    /// no timing exists, byte count past the maximum, bad MBAP, bad hex), and
    /// bytes dropped one by one to resynchronise.
    pub malformed: Tally,
    /// Frames longer than the longest legal frame.
    pub oversize: Tally,
    /// Bytes outside any frame (ASCII noise before `:`).
    pub noise: Tally,
}

impl Drops {
    /// Bytes dropped for any reason.
    pub fn total_bytes(&self) -> u64 {
        self.all().iter().map(|t| t.bytes).sum()
    }

    /// Drop events of any reason.
    pub fn total_events(&self) -> u64 {
        self.all().iter().map(|t| t.events).sum()
    }

    fn all(&self) -> [Tally; 6] {
        [
            self.timed_out,
            self.bad_check,
            self.after_bad_frame,
            self.malformed,
            self.oversize,
            self.noise,
        ]
    }
}
