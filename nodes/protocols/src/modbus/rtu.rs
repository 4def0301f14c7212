//! Modbus RTU framing: unit id, PDU, CRC-16/MODBUS low byte first.
//!
//! A frame's length follows from its function code and byte count, which
//! differ between requests and replies, so the stream decoder is told which
//! direction it listens to. A function code it does not know is delimited by
//! the silence after it, so that a slave can still answer it with exception 01.

use crate::crc::crc16_modbus;
use crate::time::SimTime;

use super::adu::{Adu, SerialAdu, pdu_of};
use super::pdu::{EncodePdu, function};
use super::serial::{FrameLen, Framing, SerialCore, Timing};
use super::{BufferTooSmall, Drops, FrameError};

/// The shortest RTU frame: unit, function, CRC.
pub const MIN_ADU_LEN: usize = 4;
/// The longest RTU frame: unit, 253-byte PDU, CRC.
pub const MAX_ADU_LEN: usize = 256;

/// A checked view over the bytes of one RTU frame: unit id, PDU, CRC.
///
/// [`RtuFrame::new_checked`] checks the length and the CRC, so every accessor
/// reads a well-formed frame; the PDU is left as bytes for
/// [`Adu::request`] or [`Adu::response`] to parse. A slave reads
/// [`Adu::unit`] first, so a frame for another slave costs one compare.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RtuFrame<T: AsRef<[u8]>> {
    buffer: T,
}

impl<T: AsRef<[u8]>> RtuFrame<T> {
    /// Checks `buffer` as one whole frame: its length, then its CRC.
    pub fn new_checked(buffer: T) -> Result<Self, FrameError> {
        check(buffer.as_ref())?;
        Ok(RtuFrame { buffer })
    }

    /// A view over bytes a decoder has already checked.
    fn new_unchecked(buffer: T) -> Self {
        RtuFrame { buffer }
    }

    /// The CRC as a number (sent low byte first).
    pub fn crc(&self) -> u16 {
        match self.buffer.as_ref() {
            [.., lo, hi] => u16::from_le_bytes([*lo, *hi]),
            _ => 0,
        }
    }

    /// Gives the buffer back.
    pub fn into_inner(self) -> T {
        self.buffer
    }
}

impl<T: AsRef<[u8]>> Adu for RtuFrame<T> {
    /// The unit id.
    const HEADER_LEN: usize = 1;
    /// The CRC.
    const CHECK_LEN: usize = 2;

    fn as_bytes(&self) -> &[u8] {
        self.buffer.as_ref()
    }
}

impl<T: AsRef<[u8]>> SerialAdu for RtuFrame<T> {}

impl<'a, T: AsRef<[u8]> + ?Sized> RtuFrame<&'a T> {
    /// Function code and data; never empty. Borrowed from the buffer, so it
    /// outlives the view (a decoder's frame can be kept while it goes on).
    pub fn pdu(&self) -> &'a [u8] {
        pdu_of::<Self>(self.buffer.as_ref())
    }
}

fn check(adu: &[u8]) -> Result<(), FrameError> {
    if adu.len() < MIN_ADU_LEN {
        return Err(FrameError::TooShort {
            len: adu.len(),
            min: MIN_ADU_LEN,
        });
    }
    if adu.len() > MAX_ADU_LEN {
        return Err(FrameError::TooLong {
            len: adu.len(),
            max: MAX_ADU_LEN,
        });
    }
    let (body, crc) = adu.split_at(adu.len() - 2);
    let received = match crc {
        &[lo, hi] => u16::from_le_bytes([lo, hi]),
        _ => 0,
    };
    let calculated = crc16_modbus(body);
    if received != calculated {
        return Err(FrameError::BadCrc {
            received,
            calculated,
        });
    }
    Ok(())
}

