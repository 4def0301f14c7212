//! Modbus PDUs (function code + data) for function codes 01, 02, 03, 04, 05,
//! 06, 15 and 16, and exception replies.
//!
//! Quantity limits (Modbus application protocol 1.1b3): read coils / discrete
//! inputs 1–2000, read registers 1–125, write multiple coils 1–1968, write
//! multiple registers 1–123; a single coil is written as 0xFF00 (on) or 0x0000
//! (off). A request that breaks one of them is a [`PduError`], and
//! [`PduError::exception`] says what the standard has a slave answer:
//! exception 01 for a function it does not know, 03 for every other fault
//! of form (quantity, byte count, coil value, length). Keeping these as errors
//! rather than folding them into the request lets a master's own checks and a
//! slave's answer share one parser.

use core::fmt;

use thiserror::Error;

pub use super::data::{Bits, CapacityError, MAX_BIT_BYTES, MAX_BITS, MAX_REGISTERS, Registers};
use super::{BufferTooSmall, MAX_PDU_LEN};

/// Function codes this codec knows.
pub mod function {
    /// 01 read coils.
    pub const READ_COILS: u8 = 0x01;
    /// 02 read discrete inputs.
    pub const READ_DISCRETE_INPUTS: u8 = 0x02;
    /// 03 read holding registers.
    pub const READ_HOLDING_REGISTERS: u8 = 0x03;
    /// 04 read input registers.
    pub const READ_INPUT_REGISTERS: u8 = 0x04;
    /// 05 write single coil.
    pub const WRITE_SINGLE_COIL: u8 = 0x05;
    /// 06 write single register.
    pub const WRITE_SINGLE_REGISTER: u8 = 0x06;
    /// 15 write multiple coils.
    pub const WRITE_MULTIPLE_COILS: u8 = 0x0F;
    /// 16 write multiple registers.
    pub const WRITE_MULTIPLE_REGISTERS: u8 = 0x10;
    /// Set on the function code of an exception reply.
    pub const EXCEPTION_BIT: u8 = 0x80;
}

use function::*;

/// Most bits one read request may ask for.
pub const MAX_READ_BITS: u16 = 2000;
/// Most registers one read request may ask for.
pub const MAX_READ_REGISTERS: u16 = 125;
/// Most coils one write-multiple request may carry.
pub const MAX_WRITE_COILS: u16 = 1968;
/// Most registers one write-multiple request may carry.
pub const MAX_WRITE_REGISTERS: u16 = 123;

const COIL_ON: u16 = 0xFF00;
const COIL_OFF: u16 = 0x0000;

/// A Modbus exception code, as carried by an exception reply (and by the
/// 8-byte variant's value field).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Exception {
    /// 01: the function code is not allowed.
    IllegalFunction,
    /// 02: the address is not allowed.
    IllegalDataAddress,
    /// 03: a value in the request is not allowed.
    IllegalDataValue,
    /// 04: the device failed while acting on the request.
    ServerDeviceFailure,
    /// 05: accepted, will take long.
    Acknowledge,
    /// 06: busy with a long command.
    ServerDeviceBusy,
    /// 08: memory parity error.
    MemoryParityError,
    /// 0A: gateway path unavailable.
    GatewayPathUnavailable,
    /// 0B: gateway target failed to respond.
    GatewayTargetFailedToRespond,
    /// Any other code; [`Exception::from_code`] never builds one of the codes above.
    Other(u8),
}

impl Exception {
    /// The exception for a wire code; unknown codes are kept as [`Exception::Other`].
    pub const fn from_code(code: u8) -> Self {
        match code {
            0x01 => Exception::IllegalFunction,
            0x02 => Exception::IllegalDataAddress,
            0x03 => Exception::IllegalDataValue,
            0x04 => Exception::ServerDeviceFailure,
            0x05 => Exception::Acknowledge,
            0x06 => Exception::ServerDeviceBusy,
            0x08 => Exception::MemoryParityError,
            0x0A => Exception::GatewayPathUnavailable,
            0x0B => Exception::GatewayTargetFailedToRespond,
            other => Exception::Other(other),
        }
    }

