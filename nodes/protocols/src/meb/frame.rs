//! One MEB frame: the checked view over its bytes and the value type.

use super::{
    MEB_BROADCAST_ID, MEB_MAX_FRAME_LEN, MEB_MAX_ID, MEB_MAX_WORDS, MebCmd, MebError, MebErrorCode,
    MebShape, MebWords,
};

/// Bytes before DATA: `@`, ID, CMD, ADDR, CNT.
const HEADER_LEN: usize = 9;
/// Bytes after DATA in canonical form: FCS, `*`, `\n`.
const TRAILER_LEN: usize = 4;
const HEX_UPPER: &[u8; 16] = b"0123456789ABCDEF";

/// A checked view over the bytes of one MEB frame, from `@` to `\n`.
///
/// [`MebFrame::new_checked`] validates every field and decodes the header; DATA
/// stays as text in the buffer and is decoded on demand by [`MebFrame::words`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MebFrame<T: AsRef<[u8]>> {
    buffer: T,
    id: u8,
    cmd: MebCmd,
    addr: u8,
    cnt: u8,
    /// Where DATA ends and the FCS begins.
    fcs_at: usize,
}

impl<T: AsRef<[u8]>> MebFrame<T> {
    /// Checks `buffer` as one whole frame, in the order the spec's vectors need:
    /// length, BOF, EOF, header length, FCS, then each field in wire order.
    pub fn new_checked(buffer: T) -> Result<Self, MebError> {
        let bytes = buffer.as_ref();
        if bytes.len() > MEB_MAX_FRAME_LEN {
            return Err(MebError::TooLong);
        }
        if bytes.first() != Some(&b'@') {
            return Err(MebError::NoBof);
        }
        let text = bytes
            .strip_suffix(b"*\r\n")
            .or_else(|| bytes.strip_suffix(b"*\n"))
            .ok_or(MebError::NoEof)?;
        let [covered @ .., f1, f2] = text else {
            return Err(MebError::Truncated);
        };
        let [_, i1, i2, c1, c2, a1, a2, n1, n2, data @ ..] = covered else {
            return Err(MebError::Truncated);
        };
        // The FCS covers the bytes as received, lower-case hex included.
        if hex_byte(*f1, *f2) != Some(fcs(covered)) {
            return Err(MebError::BadFcs);
        }
        let id = decimal(*i1, *i2).ok_or(MebError::BadId)?;
        let cmd = MebCmd::new([*c1, *c2]).ok_or(MebError::BadCmd)?;
        let addr = hex_byte(*a1, *a2).ok_or(MebError::BadAddr)?;
        let cnt = decimal(*n1, *n2).ok_or(MebError::BadCnt)?;
        if !data.is_empty() && data.len() != 4 * usize::from(cnt) {
            return Err(MebError::BadDataLength);
        }
        if !data.iter().all(u8::is_ascii_hexdigit) {
            return Err(MebError::BadData);
        }
        let fcs_at = covered.len();
        Ok(Self {
            buffer,
            id,
            cmd,
            addr,
            cnt,
            fcs_at,
        })
    }

    /// The slave number, 0–99 (0 is broadcast).
    pub fn id(&self) -> u8 {
        self.id
    }

    /// The command letters.
    pub fn cmd(&self) -> MebCmd {
        self.cmd
    }

    /// The first word address.
    pub fn addr(&self) -> u8 {
        self.addr
    }

    /// `CNT`: the number of words asked for, written or returned.
    pub fn cnt(&self) -> u8 {
        self.cnt
    }

    /// Whether DATA is present (then it holds exactly `cnt` words).
    pub fn has_data(&self) -> bool {
        self.fcs_at > HEADER_LEN
    }

    /// The DATA words, in order (none when DATA is absent).
    pub fn words(&self) -> impl Iterator<Item = u16> + '_ {
        let data = self
            .buffer
            .as_ref()
            .get(HEADER_LEN..self.fcs_at)
            .unwrap_or_default();
        // Every chunk was checked to be four hex digits, so nothing is filtered out.
        data.chunks_exact(4).filter_map(hex_word)
    }

    /// Request or reply, by shape alone.
    pub fn shape(&self) -> MebShape {
        self.cmd.shape(self.cnt, self.has_data())
    }

    /// The bytes of the frame, as received.
    pub fn as_bytes(&self) -> &[u8] {
        self.buffer.as_ref()
    }

    /// Gives the buffer back.
    pub fn into_inner(self) -> T {
        self.buffer
    }
}

/// Why a [`MebRepr`] cannot be emitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, thiserror::Error)]
pub enum MebEmitError {
    /// The output buffer is shorter than the frame.
    #[error("output buffer too small: the frame needs {needed} bytes")]
    BufferTooSmall {
        /// The frame's length.
        needed: usize,
    },
    /// ID above 99.
    #[error("ID {0} is above 99")]
    IdOutOfRange(u8),
    /// CNT above 99.
    #[error("CNT {0} is above 99")]
    CountOutOfRange(u8),
    /// DATA present but not `cnt` words long.
    #[error("{words} DATA words for CNT {cnt}")]
    DataLengthMismatch {
        /// `cnt` of the frame.
        cnt: u8,
        /// Words in `data`.
        words: usize,
    },
}

/// One MEB frame as a value. `data` is empty (requests to read, write
/// acknowledgements) or holds exactly `cnt` words (writes, read replies, errors).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MebRepr {
    /// Slave number, 0–99 (0 is broadcast).
    pub id: u8,
    /// Command letters.
    pub cmd: MebCmd,
    /// First word address.
    pub addr: u8,
    /// Word count, 0–99.
    pub cnt: u8,
    /// DATA words.
    pub data: MebWords,
}