/// One RTU frame as a value: the unit id and a PDU. Parsed, the PDU is the
/// frame's bytes (`RtuRepr<&[u8]>`); to emit, it is anything that writes a PDU
/// (a [`Request`](super::Request), a reply, raw bytes).
///
/// ```
/// use protocols::modbus::Request;
/// use protocols::modbus::rtu::RtuRepr;
///
/// let request = Request::ReadHoldingRegisters { address: 0, quantity: 10 };
/// let mut out = [0u8; 8];
/// let n = RtuRepr { unit: 1, pdu: &request }.emit(&mut out).unwrap();
/// assert_eq!(out[..n], [0x01, 0x03, 0x00, 0x00, 0x00, 0x0A, 0xC5, 0xCD]);
/// assert_eq!(RtuRepr::parse(&out).unwrap().unit, 1);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RtuRepr<P> {
    /// Unit id (slave address); 0 is the broadcast.
    pub unit: u8,
    /// Function code and data.
    pub pdu: P,
}

impl<'a> RtuRepr<&'a [u8]> {
    /// Checks one whole frame and reads its unit id and PDU.
    pub fn parse(adu: &'a [u8]) -> Result<Self, FrameError> {
        RtuFrame::new_checked(adu).map(|frame| Self::from_frame(&frame))
    }

    /// The value of a checked frame.
    pub fn from_frame<T: AsRef<[u8]> + ?Sized>(frame: &RtuFrame<&'a T>) -> Self {
        RtuRepr {
            unit: frame.unit(),
            pdu: frame.pdu(),
        }
    }
}

impl<P: EncodePdu> RtuRepr<P> {
    /// The length of the frame: unit, PDU, CRC.
    pub fn emitted_len(&self) -> usize {
        1 + self.pdu.pdu_len() + 2
    }

    /// Writes the frame to the start of `out` and returns its length.
    pub fn emit(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        let needed = self.emitted_len();
        let too_small = BufferTooSmall {
            needed,
            available: out.len(),
        };
        let frame = out.get_mut(..needed).ok_or(too_small)?;
        let (head, rest) = frame.split_first_mut().ok_or(too_small)?;
        *head = self.unit;
        let pdu_len = self.pdu.encode_pdu(rest)?;
        let body_len = 1 + pdu_len;
        let crc = crc16_modbus(frame.get(..body_len).unwrap_or(&[]));
        let slot = frame.get_mut(body_len..body_len + 2).ok_or(too_small)?;
        slot.copy_from_slice(&crc.to_le_bytes());
        Ok(body_len + 2)
    }
}

/// Which way the frames a decoder listens to travel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// Master to slave (a slave's decoder).
    Request,
    /// Slave to master (a master's decoder).
    Response,
}

/// The frame length an RTU header implies (`buf` holds the frame's first
/// bytes, however many have come).
pub fn frame_len(direction: Direction, buf: &[u8]) -> FrameLen {
    let Some(&fc) = buf.get(1) else {
        return FrameLen::NeedAtLeast(2);
    };
    let counted = |at: usize, overhead: usize| match buf.get(at) {
        Some(&count) => FrameLen::Known(overhead + usize::from(count)),
        None => FrameLen::NeedAtLeast(at + 1),
    };
    match direction {
        Direction::Request => match fc {
            function::READ_COILS..=function::WRITE_SINGLE_REGISTER => FrameLen::Known(8),
            // unit fc addr(2) qty(2) count, data, crc(2)
            function::WRITE_MULTIPLE_COILS | function::WRITE_MULTIPLE_REGISTERS => counted(6, 9),
            _ => FrameLen::UntilSilence,
        },
        Direction::Response => match fc {
            fc if fc & function::EXCEPTION_BIT != 0 => FrameLen::Known(5),
            // unit fc count, data, crc(2)
            function::READ_COILS..=function::READ_INPUT_REGISTERS => counted(2, 5),
            function::WRITE_SINGLE_COIL
            | function::WRITE_SINGLE_REGISTER
            | function::WRITE_MULTIPLE_COILS
            | function::WRITE_MULTIPLE_REGISTERS => FrameLen::Known(8),
            _ => FrameLen::UntilSilence,
        },
    }
}

#[derive(Debug, Clone, Copy)]
struct RtuFraming(Direction);

impl Framing for RtuFraming {
    type Error = FrameError;
    fn frame_len(&self, buf: &[u8]) -> FrameLen {
        frame_len(self.0, buf)
    }

    fn check(&self, frame: &[u8]) -> Result<(), FrameError> {
        check(frame)
    }
}

