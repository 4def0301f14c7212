//! Modbus TCP framing: the MBAP header (transaction id, protocol id 0, length
//! of what follows, unit id) in front of the PDU, no checksum.
//!
//! The stream decoder frames by the MBAP length. A header that cannot be
//! Modbus (protocol id not 0, length outside 2..=254) has no way back to a
//! frame boundary: TCP bytes carry no timing. A server's decoder
//! ([`TcpDecoder::for_server`]) then reports it and takes nothing more, and the
//! server closes the connection, as libmodbus and pymodbus servers do; the
//! plain decoder drops one byte at a time until a plausible header lines up,
//! counting each (for a capture read after the fact).

use super::adu::{Adu, pdu_of};
use super::pdu::EncodePdu;
use super::{BufferTooSmall, Drops, FrameError, MAX_PDU_LEN};

/// MBAP header length, unit id included.
pub const MBAP_LEN: usize = 7;
/// The shortest frame: header and a function code.
pub const MIN_ADU_LEN: usize = MBAP_LEN + 1;
/// The longest frame: header and a 253-byte PDU.
pub const MAX_ADU_LEN: usize = MBAP_LEN + MAX_PDU_LEN;

/// A checked view over the bytes of one Modbus TCP frame: the MBAP header
/// (transaction id, protocol id 0, length, unit id) and the PDU.
///
/// [`TcpFrame::new_checked`] checks the protocol id, the length field and that
/// the frame is as long as it says; the PDU is left as bytes for
/// [`Adu::request`] or [`Adu::response`] to parse.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TcpFrame<T: AsRef<[u8]>> {
    buffer: T,
}

impl<T: AsRef<[u8]>> TcpFrame<T> {
    /// Checks `buffer` as one whole frame.
    pub fn new_checked(buffer: T) -> Result<Self, FrameError> {
        check(buffer.as_ref())?;
        Ok(TcpFrame { buffer })
    }

    /// A view over bytes a decoder has already checked.
    fn new_unchecked(buffer: T) -> Self {
        TcpFrame { buffer }
    }

    /// Transaction id, echoed by the reply.
    pub fn transaction_id(&self) -> u16 {
        match self.buffer.as_ref() {
            [hi, lo, ..] => u16::from_be_bytes([*hi, *lo]),
            _ => 0,
        }
    }

    /// Gives the buffer back.
    pub fn into_inner(self) -> T {
        self.buffer
    }
}

/// The unit id is a gateway's target (often 0 or 255 for a plain TCP device).
impl<T: AsRef<[u8]>> Adu for TcpFrame<T> {
    /// The MBAP header, the unit id last.
    const HEADER_LEN: usize = MBAP_LEN;
    /// No check: TCP's own.
    const CHECK_LEN: usize = 0;

    fn as_bytes(&self) -> &[u8] {
        self.buffer.as_ref()
    }
}

impl<'a, T: AsRef<[u8]> + ?Sized> TcpFrame<&'a T> {
    /// Function code and data; never empty. Borrowed from the buffer, so it
    /// outlives the view (a decoder's frame can be kept while it goes on).
    pub fn pdu(&self) -> &'a [u8] {
        pdu_of::<Self>(self.buffer.as_ref())
    }
}

/// One Modbus TCP frame as a value: transaction id, unit id and a PDU.
/// Parsed, the PDU is the frame's bytes (`TcpRepr<&[u8]>`); to emit, it is
/// anything that writes a PDU (a [`Request`](super::Request), a reply, raw bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TcpRepr<P> {
    /// Transaction id, echoed by the reply.
    pub transaction_id: u16,
    /// Unit id (a gateway's target; often 0 or 255 for a plain TCP device).
    pub unit: u8,
    /// Function code and data.
    pub pdu: P,
}

impl<'a> TcpRepr<&'a [u8]> {
    /// Checks one whole frame and reads its header and PDU.
    pub fn parse(adu: &'a [u8]) -> Result<Self, FrameError> {
        TcpFrame::new_checked(adu).map(|frame| Self::from_frame(&frame))
    }

