//! The binary Modbus frames, written in a suite as hex bytes: standard
//! RTU (unit, PDU, CRC-16 low byte first) and TCP (the MBAP header, unit,
//! PDU), and the Controller_network project's 8-byte frames (CRC high byte
//! first). The frames are made and checked by the workspace's own codecs
//! (`protocols`), the ones the twin's slaves speak.

use super::Protocol;
use protocols::modbus::rtu::{self, Direction};
use protocols::modbus::serial::FrameLen;
use protocols::modbus::{FrameError, MAX_PDU_LEN, tcp};
use protocols::modbus8::{self, CrcOrder, Modbus8Error};

/// Bytes written as hex: two digits a byte, spaces between any pairs.
pub(super) fn hex(text: &str) -> Result<Vec<u8>, String> {
    protocols::hex::bytes(text).map_err(|e| e.to_string())
}

/// A reply's pattern: hex bytes as [`hex`], `..` for a byte of any value.
pub(super) fn pattern(text: &str) -> Result<Vec<Option<u8>>, String> {
    protocols::hex::pattern(text).map_err(|e| e.to_string())
}

/// Whether `body` (filled) is a frame `protocol` can send: unit and PDU
/// within Modbus' sizes, or the 8-byte frame's six bytes before its CRC.
pub(super) fn check_send(protocol: Protocol, body: &str) -> Result<(), String> {
    let bytes = hex(body)?;
    match protocol {
        Protocol::Modbus8 if bytes.len() != 6 => Err(format!(
            "send `{body}`: an 8-byte Modbus frame is six bytes (id, function, address, value) before its CRC; this is {}",
            bytes.len()
        )),
        _ if !(2..=1 + MAX_PDU_LEN).contains(&bytes.len()) => Err(format!(
            "send `{body}`: a Modbus frame is a unit id and 1 to {MAX_PDU_LEN} bytes of PDU; this is {} bytes",
            bytes.len()
        )),
        _ => Ok(()),
    }
}

/// The frame for `body` (filled, checked): RTU and 8-byte frames with
/// their CRC (one too many when `spoil`), TCP frames with their header.
pub(super) fn request(protocol: Protocol, body: &str, spoil: bool, transaction: u16) -> Vec<u8> {
    let bytes = hex(body).unwrap_or_default();
    let (unit, pdu) = bytes.split_first().unwrap_or((&0, &[][..]));
    let mut out = vec![0; tcp::MAX_ADU_LEN];
    let len = match protocol {
        Protocol::ModbusTcp => tcp::TcpRepr {
            transaction_id: transaction,
            unit: *unit,
            pdu,
        }
        .emit(&mut out)
        .unwrap_or(0),
        Protocol::Modbus8 => {
            let frame = modbus8::Modbus8Repr {
                id: *unit,
                function: pdu.first().copied().unwrap_or(0),
                addr: word(pdu, 1),
                value: word(pdu, 3),
            };
            frame.emit(&mut out, CrcOrder::HighFirst).unwrap_or(0)
        }
        _ => rtu::RtuRepr { unit: *unit, pdu }
            .emit(&mut out)
            .unwrap_or(0),
    };
    out.truncate(len);
    if spoil && let Some(last) = out.last_mut() {
        *last = last.wrapping_add(1);
    }
    out
}

fn word(bytes: &[u8], at: usize) -> u16 {
    match bytes.get(at..at + 2) {
        Some(&[hi, lo]) => u16::from_be_bytes([hi, lo]),
        _ => 0,
    }
}

/// Where the first reply in `bytes` ends, if it is whole: by its function
/// code and byte count (RTU), its header's length (TCP; a header that
/// cannot be Modbus takes everything, to be judged), or eight bytes.
pub(super) fn frame_end(protocol: Protocol, bytes: &[u8]) -> Option<usize> {
    let whole = |n: usize| (bytes.len() >= n).then_some(n);
    match protocol {
        Protocol::Modbus8 => whole(modbus8::FRAME_LEN),
        Protocol::ModbusTcp => {
            let &[_, _, p_hi, p_lo, l_hi, l_lo, ..] = bytes else {
                return None;
            };
            let length = usize::from(u16::from_be_bytes([l_hi, l_lo]));
            if [p_hi, p_lo] != [0, 0] || !(2..=1 + MAX_PDU_LEN).contains(&length) {
                return Some(bytes.len());
            }
            whole(6 + length)
        }
        _ => match rtu::frame_len(Direction::Response, bytes) {
            FrameLen::Known(n) => whole(n),
            FrameLen::NeedAtLeast(_) | FrameLen::UntilSilence => None,
        },
    }
}