    /// The wire code.
    pub const fn code(self) -> u8 {
        match self {
            Exception::IllegalFunction => 0x01,
            Exception::IllegalDataAddress => 0x02,
            Exception::IllegalDataValue => 0x03,
            Exception::ServerDeviceFailure => 0x04,
            Exception::Acknowledge => 0x05,
            Exception::ServerDeviceBusy => 0x06,
            Exception::MemoryParityError => 0x08,
            Exception::GatewayPathUnavailable => 0x0A,
            Exception::GatewayTargetFailedToRespond => 0x0B,
            Exception::Other(code) => code,
        }
    }
}

impl Exception {
    /// The exception's name as the Modbus Application Protocol
    /// specification (V1.1b3, section 7) gives it.
    pub const fn name(self) -> &'static str {
        match self {
            Exception::IllegalFunction => "ILLEGAL FUNCTION",
            Exception::IllegalDataAddress => "ILLEGAL DATA ADDRESS",
            Exception::IllegalDataValue => "ILLEGAL DATA VALUE",
            Exception::ServerDeviceFailure => "SERVER DEVICE FAILURE",
            Exception::Acknowledge => "ACKNOWLEDGE",
            Exception::ServerDeviceBusy => "SERVER DEVICE BUSY",
            Exception::MemoryParityError => "MEMORY PARITY ERROR",
            Exception::GatewayPathUnavailable => "GATEWAY PATH UNAVAILABLE",
            Exception::GatewayTargetFailedToRespond => "GATEWAY TARGET DEVICE FAILED TO RESPOND",
            Exception::Other(_) => "a code the specification does not define",
        }
    }
}

impl fmt::Display for Exception {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "exception {:02x} ({})", self.code(), self.name())
    }
}

/// Why a PDU could not be read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum PduError {
    /// No function code at all.
    #[error("empty PDU")]
    Empty,
    /// A function code this codec does not handle.
    #[error("function code {0:#04x} is not supported")]
    UnsupportedFunction(u8),
    /// The PDU length does not match what the function code and byte count say.
    #[error("function {function:#04x}: PDU is {len} bytes, expected {expected}")]
    Length {
        /// Function code.
        function: u8,
        /// Bytes present.
        len: usize,
        /// Bytes expected.
        expected: usize,
    },
    /// A quantity outside the function's limits.
    #[error("function {function:#04x}: quantity {quantity} outside 1..={max}")]
    Quantity {
        /// Function code.
        function: u8,
        /// Quantity asked for.
        quantity: u16,
        /// Largest legal quantity.
        max: u16,
    },
    /// A byte count that disagrees with the quantity, or is odd for registers.
    #[error("function {function:#04x}: byte count {byte_count}, expected {expected}")]
    ByteCount {
        /// Function code.
        function: u8,
        /// Byte count carried.
        byte_count: u8,
        /// Byte count the quantity implies (0 when none fits).
        expected: u8,
    },
    /// A single-coil value other than 0xFF00 or 0x0000.
    #[error("coil value {0:#06x} is neither 0xff00 nor 0x0000")]
    CoilValue(u16),
}

impl PduError {
    /// The exception a slave answers to a request that failed this way (Modbus
    /// application protocol 1.1b3, section 6 state diagrams), `None` for an
    /// empty PDU, which gets no reply.
    pub fn exception(&self) -> Option<Exception> {
        match self {
            PduError::Empty => None,
            PduError::UnsupportedFunction(_) => Some(Exception::IllegalFunction),
            PduError::Length { .. }
            | PduError::Quantity { .. }
            | PduError::ByteCount { .. }
            | PduError::CoilValue(_) => Some(Exception::IllegalDataValue),
        }
    }
}

