//! What differs between the buses a master is checked on: where a request
//! ends in the bytes the master sends, what is wrong with it in the
//! protocol's own words, the slave's reply to it, and the ways a reply is
//! spoilt. MEB's text frames, standard Modbus RTU and TCP, and the
//! Controller_network project's 8-byte Modbus; `play` and `judge` ask
//! here and are otherwise the same for all four.

use crate::framing::Protocol;
use nodes::controller_network::{
    LIGHT_ID, LightConfig, LightNode, MOTOR_ID, MotorConfig, MotorNode,
};
use nodes::firmware::{Framing, RegisterImage, SlaveFrontend};
use nodes::node::Node;
use protocols::crc::crc16_modbus;
use protocols::meb::{MebError, MebErrorCode, MebRepr};
use protocols::modbus::rtu::{self, Direction};
use protocols::modbus::serial::{FrameLen, PTY_SILENCE};
use protocols::modbus::{Adu, Exception, Request};
use protocols::modbus8::{self, CrcOrder, Modbus8Repr};
use protocols::time::SimTime;

/// A request as the slave sees it.
#[derive(Debug, Clone, Default)]
pub(crate) struct Examined {
    /// What is wrong with it, in the protocol's words; `None` when it is a
    /// well-formed request.
    pub fault: Option<String>,
    /// The slave it is for, read past a wrong check.
    pub id: Option<u8>,
    /// It is for every slave (MEB `00`, Modbus unit 0).
    pub broadcast: bool,
    /// What it reads (`true`) or writes, as a report names it.
    pub block: Option<(bool, String)>,
    /// The exception the slave's own reply carries (Modbus): it asked for
    /// what the slave does not have.
    pub refused: Option<u8>,
}

/// The next request in `pending`, if it is whole: the bytes before it that
/// belong to no frame, and its own. `quiet`: nothing more came for a
/// while, so bytes whose length cannot be told are taken as they are.
pub(crate) fn take_request(
    protocol: Protocol,
    pending: &mut Vec<u8>,
    quiet: bool,
) -> Option<(Vec<u8>, Vec<u8>)> {
    let len = match protocol {
        Protocol::Meb => {
            let nl = pending.iter().position(|&b| b == b'\n')?;
            let chunk: Vec<u8> = pending.drain(..=nl).collect();
            let start = chunk
                .iter()
                .rposition(|&b| b == b'@')
                .unwrap_or(chunk.len());
            let (junk, bytes) = chunk.split_at(start);
            return Some((junk.to_vec(), bytes.to_vec()));
        }
        Protocol::ModbusRtu => match rtu::frame_len(Direction::Request, pending) {
            FrameLen::Known(n) => n.min(rtu::MAX_ADU_LEN),
            _ if quiet => pending.len(),
            _ => return None,
        },
        Protocol::ModbusTcp => match pending.get(4..6) {
            Some(&[hi, lo]) => 6 + usize::from(u16::from_be_bytes([hi, lo])).min(254),
            _ if quiet => pending.len(),
            _ => return None,
        },
        Protocol::Modbus8 => modbus8::FRAME_LEN,
    };
    if pending.is_empty() || (pending.len() < len && !quiet) {
        return None;
    }
    let len = len.min(pending.len());
    Some((Vec::new(), pending.drain(..len).collect()))
}

/// The longest a request can be: more pending bytes than this that make
/// none are junk.
pub(crate) fn max_request(protocol: Protocol) -> usize {
    match protocol {
        Protocol::Meb => protocols::meb::MEB_MAX_FRAME_LEN,
        Protocol::ModbusRtu => rtu::MAX_ADU_LEN,
        Protocol::ModbusTcp => 260,
        Protocol::Modbus8 => modbus8::FRAME_LEN,
    }
}

