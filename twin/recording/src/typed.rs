//! The busiest channels' messages written as protobuf: a controller's
//! readings field by field ([`crate::protobuf::wire`], prost's bytes for
//! its type), a supervisor's loop report and a frame with its decoded
//! fields through their types made from the `.proto` files
//! ([`crate::protobuf::twin`]). A message type with text or lists in it is kept from one message
//! to the next (per thread), so writing one makes no string or list.

use std::cell::RefCell;

use crate::describe::{FrameFields, LinkFrameFields};
#[cfg(test)]
use crate::protobuf::twin::controller_readings;
use crate::protobuf::twin::{self as pb, frame, supervisor_loop};
use crate::protobuf::wire::Fields;
use crate::protobuf::{Protobuf, append, put_str};
use crate::topics::{self, ReadingsSample, SlaveLoop, SupervisorReport};
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

thread_local! {
    /// The loop report last written on this thread, its list kept.
    static LOOP: RefCell<pb::SupervisorLoop> = RefCell::default();
    /// The frame last written on this thread, its text and list kept.
    static FRAME: RefCell<pb::Frame> = RefCell::default();
}

impl Protobuf for SupervisorReport {
    const SCHEMA: &'static str = topics::SUPERVISOR_LOOP_SCHEMA;

    fn write_protobuf(&self, out: &mut Vec<u8>) {
        LOOP.with_borrow_mut(|message| {
            message.cycles = Some(self.cycles);
            message.loops.clear();
            message.loops.extend(self.loops.iter().map(slave_loop));
            append(&*message, out);
        });
    }
}

fn slave_loop(l: &SlaveLoop) -> supervisor_loop::Loop {
    supervisor_loop::Loop {
        slave: Some(l.slave.into()),
        set_point_rpm: Some(l.set_point_rpm),
        measured_rpm: Some(l.measured_rpm),
        error_rpm: Some(l.error_rpm),
        output: Some(l.output.into()),
        integral: Some(l.integral),
        requests: Some(l.requests),
        replies: Some(l.replies),
        timeouts: Some(l.timeouts),
        bad_checks: Some(l.bad_checks),
        exceptions: Some(l.exceptions),
        retries: Some(l.retries),
        lost: Some(l.lost),
    }
}

/// A frame's decoded fields, as the nested `twin.Frame.Decoded` message's.
pub trait DecodedProtobuf {
    /// Fill `d` (every field, those of other protocols absent).
    fn fill_decoded(&self, d: &mut frame::Decoded);
}

/// `d` with no field but its protocol.
fn only_protocol(d: &mut frame::Decoded, protocol: &str) {
    put_str(&mut d.protocol, Some(protocol));
    d.addr = None;
    d.cmd = None;
    d.cnt = None;
    d.data.clear();
    d.id = None;
    d.function = None;
    d.value = None;
    d.unit = None;
    d.transaction = None;
    d.error = None;
}

impl DecodedProtobuf for FrameFields {
    fn fill_decoded(&self, d: &mut frame::Decoded) {
        match self {
            FrameFields::Meb {
                addr,
                cmd,
                cnt,
                data,
                id,
                protocol,
            } => {
                only_protocol(d, protocol);
                d.addr = Some((*addr).into());
                // Two ASCII letters (`MebCmd::new`): the text `Display` gives.
                let letters = d.cmd.get_or_insert_default();
                letters.clear();
                letters.extend(cmd.letters().map(char::from));
                d.cnt = Some((*cnt).into());
                d.data.extend(data.as_slice().iter().map(|w| u32::from(*w)));
                d.id = Some((*id).into());
            }
            FrameFields::Modbus8 {
                addr,
                function,
                id,
                protocol,
                value,
            } => {
                only_protocol(d, protocol);
                d.addr = Some((*addr).into());
                d.function = Some((*function).into());
                d.id = Some((*id).into());
                d.value = Some((*value).into());
            }
            FrameFields::ModbusRtu {
                function,
                protocol,
                unit,
            } => {
                only_protocol(d, protocol);
                d.function = Some((*function).into());
                d.unit = Some((*unit).into());
            }
            FrameFields::Broken { error, protocol } => {
                only_protocol(d, protocol);
                put_str(&mut d.error, Some(error));
            }
        }
    }
}

impl DecodedProtobuf for LinkFrameFields<'_> {
    fn fill_decoded(&self, d: &mut frame::Decoded) {
        match self {
            LinkFrameFields::Modbus {
                function,
                protocol,
                transaction,
                unit,
            } => {
                only_protocol(d, protocol);
                d.function = function.map(u32::from);
                d.transaction = transaction.map(u32::from);
                d.unit = Some((*unit).into());
            }
            LinkFrameFields::Broken { error, protocol } => {
                only_protocol(d, protocol);
                put_str(&mut d.error, Some(error));
            }
            LinkFrameFields::Bus(fields) => fields.fill_decoded(d),
        }
    }
}

impl<T: DecodedProtobuf + ?Sized> DecodedProtobuf for &T {
    fn fill_decoded(&self, d: &mut frame::Decoded) {
        (**self).fill_decoded(d);
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
    /// Append the frame's protobuf bytes (`twin.Frame`) to `out`.
    pub fn write(&self, out: &mut Vec<u8>) {
        FRAME.with_borrow_mut(|m| {
            put_str(&mut m.from, Some(self.from));
            m.start_s = Some(self.start_s);
            m.end_s = Some(self.end_s);
            m.len = Some(u32::try_from(self.len).unwrap_or(u32::MAX));
            put_str(&mut m.text, self.text);
            match self.hex {
                Some(Hex(bytes)) => {
                    let hex = m.hex.get_or_insert_default();
                    hex.clear();
                    topics::put_hex(hex, bytes);
                }
                None => m.hex = None,
            }
            self.decoded.fill_decoded(m.decoded.get_or_insert_default());
            append(&*m, out);
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::{decode_frame, link_frame_fields};
    use crate::topics::{LoopReport, MebWords, proto_schema};
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
