//! The busiest channels' messages written as protobuf field by field
//! ([`crate::protobuf::wire`]): a controller's readings, a supervisor's
//! loop report and a frame with its decoded fields, the bytes prost writes
//! for their types made from the `.proto` files ([`crate::protobuf::twin`]),
//! as the tests check. A message type with text or lists in it is kept from one message
//! to the next (per thread), so writing one makes no string or list.

use crate::describe::{FrameFields, LinkFrameFields};
use crate::protobuf::Protobuf;
#[cfg(test)]
use crate::protobuf::twin::{self as pb, controller_readings};
use crate::protobuf::wire::Fields;
use crate::topics::{self, ReadingsSample, SupervisorReport};
use serde::Serialize;

impl Protobuf for ReadingsSample {
    const SCHEMA: &'static str = topics::READINGS_SCHEMA;

    /// The bytes prost writes for [`readings_message`] (a test holds it to
    /// them), written field by field: see [`Fields`] for why.
    fn write_protobuf(&self, out: &mut Vec<u8>) {
        let m = &mut Fields::new(out);
        m.double(1, self.battery_volts);
        m.double(2, self.bus_volts);
        m.double(3, self.inverter_amps);
        m.uint(4, self.hall_rpm.into());
        m.uint(5, self.light_rpm.into());
        m.bool(6, self.flag_dark);
        m.double(7, self.soc_percent);
        m.nested(8, |m| {
            let w = &self.meb;
            let words = [
                w.v2, w.i, w.v1, w.rpm_m, w.rpm_l, w.ldr, w.hall, w.soc, w.errs, w.status,
            ];
            for (number, word) in (1..).zip(words) {
                m.uint(number, word.into());
            }
        });
    }
}

/// The readings as the type made from `controller_readings.proto`.
#[cfg(test)]
fn readings_message(r: &ReadingsSample) -> pb::ControllerReadings {
    let w = &r.meb;
    pb::ControllerReadings {
        battery_volts: Some(r.battery_volts),
        bus_volts: Some(r.bus_volts),
        inverter_amps: Some(r.inverter_amps),
        hall_rpm: Some(r.hall_rpm.into()),
        light_rpm: Some(r.light_rpm.into()),
        flag_dark: Some(r.flag_dark),
        soc_percent: Some(r.soc_percent),
        meb: Some(controller_readings::Meb {
            v2: Some(w.v2.into()),
            i: Some(w.i.into()),
            v1: Some(w.v1.into()),
            rpm_m: Some(w.rpm_m.into()),
            rpm_l: Some(w.rpm_l.into()),
            ldr: Some(w.ldr.into()),
            hall: Some(w.hall.into()),
            soc: Some(w.soc.into()),
            errs: Some(w.errs.into()),
            status: Some(w.status.into()),
        }),
    }
}

impl Protobuf for SupervisorReport {
    const SCHEMA: &'static str = topics::SUPERVISOR_LOOP_SCHEMA;

    /// The bytes prost writes for the `.proto` file's type (a test holds it
    /// to prost-reflect's), written field by field: see [`Fields`] for why.
    fn write_protobuf(&self, out: &mut Vec<u8>) {
        let m = &mut Fields::new(out);
        m.uint(1, self.cycles);
        for l in &self.loops {
            m.nested(2, |m| {
                m.uint(1, l.slave.into());
                m.double(2, l.set_point_rpm);
                m.double(3, l.measured_rpm);
                m.double(4, l.error_rpm);
                m.uint(5, l.output.into());
                m.double(6, l.integral);
                let counts = [
                    l.requests,
                    l.replies,
                    l.timeouts,
                    l.bad_checks,
                    l.exceptions,
                    l.retries,
                    l.lost,
                ];
                for (number, count) in (7..).zip(counts) {
                    m.uint(number, count);
                }
            });
        }
    }
}

