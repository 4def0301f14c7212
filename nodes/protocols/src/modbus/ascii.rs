//! Modbus ASCII framing: `:`, the unit id, PDU and LRC as hex digit pairs,
//! CR LF. Upper-case hex is emitted; either case is accepted.
//!
//! The stream decoder needs no timing: `:` always starts a frame (so it
//! resynchronises after garbage at the next one), CR LF ends it, and the buffer
//! is bounded by the longest legal frame, 513 characters.

use crate::crc::lrc;

use super::adu::{Adu, SerialAdu, pdu_of};
use super::pdu::EncodePdu;
use super::{BufferTooSmall, Drops, FrameError, MAX_PDU_LEN};

/// The longest ASCII frame in characters: `:` + 2 × (unit + PDU + LRC) + CR LF.
pub const MAX_ADU_LEN: usize = 1 + 2 * MAX_BINARY_LEN + 2;
/// The shortest: `:`, unit, function, LRC, CR LF.
pub const MIN_ADU_LEN: usize = 1 + 2 * 3 + 2;
/// The longest binary content: unit, PDU, LRC.
pub const MAX_BINARY_LEN: usize = 1 + MAX_PDU_LEN + 1;

const START: u8 = b':';
const CR: u8 = b'\r';
const LF: u8 = b'\n';
const HEX_UPPER: &[u8; 16] = b"0123456789ABCDEF";

fn hex_value(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'A'..=b'F' => Some(c - b'A' + 10),
        b'a'..=b'f' => Some(c - b'a' + 10),
        _ => None,
    }
}

/// Checks the LRC of decoded content (unit, PDU, LRC); returns the PDU's length.
fn check_content(binary: &[u8]) -> Result<usize, FrameError> {
    let too_short = FrameError::TooShort {
        len: 1 + 2 * binary.len() + 2,
        min: MIN_ADU_LEN,
    };
    let [_unit, pdu @ .., received] = binary else {
        return Err(too_short);
    };
    if pdu.is_empty() {
        return Err(too_short);
    }
    if binary.len() > MAX_BINARY_LEN {
        return Err(FrameError::TooLong {
            len: 1 + 2 * binary.len() + 2,
            max: MAX_ADU_LEN,
        });
    }
    let calculated = lrc(binary.get(..binary.len() - 1).unwrap_or(&[]));
    if *received != calculated {
        return Err(FrameError::BadLrc {
            received: *received,
            calculated,
        });
    }
    Ok(pdu.len())
}

/// A checked view over the content of one ASCII frame: the unit id, PDU and
/// LRC that its hex digits spell.
///
/// ASCII sends each byte as two hex characters between `:` and CR LF, so the
/// view is over the bytes the characters stand for: the decoder decodes them
/// into its buffer as they come, [`AsciiFrame::decode_line`] into a scratch
/// buffer. The PDU is then a slice, as over RTU and TCP.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AsciiFrame<T: AsRef<[u8]>> {
    buffer: T,
}

impl<T: AsRef<[u8]>> AsciiFrame<T> {
    /// Checks `content` (unit, PDU, LRC, as bytes): its length, then its LRC.
    pub fn new_checked(content: T) -> Result<Self, FrameError> {
        check_content(content.as_ref())?;
        Ok(AsciiFrame { buffer: content })
    }

    /// A view over content a decoder has already checked.
    fn new_unchecked(content: T) -> Self {
        AsciiFrame { buffer: content }
    }

    /// The LRC the frame carries (and that checked).
    pub fn lrc(&self) -> u8 {
        self.buffer.as_ref().last().copied().unwrap_or(0)
    }

    /// Gives the buffer back.
    pub fn into_inner(self) -> T {
        self.buffer
    }
}

impl<T: AsRef<[u8]>> Adu for AsciiFrame<T> {
    /// The unit id.
    const HEADER_LEN: usize = 1;
    /// The LRC.
    const CHECK_LEN: usize = 1;

    /// The content as bytes: unit, PDU, LRC (not the hex characters).
    fn as_bytes(&self) -> &[u8] {
        self.buffer.as_ref()
    }
}

impl<T: AsRef<[u8]>> SerialAdu for AsciiFrame<T> {}

