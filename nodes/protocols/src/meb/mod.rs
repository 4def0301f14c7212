//! MEB, the lab's ASCII master/slave protocol (`docs/protocols/meb.md`).
//!
//! ```text
//! @ ID CMD ADDR CNT DATA… FCS * \n
//! ```
//!
//! - [`MebFrame`] is a checked view over the bytes of one frame (header decoded,
//!   DATA left as text and decoded on demand); [`MebRepr`] is the small value
//!   (`parse`/`emit`) with its words in a fixed array, following smoltcp's
//!   `wire` split of `Packet` and `Repr`.
//! - [`MebDecoder`] cuts a byte stream into frames, resynchronising at every `@`.
//!
//! No function here panics or allocates, whatever the input: a malformed frame is
//! a typed [`MebError`], and an *error reply* (`ER`) is a valid frame, not an
//! error — the slave's answer is data ([`MebErrorCode`]), the wire's fault is not.

mod decoder;
mod frame;

use core::fmt;

pub use decoder::{MebDecodeError, MebDecoder, MebDecoderStats, MebEvent, MebFrames};
pub use frame::{MebEmitError, MebFrame, MebRepr};

use super::words::FixedWords;

/// The longest frame on the wire: 9 + 4·99 + 4 bytes with `*\r\n`.
pub const MEB_MAX_FRAME_LEN: usize = 410;
/// The most 16-bit words one frame carries (`CNT` is two decimal digits).
pub const MEB_MAX_WORDS: usize = 99;
/// The highest slave number; `00` is broadcast.
pub const MEB_MAX_ID: u8 = 99;
/// The slave number every slave obeys (writes only) and none answers.
pub const MEB_BROADCAST_ID: u8 = 0;

/// The DATA words of one frame.
pub type MebWords = FixedWords<MEB_MAX_WORDS>;

/// Why bytes are not a well-formed MEB frame. A slave ignores such a frame and
/// counts it; the names ([`MebError::name`]) are the `error` kinds of
/// `vectors/meb.jsonl`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, thiserror::Error)]
pub enum MebError {
    /// Longer than [`MEB_MAX_FRAME_LEN`], decided by length alone before any other check.
    #[error("frame longer than 410 bytes")]
    TooLong,
    /// The first byte is not `@`.
    #[error("frame does not start with `@`")]
    NoBof,
    /// The frame does not end in `*\n` or `*\r\n`.
    #[error("frame does not end with `*\\n` or `*\\r\\n`")]
    NoEof,
    /// Too short to hold ID, CMD, ADDR, CNT and FCS.
    #[error("frame too short for its header and FCS")]
    Truncated,
    /// FCS not two hex digits, or not the XOR of the bytes before it.
    #[error("FCS not hex or not the XOR of the frame")]
    BadFcs,
    /// ID is not two decimal digits.
    #[error("ID is not two decimal digits")]
    BadId,
    /// CMD is not two ASCII letters.
    #[error("CMD is not two letters")]
    BadCmd,
    /// ADDR is not two hex digits.
    #[error("ADDR is not two hex digits")]
    BadAddr,
    /// CNT is not two decimal digits.
    #[error("CNT is not two decimal digits")]
    BadCnt,
    /// DATA is neither empty nor exactly 4 × CNT characters.
    #[error("DATA is neither empty nor 4 x CNT characters")]
    BadDataLength,
    /// DATA holds a character that is not a hex digit.
    #[error("DATA is not hex")]
    BadData,
}

impl MebError {
    /// Every kind, in the order [`MebDecoderStats`] counts them.
    pub const ALL: [MebError; 11] = [
        MebError::TooLong,
        MebError::NoBof,
        MebError::NoEof,
        MebError::Truncated,
        MebError::BadFcs,
        MebError::BadId,
        MebError::BadCmd,
        MebError::BadAddr,
        MebError::BadCnt,
        MebError::BadDataLength,
        MebError::BadData,
    ];

    /// The kind's name as `vectors/meb.jsonl` spells it (`bad_fcs`, `too_long`, …).
    pub const fn name(self) -> &'static str {
        match self {
            MebError::TooLong => "too_long",
            MebError::NoBof => "no_bof",
            MebError::NoEof => "no_eof",
            MebError::Truncated => "truncated",
            MebError::BadFcs => "bad_fcs",
            MebError::BadId => "bad_id",
            MebError::BadCmd => "bad_cmd",
            MebError::BadAddr => "bad_addr",
            MebError::BadCnt => "bad_cnt",
            MebError::BadDataLength => "bad_data_length",
            MebError::BadData => "bad_data",
        }
    }
}

/// A command: two ASCII letters, as received (a lower-case command parses and is
/// answered with error 01, so the case is kept).
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct MebCmd([u8; 2]);

impl MebCmd {
    /// Read analog inputs.
    pub const EA: MebCmd = MebCmd(*b"EA");
    /// Read digital inputs.
    pub const ED: MebCmd = MebCmd(*b"ED");
    /// Write analog outputs.
    pub const SA: MebCmd = MebCmd(*b"SA");
    /// Write digital outputs.
    pub const SD: MebCmd = MebCmd(*b"SD");
    /// Write analog variables.
    pub const VA: MebCmd = MebCmd(*b"VA");
    /// Write digital variables.
    pub const VD: MebCmd = MebCmd(*b"VD");
    /// Read analog flags.
    pub const FA: MebCmd = MebCmd(*b"FA");
    /// Read digital flags.
    pub const FD: MebCmd = MebCmd(*b"FD");
    /// Error reply.
    pub const ER: MebCmd = MebCmd(*b"ER");