/// A frame's decoded fields, as the nested `twin.Frame.Decoded` message's.
pub trait DecodedProtobuf {
    /// Write its fields (those of other protocols absent), in field-number
    /// order.
    fn write_decoded(&self, m: &mut Fields<'_>);
}

impl DecodedProtobuf for FrameFields {
    fn write_decoded(&self, m: &mut Fields<'_>) {
        match self {
            FrameFields::Meb {
                addr,
                cmd,
                cnt,
                data,
                id,
                protocol,
            } => {
                m.str(1, protocol);
                m.uint(2, (*addr).into());
                // Two ASCII letters (`MebCmd::new`): the text `Display`
                // gives, each letter a `char` as prost's string held it.
                let mut text = [0u8; 8];
                let mut len = 0;
                for letter in cmd.letters() {
                    len += char::from(letter).encode_utf8(&mut text[len..]).len();
                }
                m.str(3, std::str::from_utf8(&text[..len]).unwrap_or_default());
                m.uint(4, (*cnt).into());
                for w in data.as_slice() {
                    m.uint(5, (*w).into());
                }
                m.uint(6, (*id).into());
            }
            FrameFields::Modbus8 {
                addr,
                function,
                id,
                protocol,
                value,
            } => {
                m.str(1, protocol);
                m.uint(2, (*addr).into());
                m.uint(6, (*id).into());
                m.uint(7, (*function).into());
                m.uint(8, (*value).into());
            }
            FrameFields::ModbusRtu {
                function,
                protocol,
                unit,
            } => {
                m.str(1, protocol);
                m.uint(7, (*function).into());
                m.uint(9, (*unit).into());
            }
            FrameFields::Broken { error, protocol } => {
                m.str(1, protocol);
                m.str(11, error);
            }
        }
    }
}

impl DecodedProtobuf for LinkFrameFields<'_> {
    fn write_decoded(&self, m: &mut Fields<'_>) {
        match self {
            LinkFrameFields::Modbus {
                function,
                protocol,
                transaction,
                unit,
            } => {
                m.str(1, protocol);
                if let Some(function) = function {
                    m.uint(7, (*function).into());
                }
                m.uint(9, (*unit).into());
                if let Some(transaction) = transaction {
                    m.uint(10, (*transaction).into());
                }
            }
            LinkFrameFields::Broken { error, protocol } => {
                m.str(1, protocol);
                m.str(11, error);
            }
            LinkFrameFields::Bus(fields) => fields.write_decoded(m),
        }
    }
}

impl<T: DecodedProtobuf + ?Sized> DecodedProtobuf for &T {
    fn write_decoded(&self, m: &mut Fields<'_>) {
        (**self).write_decoded(m);
    }
}

/// A frame's bytes as its `hex` field holds them: two lowercase hex digits
/// each, spelled where the field is written, so no string is made for them.
#[derive(Debug, Clone, Copy)]
pub struct Hex<'a>(pub &'a [u8]);

impl Serialize for Hex<'_> {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

impl std::fmt::Display for Hex<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        crate::protobuf::hex_runs(self.0, |run| f.write_str(run))
    }
}

/// One frame as the frame channels record it (`twin.Frame`), from the
/// virtual engine and the real-time sink alike: serialised (a JSON channel,
/// a PWM-capture bus's) or written by [`FrameMessage::write`].
#[derive(Debug, Serialize)]
pub struct FrameMessage<'a, D: ?Sized> {
    /// The sending node (a session's link: `twin`, `client N`, or on a
    /// supervisor's bus `slave NN`).
    pub from: &'a str,
    pub start_s: f64,
    pub end_s: f64,
    pub len: usize,
    /// The bytes as text when they are printable ASCII (MEB), else empty;
    /// left out of a protobuf frame whose bytes are not printable.
    pub text: Option<&'a str>,
    /// The bytes, two lowercase hex digits each; left out of a protobuf
    /// frame whose `text` holds them.
    pub hex: Option<Hex<'a>>,
    pub decoded: &'a D,
}