    /// The value of a checked frame.
    pub fn from_frame<T: AsRef<[u8]> + ?Sized>(frame: &TcpFrame<&'a T>) -> Self {
        TcpRepr {
            transaction_id: frame.transaction_id(),
            unit: frame.unit(),
            pdu: frame.pdu(),
        }
    }
}

impl<P: EncodePdu> TcpRepr<P> {
    /// The length of the frame: MBAP header and PDU.
    pub fn emitted_len(&self) -> usize {
        MBAP_LEN + self.pdu.pdu_len()
    }

    /// Writes the frame to the start of `out` and returns its length.
    pub fn emit(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        let pdu_len = self.pdu.pdu_len();
        let needed = MBAP_LEN + pdu_len;
        let available = out.len();
        let frame = out
            .get_mut(..needed)
            .ok_or(BufferTooSmall { needed, available })?;
        let (header, body) = frame.split_at_mut(MBAP_LEN);
        let [t_hi, t_lo] = self.transaction_id.to_be_bytes();
        // The PDU is at most 253 bytes, so the length always fits.
        let [l_hi, l_lo] = (1 + pdu_len as u16).to_be_bytes();
        header.copy_from_slice(&[t_hi, t_lo, 0, 0, l_hi, l_lo, self.unit]);
        self.pdu.encode_pdu(body)?;
        Ok(needed)
    }
}

/// The header's bytes up to the end of its protocol id, and of its length.
const PROTOCOL_END: usize = 4;
const LENGTH_END: usize = 6;

/// Why a header starting with `bytes` (at least [`PROTOCOL_END`] of them)
/// cannot be Modbus, judged by its protocol id alone.
fn protocol_fault(bytes: &[u8]) -> Option<FrameError> {
    let &[_, _, p_hi, p_lo, ..] = bytes else {
        return None;
    };
    let protocol = u16::from_be_bytes([p_hi, p_lo]);
    (protocol != 0).then_some(FrameError::ProtocolId(protocol))
}

/// Reads the MBAP header at the start of `bytes` (its first six bytes are
/// enough) and returns the whole frame's length, or why no Modbus frame can
/// start there.
fn header_len(bytes: &[u8]) -> Result<usize, FrameError> {
    let &[_, _, _, _, l_hi, l_lo, ..] = bytes else {
        return Err(FrameError::TooShort {
            len: bytes.len(),
            min: MIN_ADU_LEN,
        });
    };
    if let Some(fault) = protocol_fault(bytes) {
        return Err(fault);
    }
    let length = u16::from_be_bytes([l_hi, l_lo]);
    if !(2..=(1 + MAX_PDU_LEN as u16)).contains(&length) {
        return Err(FrameError::MbapLength(length));
    }
    Ok(6 + usize::from(length))
}

/// Checks a whole Modbus TCP frame.
fn check(adu: &[u8]) -> Result<(), FrameError> {
    let expected = header_len(adu)?;
    if adu.len() < MBAP_LEN {
        return Err(FrameError::TooShort {
            len: adu.len(),
            min: MIN_ADU_LEN,
        });
    }
    if adu.len() != expected {
        return Err(FrameError::LengthMismatch {
            expected: expected - 6,
            actual: adu.len() - 6,
        });
    }
    Ok(())
}

