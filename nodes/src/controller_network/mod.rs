//! The Controller_network project (`docs/protocols/modbus8.md`): the motor node (id 01),
//! the light-sensor node (id 02) and the Raspberry Pi master, all speaking the
//! 8-byte Modbus variant of [`protocols::modbus8`].
//!
//! The two Arduinos are [`Node`](crate::node::Node)s for their serial port and
//! [`Firmware`](crate::node::Firmware) for the bench they control; the master
//! is a plain node. Everything is driven by `now`; nothing here reads a clock.

mod light;
mod master;
mod motor;

pub use light::{LightConfig, LightNode};
pub use master::{
    ControllerNetworkMaster, MasterConfig, MasterPhase, MasterProgram, ScriptedRequest,
};
pub use motor::{MotorConfig, MotorNode, MotorState};

use std::collections::VecDeque;

use protocols::modbus::Exception;
use protocols::modbus8::{self, CrcOrder, FRAME_LEN, Modbus8Decoder, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};

/// Slave id of the motor node.
pub const MOTOR_ID: u8 = 0x01;
/// Slave id of the light-sensor node.
pub const LIGHT_ID: u8 = 0x02;
/// Motor register: control state (read / write).
pub const REG_STATE: u16 = 0x0001;
/// Motor register: shaft rpm, signed 16-bit (read only).
pub const REG_RPM: u16 = 0x0005;
/// Motor register: rpm set point, decimal 21..=12499 (write only).
pub const REG_SET_SPEED: u16 = 0x0009;
/// Light-sensor register: wheel rpm × 100 (read only).
pub const REG_LIGHT_VALUE: u16 = 0x0006;
/// The line speed of the network.
pub const BAUD: u32 = 115_200;

/// What a register allows, checked after its address and before its value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Access {
    Read,
    Write,
    ReadWrite,
}

/// A slave's register image as the request handler sees it.
trait RegisterMap {
    /// What `addr` allows; `None` for an unknown address.
    fn access(&self, addr: u16) -> Option<Access>;
    /// The value of a readable register.
    fn read(&self, addr: u16) -> u16;
    /// Stores `value` in a writable register, or says why not (exception 03).
    fn write(&mut self, addr: u16, value: u16) -> Result<(), Exception>;
}

/// The reply to `request`, checked in the spec's order: address (02), then
/// function (01), then value (03). A write is answered by its echo.
fn answer(map: &mut impl RegisterMap, request: Modbus8Repr) -> Modbus8Repr {
    let exception = |e| Modbus8Repr::exception(request.id, request.function, request.addr, e);
    let Some(access) = map.access(request.addr) else {
        return exception(Exception::IllegalDataAddress);
    };
    match (request.function, access) {
        (modbus8::READ, Access::Read | Access::ReadWrite) => Modbus8Repr {
            value: map.read(request.addr),
            ..request
        },
        (modbus8::WRITE, Access::Write | Access::ReadWrite) => {
            match map.write(request.addr, request.value) {
                Ok(()) => request,
                Err(e) => exception(e),
            }
        }
        _ => exception(Exception::IllegalFunction),
    }
}

/// Settings of a slave's serial port.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PortConfig {
    /// CRC byte order (the project's own: high byte first).
    pub crc_order: CrcOrder,
    /// Line quiet that ends a partial frame or a discard.
    pub silence: SimDuration,
    /// Injected fault: add 1 to the CRC of every reply, as the project's
    /// `snd_crc += 1` test did.
    pub corrupt_reply_crc: bool,
}

impl Default for PortConfig {
    fn default() -> Self {
        PortConfig {
            crc_order: CrcOrder::HighFirst,
            silence: protocols::modbus::serial::silence_3_5_chars(BAUD, 10),
            corrupt_reply_crc: false,
        }
    }
}

/// Replies a port is made room for at first: every request of one read is
/// answered, in order (a master on a pty or TCP may write several at once,
/// as the sketch's loop would answer them one after another).
const FIRST_REPLIES: usize = 16;