/// Turns RTU bytes, in chunks of any size with their arrival times, into frames.
///
/// ```
/// use protocols::modbus::Adu;
/// use protocols::modbus::rtu::{Direction, RtuDecoder};
/// use protocols::modbus::serial::{PTY_SILENCE, Timing};
/// use protocols::time::SimTime;
///
/// let mut decoder = RtuDecoder::new(Direction::Request, Timing::Silence(PTY_SILENCE));
/// let mut input: &[u8] = &[0x01, 0x03, 0x00, 0x00, 0x00, 0x0A, 0xC5, 0xCD];
/// let frame = decoder.decode(SimTime::ZERO, &mut input).unwrap().unwrap();
/// assert_eq!((frame.unit(), frame.pdu()), (1, &[0x03, 0x00, 0x00, 0x00, 0x0A][..]));
/// assert!(decoder.decode(SimTime::ZERO, &mut input).is_none());
/// ```
#[derive(Debug, Clone)]
pub struct RtuDecoder {
    core: SerialCore<MAX_ADU_LEN>,
    framing: RtuFraming,
}

impl RtuDecoder {
    /// A decoder for frames travelling in `direction`, delimited as `timing` says.
    pub fn new(direction: Direction, timing: Timing) -> Self {
        RtuDecoder {
            core: SerialCore::new(timing),
            framing: RtuFraming(direction),
        }
    }

    /// Takes bytes that arrived at `now` from the front of `input` until a frame
    /// is complete. `None` means `input` is used up and a frame needs more;
    /// call again while `input` is not empty. A frame whose CRC fails is
    /// returned as an error once (a master reports it; a slave ignores it).
    pub fn decode(
        &mut self,
        now: SimTime,
        input: &mut &[u8],
    ) -> Option<Result<RtuFrame<&[u8]>, FrameError>> {
        let item = self.core.decode(&self.framing, now, input)?;
        // The core hands out only bytes the framing's check passed.
        Some(item.map(RtuFrame::new_unchecked))
    }

    /// When [`RtuDecoder::handle_timeout`] should next be called, if a partial
    /// frame or a discard is waiting for a silence.
    pub fn poll_timeout(&self) -> Option<SimTime> {
        self.core.poll_timeout()
    }

    /// Applies the silence rule at `now`: drops a partial frame, or completes one
    /// whose length only the silence gives (an unknown function code).
    pub fn handle_timeout(&mut self, now: SimTime) -> Option<Result<RtuFrame<&[u8]>, FrameError>> {
        let item = self.core.handle_timeout(&self.framing, now)?;
        Some(item.map(RtuFrame::new_unchecked))
    }

    /// What has been thrown away so far, by reason.
    pub fn drops(&self) -> &Drops {
        &self.core.drops
    }

    /// Bytes held for a frame that is not complete yet.
    pub fn pending(&self) -> usize {
        self.core.pending()
    }

