//! How a suite's protocol puts a step's frame on the line and reads the
//! reply back: MEB's text frames ([`meb`]) and the binary Modbus frames
//! ([`binary`]: standard RTU and TCP, and the Controller_network project's
//! 8-byte variant). The runner plays steps; what a frame looks like, where
//! a reply ends and whether its check bytes hold is asked here.

mod binary;
mod meb;

/// The protocol a suite speaks, from its `protocol` field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Protocol {
    /// The M3CVME tool's MEB: text frames, an XOR FCS, `*\n`.
    Meb,
    /// Standard Modbus RTU: unit, PDU, CRC-16 low byte first.
    ModbusRtu,
    /// Standard Modbus TCP: the MBAP header, unit, PDU.
    ModbusTcp,
    /// The Controller_network project's 8-byte Modbus: CRC high byte first.
    Modbus8,
}

/// What a suite's `protocol` may say.
pub const PROTOCOLS: &str = "\"meb\", \"modbus-rtu\", \"modbus-tcp\" or \"modbus8\"";

impl Protocol {
    pub fn from_name(name: &str) -> Option<Self> {
        Some(match name {
            "meb" => Protocol::Meb,
            "modbus-rtu" => Protocol::ModbusRtu,
            "modbus-tcp" => Protocol::ModbusTcp,
            "modbus8" => Protocol::Modbus8,
            _ => return None,
        })
    }