/// What the slave makes of `bytes`.
pub(crate) fn examine(protocol: Protocol, bytes: &[u8]) -> Examined {
    let text = protocol.shown(bytes);
    match protocol {
        Protocol::Meb => examine_meb(bytes, &text),
        Protocol::ModbusRtu | Protocol::ModbusTcp => examine_modbus(protocol, bytes, &text),
        Protocol::Modbus8 => examine_modbus8(bytes, &text),
    }
}

fn examine_meb(bytes: &[u8], text: &str) -> Examined {
    let frame = MebRepr::parse(bytes);
    let id = frame.as_ref().ok().map(|f| f.id).or_else(|| {
        repaired(Protocol::Meb, bytes)
            .and_then(|b| MebRepr::parse(&b).ok())
            .map(|f| f.id)
    });
    let mut seen = Examined {
        id,
        ..Examined::default()
    };
    let frame = match frame {
        Ok(frame) => frame,
        Err(MebError::BadFcs) => {
            seen.fault = Some(format!(
                "`{text}`: its FCS is not the XOR of its bytes (the page: XOR of every byte from @ to the last before the FCS)"
            ));
            return seen;
        }
        Err(e) => {
            seen.fault = Some(format!("`{text}` is not a well-formed frame: {e}"));
            return seen;
        }
    };
    seen.broadcast = frame.is_broadcast();
    seen.block = Some((
        matches!(
            frame.cmd.block().map(|(b, _)| b.access()),
            Some(protocols::meb::MebAccess::Read)
        ),
        meb_span(&frame),
    ));
    if frame.shape().is_reply() {
        seen.fault = Some(format!("`{text}` has a reply's shape, not a request's"));
    } else if emit_meb(&frame).is_some_and(|canonical| canonical != bytes) {
        seen.fault = Some(format!(
            "`{text}` is not written as the page says to emit a frame (upper-case hex, ending *\\n)"
        ));
    }
    seen
}

fn meb_span(frame: &MebRepr) -> String {
    let last = u16::from(frame.addr) + u16::from(frame.cnt.max(1)) - 1;
    if frame.cnt <= 1 {
        format!("{} {:02X}", frame.cmd, frame.addr)
    } else {
        format!("{} {:02X}-{last:02X}", frame.cmd, frame.addr)
    }
}

/// A Modbus RTU or TCP request's unit and PDU, or what is wrong with its
/// framing.
fn modbus_body(protocol: Protocol, bytes: &[u8]) -> Result<(u8, Vec<u8>), String> {
    if protocol == Protocol::ModbusTcp {
        let (Some(header), Some(&unit)) = (bytes.get(..6), bytes.get(6)) else {
            return Err(format!(
                "{} bytes: shorter than an MBAP header and a unit id",
                bytes.len()
            ));
        };
        if header[2..4] != [0, 0] {
            return Err("its MBAP protocol id is not 0 (Modbus)".into());
        }
        let said = usize::from(u16::from_be_bytes([header[4], header[5]]));
        if said != bytes.len() - 6 {
            return Err(format!(
                "its MBAP length says {said} bytes follow, {} do",
                bytes.len() - 6
            ));
        }
        return Ok((unit, bytes[7..].to_vec()));
    }
    match rtu::RtuFrame::new_checked(bytes) {
        Ok(frame) => Ok((frame.unit(), frame.pdu().to_vec())),
        Err(protocols::modbus::FrameError::BadCrc { .. }) => {
            let body = &bytes[..bytes.len() - 2];
            let right = crc16_modbus(body).to_le_bytes();
            let sent = &bytes[bytes.len() - 2..];
            Err(if sent == [right[1], right[0]] {
                format!(
                    "its CRC is sent high byte first ({:02X} {:02X}): Modbus RTU sends it low byte first ({:02X} {:02X})",
                    sent[0], sent[1], right[0], right[1]
                )
            } else {
                format!(
                    "its CRC {:02X} {:02X} is not the CRC-16 of its bytes ({:02X} {:02X}, low byte first)",
                    sent[0], sent[1], right[0], right[1]
                )
            })
        }
        Err(e) => Err(format!("it is not a well-formed RTU frame: {e}")),
    }
}