impl<'a, D: ?Sized> FrameMessage<'a, D> {
    /// The same frame carrying `decoded` instead.
    pub fn with_decoded<E: ?Sized>(&self, decoded: &'a E) -> FrameMessage<'a, E> {
        FrameMessage {
            from: self.from,
            start_s: self.start_s,
            end_s: self.end_s,
            len: self.len,
            text: self.text,
            hex: self.hex,
            decoded,
        }
    }
}

impl<D: DecodedProtobuf + ?Sized> FrameMessage<'_, D> {
    /// Append the frame's protobuf bytes (`twin.Frame`) to `out`: those
    /// prost writes for the `.proto` file's type (tests hold them to
    /// prost-reflect's), written field by field: see [`Fields`] for why.
    pub fn write(&self, out: &mut Vec<u8>) {
        let m = &mut Fields::new(out);
        m.str(1, self.from);
        m.double(2, self.start_s);
        m.double(3, self.end_s);
        m.uint(4, u32::try_from(self.len).unwrap_or(u32::MAX).into());
        if let Some(text) = self.text {
            m.str(5, text);
        }
        if let Some(Hex(bytes)) = self.hex {
            m.hex(6, bytes);
        }
        m.nested(7, |m| self.decoded.write_decoded(m));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::{decode_frame, link_frame_fields};
    use crate::protobuf::append;
    use crate::topics::{LoopReport, MebWords, SlaveLoop, proto_schema};
    use serde_json::Value;

    /// What a reader makes of `bytes` on `topic`.
    fn read_back(topic: &str, bytes: &[u8]) -> Value {
        let schema = proto_schema(topic).expect("a protobuf channel");
        crate::protobuf::to_value(&schema, bytes).expect("reads back")
    }

    /// The JSON a JSON recording holds for `value`, as a protobuf one reads
    /// back: an empty list is left out, and so is a `null` below the top.
    fn as_read<T: Serialize>(value: &T) -> Value {
        fn strip(v: &mut Value, top: bool) {
            if let Value::Object(fields) = v {
                fields.retain(|_, f| {
                    (top || !f.is_null()) && f.as_array().is_none_or(|a| !a.is_empty())
                });
                for f in fields.values_mut() {
                    strip(f, false);
                }
            }
        }
        let mut json = serde_json::to_value(value).unwrap();
        strip(&mut json, true);
        json
    }

    fn by_hand(write: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
        let mut bytes = Vec::new();
        write(&mut bytes);
        bytes
    }

    #[test]
    fn readings_and_loop_reports_read_back_as_their_json() {
        let readings = ReadingsSample {
            battery_volts: 12.345678901234567,
            bus_volts: -0.0,
            inverter_amps: f64::NAN,
            hall_rpm: 65535,
            light_rpm: 127,
            flag_dark: true,
            soc_percent: 99.5,
            meb: MebWords {
                v2: 1,
                i: 128,
                v1: 300,
                rpm_m: 16384,
                rpm_l: 0,
                ldr: 3280,
                hall: 5,
                soc: 99,
                errs: 2,
                status: 0x8001,
            },
        };
        let topic = "/controller/ev1/readings";
        let hand = by_hand(|m| readings.write_protobuf(m));
        assert_eq!(read_back(topic, &hand), as_read(&readings));
        // Byte for byte what prost writes for the `.proto` file's type.
        assert_eq!(hand, by_hand(|m| append(&readings_message(&readings), m)));
        assert_eq!(
            proto_schema(topic).unwrap().full_name(),
            ReadingsSample::SCHEMA
        );

        let slave = |n: u8| SlaveLoop {
            slave: n,
            set_point_rpm: 1500.0,
            measured_rpm: 1499.25,
            error_rpm: 0.75,
            output: 4095,
            integral: -12.5,
            requests: u64::from(u32::MAX) + 9,
            replies: 0,
            timeouts: 127,
            bad_checks: 128,
            exceptions: 3,
            retries: 4,
            lost: 5,
        };
        // Ten slaves: the report is longer than a one-byte length.
        for slaves in [0, 1, 10] {
            let report = SupervisorReport {
                cycles: 123_456,
                loops: (1..=slaves).map(slave).collect(),
            };
            let topic = "/master/supervisor/loop";
            let hand = by_hand(|m| report.write_protobuf(m));
            let typed = LoopReport::Supervisor(report.clone());
            assert_eq!(read_back(topic, &hand), as_read(&typed), "{slaves} slaves");
            // prost-reflect, from the value's JSON, writes the same bytes.
            assert_eq!(hand, by_schema(topic, &typed), "{slaves} slaves");
            assert_eq!(
                proto_schema(topic).unwrap().full_name(),
                SupervisorReport::SCHEMA
            );
        }
    }

    /// What prost-reflect writes for `value` on `topic`, from its JSON.
    fn by_schema<T: Serialize>(topic: &str, value: &T) -> Vec<u8> {
        let schema = proto_schema(topic).expect("a protobuf channel");
        let mut bytes = Vec::new();
        crate::protobuf::transcode(&schema, value, &mut bytes).expect("fits its schema");
        bytes
    }

    /// A frame carrying `decoded`, written through its type and by
    /// prost-reflect from its JSON; checked to read back as its JSON.
    fn frame_both_ways<D: DecodedProtobuf + Serialize>(
        decoded: &D,
        len: usize,
        text: Option<&str>,
        hex: Option<Hex<'_>>,
    ) -> (Vec<u8>, Vec<u8>) {
        let message = FrameMessage {
            from: "client 3",
            start_s: 0.25,
            end_s: 0.2501,
            len,
            text,
            hex,
            decoded,
        };
        let topic = "/link/modbus-tcp/frames";
        let hand = by_hand(|m| message.write(m));
        assert_eq!(read_back(topic, &hand), as_read(&message));
        (hand, by_schema(topic, &message))
    }

    #[test]
    fn hex_in_json_is_the_string_of_its_digits() {
        let bytes: Vec<u8> = (0..=200).collect();
        let mut spelled = String::new();
        topics::put_hex(&mut spelled, &bytes);
        assert_eq!(spelled.len(), 2 * bytes.len());
        assert!(spelled.starts_with("000102") && spelled.ends_with("c6c7c8"));
        let json = serde_json::to_string(&Hex(&bytes)).unwrap();
        assert_eq!(json, format!("\"{spelled}\""));
    }

    #[test]
    fn frames_of_every_protocol_read_back_as_their_json() {
        let long_error = [b'@'; 150];
        let frames: [(&str, &[u8]); 11] = [
            ("meb", b"@01EA0006FF*\n"),
            ("meb", b"@01SD0002000E000120*\n"),
            ("meb", b"@zz"),
            ("meb", &long_error),
            ("modbus8", &[0x01, 0x06, 0x00, 0x01, 0x27, 0x10, 0x00, 0x00]),
            ("modbus-tcp", &[0, 7, 0, 0, 0, 6, 1, 4, 0, 0, 0, 10]),
            ("modbus-tcp", &[0, 7, 0]),
            ("modbus-rtu", &[1, 3, 0, 0, 0, 3, 0x05, 0xcb]),
            ("modbus-rtu", &[1, 3, 0]),
            ("modbus-ascii", b":010300000001FB\r\n"),
            ("modbus-ascii", b":01"),
        ];
        let schema = proto_schema("/link/modbus-tcp/frames").unwrap();
        assert_eq!(schema.full_name(), topics::FRAME_SCHEMA);
        let fields = [
            (Some("@01"), None),
            (None, Some(Hex(&[0, 7]))),
            (None, Some(Hex(&[0, 7, 0xab, 0xff]))),
            (Some(""), Some(Hex(&[]))),
        ];
        for (protocol, bytes) in frames {
            for (text, hex) in fields {
                let link = link_frame_fields(protocol, bytes);
                let (hand, schema) = frame_both_ways(&link, bytes.len(), text, hex);
                assert_eq!(hand, schema, "{protocol} {bytes:?} on a link");
                let bus = decode_frame(bytes);
                let (hand, schema) = frame_both_ways(&bus, bytes.len(), text, hex);
                assert_eq!(hand, schema, "{protocol} {bytes:?} on a bus");
            }
        }
    }
}