/// A master's request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Request {
    /// 01: read `quantity` coils from `address`.
    ReadCoils {
        /// First coil.
        address: u16,
        /// Coils to read, 1–2000.
        quantity: u16,
    },
    /// 02: read `quantity` discrete inputs from `address`.
    ReadDiscreteInputs {
        /// First input.
        address: u16,
        /// Inputs to read, 1–2000.
        quantity: u16,
    },
    /// 03: read `quantity` holding registers from `address`.
    ReadHoldingRegisters {
        /// First register.
        address: u16,
        /// Registers to read, 1–125.
        quantity: u16,
    },
    /// 04: read `quantity` input registers from `address`.
    ReadInputRegisters {
        /// First register.
        address: u16,
        /// Registers to read, 1–125.
        quantity: u16,
    },
    /// 05: set one coil.
    WriteSingleCoil {
        /// The coil.
        address: u16,
        /// On (0xFF00) or off (0x0000).
        value: bool,
    },
    /// 06: set one holding register.
    WriteSingleRegister {
        /// The register.
        address: u16,
        /// Its new value.
        value: u16,
    },
    /// 15: set consecutive coils.
    WriteMultipleCoils {
        /// First coil.
        address: u16,
        /// The values, 1–1968 of them.
        coils: Bits,
    },
    /// 16: set consecutive holding registers.
    WriteMultipleRegisters {
        /// First register.
        address: u16,
        /// The values, 1–123 of them.
        registers: Registers,
    },
}

/// A slave's normal reply.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Response {
    /// 01: coil values; the quantity is the byte count times 8, the master knows
    /// how many of them it asked for.
    ReadCoils(Bits),
    /// 02: discrete input values, padded to whole bytes like [`Response::ReadCoils`].
    ReadDiscreteInputs(Bits),
    /// 03: holding register values.
    ReadHoldingRegisters(Registers),
    /// 04: input register values.
    ReadInputRegisters(Registers),
    /// 05: echo of the request.
    WriteSingleCoil {
        /// The coil.
        address: u16,
        /// Its value.
        value: bool,
    },
    /// 06: echo of the request.
    WriteSingleRegister {
        /// The register.
        address: u16,
        /// Its value.
        value: u16,
    },
    /// 15: how many coils were written.
    WriteMultipleCoils {
        /// First coil.
        address: u16,
        /// Coils written.
        quantity: u16,
    },
    /// 16: how many registers were written.
    WriteMultipleRegisters {
        /// First register.
        address: u16,
        /// Registers written.
        quantity: u16,
    },
}

/// An exception reply: the function code that failed and why.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExceptionResponse {
    /// The request's function code (without the top bit).
    pub function: u8,
    /// The reason.
    pub exception: Exception,
}

/// Anything that can be written as a PDU into a byte buffer.
pub trait EncodePdu {
    /// Bytes the PDU takes.
    fn pdu_len(&self) -> usize;

    /// Writes the PDU into the start of `out`, returning the bytes written.
    fn encode_pdu(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall>;
}

/// Checks that `out` holds `needed` bytes, then lets `write` fill them.
pub(super) fn encode_with(
    needed: usize,
    out: &mut [u8],
    write: impl FnOnce(&mut Writer<'_>),
) -> Result<usize, BufferTooSmall> {
    let available = out.len();
    let dst = out
        .get_mut(..needed)
        .ok_or(BufferTooSmall { needed, available })?;
    write(&mut Writer { out: dst, pos: 0 });
    Ok(needed)
}

/// A cursor over an output slice that the caller sized beforehand; writes past
/// its end are ignored rather than panicking.
pub(super) struct Writer<'a> {
    out: &'a mut [u8],
    pos: usize,
}

impl Writer<'_> {
    pub(super) fn u8(&mut self, value: u8) {
        if let Some(slot) = self.out.get_mut(self.pos) {
            *slot = value;
        }
        self.pos += 1;
    }

    pub(super) fn u16(&mut self, value: u16) {
        let [hi, lo] = value.to_be_bytes();
        self.u8(hi);
        self.u8(lo);
    }

    pub(super) fn bytes(&mut self, bytes: &[u8]) {
        let end = self.pos + bytes.len();
        if let Some(slot) = self.out.get_mut(self.pos..end) {
            slot.copy_from_slice(bytes);
        }
        self.pos = end;
    }
}

pub(super) fn be16(pdu: &[u8], at: usize) -> u16 {
    match pdu.get(at..at + 2) {
        Some(&[hi, lo]) => u16::from_be_bytes([hi, lo]),
        _ => 0,
    }
}