fn examine_modbus(protocol: Protocol, bytes: &[u8], text: &str) -> Examined {
    let mut seen = Examined::default();
    let (unit, pdu) = match modbus_body(protocol, bytes) {
        Ok(body) => body,
        Err(why) => {
            seen.id = match protocol {
                Protocol::ModbusTcp => bytes.get(6).copied(),
                _ => bytes.first().copied(),
            };
            seen.fault = Some(format!("`{text}`: {why}"));
            return seen;
        }
    };
    seen.id = Some(unit);
    seen.broadcast = unit == 0 && protocol == Protocol::ModbusRtu;
    let request = match Request::parse(&pdu) {
        Ok(request) => request,
        Err(e) => {
            seen.fault = Some(format!(
                "`{text}` is not a request the Modbus standard defines: {e}"
            ));
            return seen;
        }
    };
    let (read, table, address, count) = match &request {
        Request::ReadCoils { address, quantity } => (true, "coils", *address, *quantity),
        Request::ReadDiscreteInputs { address, quantity } => {
            (true, "discrete inputs", *address, *quantity)
        }
        Request::ReadHoldingRegisters { address, quantity } => {
            (true, "holding registers", *address, *quantity)
        }
        Request::ReadInputRegisters { address, quantity } => {
            (true, "input registers", *address, *quantity)
        }
        Request::WriteSingleCoil { address, .. } => (false, "coil", *address, 1),
        Request::WriteSingleRegister { address, .. } => (false, "holding register", *address, 1),
        Request::WriteMultipleCoils { address, coils } => {
            (false, "coils", *address, coils.quantity())
        }
        Request::WriteMultipleRegisters { address, registers } => {
            (false, "holding registers", *address, registers.len() as u16)
        }
    };
    let last = u32::from(address) + u32::from(count.max(1)) - 1;
    seen.block = Some((
        read,
        if count <= 1 {
            format!("{table} {address}")
        } else {
            format!("{table} {address}-{last}")
        },
    ));
    seen
}

fn examine_modbus8(bytes: &[u8], text: &str) -> Examined {
    let mut seen = Examined {
        id: bytes.first().copied(),
        ..Examined::default()
    };
    let frame = match Modbus8Repr::parse(bytes, CrcOrder::HighFirst) {
        Ok(frame) => frame,
        Err(modbus8::Modbus8Error::BadCrc { .. }) => {
            seen.fault = Some(if Modbus8Repr::parse(bytes, CrcOrder::LowFirst).is_ok() {
                format!(
                    "`{text}`: its CRC is sent low byte first, as standard Modbus does: the Controller_network project sends it high byte first"
                )
            } else {
                format!("`{text}`: its CRC is not the CRC-16 of its first six bytes")
            });
            return seen;
        }
        Err(e) => {
            seen.fault = Some(format!("`{text}` is not an 8-byte frame: {e}"));
            return seen;
        }
    };
    let read = frame.function == modbus8::READ;
    if !read && frame.function != modbus8::WRITE {
        seen.fault = Some(format!(
            "`{text}`: function {:02X} is none of the project's (03 reads a register, 06 writes one)",
            frame.function
        ));
        return seen;
    }
    seen.block = Some((read, format!("{:02X}:{:04X}", frame.id, frame.addr)));
    seen
}

/// `bytes` with its check bytes made right, if only they were wrong.
pub(crate) fn repaired(protocol: Protocol, bytes: &[u8]) -> Option<Vec<u8>> {
    match protocol {
        Protocol::Meb => with_fcs(bytes, |right| right),
        Protocol::ModbusTcp => Some(bytes.to_vec()),
        Protocol::ModbusRtu => {
            let body = bytes.get(..bytes.len().checked_sub(2)?)?;
            let mut out = body.to_vec();
            out.extend_from_slice(&crc16_modbus(body).to_le_bytes());
            Some(out)
        }
        Protocol::Modbus8 => {
            let body = bytes.get(..6).filter(|_| bytes.len() == 8)?;
            let mut out = body.to_vec();
            out.extend_from_slice(&crc16_modbus(body).to_be_bytes());
            Some(out)
        }
    }
}