impl<'a, T: AsRef<[u8]> + ?Sized> AsciiFrame<&'a T> {
    /// Function code and data; never empty. Borrowed from the buffer, so it
    /// outlives the view (a decoder's frame can be kept while it goes on).
    pub fn pdu(&self) -> &'a [u8] {
        pdu_of::<Self>(self.buffer.as_ref())
    }
}

impl<'s> AsciiFrame<&'s [u8]> {
    /// Checks a whole ASCII line (`:` … CR LF), decoding its hex into
    /// `scratch`; the view is over `scratch`.
    pub fn decode_line(
        line: &[u8],
        scratch: &'s mut [u8; MAX_BINARY_LEN],
    ) -> Result<Self, FrameError> {
        let Some((&START, rest)) = line.split_first() else {
            return Err(FrameError::MissingStart);
        };
        let Some(hex) = rest.strip_suffix(&[CR, LF]) else {
            return Err(FrameError::MissingEnd);
        };
        if line.len() > MAX_ADU_LEN {
            return Err(FrameError::TooLong {
                len: line.len(),
                max: MAX_ADU_LEN,
            });
        }
        if hex.len() % 2 != 0 {
            return Err(FrameError::OddHexLength);
        }
        let binary_len = hex.len() / 2;
        for (i, (slot, pair)) in scratch.iter_mut().zip(hex.chunks_exact(2)).enumerate() {
            let digit = |k: usize| {
                let c = pair.get(k).copied().unwrap_or(0);
                hex_value(c).ok_or(FrameError::NotHex {
                    byte: c,
                    position: 1 + 2 * i + k,
                })
            };
            *slot = digit(0)? << 4 | digit(1)?;
        }
        let scratch: &'s [u8; MAX_BINARY_LEN] = scratch;
        AsciiFrame::new_checked(scratch.get(..binary_len).unwrap_or(&[]))
    }
}

/// One ASCII frame as a value: the unit id and a PDU. Parsed, the PDU is
/// bytes of the decoded content (`AsciiRepr<&[u8]>`); to emit, it is anything
/// that writes a PDU (a [`Request`](super::Request), a reply, raw bytes), spelt out in hex.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AsciiRepr<P> {
    /// Unit id (slave address); 0 is the broadcast.
    pub unit: u8,
    /// Function code and data.
    pub pdu: P,
}

impl<'s> AsciiRepr<&'s [u8]> {
    /// Checks a whole ASCII line (`:` … CR LF) and reads its unit id and PDU,
    /// decoding the hex into `scratch`.
    pub fn parse(line: &[u8], scratch: &'s mut [u8; MAX_BINARY_LEN]) -> Result<Self, FrameError> {
        AsciiFrame::decode_line(line, scratch).map(|frame| Self::from_frame(&frame))
    }

    /// The value of a checked frame.
    pub fn from_frame<T: AsRef<[u8]> + ?Sized>(frame: &AsciiFrame<&'s T>) -> Self {
        AsciiRepr {
            unit: frame.unit(),
            pdu: frame.pdu(),
        }
    }
}

impl<P: EncodePdu> AsciiRepr<P> {
    /// The length of the line in characters: `:`, unit, PDU and LRC in hex, CR LF.
    pub fn emitted_len(&self) -> usize {
        1 + 2 * (1 + self.pdu.pdu_len() + 1) + 2
    }