/// Whether `frame` is a reply with its check bytes right (over TCP: a
/// header answering `transaction`) whose unit and PDU match `pattern` and
/// then `data` bytes of any value.
pub(super) fn judge(
    protocol: Protocol,
    frame: &[u8],
    pattern_text: &str,
    data: u16,
    transaction: u16,
) -> Result<(), String> {
    let body = checked(protocol, frame, transaction)?;
    let pattern = pattern(pattern_text)?;
    let fits = body.len() == pattern.len() + usize::from(data)
        && body
            .iter()
            .zip(&pattern)
            .all(|(b, p)| p.is_none_or(|p| p == *b));
    if fits {
        Ok(())
    } else {
        Err(format!("the reply was `{}`", shown(body)))
    }
}

/// The unit and PDU of a reply whose framing holds, or what is wrong.
fn checked(protocol: Protocol, frame: &[u8], transaction: u16) -> Result<&[u8], String> {
    let seen = shown(frame);
    match protocol {
        Protocol::Modbus8 => match modbus8::Modbus8Repr::parse(frame, CrcOrder::HighFirst) {
            Ok(_) => Ok(frame.get(..6).unwrap_or_default()),
            Err(Modbus8Error::WrongLength { len }) => {
                Err(format!("`{seen}` is {len} bytes; a frame is 8"))
            }
            Err(Modbus8Error::BadCrc { calculated, .. }) => Err(bad_crc(
                frame,
                calculated.to_be_bytes(),
                "the 8-byte Modbus sends the CRC's high byte first",
            )),
        },
        Protocol::ModbusTcp => {
            let reply = tcp::TcpFrame::new_checked(frame).map_err(|e| match e {
                FrameError::ProtocolId(id) => {
                    format!("`{seen}`: its header's protocol id is {id:04X}; Modbus is 0000")
                }
                FrameError::MbapLength(n) => {
                    format!("`{seen}`: its header gives a length of {n}; Modbus allows 2 to 254")
                }
                FrameError::LengthMismatch { expected, actual } => format!(
                    "`{seen}`: its header gives a length of {expected}; {actual} bytes followed"
                ),
                _ => format!("`{seen}` is too short for a Modbus TCP frame"),
            })?;
            if reply.transaction_id() != transaction {
                return Err(format!(
                    "`{seen}` carries transaction id {:04X}; the request's was {transaction:04X}",
                    reply.transaction_id()
                ));
            }
            Ok(frame.get(tcp::MBAP_LEN - 1..).unwrap_or_default())
        }
        _ => match rtu::RtuFrame::new_checked(frame) {
            Ok(_) => Ok(frame.get(..frame.len() - 2).unwrap_or_default()),
            Err(FrameError::BadCrc { calculated, .. }) => Err(bad_crc(
                frame,
                calculated.to_le_bytes(),
                "Modbus RTU sends the CRC's low byte first",
            )),
            Err(_) => Err(format!("`{seen}` is too short for a Modbus RTU frame")),
        },
    }
}

/// A reply's wrong CRC, with the bytes it should have been, and whether
/// they were only swapped.
fn bad_crc(frame: &[u8], right: [u8; 2], order: &str) -> String {
    let at = frame.len().saturating_sub(2);
    let (body, crc) = frame.split_at(at);
    let mut why = format!(
        "its CRC is `{}`; its bytes `{}` give `{}`",
        shown(crc),
        shown(body),
        shown(&right)
    );
    if crc == [right[1], right[0]] {
        why += &format!(" (the two bytes swapped: {order})");
    }
    why
}

/// The exception reply of `code` to `request` (its unit and PDU, or the
/// 8-byte frame's first six bytes): the function's top bit set, and the
/// code; the 8-byte Modbus keeps the address and carries the code in the
/// value.
pub(super) fn exception_pattern(protocol: Protocol, request: &[u8], code: u8) -> String {
    let byte = |at: usize| request.get(at).copied().unwrap_or(0);
    let function = byte(1) | 0x80;
    match protocol {
        Protocol::Modbus8 => format!(
            "{:02X} {function:02X} {:02X}{:02X} 00{code:02X}",
            byte(0),
            byte(2),
            byte(3)
        ),
        _ => format!("{:02X} {function:02X} {code:02X}", byte(0)),
    }
}

