//! A slave's refusal of a request, shared by the node trait (a fault that
//! refuses every request), the slave firmware and the Controller_network
//! nodes.

use protocols::meb::MebErrorCode;
use protocols::modbus::Exception;

/// Why a request was refused, in the terms both protocols share.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, thiserror::Error)]
pub enum Refusal {
    /// No such command / function, or its block holds no words.
    #[error("illegal command")]
    IllegalCommand,
    /// An address outside the block.
    #[error("illegal address")]
    IllegalAddress,
    /// A count of 0 or a value out of range.
    #[error("illegal data")]
    IllegalData,
    /// Enabling the module while a trip's cause persists.
    #[error("device failure: a trip's cause persists")]
    DeviceFailure,
}

impl Refusal {
    /// The refusal an exception or `ER` code names: 1 illegal function /
    /// command, 2 illegal address, 3 illegal data, 4 device failure.
    pub fn from_code(code: u8) -> Option<Refusal> {
        match code {
            1 => Some(Refusal::IllegalCommand),
            2 => Some(Refusal::IllegalAddress),
            3 => Some(Refusal::IllegalData),
            4 => Some(Refusal::DeviceFailure),
            _ => None,
        }
    }

    /// The MEB error code.
    pub fn meb(self) -> MebErrorCode {
        match self {
            Refusal::IllegalCommand => MebErrorCode::IllegalCommand,
            Refusal::IllegalAddress => MebErrorCode::IllegalAddress,
            Refusal::IllegalData => MebErrorCode::IllegalData,
            Refusal::DeviceFailure => MebErrorCode::DeviceFailure,
        }
    }

    /// The Modbus exception.
    pub fn modbus(self) -> Exception {
        match self {
            Refusal::IllegalCommand => Exception::IllegalFunction,
            Refusal::IllegalAddress => Exception::IllegalDataAddress,
            Refusal::IllegalData => Exception::IllegalDataValue,
            Refusal::DeviceFailure => Exception::ServerDeviceFailure,
        }
    }
}
