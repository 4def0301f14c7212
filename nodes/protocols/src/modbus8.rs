//! The 8-byte Modbus variant of the Controller_network project
//! (`docs/protocols/modbus8.md`): every request and reply is id, function,
//! address, value, CRC — eight bytes, with the CRC high byte first unless the
//! order is set to the standard one.
//!
//! - [`Modbus8Frame`] is a checked view over the eight bytes (CRC checked in
//!   the order given); [`Modbus8Repr`] is the value (`parse`, `from_frame`,
//!   `emit`), following smoltcp's `wire` split of `Packet` and `Repr`, as MEB
//!   and standard Modbus do.
//! - [`Modbus8Decoder`] cuts a byte stream into frames by the spec's silence rule.
//!
//! A reply with the function's top bit set is an exception; it is still a
//! valid frame, and `reply()` separates the two as `Result<value, Exception>`.
//! A bad CRC or a wrong length is a [`Modbus8Error`]. Nothing here panics or
//! allocates, whatever the input.

use thiserror::Error;

use crate::crc::crc16_modbus;
use crate::modbus::serial::{FrameLen, Framing, SerialCore, Timing};
use crate::modbus::{BufferTooSmall, Drops, Exception};
use crate::time::{SimDuration, SimTime};

/// Every frame of this variant is this long.
pub const FRAME_LEN: usize = 8;

/// Function 03: read one register.
pub const READ: u8 = 0x03;
/// Function 06: write one register (answered by an echo).
pub const WRITE: u8 = 0x06;
/// Set on the function of an exception reply.
pub const EXCEPTION_BIT: u8 = 0x80;

/// The order in which the CRC's two bytes go on the wire.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum CrcOrder {
    /// High byte first: what the Controller_network master and Arduinos send.
    #[default]
    HighFirst,
    /// Low byte first, as standard Modbus RTU, to serve a standard-order peer.
    LowFirst,
}

impl CrcOrder {
    fn write(self, crc: u16) -> [u8; 2] {
        match self {
            CrcOrder::HighFirst => crc.to_be_bytes(),
            CrcOrder::LowFirst => crc.to_le_bytes(),
        }
    }

    fn read(self, bytes: [u8; 2]) -> u16 {
        match self {
            CrcOrder::HighFirst => u16::from_be_bytes(bytes),
            CrcOrder::LowFirst => u16::from_le_bytes(bytes),
        }
    }
}

/// Why eight bytes are not a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum Modbus8Error {
    /// Not exactly eight bytes.
    #[error("frame of {len} bytes, expected 8")]
    WrongLength {
        /// Bytes received.
        len: usize,
    },
    /// The CRC does not match (values read in the configured byte order, as the
    /// Controller_network master prints them: "Received: 0xaada Calculated: 0xaad9").
    #[error("CRC error: received {received:#06x}, calculated {calculated:#06x}")]
    BadCrc {
        /// CRC carried by the frame.
        received: u16,
        /// CRC computed over its first six bytes.
        calculated: u16,
    },
}

/// A checked view over the eight bytes of one frame, request or reply.
///
/// [`Modbus8Frame::new_checked`] checks the length and the CRC in the order
/// given, so every accessor reads a well-formed frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Modbus8Frame<T: AsRef<[u8]>> {
    buffer: T,
    order: CrcOrder,
}

impl<T: AsRef<[u8]>> Modbus8Frame<T> {
    /// Checks `buffer` as one whole frame: exactly eight bytes, the CRC in `order`.
    pub fn new_checked(buffer: T, order: CrcOrder) -> Result<Self, Modbus8Error> {
        check(buffer.as_ref(), order)?;
        Ok(Modbus8Frame { buffer, order })
    }

    /// A view over bytes a decoder has already checked.
    fn new_unchecked(buffer: T, order: CrcOrder) -> Self {
        Modbus8Frame { buffer, order }
    }

    fn byte(&self, at: usize) -> u8 {
        self.buffer.as_ref().get(at).copied().unwrap_or(0)
    }

    fn word(&self, at: usize) -> u16 {
        u16::from_be_bytes([self.byte(at), self.byte(at + 1)])
    }

    /// Slave id: 1 motor, 2 light sensor.
    pub fn id(&self) -> u8 {
        self.byte(0)
    }

    /// Function: 03 read, 06 write; top bit set on an exception reply.
    pub fn function(&self) -> u8 {
        self.byte(1)
    }

    /// Register address.
    pub fn addr(&self) -> u16 {
        self.word(2)
    }

    /// Register value; on an exception reply, the exception code.
    pub fn value(&self) -> u16 {
        self.word(4)
    }

    /// The CRC as a number, read in the frame's byte order.
    pub fn crc(&self) -> u16 {
        self.order.read([self.byte(6), self.byte(7)])
    }

    /// The order the CRC was checked in.
    pub fn crc_order(&self) -> CrcOrder {
        self.order
    }

    /// True for an exception reply.
    pub fn is_exception(&self) -> bool {
        self.function() & EXCEPTION_BIT != 0
    }