/// MEB `frame` with its FCS replaced by `fcs(the right one)`.
fn with_fcs(frame: &[u8], fcs: impl Fn(u8) -> u8) -> Option<Vec<u8>> {
    let star = frame.iter().rposition(|&b| b == b'*')?;
    let body = frame.get(..star.checked_sub(2)?)?;
    let right = body.iter().fold(0, |x, b| x ^ b);
    let mut out = body.to_vec();
    out.extend_from_slice(format!("{:02X}", fcs(right)).as_bytes());
    out.extend_from_slice(frame.get(star..)?);
    Some(out)
}

fn emit_meb(frame: &MebRepr) -> Option<Vec<u8>> {
    let mut buf = [0u8; 512];
    let n = frame.emit(&mut buf).ok()?;
    buf.get(..n).map(<[u8]>::to_vec)
}

/// The twin's slaves on the master's line, each answering from its own
/// code: the EV module's controller (MEB and Modbus, over a register image
/// at power-up), or the Controller_network project's motor and light nodes.
pub(crate) enum Slaves {
    Image(Vec<(u8, RegisterImage, SlaveFrontend)>),
    Network {
        motor: Option<Box<MotorNode>>,
        light: Option<Box<LightNode>>,
    },
}

impl Slaves {
    pub(crate) fn new(protocol: Protocol, ids: &[u8]) -> Self {
        let framing = match protocol {
            Protocol::Meb => Framing::Meb,
            Protocol::ModbusRtu => Framing::ModbusRtu(PTY_SILENCE),
            Protocol::ModbusTcp => Framing::ModbusTcp,
            Protocol::Modbus8 => {
                return Slaves::Network {
                    motor: ids
                        .contains(&MOTOR_ID)
                        .then(|| Box::new(MotorNode::new(MotorConfig::default()))),
                    light: ids
                        .contains(&LIGHT_ID)
                        .then(|| Box::new(LightNode::new(LightConfig::default()))),
                };
            }
        };
        Slaves::Image(
            ids.iter()
                .map(|&id| {
                    // The EV module's controller at power-up (12-bit DAC and
                    // ADC, the default light threshold and speed window).
                    let image = RegisterImage::new(12, 12, 1933, 100);
                    (id, image, SlaveFrontend::new(framing, id))
                })
                .collect(),
        )
    }

    /// The reply of the slave `request` (well-formed, its check right) is
    /// for, if one answers it.
    pub(crate) fn reply(&mut self, now: SimTime, id: u8, request: &[u8]) -> Option<Vec<u8>> {
        let mut out = [0u8; 512];
        let n = match self {
            Slaves::Image(slaves) => {
                let (_, image, frontend) = slaves.iter_mut().find(|(i, _, _)| *i == id)?;
                frontend.handle_bytes(image, now, request);
                // A function of no known length ends with the silence
                // after it: the request is whole, so that is now.
                if let Some(at) = frontend.poll_timeout() {
                    frontend.handle_timeout(image, at);
                }
                while frontend.poll_event().is_some() {}
                let n = frontend.poll_transmit(&mut out)?;
                while frontend.poll_transmit(&mut [0u8; 512]).is_some() {}
                n
            }
            Slaves::Network { motor, light } => {
                let node: &mut dyn Node = match id {
                    MOTOR_ID => motor.as_deref_mut()?,
                    LIGHT_ID => light.as_deref_mut()?,
                    _ => return None,
                };
                node.handle_bytes(now, request);
                while node.poll_event().is_some() {}
                let n = node.poll_transmit(now, &mut out)?;
                while node.poll_transmit(now, &mut [0u8; 512]).is_some() {}
                n
            }
        };
        out.get(..n).map(<[u8]>::to_vec)
    }
}

