//! The one frame describer: what a frame on the bench's buses and links
//! says, in the fields every recording stores beside its bytes (`decoded`).
//! The virtual engine, the real-time sink and the viewer all call these, so a
//! frame reads the same wherever it was recorded.

use protocols::meb::{MebCmd, MebRepr, MebWords};
use protocols::modbus::Adu;
use protocols::{modbus, modbus8};
use serde::Serialize;
use serde_json::Value;

/// The wire format a frame was sent in, told from the sent bytes: one place
/// for the engine's check tally and the recording's decoder to agree on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameKind {
    Meb,
    Modbus8,
    ModbusRtu,
}

impl FrameKind {
    /// MEB frames start with `@`; an 8-byte frame whose CRC checks high byte
    /// first is the Controller_network variant; anything else is read as Modbus RTU.
    pub fn of(sent: &[u8]) -> Self {
        use protocols::modbus8::{CrcOrder, Modbus8Repr};
        if sent.first() == Some(&b'@') {
            FrameKind::Meb
        } else if sent.len() == 8 && Modbus8Repr::parse(sent, CrcOrder::HighFirst).is_ok() {
            FrameKind::Modbus8
        } else {
            FrameKind::ModbusRtu
        }
    }

    /// Whether `received` passes this format's check.
    pub fn passes_check(self, received: &[u8]) -> bool {
        use protocols::{meb::MebRepr, modbus, modbus8};
        match self {
            FrameKind::Meb => MebRepr::parse(received).is_ok(),
            FrameKind::Modbus8 => {
                modbus8::Modbus8Repr::parse(received, modbus8::CrcOrder::HighFirst).is_ok()
            }
            FrameKind::ModbusRtu => modbus::rtu::RtuFrame::new_checked(received).is_ok(),
        }
    }
}

/// Decoded fields of a frame on a bus: MEB, the 8-byte variant or Modbus
/// RTU. A small value serialised straight to the recording (the engine
/// describes every frame it records, and building a `serde_json::Value` map
/// cost more than the decoding); the keys are in the order a `Value` map
/// sorts them, so the JSON is the one that map wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(untagged)]
pub enum FrameFields {
    Meb {
        addr: u8,
        #[serde(serialize_with = "as_text")]
        cmd: MebCmd,
        cnt: u8,
        #[serde(serialize_with = "as_list")]
        data: MebWords,
        id: u8,
        protocol: &'static str,
    },
    Modbus8 {
        addr: u16,
        function: u8,
        id: u8,
        protocol: &'static str,
        value: u16,
    },
    ModbusRtu {
        function: u8,
        protocol: &'static str,
        unit: u8,
    },
    Broken {
        error: String,
        protocol: &'static str,
    },
}

/// A value written as its text (an MEB command's two letters).
fn as_text<T: std::fmt::Display, S: serde::Serializer>(
    value: &T,
    serializer: S,
) -> Result<S::Ok, S::Error> {
    serializer.collect_str(value)
}

/// MEB words written as a list of numbers.
fn as_list<S: serde::Serializer>(words: &MebWords, serializer: S) -> Result<S::Ok, S::Error> {
    serializer.collect_seq(words.as_slice())
}

impl FrameFields {
    /// The same fields as a JSON value (readers that look fields up).
    pub fn to_value(&self) -> Value {
        serde_json::to_value(self).unwrap_or(Value::Null)
    }

    /// The fields but the carried values (MEB `data`, the 8-byte `value`):
    /// two frames equal here differ only in what they carry.
    pub fn header(&self) -> Self {
        let mut header = self.clone();
        match &mut header {
            FrameFields::Meb { data, .. } => *data = MebWords::new(),
            FrameFields::Modbus8 { value, .. } => *value = 0,
            FrameFields::ModbusRtu { .. } | FrameFields::Broken { .. } => {}
        }
        header
    }
}

/// Decoded fields of a frame: MEB, the 8-byte variant or Modbus RTU.
pub fn decode_frame(bytes: &[u8]) -> FrameFields {
    let broken = |protocol, error: &dyn std::fmt::Display| FrameFields::Broken {
        error: error.to_string(),
        protocol,
    };
    match FrameKind::of(bytes) {
        FrameKind::Meb => match MebRepr::parse(bytes) {
            Ok(r) => FrameFields::Meb {
                addr: r.addr,
                cmd: r.cmd,
                cnt: r.cnt,
                data: r.data,
                id: r.id,
                protocol: "meb",
            },
            Err(e) => broken("meb", &e),
        },
        FrameKind::Modbus8 => {
            match modbus8::Modbus8Repr::parse(bytes, modbus8::CrcOrder::HighFirst) {
                Ok(f) => FrameFields::Modbus8 {
                    addr: f.addr,
                    function: f.function,
                    id: f.id,
                    protocol: "modbus8",
                    value: f.value,
                },
                Err(e) => broken("modbus8", &e),
            }
        }
        FrameKind::ModbusRtu => match modbus::rtu::RtuFrame::new_checked(bytes) {
            Ok(f) => FrameFields::ModbusRtu {
                function: f.function(),
                protocol: "modbus-rtu",
                unit: f.unit(),
            },
            Err(e) => broken("unknown", &e),
        },
    }
}