impl MebRepr {
    /// Parses one whole frame (`@` to `\n`).
    pub fn parse(bytes: &[u8]) -> Result<Self, MebError> {
        MebFrame::new_checked(bytes).map(|frame| Self::from_frame(&frame))
    }

    /// The value of a checked frame.
    pub fn from_frame<T: AsRef<[u8]>>(frame: &MebFrame<T>) -> Self {
        let mut data = MebWords::new();
        for word in frame.words() {
            // At most 99 words: CNT has two digits and DATA is exactly CNT words.
            let _ = data.push(word);
        }
        Self {
            id: frame.id(),
            cmd: frame.cmd(),
            addr: frame.addr(),
            cnt: frame.cnt(),
            data,
        }
    }

    /// The error reply `@ ID ER ADDR 01 00EE` a slave sends for a request to `addr`.
    pub fn error_reply(id: u8, addr: u8, code: MebErrorCode) -> Self {
        let mut data = MebWords::new();
        let _ = data.push(code.word());
        Self {
            id,
            cmd: MebCmd::ER,
            addr,
            cnt: 1,
            data,
        }
    }

    /// The acknowledgement of this write: its header echoed, without DATA.
    pub fn acknowledgement(&self) -> Self {
        Self {
            data: MebWords::new(),
            ..*self
        }
    }

    /// The code of an error reply, or `None` if this is not one with a known code.
    pub fn error_code(&self) -> Option<MebErrorCode> {
        match (self.cmd == MebCmd::ER, self.data.as_slice()) {
            (true, &[word]) => MebErrorCode::from_word(word),
            _ => None,
        }
    }

    /// Request or reply, by shape alone.
    pub fn shape(&self) -> MebShape {
        self.cmd.shape(self.cnt, !self.data.is_empty())
    }

    /// Whether the frame is addressed to every slave.
    pub fn is_broadcast(&self) -> bool {
        self.id == MEB_BROADCAST_ID
    }

    /// The length of the canonical frame: 13 bytes plus 4 per word.
    pub fn emitted_len(&self) -> usize {
        HEADER_LEN + 4 * self.data.len() + TRAILER_LEN
    }

    /// Writes the canonical frame (upper-case hex, `*\n`) to the start of `out`
    /// and returns its length.
    pub fn emit(&self, out: &mut [u8]) -> Result<usize, MebEmitError> {
        if self.id > MEB_MAX_ID {
            return Err(MebEmitError::IdOutOfRange(self.id));
        }
        if usize::from(self.cnt) > MEB_MAX_WORDS {
            return Err(MebEmitError::CountOutOfRange(self.cnt));
        }
        if !self.data.is_empty() && self.data.len() != usize::from(self.cnt) {
            return Err(MebEmitError::DataLengthMismatch {
                cnt: self.cnt,
                words: self.data.len(),
            });
        }
        let needed = self.emitted_len();
        let frame = out
            .get_mut(..needed)
            .ok_or(MebEmitError::BufferTooSmall { needed })?;
        let [bof, i1, i2, c1, c2, a1, a2, n1, n2, rest @ ..] = frame else {
            return Err(MebEmitError::BufferTooSmall { needed });
        };
        *bof = b'@';
        [*i1, *i2] = decimal_digits(self.id);
        [*c1, *c2] = self.cmd.letters();
        [*a1, *a2] = hex_digits(self.addr);
        [*n1, *n2] = decimal_digits(self.cnt);
        for (chunk, word) in rest.chunks_exact_mut(4).zip(self.data.iter()) {
            chunk.copy_from_slice(&word_digits(*word));
        }
        let fcs_at = needed - TRAILER_LEN;
        let (covered, trailer) = frame.split_at_mut(fcs_at);
        let [f1, f2] = hex_digits(fcs(covered));
        trailer.copy_from_slice(&[f1, f2, b'*', b'\n']);
        Ok(needed)
    }
}

/// The frame check sequence: XOR of every byte from `@` to the last one before it.
fn fcs(covered: &[u8]) -> u8 {
    covered.iter().fold(0, |acc, byte| acc ^ byte)
}

/// A receiver accepts hex digits in either case.
fn hex_value(digit: u8) -> Option<u8> {
    match digit {
        b'0'..=b'9' => Some(digit - b'0'),
        b'A'..=b'F' => Some(digit - b'A' + 10),
        b'a'..=b'f' => Some(digit - b'a' + 10),
        _ => None,
    }
}

fn hex_byte(high: u8, low: u8) -> Option<u8> {
    Some(hex_value(high)? << 4 | hex_value(low)?)
}

fn hex_word(digits: &[u8]) -> Option<u16> {
    match *digits {
        [a, b, c, d] => Some(u16::from_be_bytes([hex_byte(a, b)?, hex_byte(c, d)?])),
        _ => None,
    }
}

fn decimal(tens: u8, units: u8) -> Option<u8> {
    if tens.is_ascii_digit() && units.is_ascii_digit() {
        Some((tens - b'0') * 10 + (units - b'0'))
    } else {
        None
    }
}

fn hex_digits(byte: u8) -> [u8; 2] {
    [
        HEX_UPPER[usize::from(byte >> 4)],
        HEX_UPPER[usize::from(byte & 0x0F)],
    ]
}

fn word_digits(word: u16) -> [u8; 4] {
    let [high, low] = word.to_be_bytes();
    let ([a, b], [c, d]) = (hex_digits(high), hex_digits(low));
    [a, b, c, d]
}

/// Two decimal digits of a value already checked to be at most 99.
fn decimal_digits(value: u8) -> [u8; 2] {
    [b'0' + value / 10 % 10, b'0' + value % 10]
}