    /// Writes the line (upper-case hex) to the start of `out` and returns its length.
    pub fn emit(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        let needed = self.emitted_len();
        let too_small = BufferTooSmall {
            needed,
            available: out.len(),
        };
        let frame = out.get_mut(..needed).ok_or(too_small)?;
        // The binary content is built on the stack, then spelt out in hex.
        let mut binary = [0u8; MAX_BINARY_LEN];
        binary[0] = self.unit;
        let pdu_len = self.pdu.encode_pdu(&mut binary[1..MAX_BINARY_LEN - 1])?;
        let checked = 1 + pdu_len;
        binary[checked] = lrc(&binary[..checked]);
        let content = &binary[..checked + 1];

        let (start, rest) = frame.split_first_mut().ok_or(too_small)?;
        *start = START;
        for (pair, &byte) in rest.chunks_exact_mut(2).zip(content) {
            pair.copy_from_slice(&[
                HEX_UPPER[usize::from(byte >> 4)],
                HEX_UPPER[usize::from(byte & 0x0F)],
            ]);
        }
        let end = 1 + 2 * content.len();
        frame
            .get_mut(end..end + 2)
            .ok_or(too_small)?
            .copy_from_slice(&[CR, LF]);
        Ok(end + 2)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// Between frames: everything but `:` is noise.
    Idle,
    /// Inside a frame, after `:`.
    Frame {
        /// A high nibble waiting for its low one.
        high: Option<u8>,
        /// CR seen, LF expected next.
        cr: bool,
    },
}

/// Turns a Modbus ASCII byte stream, in chunks of any size, into frames.
///
/// ```
/// use protocols::modbus::Adu;
/// use protocols::modbus::ascii::AsciiDecoder;
///
/// let mut decoder = AsciiDecoder::new();
/// let mut input: &[u8] = b"noise:F7031389000A60\r\n";
/// let frame = decoder.decode(&mut input).unwrap().unwrap();
/// assert_eq!((frame.unit(), frame.pdu()), (0xF7, &[0x03, 0x13, 0x89, 0x00, 0x0A][..]));
/// assert_eq!(decoder.drops().noise.bytes, 5);
/// ```
#[derive(Debug, Clone)]
pub struct AsciiDecoder {
    binary: [u8; MAX_BINARY_LEN],
    len: usize,
    /// Characters of the current frame so far, `:` included.
    chars: usize,
    state: State,
    in_noise: bool,
    drops: Drops,
}

impl Default for AsciiDecoder {
    fn default() -> Self {
        AsciiDecoder::new()
    }
}

impl AsciiDecoder {
    /// An idle decoder.
    pub fn new() -> Self {
        AsciiDecoder {
            binary: [0; MAX_BINARY_LEN],
            len: 0,
            chars: 0,
            state: State::Idle,
            in_noise: false,
            drops: Drops::default(),
        }
    }

    /// Takes bytes from the front of `input` until a frame ends. `None` means
    /// `input` is used up; call again while it is not empty. A frame that ends
    /// in CR LF but fails its LRC or form is returned as an error once; frames
    /// cut short by a new `:` or a stray character are only counted.
    pub fn decode(&mut self, input: &mut &[u8]) -> Option<Result<AsciiFrame<&[u8]>, FrameError>> {
        while let Some((&c, rest)) = input.split_first() {
            *input = rest;
            match self.state {
                State::Idle => {
                    if c == START {
                        self.start_frame();
                    } else {
                        if !self.in_noise {
                            self.drops.noise.events += 1;
                            self.in_noise = true;
                        }
                        self.drops.noise.bytes += 1;
                    }
                }
                State::Frame { high, cr } => {
                    self.chars += 1;
                    match (c, cr) {
                        (START, _) => {
                            // A new start inside a frame: the old one was cut short.
                            self.chars -= 1;
                            self.abort(false);
                            self.start_frame();
                        }
                        (LF, true) => {
                            self.state = State::Idle;
                            let chars = core::mem::take(&mut self.chars);
                            let checked = match high {
                                Some(_) => Err(FrameError::OddHexLength),
                                None => check_content(&self.binary[..self.len]),
                            };
                            return Some(match checked {
                                Ok(_) => Ok(AsciiFrame::new_unchecked(&self.binary[..self.len])),
                                Err(err) => {
                                    self.drops.bad_check.add(chars);
                                    Err(err)
                                }
                            });
                        }
                        (CR, false) => self.state = State::Frame { high, cr: true },
                        (_, true) => self.abort(false),
                        (_, false) => match (hex_value(c), high) {
                            (None, _) => self.abort(false),
                            (Some(h), None) => {
                                self.state = State::Frame {
                                    high: Some(h),
                                    cr: false,
                                }
                            }
                            (Some(l), Some(h)) => {
                                if let Some(slot) = self.binary.get_mut(self.len) {
                                    *slot = h << 4 | l;
                                    self.len += 1;
                                    self.state = State::Frame {
                                        high: None,
                                        cr: false,
                                    };
                                } else {
                                    self.abort(true);
                                }
                            }
                        },
                    }
                }
            }
        }
        None
    }