    /// A reply's content: the register value, or the exception it carries.
    pub fn reply(&self) -> Result<u16, Exception> {
        Modbus8Repr::from_frame(self).reply()
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

fn check(bytes: &[u8], order: CrcOrder) -> Result<(), Modbus8Error> {
    let &[id, function, a_hi, a_lo, v_hi, v_lo, c0, c1] = bytes else {
        return Err(Modbus8Error::WrongLength { len: bytes.len() });
    };
    let received = order.read([c0, c1]);
    let calculated = crc16_modbus(&[id, function, a_hi, a_lo, v_hi, v_lo]);
    if received != calculated {
        return Err(Modbus8Error::BadCrc {
            received,
            calculated,
        });
    }
    Ok(())
}

/// One 8-byte frame as a value, request or reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Modbus8Repr {
    /// Slave id: 1 motor, 2 light sensor.
    pub id: u8,
    /// Function: 03 read, 06 write; top bit set on an exception reply.
    pub function: u8,
    /// Register address.
    pub addr: u16,
    /// Register value; on an exception reply, the exception code.
    pub value: u16,
}

impl Modbus8Repr {
    /// Checks exactly eight bytes as a frame, the CRC in `order`, and reads it.
    pub fn parse(bytes: &[u8], order: CrcOrder) -> Result<Self, Modbus8Error> {
        Modbus8Frame::new_checked(bytes, order).map(|frame| Self::from_frame(&frame))
    }

    /// The value of a checked frame.
    pub fn from_frame<T: AsRef<[u8]>>(frame: &Modbus8Frame<T>) -> Self {
        Modbus8Repr {
            id: frame.id(),
            function: frame.function(),
            addr: frame.addr(),
            value: frame.value(),
        }
    }

    /// The exception reply to a request with `function` at `addr`: id and
    /// address kept, top bit of the function set, the code in the value.
    pub fn exception(id: u8, function: u8, addr: u16, exception: Exception) -> Self {
        Modbus8Repr {
            id,
            function: function | EXCEPTION_BIT,
            addr,
            value: u16::from(exception.code()),
        }
    }

    /// True for an exception reply.
    pub fn is_exception(&self) -> bool {
        self.function & EXCEPTION_BIT != 0
    }

    /// A reply's content: the register value, or the exception it carries
    /// (codes above 0xFF, which no slave sends, read as [`Exception::Other`]).
    pub fn reply(&self) -> Result<u16, Exception> {
        if self.is_exception() {
            Err(Exception::from_code(
                u8::try_from(self.value).unwrap_or(0xFF),
            ))
        } else {
            Ok(self.value)
        }
    }

    /// The frame's eight bytes with the CRC in `order`.
    pub fn to_bytes(&self, order: CrcOrder) -> [u8; FRAME_LEN] {
        let [a_hi, a_lo] = self.addr.to_be_bytes();
        let [v_hi, v_lo] = self.value.to_be_bytes();
        let body = [self.id, self.function, a_hi, a_lo, v_hi, v_lo];
        let [c0, c1] = order.write(crc16_modbus(&body));
        [self.id, self.function, a_hi, a_lo, v_hi, v_lo, c0, c1]
    }

    /// Writes the frame, the CRC in `order`, to the start of `out`; returns 8.
    pub fn emit(&self, out: &mut [u8], order: CrcOrder) -> Result<usize, BufferTooSmall> {
        let available = out.len();
        let slot = out.get_mut(..FRAME_LEN).ok_or(BufferTooSmall {
            needed: FRAME_LEN,
            available,
        })?;
        slot.copy_from_slice(&self.to_bytes(order));
        Ok(FRAME_LEN)
    }
}

#[derive(Debug, Clone, Copy)]
struct Modbus8Framing(CrcOrder);

impl Framing for Modbus8Framing {
    type Error = Modbus8Error;

    fn frame_len(&self, _buf: &[u8]) -> FrameLen {
        FrameLen::Known(FRAME_LEN)
    }

    fn check(&self, frame: &[u8]) -> Result<(), Modbus8Error> {
        check(frame, self.0)
    }
}

/// Turns the bytes of an 8-byte Modbus line, in chunks of any size with their
/// arrival times, into frames, by the spec's rule: eight bytes are a frame as
/// soon as they are there; a partial frame followed by a silence is dropped, and
/// so are the bytes after a bad CRC up to the next silence, so a stray byte
/// cannot misalign every later frame.
///
/// ```
/// use protocols::modbus8::{CrcOrder, Modbus8Decoder};
/// use protocols::time::SimTime;
///
/// let mut decoder = Modbus8Decoder::for_pty(CrcOrder::HighFirst);
/// let mut input: &[u8] = &[0x01, 0x06, 0x00, 0x01, 0x00, 0x80, 0xaa, 0xd9];
/// let frame = decoder.decode(SimTime::ZERO, &mut input).unwrap().unwrap();
/// assert_eq!((frame.id(), frame.function(), frame.addr(), frame.value()), (1, 6, 1, 0x80));
/// ```
#[derive(Debug, Clone)]
pub struct Modbus8Decoder {
    core: SerialCore<FRAME_LEN>,
    framing: Modbus8Framing,
}

impl Modbus8Decoder {
    /// A decoder checking CRCs in `order`, for which `silence` of line quiet
    /// ends a partial frame or a discard.
    pub fn new(order: CrcOrder, silence: SimDuration) -> Self {
        Modbus8Decoder {
            core: SerialCore::new(Timing::Silence(silence)),
            framing: Modbus8Framing(order),
        }
    }

