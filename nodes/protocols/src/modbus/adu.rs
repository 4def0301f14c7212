//! What the three framings' checked views share: an ADU is a unit id and a
//! PDU, wherever a framing puts them, and on a serial line the unit id also
//! says who acts on the frame.
//!
//! A view states where its unit id and PDU lie ([`Adu::HEADER_LEN`],
//! [`Adu::CHECK_LEN`]) and hands over its bytes ([`Adu::as_bytes`]); reading
//! the unit id, the function code and the PDU as a request or a reply is
//! written once, here. Every method is generic over the view, so it costs
//! what the view's own accessor did.

use super::pdu::{ExceptionResponse, PduError, Request, Response};

/// A checked view over one Modbus ADU: a unit id and a PDU.
pub trait Adu {
    /// Bytes before the PDU, the unit id the last of them (RTU and ASCII: the
    /// unit id alone; TCP: the MBAP header).
    const HEADER_LEN: usize;
    /// Bytes after the PDU: the check (RTU's CRC 2, ASCII's LRC 1, TCP none).
    const CHECK_LEN: usize;

    /// The frame's bytes as received (ASCII: the content its hex digits
    /// spell, not the characters).
    fn as_bytes(&self) -> &[u8];

    /// Unit id (slave address).
    fn unit(&self) -> u8 {
        self.as_bytes()
            .get(Self::HEADER_LEN - 1)
            .copied()
            .unwrap_or(0)
    }

    /// The function code (first PDU byte; top bit set on an exception reply).
    fn function(&self) -> u8 {
        self.as_bytes().get(Self::HEADER_LEN).copied().unwrap_or(0)
    }

    /// Parses the PDU as a request (master to slave).
    fn request(&self) -> Result<Request, PduError> {
        Request::parse(pdu_of::<Self>(self.as_bytes()))
    }

    /// Parses the PDU as a reply (slave to master).
    fn response(&self) -> Result<Result<Response, ExceptionResponse>, PduError> {
        Response::parse(pdu_of::<Self>(self.as_bytes()))
    }
}

/// An ADU on a serial line (RTU, ASCII), where unit id 0 is the broadcast.
/// (Modbus TCP has no broadcast: a server is reached by its address.)
pub trait SerialAdu: Adu {
    /// True when a slave with id `unit` must act on this frame: its own id, or
    /// the broadcast id 0 (which is acted on but never answered).
    fn is_for(&self, unit: u8) -> bool {
        self.unit() == unit || self.is_broadcast()
    }

    /// True for the broadcast id 0.
    fn is_broadcast(&self) -> bool {
        self.unit() == 0
    }
}

/// The PDU in a checked `A`'s bytes: between its header and its check.
pub(super) fn pdu_of<A: Adu + ?Sized>(adu: &[u8]) -> &[u8] {
    adu.get(A::HEADER_LEN..adu.len().saturating_sub(A::CHECK_LEN))
        .unwrap_or_default()
}