    /// What has been thrown away so far, by reason.
    pub fn drops(&self) -> &Drops {
        &self.drops
    }

    /// Characters held for a frame that is not complete yet, `:` included.
    pub fn pending(&self) -> usize {
        match self.state {
            State::Idle => 0,
            State::Frame { .. } => self.chars,
        }
    }

    fn start_frame(&mut self) {
        self.in_noise = false;
        self.len = 0;
        self.chars = 1;
        self.state = State::Frame {
            high: None,
            cr: false,
        };
    }

    /// Drops the frame in progress (counting its characters) and goes idle.
    fn abort(&mut self, oversize: bool) {
        let tally = if oversize {
            &mut self.drops.oversize
        } else {
            &mut self.drops.malformed
        };
        tally.add(self.chars);
        self.chars = 0;
        self.len = 0;
        self.state = State::Idle;
        // What follows up to the next `:` is noise of its own.
        self.in_noise = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::pdu::Request;

    #[test]
    fn spec_example_round_trips() {
        let line = b":F7031389000A60\r\n";
        let mut scratch = [0u8; MAX_BINARY_LEN];
        let frame = AsciiFrame::decode_line(line, &mut scratch).unwrap();
        assert_eq!((frame.unit(), frame.lrc()), (0xF7, 0x60));
        let request = frame.request().unwrap();
        assert_eq!(
            request,
            Request::ReadHoldingRegisters {
                address: 0x1389,
                quantity: 10
            }
        );
        let mut out = [0u8; MAX_ADU_LEN];
        let n = AsciiRepr {
            unit: 0xF7,
            pdu: &request,
        }
        .emit(&mut out)
        .unwrap();
        assert_eq!(&out[..n], line);
        // Lower case is accepted and re-emits upper case.
        let lower = b":f7031389000a60\r\n";
        assert_eq!(
            AsciiFrame::decode_line(lower, &mut scratch)
                .unwrap()
                .request()
                .unwrap(),
            request
        );
    }

    #[test]
    fn malformed_lines_are_typed() {
        let mut s = [0u8; MAX_BINARY_LEN];
        assert_eq!(
            AsciiFrame::decode_line(b"F7031389000A60\r\n", &mut s),
            Err(FrameError::MissingStart)
        );
        assert_eq!(
            AsciiFrame::decode_line(b":F7031389000A60\n", &mut s),
            Err(FrameError::MissingEnd)
        );
        assert_eq!(
            AsciiFrame::decode_line(b":F7031389000A6\r\n", &mut s),
            Err(FrameError::OddHexLength)
        );
        assert_eq!(
            AsciiFrame::decode_line(b":F7031389000A61\r\n", &mut s),
            Err(FrameError::BadLrc {
                received: 0x61,
                calculated: 0x60
            })
        );
        assert_eq!(
            AsciiFrame::decode_line(b":F70G1389000A60\r\n", &mut s),
            Err(FrameError::NotHex {
                byte: b'G',
                position: 4
            })
        );
        assert!(matches!(
            AsciiFrame::decode_line(b":0101\r\n", &mut s),
            Err(FrameError::TooShort { .. })
        ));
    }

    #[test]
    fn decoder_resyncs_at_colon_and_counts() {
        let mut decoder = AsciiDecoder::new();
        let mut input: &[u8] = b":F703\r\nxx:F7031:F7031389000A60\r\n:F7031389000A61\r\n";
        // ":F703\r\n" is complete but too short: an error, counted.
        assert!(matches!(
            decoder.decode(&mut input),
            Some(Err(FrameError::TooShort { .. }))
        ));
        let frame = decoder.decode(&mut input).unwrap().unwrap();
        assert_eq!(frame.unit(), 0xF7);
        assert_eq!(
            decoder.decode(&mut input),
            Some(Err(FrameError::BadLrc {
                received: 0x61,
                calculated: 0x60
            }))
        );
        assert!(decoder.decode(&mut input).is_none());
        let drops = decoder.drops();
        assert_eq!(drops.noise.bytes, 2);
        assert_eq!(drops.malformed.bytes, ":F7031".len() as u64);
        assert_eq!(drops.bad_check.events, 2);
    }
}