/// Turns a Modbus TCP byte stream, in chunks of any size, into frames.
///
/// ```
/// use protocols::modbus::Adu;
/// use protocols::modbus::tcp::TcpDecoder;
///
/// let mut decoder = TcpDecoder::new();
/// let mut input: &[u8] = &[0x00, 0x07, 0, 0, 0, 6, 0x01, 0x03, 0x00, 0x00, 0x00, 0x05];
/// let frame = decoder.decode(&mut input).unwrap().unwrap();
/// assert_eq!((frame.transaction_id(), frame.unit()), (7, 1));
/// ```
#[derive(Debug, Clone)]
pub struct TcpDecoder {
    buf: [u8; MAX_ADU_LEN],
    len: usize,
    /// Bytes at the front of `buf` handed out as a frame last call.
    yielded: usize,
    drops: Drops,
    /// Whether a header that cannot be Modbus ends the stream (a server's).
    stop_on_bad_header: bool,
    /// The header fault that ended the stream.
    stopped: Option<FrameError>,
}

impl Default for TcpDecoder {
    fn default() -> Self {
        TcpDecoder::new()
    }
}

impl TcpDecoder {
    /// An empty decoder.
    pub fn new() -> Self {
        TcpDecoder {
            buf: [0; MAX_ADU_LEN],
            len: 0,
            yielded: 0,
            drops: Drops::default(),
            stop_on_bad_header: false,
            stopped: None,
        }
    }

    /// A decoder as a server uses it: a header that cannot be Modbus is
    /// returned as its error, once, and ends the stream; everything after it
    /// is discarded (the connection is to be closed).
    pub fn for_server() -> Self {
        TcpDecoder {
            stop_on_bad_header: true,
            ..TcpDecoder::new()
        }
    }

    /// Takes bytes from the front of `input` until a frame is complete. `None`
    /// means `input` is used up; call again while it is not empty. A header
    /// that cannot be Modbus is counted in [`Drops::malformed`]; the plain
    /// decoder resynchronises past it, a server's returns it (see
    /// [`TcpDecoder::for_server`]).
    pub fn decode(&mut self, input: &mut &[u8]) -> Option<Result<TcpFrame<&[u8]>, FrameError>> {
        if self.stopped.is_some() {
            *input = &[];
            return None;
        }
        match self.advance(input)? {
            // `advance` hands out a frame only when its header checked and
            // exactly the length it announces is in.
            Ok(end) => Some(Ok(TcpFrame::new_unchecked(&self.buf[..end]))),
            Err(fault) => {
                *input = &[];
                self.len = 0;
                self.stopped = Some(fault);
                Some(Err(fault))
            }
        }
    }

    fn advance(&mut self, input: &mut &[u8]) -> Option<Result<usize, FrameError>> {
        if self.yielded > 0 {
            self.buf.copy_within(self.yielded..self.len, 0);
            self.len -= self.yielded;
            self.yielded = 0;
        }
        loop {
            // The protocol id and the length field are checked as soon as
            // they are in (4 and 6 bytes), not when the unit id comes: a
            // header that cannot be Modbus must not hold a connection open
            // waiting for a byte that changes nothing.
            let header = if self.len < PROTOCOL_END {
                Ok(PROTOCOL_END)
            } else if self.len < LENGTH_END {
                protocol_fault(&self.buf[..self.len]).map_or(Ok(LENGTH_END), Err)
            } else {
                header_len(&self.buf[..self.len])
            };
            let wanted = match header {
                Ok(total) if self.len >= total => {
                    self.yielded = total;
                    return Some(Ok(total));
                }
                Ok(wanted) => wanted,
                Err(fault) if self.stop_on_bad_header => {
                    self.drops.malformed.add(self.len);
                    return Some(Err(fault));
                }
                Err(_) => {
                    self.drops.malformed.add(1);
                    self.buf.copy_within(1..self.len, 0);
                    self.len -= 1;
                    continue;
                }
            };
            if input.is_empty() {
                return None;
            }
            let take = (wanted - self.len).min(input.len());
            let (head, rest) = input.split_at(take);
            self.buf[self.len..self.len + take].copy_from_slice(head);
            self.len += take;
            *input = rest;
        }
    }

    /// Bytes waiting for the rest of their frame.
    pub fn pending(&self) -> usize {
        self.len - self.yielded
    }