    /// The command spelled by `letters`, or `None` unless both are ASCII letters.
    pub const fn new(letters: [u8; 2]) -> Option<Self> {
        if letters[0].is_ascii_alphabetic() && letters[1].is_ascii_alphabetic() {
            Some(MebCmd(letters))
        } else {
            None
        }
    }

    /// The two letters, as on the wire.
    pub const fn letters(self) -> [u8; 2] {
        self.0
    }

    /// The block and word type this command addresses; `None` for `ER` and for
    /// letters outside the command table (lower case included).
    pub const fn block(self) -> Option<(MebBlock, MebWordType)> {
        use MebBlock::*;
        use MebWordType::*;
        Some(match &self.0 {
            b"EA" => (Inputs, Analog),
            b"ED" => (Inputs, Digital),
            b"SA" => (Outputs, Analog),
            b"SD" => (Outputs, Digital),
            b"VA" => (Variables, Analog),
            b"VD" => (Variables, Digital),
            b"FA" => (Flags, Analog),
            b"FD" => (Flags, Digital),
            _ => return None,
        })
    }

    /// Whether a frame with this command, `cnt` and DATA present or not is a
    /// request or one of the reply shapes (spec: "Reply-shaped frames are never
    /// answered").
    pub const fn shape(self, cnt: u8, has_data: bool) -> MebShape {
        if matches!(&self.0, b"ER") {
            return MebShape::ErrorReply;
        }
        match self.block() {
            Some((block, _)) => match block.access() {
                MebAccess::Read if has_data => MebShape::ReadReply,
                MebAccess::Write if cnt >= 1 && !has_data => MebShape::WriteAck,
                _ => MebShape::Request,
            },
            // Unknown commands are requests: the slave answers them with error 01.
            None => MebShape::Request,
        }
    }
}

impl fmt::Display for MebCmd {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}{}", char::from(self.0[0]), char::from(self.0[1]))
    }
}

impl fmt::Debug for MebCmd {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "MebCmd({self})")
    }
}

/// The four blocks of a slave's image (paper, Table 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MebBlock {
    /// Inputs (`E…`): what the module measures. Read only.
    Inputs,
    /// Outputs (`S…`): what drives the module. Write only.
    Outputs,
    /// Variables (`V…`): firmware settings. Write only.
    Variables,
    /// Flags (`F…`): firmware status. Read only.
    Flags,
}

impl MebBlock {
    /// The direction the block's commands go.
    pub const fn access(self) -> MebAccess {
        match self {
            MebBlock::Inputs | MebBlock::Flags => MebAccess::Read,
            MebBlock::Outputs | MebBlock::Variables => MebAccess::Write,
        }
    }
}

/// Analog words are converter counts; digital words are 16 bits each.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MebWordType {
    /// `…A` commands.
    Analog,
    /// `…D` commands.
    Digital,
}

/// The direction of a block's commands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MebAccess {
    /// The master asks, the reply carries the words.
    Read,
    /// The master sends the words, the reply echoes the header.
    Write,
}

/// What a well-formed frame is, by its shape alone.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MebShape {
    /// Something a slave answers (if the ID is its own, and not broadcast for reads).
    Request,
    /// A read command carrying DATA.
    ReadReply,
    /// A write command with `CNT` ≥ 1 and no DATA.
    WriteAck,
    /// An `ER` frame.
    ErrorReply,
}

impl MebShape {
    /// Replies are never answered: on a shared bus every slave hears the others'.
    pub const fn is_reply(self) -> bool {
        !matches!(self, MebShape::Request)
    }
}

/// The code of an error reply (`@ ID ER ADDR 01 00EE`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MebErrorCode {
    /// 01: `CMD` not in the table, or its block holds no words in this slave.
    IllegalCommand = 1,
    /// 02: `ADDR + CNT − 1` outside the block.
    IllegalAddress = 2,
    /// 03: `CNT` = 0, or a value out of range.
    IllegalData = 3,
    /// 04: the slave cannot apply it now (enabling while a trip's cause persists).
    DeviceFailure = 4,
}

impl MebErrorCode {
    /// The code for a DATA word, or `None` outside 01–04.
    pub const fn from_word(word: u16) -> Option<Self> {
        Some(match word {
            1 => MebErrorCode::IllegalCommand,
            2 => MebErrorCode::IllegalAddress,
            3 => MebErrorCode::IllegalData,
            4 => MebErrorCode::DeviceFailure,
            _ => return None,
        })
    }

    /// The DATA word that carries this code.
    pub const fn word(self) -> u16 {
        self as u16
    }

    /// The code's name as `docs/protocols/meb.md` gives it.
    pub const fn name(self) -> &'static str {
        match self {
            MebErrorCode::IllegalCommand => "illegal command",
            MebErrorCode::IllegalAddress => "illegal address",
            MebErrorCode::IllegalData => "illegal data",
            MebErrorCode::DeviceFailure => "device failure",
        }
    }
}