    /// A decoder for a serial line at `baud` (8N1): 3.5 character times.
    pub fn for_baud(order: CrcOrder, baud: u32) -> Self {
        Self::new(order, crate::modbus::serial::silence_3_5_chars(baud, 10))
    }

    /// A decoder for a pseudo-terminal, whose bytes carry no timing: 5 ms.
    pub fn for_pty(order: CrcOrder) -> Self {
        Self::new(order, crate::modbus::serial::PTY_SILENCE)
    }

    /// Takes bytes that arrived at `now` from the front of `input` until a frame
    /// is complete. `None` means `input` is used up; call again while it is not
    /// empty. A bad CRC comes out once as an error (a master reports it, a slave
    /// stays silent), then the line is ignored up to the next silence.
    pub fn decode(
        &mut self,
        now: SimTime,
        input: &mut &[u8],
    ) -> Option<Result<Modbus8Frame<&[u8]>, Modbus8Error>> {
        let order = self.framing.0;
        let item = self.core.decode(&self.framing, now, input)?;
        // The core hands out only bytes the framing's check passed.
        Some(item.map(|bytes| Modbus8Frame::new_unchecked(bytes, order)))
    }

    /// When [`Modbus8Decoder::handle_timeout`] should next be called, if a
    /// partial frame or a discard is waiting for a silence.
    pub fn poll_timeout(&self) -> Option<SimTime> {
        self.core.poll_timeout()
    }

    /// Applies the silence rule at `now` (drops a partial frame, ends a discard).
    pub fn handle_timeout(&mut self, now: SimTime) {
        // Every frame has a known length, so a silence never completes one.
        let _ = self.core.handle_timeout(&self.framing, now);
    }

    /// What has been thrown away so far, by reason.
    pub fn drops(&self) -> &Drops {
        &self.core.drops
    }

    /// Bytes held for a frame that is not complete yet.
    pub fn pending(&self) -> usize {
        self.core.pending()
    }

    /// The CRC byte order this decoder checks.
    pub fn crc_order(&self) -> CrcOrder {
        self.framing.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const WRITE_80: [u8; 8] = [0x01, 0x06, 0x00, 0x01, 0x00, 0x80, 0xaa, 0xd9];

    #[test]
    fn controller_network_bad_crc_message_values() {
        let mut bad = WRITE_80;
        bad[7] = 0xda;
        assert_eq!(
            Modbus8Repr::parse(&bad, CrcOrder::HighFirst),
            Err(Modbus8Error::BadCrc {
                received: 0xaada,
                calculated: 0xaad9
            })
        );
        assert_eq!(
            Modbus8Error::BadCrc {
                received: 0xaada,
                calculated: 0xaad9
            }
            .to_string(),
            "CRC error: received 0xaada, calculated 0xaad9"
        );
    }

    #[test]
    fn exception_reply_round_trip() {
        let frame = Modbus8Repr::exception(1, WRITE, 2, Exception::IllegalDataAddress);
        assert_eq!(frame.reply(), Err(Exception::IllegalDataAddress));
        let bytes = frame.to_bytes(CrcOrder::HighFirst);
        assert_eq!(bytes, [0x01, 0x86, 0x00, 0x02, 0x00, 0x02, 0x15, 0xa8]);
        let view = Modbus8Frame::new_checked(&bytes, CrcOrder::HighFirst).unwrap();
        assert_eq!(view.reply(), Err(Exception::IllegalDataAddress));
        assert_eq!(
            (view.crc(), Modbus8Repr::from_frame(&view)),
            (0x15a8, frame)
        );
    }

    #[test]
    fn wrong_lengths_are_rejected() {
        assert_eq!(
            Modbus8Repr::parse(&WRITE_80[..7], CrcOrder::HighFirst),
            Err(Modbus8Error::WrongLength { len: 7 })
        );
        let mut nine = [0u8; 9];
        nine[..8].copy_from_slice(&WRITE_80);
        assert_eq!(
            Modbus8Repr::parse(&nine, CrcOrder::HighFirst),
            Err(Modbus8Error::WrongLength { len: 9 })
        );
        let mut short = [0u8; 7];
        assert!(
            Modbus8Repr::parse(&WRITE_80, CrcOrder::HighFirst)
                .unwrap()
                .emit(&mut short, CrcOrder::HighFirst)
                .is_err()
        );
    }
}