/// The slave a reply is from.
pub(crate) fn reply_id(protocol: Protocol, reply: &[u8]) -> Option<u8> {
    match protocol {
        Protocol::Meb => MebRepr::parse(reply).ok().map(|r| r.id),
        Protocol::ModbusTcp => reply.get(6).copied(),
        _ => reply.first().copied(),
    }
}

/// `reply` with its check bytes wrong (every bit flipped), or `None` where
/// the protocol has none (TCP).
pub(crate) fn spoil_check(protocol: Protocol, reply: &[u8]) -> Option<Vec<u8>> {
    match protocol {
        Protocol::Meb => with_fcs(reply, |right| !right),
        Protocol::ModbusTcp => None,
        Protocol::ModbusRtu | Protocol::Modbus8 => {
            let mut out = reply.to_vec();
            let n = out.len();
            for b in out.get_mut(n.checked_sub(2)?..)? {
                *b = !*b;
            }
            Some(out)
        }
    }
}

/// `reply` as slave `other` would send it.
pub(crate) fn with_id(protocol: Protocol, reply: &[u8], other: u8) -> Option<Vec<u8>> {
    match protocol {
        Protocol::Meb => MebRepr::parse(reply)
            .ok()
            .and_then(|r| emit_meb(&MebRepr { id: other, ..r })),
        Protocol::ModbusTcp => {
            let mut out = reply.to_vec();
            *out.get_mut(6)? = other;
            Some(out)
        }
        Protocol::ModbusRtu => {
            let mut out = reply.get(..reply.len().checked_sub(2)?)?.to_vec();
            *out.first_mut()? = other;
            out.extend_from_slice(&crc16_modbus(&out).to_le_bytes());
            Some(out)
        }
        Protocol::Modbus8 => {
            let mut frame = Modbus8Repr::parse(reply, CrcOrder::HighFirst).ok()?;
            frame.id = other;
            Some(frame.to_bytes(CrcOrder::HighFirst).to_vec())
        }
    }
}

/// The refusal of `code` the slave sends instead of `reply`, its good
/// reply: MEB's error reply, Modbus' exception.
pub(crate) fn refusal(protocol: Protocol, reply: &[u8], code: u8) -> Option<Vec<u8>> {
    match protocol {
        Protocol::Meb => {
            let good = MebRepr::parse(reply).ok()?;
            let code = MebErrorCode::from_word(code.into()).unwrap_or(MebErrorCode::DeviceFailure);
            emit_meb(&MebRepr::error_reply(good.id, good.addr, code))
        }
        Protocol::ModbusRtu => {
            let mut out = vec![*reply.first()?, reply.get(1)? | 0x80, code];
            out.extend_from_slice(&crc16_modbus(&out).to_le_bytes());
            Some(out)
        }
        Protocol::ModbusTcp => {
            let mut out = reply.get(..4)?.to_vec();
            out.extend_from_slice(&[0, 3, *reply.get(6)?, reply.get(7)? | 0x80, code]);
            Some(out)
        }
        Protocol::Modbus8 => {
            // A reply keeps its request's id, function and address.
            let asked = Modbus8Repr::parse(reply, CrcOrder::HighFirst).ok()?;
            let frame = Modbus8Repr::exception(
                asked.id,
                asked.function & !modbus8::EXCEPTION_BIT,
                asked.addr,
                Exception::from_code(code),
            );
            Some(frame.to_bytes(CrcOrder::HighFirst).to_vec())
        }
    }
}