/// Decoded fields of a frame on a link of `protocol`.
fn decode_link_frame(protocol: &str, bytes: &[u8]) -> Value {
    serde_json::to_value(link_frame_fields(protocol, bytes)).unwrap_or(Value::Null)
}

/// Decoded fields of a frame on a link, as recorded. A Modbus frame's are a
/// small value (the sink decodes every frame a loaded server answers, and
/// a `Value`'s map cost it more than the decoding); their keys are in the
/// order a `Value` map sorts them, so the JSON is the same either way.
#[derive(Debug, Serialize)]
#[serde(untagged)]
pub enum LinkFrameFields<'a> {
    Modbus {
        function: Option<u8>,
        protocol: &'a str,
        #[serde(skip_serializing_if = "Option::is_none")]
        transaction: Option<u16>,
        unit: u8,
    },
    Broken {
        error: String,
        protocol: &'a str,
    },
    Bus(FrameFields),
}

impl LinkFrameFields<'_> {
    /// The slave (MEB id, Modbus unit) the frame is addressed to or sent
    /// by, if it decodes.
    pub fn node_id(&self) -> Option<u8> {
        match self {
            LinkFrameFields::Modbus { unit, .. } => Some(*unit),
            LinkFrameFields::Bus(FrameFields::Meb { id, .. } | FrameFields::Modbus8 { id, .. }) => {
                Some(*id)
            }
            LinkFrameFields::Bus(FrameFields::ModbusRtu { unit, .. }) => Some(*unit),
            LinkFrameFields::Broken { .. } | LinkFrameFields::Bus(FrameFields::Broken { .. }) => {
                None
            }
        }
    }
}

pub fn link_frame_fields<'a>(protocol: &'a str, bytes: &[u8]) -> LinkFrameFields<'a> {
    // RTU and ASCII frames read alike: a unit id and a function code.
    let modbus = |f: Result<(u8, u8), modbus::FrameError>| match f {
        Ok((unit, function)) => LinkFrameFields::Modbus {
            function: Some(function),
            protocol,
            transaction: None,
            unit,
        },
        Err(e) => LinkFrameFields::Broken {
            error: e.to_string(),
            protocol,
        },
    };
    match protocol {
        "modbus-tcp" => match modbus::tcp::TcpFrame::new_checked(bytes) {
            Ok(f) => LinkFrameFields::Modbus {
                function: f.pdu().first().copied(),
                protocol,
                transaction: Some(f.transaction_id()),
                unit: f.unit(),
            },
            Err(e) => LinkFrameFields::Broken {
                error: e.to_string(),
                protocol,
            },
        },
        "modbus-ascii" => modbus(
            modbus::ascii::AsciiFrame::decode_line(bytes, &mut [0; modbus::ascii::MAX_BINARY_LEN])
                .map(|f| (f.unit(), f.function())),
        ),
        "modbus-rtu" => {
            modbus(modbus::rtu::RtuFrame::new_checked(bytes).map(|f| (f.unit(), f.function())))
        }
        _ => LinkFrameFields::Bus(decode_frame(bytes)),
    }
}

/// A frame's decoded fields when its link's protocol is not known (a
/// viewer reading frames back): MEB, the Controller_network and RTU frames
/// of a bus, or the Modbus TCP and ASCII frames a real-time session's links
/// carry.
pub fn decode_any(bytes: &[u8]) -> Value {
    let decoded = decode_frame(bytes).to_value();
    if decoded.get("error").is_none() {
        return decoded;
    }
    let other = if bytes.first() == Some(&b':') {
        "modbus-ascii"
    } else {
        "modbus-tcp"
    };
    let retried = decode_link_frame(other, bytes);
    if retried.get("error").is_none() {
        retried
    } else {
        decoded
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn fields(protocol: &str, bytes: &[u8]) -> String {
        serde_json::to_string(&link_frame_fields(protocol, bytes)).unwrap()
    }

    #[test]
    fn link_frames_decode_to_the_json_a_value_map_gave() {
        // The keys sorted, as a `serde_json::Value` map wrote them.
        let tcp = [0, 7, 0, 0, 0, 6, 1, 4, 0, 0, 0, 10];
        assert_eq!(
            fields("modbus-tcp", &tcp),
            r#"{"function":4,"protocol":"modbus-tcp","transaction":7,"unit":1}"#
        );
        let rtu = [1, 3, 0, 0, 0, 3, 0x05, 0xcb];
        assert_eq!(
            fields("modbus-rtu", &rtu),
            r#"{"function":3,"protocol":"modbus-rtu","unit":1}"#
        );
        let broken = fields("modbus-rtu", &[1, 3, 0, 0, 0, 3, 0, 0]);
        assert!(
            broken.starts_with(r#"{"error":""#)
                && broken.ends_with(r#"","protocol":"modbus-rtu"}"#),
            "{broken}"
        );
        let meb = fields("meb", b"@01EA0006FF*\n");
        assert_eq!(
            meb,
            serde_json::to_string(&decode_frame(b"@01EA0006FF*\n")).unwrap()
        );
        assert_eq!(
            decode_link_frame("modbus-tcp", &tcp)["transaction"],
            json!(7)
        );
    }
}