    /// How this decoder delimits frames.
    pub fn timing(&self) -> Timing {
        self.core.timing()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::pdu::{ExceptionResponse, Request, Response};
    use crate::modbus::serial::PTY_SILENCE;

    const READ_10: [u8; 8] = [0x01, 0x03, 0x00, 0x00, 0x00, 0x0A, 0xC5, 0xCD];

    #[test]
    fn parse_and_emit_a_known_frame() {
        let frame = RtuFrame::new_checked(&READ_10).unwrap();
        assert_eq!(frame.unit(), 1);
        assert_eq!(frame.crc(), 0xCDC5);
        let request = frame.request().unwrap();
        assert_eq!(
            request,
            Request::ReadHoldingRegisters {
                address: 0,
                quantity: 10
            }
        );
        let mut out = [0u8; MAX_ADU_LEN];
        let n = RtuRepr {
            unit: 1,
            pdu: &request,
        }
        .emit(&mut out)
        .unwrap();
        assert_eq!(&out[..n], READ_10);
        let repr = RtuRepr::parse(&out[..n]).unwrap();
        assert_eq!((repr.unit, repr.pdu), (1, &READ_10[1..6]));
    }

    #[test]
    fn bad_crc_reports_both_values() {
        let mut bad = READ_10;
        bad[7] ^= 1;
        assert_eq!(
            RtuFrame::new_checked(&bad),
            Err(FrameError::BadCrc {
                received: 0xCCC5,
                calculated: 0xCDC5
            })
        );
    }

    #[test]
    fn emit_into_a_short_buffer_fails_cleanly() {
        let request = Request::ReadCoils {
            address: 0,
            quantity: 1,
        };
        let mut out = [0u8; 7];
        assert_eq!(
            RtuRepr {
                unit: 1,
                pdu: &request
            }
            .emit(&mut out),
            Err(BufferTooSmall {
                needed: 8,
                available: 7
            })
        );
    }

    #[test]
    fn unknown_function_is_delimited_by_silence() {
        // 0x2B read device identification: a slave must see it to answer 01.
        let mut out = [0u8; 16];
        let pdu: &[u8] = &[0x2B, 0x0E, 0x01, 0x00];
        let n = RtuRepr { unit: 1, pdu }.emit(&mut out).unwrap();
        let mut decoder = RtuDecoder::new(Direction::Request, Timing::Silence(PTY_SILENCE));
        let mut input = &out[..n];
        assert!(decoder.decode(SimTime::ZERO, &mut input).is_none());
        let due = decoder.poll_timeout().unwrap();
        assert_eq!(due, SimTime::ZERO + PTY_SILENCE);
        assert!(decoder.handle_timeout(SimTime(due.0 - 1)).is_none());
        let frame = decoder.handle_timeout(due).unwrap().unwrap();
        assert_eq!(frame.pdu(), &[0x2B, 0x0E, 0x01, 0x00]);
        assert_eq!(decoder.poll_timeout(), None);
    }

    #[test]
    fn a_slave_skips_another_slaves_reply_on_a_shared_line() {
        use crate::modbus::{Registers, serial::silence_3_5_chars};
        use crate::time::SimDuration;

        const BAUD: u32 = 115_200;
        let mut line = Vec::new();
        let mut out = [0u8; MAX_ADU_LEN];
        let read = Request::ReadHoldingRegisters {
            address: 0,
            quantity: 10,
        };
        let n = RtuRepr {
            unit: 1,
            pdu: &read,
        }
        .emit(&mut out)
        .unwrap();
        line.push(out[..n].to_vec());
        let values: Vec<u16> = (0..10).map(|i| 0x0101 * i).collect();
        let reply = Response::ReadHoldingRegisters(Registers::from_slice(&values).unwrap());
        let n = RtuRepr {
            unit: 1,
            pdu: &Ok::<_, ExceptionResponse>(reply),
        }
        .emit(&mut out)
        .unwrap();
        line.push(out[..n].to_vec());
        let n = RtuRepr {
            unit: 2,
            pdu: &read,
        }
        .emit(&mut out)
        .unwrap();
        line.push(out[..n].to_vec());

        // Slave 2 hears all three frames, byte by byte, 3.5 characters apart.
        let char_time = SimDuration::bit_times(10, BAUD);
        let silence = silence_3_5_chars(BAUD, 10);
        let mut decoder = RtuDecoder::new(Direction::Request, Timing::Silence(silence));
        let mut now = SimTime::ZERO;
        let mut mine = Vec::new();
        for frame in &line {
            for byte in frame {
                now += char_time;
                let mut input = core::slice::from_ref(byte);
                while let Some(item) = decoder.decode(now, &mut input) {
                    if let Ok(frame) = item
                        && frame.is_for(2)
                    {
                        mine.push(frame.request().unwrap());
                    }
                }
            }
            now += silence;
        }
        assert_eq!(mine, [read]);
        // The reply (25 bytes) read as a request: 8 bytes fail the CRC, the
        // other 17 are thrown away up to the silence.
        let drops = decoder.drops();
        assert_eq!((drops.bad_check.events, drops.bad_check.bytes), (1, 8));
        assert_eq!(drops.after_bad_frame.bytes, 17);
    }

    #[test]
    fn without_timing_garbage_is_dropped_byte_by_byte() {
        let mut decoder = RtuDecoder::new(Direction::Request, Timing::None);
        let mut stream = vec![0x00, 0x11];
        stream.extend(READ_10);
        let mut input = &stream[..];
        let frame = decoder.decode(SimTime::ZERO, &mut input).unwrap().unwrap();
        assert_eq!(frame.unit(), 1);
        assert!(input.is_empty());
        assert_eq!(decoder.drops().malformed.bytes, 2);
    }
}