/// The exception code a Modbus reply carries, if it is a refusal (MEB's
/// error replies are left to the MEB page's own checks).
pub(crate) fn exception_of(protocol: Protocol, reply: &[u8]) -> Option<u8> {
    let (function, code) = match protocol {
        Protocol::Meb => return None,
        Protocol::ModbusRtu => (*reply.get(1)?, *reply.get(2)?),
        Protocol::ModbusTcp => (*reply.get(7)?, *reply.get(8)?),
        Protocol::Modbus8 => (*reply.get(1)?, *reply.get(5)?),
    };
    (function & 0x80 != 0).then_some(code)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rtu(body: &[u8]) -> Vec<u8> {
        let mut out = body.to_vec();
        out.extend_from_slice(&crc16_modbus(body).to_le_bytes());
        out
    }

    #[test]
    fn an_rtu_request_ends_where_its_function_says_and_waits_for_the_rest() {
        let read = rtu(&[1, 4, 0, 0, 0, 10]);
        let mut pending = read[..5].to_vec();
        assert!(take_request(Protocol::ModbusRtu, &mut pending, false).is_none());
        pending.extend_from_slice(&read[5..]);
        pending.extend_from_slice(&read[..3]);
        let (junk, taken) = take_request(Protocol::ModbusRtu, &mut pending, false).unwrap();
        assert!(junk.is_empty());
        assert_eq!(taken, read);
        assert_eq!(pending.len(), 3);
        // Once the line is quiet, what is there is taken as it is.
        let (_, rest) = take_request(Protocol::ModbusRtu, &mut pending, true).unwrap();
        assert_eq!(rest.len(), 3);
        assert!(examine(Protocol::ModbusRtu, &rest).fault.is_some());
    }

    #[test]
    fn a_crc_in_the_wrong_order_is_named_so() {
        let mut swapped = rtu(&[1, 3, 0, 0, 0, 1]);
        swapped.swap(6, 7);
        let seen = examine(Protocol::ModbusRtu, &swapped);
        assert!(
            seen.fault.as_deref().unwrap().contains("high byte first"),
            "{seen:?}"
        );
        assert_eq!(seen.id, Some(1));
        assert_eq!(
            repaired(Protocol::ModbusRtu, &swapped).unwrap(),
            rtu(&[1, 3, 0, 0, 0, 1])
        );
        let eight = Modbus8Repr {
            id: 1,
            function: modbus8::READ,
            addr: 5,
            value: 0,
        };
        let low_first = eight.to_bytes(CrcOrder::LowFirst);
        let seen = examine(Protocol::Modbus8, &low_first);
        assert!(
            seen.fault.as_deref().unwrap().contains("low byte first"),
            "{seen:?}"
        );
        let right = eight.to_bytes(CrcOrder::HighFirst);
        let seen = examine(Protocol::Modbus8, &right);
        assert!(seen.fault.is_none(), "{seen:?}");
        assert_eq!(seen.block, Some((true, "01:0005".into())));
    }

    #[test]
    fn the_modbus_slave_answers_and_its_reply_is_spoilt_as_asked() {
        let mut slaves = Slaves::new(Protocol::ModbusRtu, &[1]);
        let request = rtu(&[1, 4, 0, 0, 0, 10]);
        let reply = slaves.reply(SimTime::ZERO, 1, &request).unwrap();
        assert_eq!(&reply[..3], &[1, 4, 20]);
        assert!(rtu::RtuFrame::new_checked(&reply).is_ok());
        let bad = spoil_check(Protocol::ModbusRtu, &reply).unwrap();
        assert!(rtu::RtuFrame::new_checked(&bad).is_err());
        let other = with_id(Protocol::ModbusRtu, &reply, 7).unwrap();
        assert_eq!(rtu::RtuFrame::new_checked(&other).unwrap().unit(), 7);
        let refused = refusal(Protocol::ModbusRtu, &reply, 4).unwrap();
        assert_eq!(&refused[..3], &[1, 0x84, 4]);
        assert_eq!(exception_of(Protocol::ModbusRtu, &refused), Some(4));
        // The map has three holding registers: a read of four is refused.
        let four = rtu(&[1, 3, 0, 0, 0, 4]);
        let reply = slaves.reply(SimTime::ZERO, 1, &four).unwrap();
        assert_eq!(exception_of(Protocol::ModbusRtu, &reply), Some(2));
    }
}
