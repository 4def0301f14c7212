//! Requests: what a master sends.

use super::BufferTooSmall;
use super::pdu::function::*;
use super::pdu::{
    Bits, EncodePdu, MAX_READ_BITS, MAX_READ_REGISTERS, MAX_WRITE_COILS, MAX_WRITE_REGISTERS,
    PduError, Registers, Request, Writer, be16, check_quantity, coil_value, coil_word,
    counted_data, encode_with, expect_len,
};

impl Request {
    /// Reads a request PDU.
    pub fn parse(pdu: &[u8]) -> Result<Request, PduError> {
        let &function = pdu.first().ok_or(PduError::Empty)?;
        match function {
            READ_COILS | READ_DISCRETE_INPUTS | READ_HOLDING_REGISTERS | READ_INPUT_REGISTERS => {
                expect_len(function, pdu, 5)?;
                let address = be16(pdu, 1);
                let max = if function <= READ_DISCRETE_INPUTS {
                    MAX_READ_BITS
                } else {
                    MAX_READ_REGISTERS
                };
                let quantity = check_quantity(function, be16(pdu, 3), max)?;
                Ok(match function {
                    READ_COILS => Request::ReadCoils { address, quantity },
                    READ_DISCRETE_INPUTS => Request::ReadDiscreteInputs { address, quantity },
                    READ_HOLDING_REGISTERS => Request::ReadHoldingRegisters { address, quantity },
                    _ => Request::ReadInputRegisters { address, quantity },
                })
            }
            WRITE_SINGLE_COIL => {
                expect_len(function, pdu, 5)?;
                Ok(Request::WriteSingleCoil {
                    address: be16(pdu, 1),
                    value: coil_value(be16(pdu, 3))?,
                })
            }
            WRITE_SINGLE_REGISTER => {
                expect_len(function, pdu, 5)?;
                Ok(Request::WriteSingleRegister {
                    address: be16(pdu, 1),
                    value: be16(pdu, 3),
                })
            }
            WRITE_MULTIPLE_COILS | WRITE_MULTIPLE_REGISTERS => {
                if pdu.len() < 6 {
                    return Err(PduError::Length {
                        function,
                        len: pdu.len(),
                        expected: 6,
                    });
                }
                let address = be16(pdu, 1);
                if function == WRITE_MULTIPLE_COILS {
                    let quantity = check_quantity(function, be16(pdu, 3), MAX_WRITE_COILS)?;
                    let data = counted_data(function, pdu, 5, usize::from(quantity).div_ceil(8))?;
                    let coils =
                        Bits::from_packed(data, quantity).map_err(|_| PduError::Length {
                            function,
                            len: pdu.len(),
                            expected: 6 + usize::from(quantity).div_ceil(8),
                        })?;
                    Ok(Request::WriteMultipleCoils { address, coils })
                } else {
                    let quantity = check_quantity(function, be16(pdu, 3), MAX_WRITE_REGISTERS)?;
                    let data = counted_data(function, pdu, 5, 2 * usize::from(quantity))?;
                    let registers = Registers::from_be_bytes(data).ok_or(PduError::Length {
                        function,
                        len: pdu.len(),
                        expected: 6 + 2 * usize::from(quantity),
                    })?;
                    Ok(Request::WriteMultipleRegisters { address, registers })
                }
            }
            other => Err(PduError::UnsupportedFunction(other)),
        }
    }

    /// The function code.
    pub fn function(&self) -> u8 {
        match self {
            Request::ReadCoils { .. } => READ_COILS,
            Request::ReadDiscreteInputs { .. } => READ_DISCRETE_INPUTS,
            Request::ReadHoldingRegisters { .. } => READ_HOLDING_REGISTERS,
            Request::ReadInputRegisters { .. } => READ_INPUT_REGISTERS,
            Request::WriteSingleCoil { .. } => WRITE_SINGLE_COIL,
            Request::WriteSingleRegister { .. } => WRITE_SINGLE_REGISTER,
            Request::WriteMultipleCoils { .. } => WRITE_MULTIPLE_COILS,
            Request::WriteMultipleRegisters { .. } => WRITE_MULTIPLE_REGISTERS,
        }
    }
}

impl EncodePdu for Request {
    fn pdu_len(&self) -> usize {
        match self {
            Request::WriteMultipleCoils { coils, .. } => 6 + coils.packed().len(),
            Request::WriteMultipleRegisters { registers, .. } => 6 + 2 * registers.len(),
            _ => 5,
        }
    }

    fn encode_pdu(&self, out: &mut [u8]) -> Result<usize, BufferTooSmall> {
        encode_with(self.pdu_len(), out, |w| self.write_to(w))
    }
}

impl Request {
    fn write_to(&self, w: &mut Writer<'_>) {
        w.u8(self.function());
        match self {
            Request::ReadCoils { address, quantity }
            | Request::ReadDiscreteInputs { address, quantity }
            | Request::ReadHoldingRegisters { address, quantity }
            | Request::ReadInputRegisters { address, quantity } => {
                w.u16(*address);
                w.u16(*quantity);
            }
            Request::WriteSingleCoil { address, value } => {
                w.u16(*address);
                w.u16(coil_word(*value));
            }
            Request::WriteSingleRegister { address, value } => {
                w.u16(*address);
                w.u16(*value);
            }
            Request::WriteMultipleCoils { address, coils } => {
                w.u16(*address);
                w.u16(coils.quantity());
                // At most 250 packed bytes, so the count fits in a byte.
                w.u8(coils.packed().len() as u8);
                w.bytes(coils.packed());
            }
            Request::WriteMultipleRegisters { address, registers } => {
                w.u16(*address);
                w.u16(registers.len() as u16);
                w.u8((2 * registers.len()) as u8);
                for &value in registers.as_slice() {
                    w.u16(value);
                }
            }
        }
    }
}