/// A slave's serial port: frames in, the replies waiting to go out.
#[derive(Debug, Clone)]
struct SlavePort {
    id: u8,
    config: PortConfig,
    decoder: Modbus8Decoder,
    replies: VecDeque<[u8; FRAME_LEN]>,
    /// The port is closed (reset communication) until then: bytes are lost.
    closed_until: Option<SimTime>,
    /// Every request refused with this exception (an injected fault).
    forced: Option<Exception>,
}

impl SlavePort {
    fn new(id: u8, config: PortConfig) -> Self {
        SlavePort {
            id,
            config,
            decoder: Modbus8Decoder::new(config.crc_order, config.silence),
            replies: VecDeque::with_capacity(FIRST_REPLIES),
            closed_until: None,
            forced: None,
        }
    }

    /// Feeds bytes that arrived at `now` and answers every request for this
    /// slave from `map`; a bad CRC, another id or a partial frame stay silent.
    fn receive(&mut self, map: &mut impl RegisterMap, now: SimTime, mut bytes: &[u8]) {
        if let Some(until) = self.closed_until {
            if now < until {
                return;
            }
            self.closed_until = None;
        }
        while !bytes.is_empty() {
            let Some(decoded) = self.decoder.decode(now, &mut bytes) else {
                break;
            };
            let decoded = decoded.map(|frame| Modbus8Repr::from_frame(&frame));
            if let Ok(request) = decoded
                && request.id == self.id
            {
                let reply = match self.forced {
                    Some(e) => {
                        Modbus8Repr::exception(request.id, request.function, request.addr, e)
                    }
                    None => answer(map, request),
                };
                let mut reply = reply.to_bytes(self.config.crc_order);
                if self.config.corrupt_reply_crc {
                    corrupt_crc(&mut reply, self.config.crc_order);
                }
                self.replies.push_back(reply);
            }
        }
    }

    /// Closes the port for `pause` from `now`: pending input and any unsent
    /// reply are lost, as when the Arduino calls `Serial.end()`.
    fn close_for(&mut self, now: SimTime, pause: SimDuration) {
        self.decoder = Modbus8Decoder::new(self.config.crc_order, self.config.silence);
        self.replies.clear();
        self.closed_until = Some(now + pause);
    }

    fn poll_transmit(&mut self, buf: &mut [u8]) -> Option<usize> {
        let slot = buf.get_mut(..FRAME_LEN)?;
        let reply = self.replies.pop_front()?;
        slot.copy_from_slice(&reply);
        Some(FRAME_LEN)
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        self.decoder.poll_timeout()
    }

    fn handle_timeout(&mut self, now: SimTime) {
        if self.decoder.poll_timeout().is_some_and(|at| at <= now) {
            self.decoder.handle_timeout(now);
        }
    }
}

/// Adds 1 to the CRC carried by `frame` (read and written in `order`).
fn corrupt_crc(frame: &mut [u8; FRAME_LEN], order: CrcOrder) {
    let [.., c0, c1] = *frame;
    let crc = match order {
        CrcOrder::HighFirst => u16::from_be_bytes([c0, c1]).wrapping_add(1).to_be_bytes(),
        CrcOrder::LowFirst => u16::from_le_bytes([c0, c1]).wrapping_add(1).to_le_bytes(),
    };
    frame[FRAME_LEN - 2..].copy_from_slice(&crc);
}

/// Whole milliseconds since the start of the run, as Arduino's `millis()`.
fn millis(now: SimTime) -> u64 {
    now.0 / (protocols::time::TICKS_PER_SECOND / 1_000)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corrupted_crc_is_the_projects_plus_one() {
        let mut frame = Modbus8Repr {
            id: 1,
            function: 6,
            addr: 1,
            value: 0x80,
        }
        .to_bytes(CrcOrder::HighFirst);
        corrupt_crc(&mut frame, CrcOrder::HighFirst);
        assert_eq!(frame[6..], [0xaa, 0xda]);
    }
}