    /// The protocol as the recording's frame describer names a link's
    /// (`describe::link_frame_fields`): the 8-byte Modbus decodes as a
    /// bus's frames do.
    pub fn link_name(self) -> &'static str {
        match self {
            Protocol::Meb => "meb",
            Protocol::ModbusRtu => "modbus-rtu",
            Protocol::ModbusTcp => "modbus-tcp",
            Protocol::Modbus8 => "modbus8",
        }
    }

    /// True for MEB, whose frames are written as text.
    pub fn is_text(self) -> bool {
        self == Protocol::Meb
    }

    /// The ids a slave of this protocol may have.
    pub fn ids(self) -> std::ops::RangeInclusive<u8> {
        match self {
            Protocol::Meb => 1..=99,
            _ => 1..=247,
        }
    }

    /// `text` with `{id}` and `{other}` (an id that is not the slave's)
    /// written as the protocol writes an id: two decimal digits in MEB, a
    /// hex byte in the binary ones.
    pub fn fill(self, text: &str, id: u8) -> String {
        let other = if id == *self.ids().end() {
            id - 1
        } else {
            id + 1
        };
        let write = |id: u8| match self {
            Protocol::Meb => format!("{id:02}"),
            _ => format!("{id:02X}"),
        };
        text.replace("{id}", &write(id))
            .replace("{other}", &write(other))
    }

    /// Whether a step's `send` is a frame this protocol can write.
    pub fn check_send(self, body: &str) -> Result<(), String> {
        match self {
            Protocol::Meb => meb::check_send(body),
            _ => binary::check_send(self, &self.fill(body, 1)),
        }
    }

    /// Whether a step's `raw` can be sent.
    pub fn check_raw(self, raw: &str) -> Result<(), String> {
        match self {
            Protocol::Meb => Ok(()),
            _ => binary::hex(&self.fill(raw, 1)).map(drop),
        }
    }

    /// Whether a step's `expect` is a reply this protocol can judge.
    pub fn check_pattern(self, pattern: &str) -> Result<(), String> {
        match self {
            Protocol::Meb => meb::check_pattern(pattern),
            _ => binary::pattern(&self.fill(pattern, 1)).map(drop),
        }
    }

    /// The bytes on the line for a `send` of `body` (filled, checked at
    /// load): its check bytes added, or spoilt when `spoil`; `ending` ends
    /// an MEB frame; `transaction` goes in a Modbus TCP header.
    pub fn request(self, body: &str, spoil: bool, ending: &str, transaction: u16) -> Vec<u8> {
        match self {
            Protocol::Meb => meb::request(body, spoil, ending),
            _ => binary::request(self, body, spoil, transaction),
        }
    }

    /// The bytes of a `raw` step (filled, checked at load).
    pub fn raw(self, text: &str) -> Vec<u8> {
        match self {
            Protocol::Meb => text.as_bytes().to_vec(),
            _ => binary::hex(text).unwrap_or_default(),
        }
    }

    /// The bytes of a `send`'s body (filled, checked at load), which an
    /// error reply is made from: MEB's frame up to its FCS, a binary
    /// frame's unit and PDU (or the 8-byte frame's six bytes).
    pub fn body(self, body: &str) -> Vec<u8> {
        match self {
            Protocol::Meb => body.as_bytes().to_vec(),
            _ => binary::hex(body).unwrap_or_default(),
        }
    }

    /// Where the first reply in `bytes` ends, if it is whole.
    pub fn frame_end(self, bytes: &[u8]) -> Option<usize> {
        match self {
            Protocol::Meb => meb::frame_end(bytes),
            _ => binary::frame_end(self, bytes),
        }
    }

    /// Whether `frame` is a well-formed reply (its own check bytes right;
    /// over TCP, the transaction id of the request it answers) matching
    /// `pattern` and then `data` words (MEB) or bytes of any value.
    pub fn judge(
        self,
        frame: &[u8],
        pattern: &str,
        data: u16,
        transaction: u16,
    ) -> Result<(), String> {
        match self {
            Protocol::Meb => meb::judge(frame, pattern, data),
            _ => binary::judge(self, frame, pattern, data, transaction),
        }
    }

    /// The pattern of the error (MEB) or exception (Modbus) reply of
    /// `code` to the request whose body is `request`, for slave `id`.
    pub fn error_pattern(self, request: &[u8], id: u8, code: u8) -> String {
        match self {
            Protocol::Meb => meb::error_pattern(request, id, code),
            _ => binary::exception_pattern(self, request, code),
        }
    }

    /// The data words of a well-formed read reply: MEB's four-digit hex
    /// words between the header and the FCS; a Modbus register read's
    /// bytes after its byte count, two to a word, high byte first.
    pub fn data_words(self, frame: &[u8]) -> Vec<u16> {
        let hex_words = |text: &[u8]| -> Vec<u16> {
            text.chunks_exact(4)
                .filter_map(|w| u16::from_str_radix(std::str::from_utf8(w).ok()?, 16).ok())
                .collect()
        };
        let registers = |pdu: &[u8]| -> Vec<u16> {
            let count = usize::from(pdu.get(1).copied().unwrap_or(0));
            pdu.get(2..2 + count)
                .unwrap_or(&[])
                .chunks_exact(2)
                .map(|b| u16::from_be_bytes([b[0], b[1]]))
                .collect()
        };
        match self {
            // `@IDCCAACN` then the words, the FCS's two digits and `*`.
            Protocol::Meb => {
                let star = frame.iter().rposition(|&b| b == b'*').unwrap_or(0);
                frame
                    .get(9..star.saturating_sub(2))
                    .map_or_else(Vec::new, hex_words)
            }
            Protocol::ModbusRtu => frame
                .get(1..frame.len().saturating_sub(2))
                .map_or_else(Vec::new, registers),
            Protocol::ModbusTcp => frame.get(7..).map_or_else(Vec::new, registers),
            Protocol::Modbus8 => Vec::new(),
        }
    }

    /// What the data after a pattern is counted in.
    pub fn data_unit(self) -> (&'static str, &'static str) {
        match self {
            Protocol::Meb => ("data word", "data words"),
            _ => ("data byte", "data bytes"),
        }
    }

    /// Bytes as a report shows them: MEB as text, `\r` and `\n` spelt out;
    /// binary frames as hex bytes.
    pub fn shown(self, bytes: &[u8]) -> String {
        match self {
            Protocol::Meb => shown_text(bytes),
            _ => binary::shown(bytes),
        }
    }
}

/// Text with `\r` and `\n` spelt out, other control bytes in hex.
pub fn shown_text(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len() + 4);
    for &b in bytes {
        match b {
            b'\n' => out.push_str("\\n"),
            b'\r' => out.push_str("\\r"),
            0x20..=0x7e => out.push(char::from(b)),
            _ => out.push_str(&format!("\\x{b:02X}")),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::Protocol;

    #[test]
    fn a_read_replys_data_words_are_read_back() {
        assert_eq!(
            Protocol::Meb.data_words(b"@01EA00020BD60001FF*\n"),
            vec![0x0BD6, 0x0001]
        );
        assert_eq!(
            Protocol::ModbusRtu.data_words(&[1, 4, 4, 0x0B, 0xD6, 0, 1, 0xAA, 0xBB]),
            vec![0x0BD6, 1]
        );
        assert_eq!(
            Protocol::ModbusTcp.data_words(&[0, 1, 0, 0, 0, 5, 1, 4, 2, 0x12, 0x34]),
            vec![0x1234]
        );
        assert!(Protocol::Meb.data_words(b"junk").is_empty());
    }
}