/// Bytes as hex, a space between them.
pub(super) fn shown(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(3 * bytes.len());
    for (i, b) in bytes.iter().enumerate() {
        if i > 0 {
            out.push(' ');
        }
        out.push_str(&format!("{b:02X}"));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_bytes_take_spaces_between_pairs_and_dots_for_any_byte() {
        assert_eq!(hex("01 03 0000 000A"), Ok(vec![1, 3, 0, 0, 0, 0x0A]));
        assert_eq!(pattern("01 .. 0c"), Ok(vec![Some(1), None, Some(0x0C)]));
        assert!(hex("01 3").unwrap_err().contains("odd number"));
        assert!(hex("01 0G").unwrap_err().contains("`0G`"));
        assert!(hex("01 ..").unwrap_err().contains("replies only"));
    }

    #[test]
    fn an_rtu_request_carries_its_crc_low_byte_first() {
        let frame = request(Protocol::ModbusRtu, "01 03 0000 000A", false, 0);
        assert_eq!(frame, [0x01, 0x03, 0x00, 0x00, 0x00, 0x0A, 0xC5, 0xCD]);
        let spoilt = request(Protocol::ModbusRtu, "01 03 0000 000A", true, 0);
        assert_eq!(spoilt[7], 0xCE);
    }

    #[test]
    fn an_eight_byte_frame_carries_its_crc_high_byte_first() {
        // The Controller_network master's own write of 0x80 to the motor.
        let frame = request(Protocol::Modbus8, "01 06 0001 0080", false, 0);
        assert_eq!(frame, [0x01, 0x06, 0x00, 0x01, 0x00, 0x80, 0xAA, 0xD9]);
        assert_eq!(
            judge(Protocol::Modbus8, &frame, "01 06 0001 0080", 0, 0),
            Ok(())
        );
        let swapped = [0x01, 0x06, 0x00, 0x01, 0x00, 0x80, 0xD9, 0xAA];
        let why = judge(Protocol::Modbus8, &swapped, "01 06 0001 0080", 0, 0).unwrap_err();
        assert!(why.contains("two bytes swapped"), "{why}");
    }

    #[test]
    fn a_tcp_reply_must_answer_the_requests_transaction() {
        let frame = request(Protocol::ModbusTcp, "01 03 0000 0001", false, 7);
        assert_eq!(frame, [0, 7, 0, 0, 0, 6, 1, 3, 0, 0, 0, 1]);
        let reply = [0, 7, 0, 0, 0, 5, 1, 3, 2, 0x12, 0x34];
        assert_eq!(frame_end(Protocol::ModbusTcp, &reply), Some(11));
        assert_eq!(judge(Protocol::ModbusTcp, &reply, "01 03 02", 2, 7), Ok(()));
        let why = judge(Protocol::ModbusTcp, &reply, "01 03 02", 2, 8).unwrap_err();
        assert!(why.contains("transaction id 0007"), "{why}");
    }

    #[test]
    fn an_rtu_reply_is_delimited_by_its_byte_count_and_judged() {
        let reply = request(Protocol::ModbusRtu, "01 04 04 0001 0002", false, 0);
        let mut more = reply.clone();
        more.extend_from_slice(&[0x01, 0x84]);
        assert_eq!(frame_end(Protocol::ModbusRtu, &more), Some(reply.len()));
        assert_eq!(frame_end(Protocol::ModbusRtu, &reply[..5]), None);
        assert_eq!(judge(Protocol::ModbusRtu, &reply, "01 04 04", 4, 0), Ok(()));
        let why = judge(Protocol::ModbusRtu, &reply, "01 04 04", 2, 0).unwrap_err();
        assert_eq!(why, "the reply was `01 04 04 00 01 00 02`");
        let exception = exception_pattern(Protocol::ModbusRtu, &[1, 4, 0, 0x20, 0, 1], 2);
        assert_eq!(exception, "01 84 02");
    }
}