pub(super) fn expect_len(function: u8, pdu: &[u8], expected: usize) -> Result<(), PduError> {
    if pdu.len() == expected {
        Ok(())
    } else {
        Err(PduError::Length {
            function,
            len: pdu.len(),
            expected,
        })
    }
}

pub(super) fn check_quantity(function: u8, quantity: u16, max: u16) -> Result<u16, PduError> {
    if (1..=max).contains(&quantity) {
        Ok(quantity)
    } else {
        Err(PduError::Quantity {
            function,
            quantity,
            max,
        })
    }
}

pub(super) fn coil_value(value: u16) -> Result<bool, PduError> {
    match value {
        COIL_ON => Ok(true),
        COIL_OFF => Ok(false),
        other => Err(PduError::CoilValue(other)),
    }
}

pub(super) fn coil_word(on: bool) -> u16 {
    if on { COIL_ON } else { COIL_OFF }
}

/// Reads the byte count at `pdu[at]` and checks that it is `expected` and that
/// exactly that many bytes follow it.
pub(super) fn counted_data(
    function: u8,
    pdu: &[u8],
    at: usize,
    expected: usize,
) -> Result<&[u8], PduError> {
    let byte_count = pdu.get(at).copied().ok_or(PduError::Length {
        function,
        len: pdu.len(),
        expected: at + 1 + expected,
    })?;
    if usize::from(byte_count) != expected {
        return Err(PduError::ByteCount {
            function,
            byte_count,
            expected: u8::try_from(expected).unwrap_or(0),
        });
    }
    expect_len(function, pdu, at + 1 + expected)?;
    Ok(pdu.get(at + 1..).unwrap_or(&[]))
}

impl EncodePdu for ExceptionResponse {
    fn pdu_len(&self) -> usize {
        2
    }

    fn encode_pdu(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        encode_with(2, out, |w| {
            w.u8(self.function | EXCEPTION_BIT);
            w.u8(self.exception.code());
        })
    }
}

impl EncodePdu for Result<Response, ExceptionResponse> {
    fn pdu_len(&self) -> usize {
        match self {
            Ok(response) => response.pdu_len(),
            Err(exception) => exception.pdu_len(),
        }
    }

    fn encode_pdu(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        match self {
            Ok(response) => response.encode_pdu(out),
            Err(exception) => exception.encode_pdu(out),
        }
    }
}

/// A PDU behind a reference writes as the PDU itself, so a frame's value can
/// borrow what it emits (`RtuRepr { unit, pdu: &request }`).
impl<P: EncodePdu + ?Sized> EncodePdu for &P {
    fn pdu_len(&self) -> usize {
        (**self).pdu_len()
    }

    fn encode_pdu(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        (**self).encode_pdu(out)
    }
}

/// Raw PDU bytes (forwarded or echoed without interpretation); at most
/// [`MAX_PDU_LEN`] of them are written.
impl EncodePdu for [u8] {
    fn pdu_len(&self) -> usize {
        self.len().min(MAX_PDU_LEN)
    }

