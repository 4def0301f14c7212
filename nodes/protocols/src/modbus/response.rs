//! Replies: what a slave sends back.

use super::BufferTooSmall;
use super::pdu::function::*;
use super::pdu::{
    Bits, EncodePdu, Exception, ExceptionResponse, MAX_BIT_BYTES, MAX_REGISTERS, MAX_WRITE_COILS,
    MAX_WRITE_REGISTERS, PduError, Registers, Response, Writer, be16, check_quantity, coil_value,
    coil_word, counted_data, encode_with, expect_len,
};

impl Response {
    /// Reads a reply PDU: `Ok(Ok(_))` for a normal reply, `Ok(Err(_))` for an
    /// exception reply (any code), `Err(_)` for a malformed PDU.
    pub fn parse(pdu: &[u8]) -> Result<Result<Response, ExceptionResponse>, PduError> {
        let &function = pdu.first().ok_or(PduError::Empty)?;
        if function & EXCEPTION_BIT != 0 {
            expect_len(function, pdu, 2)?;
            let code = pdu.get(1).copied().unwrap_or(0);
            return Ok(Err(ExceptionResponse {
                function: function & !EXCEPTION_BIT,
                exception: Exception::from_code(code),
            }));
        }
        let response = match function {
            READ_COILS | READ_DISCRETE_INPUTS | READ_HOLDING_REGISTERS | READ_INPUT_REGISTERS => {
                let byte_count = pdu.get(1).copied().ok_or(PduError::Length {
                    function,
                    len: pdu.len(),
                    expected: 2,
                })?;
                let registers = function >= READ_HOLDING_REGISTERS;
                let max = if registers {
                    2 * MAX_REGISTERS
                } else {
                    MAX_BIT_BYTES
                };
                if byte_count == 0
                    || usize::from(byte_count) > max
                    || (registers && byte_count % 2 != 0)
                {
                    return Err(PduError::ByteCount {
                        function,
                        byte_count,
                        expected: 0,
                    });
                }
                let data = counted_data(function, pdu, 1, usize::from(byte_count))?;
                let malformed = PduError::ByteCount {
                    function,
                    byte_count,
                    expected: 0,
                };
                match function {
                    READ_COILS | READ_DISCRETE_INPUTS => {
                        let bits = Bits::from_packed(data, u16::from(byte_count) * 8)
                            .map_err(|_| malformed)?;
                        if function == READ_COILS {
                            Response::ReadCoils(bits)
                        } else {
                            Response::ReadDiscreteInputs(bits)
                        }
                    }
                    _ => {
                        let values = Registers::from_be_bytes(data).ok_or(malformed)?;
                        if function == READ_HOLDING_REGISTERS {
                            Response::ReadHoldingRegisters(values)
                        } else {
                            Response::ReadInputRegisters(values)
                        }
                    }
                }
            }
            WRITE_SINGLE_COIL => {
                expect_len(function, pdu, 5)?;
                Response::WriteSingleCoil {
                    address: be16(pdu, 1),
                    value: coil_value(be16(pdu, 3))?,
                }
            }
            WRITE_SINGLE_REGISTER => {
                expect_len(function, pdu, 5)?;
                Response::WriteSingleRegister {
                    address: be16(pdu, 1),
                    value: be16(pdu, 3),
                }
            }
            WRITE_MULTIPLE_COILS => {
                expect_len(function, pdu, 5)?;
                Response::WriteMultipleCoils {
                    address: be16(pdu, 1),
                    quantity: check_quantity(function, be16(pdu, 3), MAX_WRITE_COILS)?,
                }
            }
            WRITE_MULTIPLE_REGISTERS => {
                expect_len(function, pdu, 5)?;
                Response::WriteMultipleRegisters {
                    address: be16(pdu, 1),
                    quantity: check_quantity(function, be16(pdu, 3), MAX_WRITE_REGISTERS)?,
                }
            }
            other => return Err(PduError::UnsupportedFunction(other)),
        };
        Ok(Ok(response))
    }

    /// The function code.
    pub fn function(&self) -> u8 {
        match self {
            Response::ReadCoils(_) => READ_COILS,
            Response::ReadDiscreteInputs(_) => READ_DISCRETE_INPUTS,
            Response::ReadHoldingRegisters(_) => READ_HOLDING_REGISTERS,
            Response::ReadInputRegisters(_) => READ_INPUT_REGISTERS,
            Response::WriteSingleCoil { .. } => WRITE_SINGLE_COIL,
            Response::WriteSingleRegister { .. } => WRITE_SINGLE_REGISTER,
            Response::WriteMultipleCoils { .. } => WRITE_MULTIPLE_COILS,
            Response::WriteMultipleRegisters { .. } => WRITE_MULTIPLE_REGISTERS,
        }
    }
}

impl EncodePdu for Response {
    fn pdu_len(&self) -> usize {
        match self {
            Response::ReadCoils(bits) | Response::ReadDiscreteInputs(bits) => {
                2 + bits.packed().len()
            }
            Response::ReadHoldingRegisters(values) | Response::ReadInputRegisters(values) => {
                2 + 2 * values.len()
            }
            _ => 5,
        }
    }

    fn encode_pdu(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        encode_with(self.pdu_len(), out, |w| self.write_to(w))
    }
}

impl Response {
    fn write_to(&self, w: &mut Writer<'_>) {
        w.u8(self.function());
        match self {
            Response::ReadCoils(bits) | Response::ReadDiscreteInputs(bits) => {
                w.u8(bits.packed().len() as u8);
                w.bytes(bits.packed());
            }
            Response::ReadHoldingRegisters(values) | Response::ReadInputRegisters(values) => {
                w.u8((2 * values.len()) as u8);
                for &value in values.as_slice() {
                    w.u16(value);
                }
            }
            Response::WriteSingleCoil { address, value } => {
                w.u16(*address);
                w.u16(coil_word(*value));
            }
            Response::WriteSingleRegister { address, value } => {
                w.u16(*address);
                w.u16(*value);
            }
            Response::WriteMultipleCoils { address, quantity }
            | Response::WriteMultipleRegisters { address, quantity } => {
                w.u16(*address);
                w.u16(*quantity);
            }
        }
    }
}