    /// What has been thrown away so far, by reason.
    pub fn drops(&self) -> &Drops {
        &self.drops
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_and_emit_a_known_frame() {
        let adu = [
            0x00, 0x01, 0x00, 0x00, 0x00, 0x06, 0x11, 0x03, 0x00, 0x6B, 0x00, 0x03,
        ];
        let frame = TcpFrame::new_checked(&adu).unwrap();
        assert_eq!((frame.transaction_id(), frame.unit()), (1, 0x11));
        let request = frame.request().unwrap();
        let mut out = [0u8; MAX_ADU_LEN];
        let repr = TcpRepr {
            transaction_id: 1,
            unit: 0x11,
            pdu: &request,
        };
        let n = repr.emit(&mut out).unwrap();
        assert_eq!(n, repr.emitted_len());
        assert_eq!(&out[..n], adu);
    }

    #[test]
    fn a_server_refuses_a_bad_header_before_its_unit_id() {
        // Length 0 is known at six bytes, a protocol id at four: no seventh
        // byte is waited for.
        for header in [&[0, 1, 0, 0, 0, 0][..], &[0, 1, 0, 7]] {
            let mut decoder = TcpDecoder::for_server();
            let mut input = header;
            assert!(
                matches!(decoder.decode(&mut input), Some(Err(_))),
                "{header:?}"
            );
        }
        let mut decoder = TcpDecoder::for_server();
        let mut input: &[u8] = &[0, 1, 0, 0, 0, 6];
        assert!(decoder.decode(&mut input).is_none(), "a good header waits");
    }

    #[test]
    fn header_faults_are_typed() {
        let good = [0, 1, 0, 0, 0, 2, 1, 0x03];
        assert!(TcpFrame::new_checked(&good).is_ok());
        let mut bad = good;
        bad[2] = 1;
        assert_eq!(
            TcpFrame::new_checked(&bad),
            Err(FrameError::ProtocolId(0x0100))
        );
        let mut bad = good;
        bad[5] = 1;
        assert_eq!(TcpFrame::new_checked(&bad), Err(FrameError::MbapLength(1)));
        assert_eq!(
            TcpFrame::new_checked(&[0, 1, 0, 0, 0, 3, 1, 0x03]),
            Err(FrameError::LengthMismatch {
                expected: 3,
                actual: 2
            })
        );
    }

    #[test]
    fn decoder_skips_a_bad_header() {
        let mut decoder = TcpDecoder::new();
        let mut stream = vec![0xFF, 0xFF, 0xFF];
        stream.extend([0, 9, 0, 0, 0, 6, 1, 0x06, 0, 1, 0, 2]);
        let mut input = &stream[..];
        let frame = decoder.decode(&mut input).unwrap().unwrap();
        assert_eq!(frame.transaction_id(), 9);
        assert_eq!(decoder.drops().malformed.bytes, 3);
        assert!(decoder.decode(&mut input).is_none());
        assert_eq!(decoder.pending(), 0);
    }

    #[test]
    fn a_servers_decoder_stops_at_a_bad_header() {
        let good = [0, 9, 0, 0, 0, 6, 1, 0x06, 0, 1, 0, 2];
        for (at, byte) in [(5, 0u8), (5, 1), (5, 255), (2, 0x80), (3, 1), (3, 2)] {
            let mut decoder = TcpDecoder::for_server();
            let mut bad = good;
            bad[at] = byte;
            let mut stream = bad.to_vec();
            stream.extend(good);
            let mut input = &stream[..];
            let fault = decoder.decode(&mut input).unwrap().unwrap_err();
            assert!(
                matches!(fault, FrameError::ProtocolId(_) | FrameError::MbapLength(_)),
                "{fault:?}"
            );
            assert!(input.is_empty(), "nothing is taken after the fault");
            // The stream has ended: a good frame after it is not taken.
            assert!(decoder.decode(&mut &good[..]).is_none());
            assert_eq!(decoder.pending(), 0);
        }
    }
}