    fn encode_pdu(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        let pdu = self.get(..MAX_PDU_LEN).unwrap_or(self);
        encode_with(pdu.len(), out, |w| w.bytes(pdu))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn encode(pdu: &impl EncodePdu) -> Vec<u8> {
        let mut out = [0u8; MAX_PDU_LEN];
        let n = pdu.encode_pdu(&mut out).unwrap();
        out[..n].to_vec()
    }

    #[test]
    fn spec_examples_parse_and_emit() {
        // Examples from the Modbus application protocol 1.1b3, section 6.
        let read = [0x03, 0x00, 0x6B, 0x00, 0x03];
        let request = Request::parse(&read).unwrap();
        assert_eq!(
            request,
            Request::ReadHoldingRegisters {
                address: 0x6B,
                quantity: 3
            }
        );
        assert_eq!(encode(&request), read);

        let reply = [0x03, 0x06, 0x02, 0x2B, 0x00, 0x00, 0x00, 0x64];
        let response = Response::parse(&reply).unwrap().unwrap();
        assert_eq!(
            response,
            Response::ReadHoldingRegisters(Registers::from_slice(&[0x022B, 0, 0x64]).unwrap())
        );
        assert_eq!(encode(&response), reply);

        let write_coils = [0x0F, 0x00, 0x13, 0x00, 0x0A, 0x02, 0xCD, 0x01];
        let request = Request::parse(&write_coils).unwrap();
        let Request::WriteMultipleCoils { address, coils } = &request else {
            panic!("{request:?}");
        };
        assert_eq!((*address, coils.quantity()), (0x13, 10));
        assert_eq!(encode(&request), write_coils);

        let exception = [0x81, 0x02];
        assert_eq!(
            Response::parse(&exception).unwrap(),
            Err(ExceptionResponse {
                function: 1,
                exception: Exception::IllegalDataAddress
            })
        );
    }

    #[test]
    fn quantity_limits_are_enforced_at_the_edges() {
        let read = |fc: u8, q: u16| {
            let [hi, lo] = q.to_be_bytes();
            Request::parse(&[fc, 0, 0, hi, lo])
        };
        for (fc, max) in [(1, 2000), (2, 2000), (3, 125), (4, 125)] {
            assert!(read(fc, 1).is_ok());
            assert!(read(fc, max).is_ok());
            for bad in [0, max + 1] {
                let err = read(fc, bad).unwrap_err();
                assert_eq!(
                    err,
                    PduError::Quantity {
                        function: fc,
                        quantity: bad,
                        max
                    }
                );
                assert_eq!(err.exception(), Some(Exception::IllegalDataValue));
            }
        }
        let mut coils = vec![0x0F, 0, 0, 0x07, 0xB1, 247];
        coils.extend([0; 247]);
        assert!(matches!(
            Request::parse(&coils),
            Err(PduError::Quantity { max: 1968, .. })
        ));
        let mut regs = vec![0x10, 0, 0, 0, 124, 248];
        regs.extend([0; 248]);
        assert!(matches!(
            Request::parse(&regs),
            Err(PduError::Quantity { max: 123, .. })
        ));
    }

    #[test]
    fn malformed_requests_map_to_the_standard_exceptions() {
        let err = Request::parse(&[0x05, 0, 1, 0x12, 0x34]).unwrap_err();
        assert_eq!(err, PduError::CoilValue(0x1234));
        assert_eq!(err.exception(), Some(Exception::IllegalDataValue));
        // Byte count that disagrees with the quantity.
        let err = Request::parse(&[0x10, 0, 0, 0, 2, 2, 0, 1]).unwrap_err();
        assert_eq!(
            err,
            PduError::ByteCount {
                function: 0x10,
                byte_count: 2,
                expected: 4
            }
        );
        let err = Request::parse(&[0x2B, 0x0E, 1, 0]).unwrap_err();
        assert_eq!(err.exception(), Some(Exception::IllegalFunction));
        assert_eq!(Request::parse(&[]).unwrap_err().exception(), None);
        assert!(matches!(
            Request::parse(&[0x03, 0, 0, 0]),
            Err(PduError::Length { .. })
        ));
    }

    #[test]
    fn unknown_exception_codes_are_kept() {
        let reply = Response::parse(&[0x83, 0x42]).unwrap().unwrap_err();
        assert_eq!(reply.exception, Exception::Other(0x42));
        assert_eq!(reply.exception.code(), 0x42);
        assert_eq!(encode(&reply), [0x83, 0x42]);
    }

    #[test]
    fn exceptions_read_as_the_modbus_specification_names_them() {
        assert_eq!(
            Exception::IllegalDataAddress.to_string(),
            "exception 02 (ILLEGAL DATA ADDRESS)"
        );
        assert_eq!(
            Exception::GatewayTargetFailedToRespond.to_string(),
            "exception 0b (GATEWAY TARGET DEVICE FAILED TO RESPOND)"
        );
        assert_eq!(
            Exception::Other(0x42).to_string(),
            "exception 42 (a code the specification does not define)"
        );
    }

    #[test]
    fn emit_reports_a_short_buffer() {
        let request = Request::WriteSingleRegister {
            address: 1,
            value: 2,
        };
        let mut out = [0u8; 4];
        assert_eq!(
            request.encode_pdu(&mut out),
            Err(BufferTooSmall {
                needed: 5,
                available: 4
            })
        );
    }
}
