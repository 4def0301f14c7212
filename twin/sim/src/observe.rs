//! What a virtual run writes to its recording. Channels (all JSON, JSON-schema):
//!
//! | topic | when | content |
//! |---|---|---|
//! | `/plant/<module>/sensors` | at the scenario's `record_hz` | every sensor, hall/encoder counts, energy ledger |
//! | `/plant/<module>/actuators` | on every change | what the firmware drives |
//! | `/bus/<bus>/frames` | every frame sent | sender, start and end time, raw bytes, decoded fields (PWM-capture: widths sent and captured per listener, values, pulses lost, values wrong) |
//! | `/bus/<bus>/line` | only where a collision garbled a character or noise flipped bits | the frame (sender, first start bit), the character, the listener (noise), the bits changed, the byte as it was then |
//! | `/events` | as they happen | node, kind (`timeout`, `bad_check`, `retry`, `log`, …), detail |
//! | `/master/<node>/loop` | every poll cycle | set point, measured rpm, error, output, counters |
//! | `/controller/<node>/readings` | beside each plant sample | an EV controller's readings, named (`hall_rpm`, `light_rpm`, …) |
//! | `/firmware/<node>/uart`, `/firmware/<node>/io` | UART bursts; every 10 ms | compiled firmware: its UART bytes with their cycles, its pins, ADC inputs and cycle count |

use nodes::link::{LineMark, PortId};
use nodes::node::NodeEvent;
use protocols::time::SimTime;
use serde::Serialize;
use serde_json::{Value, json};
use std::collections::{BTreeMap, VecDeque};

use crate::engine::{BusSlot, FirmwareRecord, ModuleSlot, NodeSlot, ObserveError, Observer};

type Result<T, E = ObserveError> = std::result::Result<T, E>;
use twin_recording::describe::{FrameFields, LinkFrameFields, decode_frame};
use twin_recording::protobuf::Protobuf;
use twin_recording::record::{ChannelId, Recorder, WriteError};
use twin_recording::topics::{
    self, FirmwareIo, LineMessage, LoopReport, ReadingsSample, UartBurst,
};
use twin_recording::typed::{DecodedProtobuf, FrameMessage, Hex};

pub use crate::plant_sample::PlantSample;

/// The recording of a run or session. Its plant samples, most of its bytes,
/// are handed over as values and serialised by the writer (a virtual run's
/// writer thread, off the engine's).
pub type SimRecorder = Recorder<PlantSample>;

/// How many log lines the end-of-run summary shows.
const LOG_TAIL: usize = 12;

/// Writes a run to MCAP; topics are created on first use.
#[derive(Debug)]
pub struct McapObserver {
    pub recorder: SimRecorder,
    pub frames: u64,
    pub events: BTreeMap<String, u64>,
    /// The last lines the nodes logged (kind `log`), and what firmware that
    /// never answers its bus was doing (kind `silent`), for the summary.
    pub log_tail: VecDeque<String>,
    /// Channels by the name of what writes them (a run has a few of each):
    /// a message's topic is formatted once, not per message.
    channels: [Vec<LazyChannel>; Kind::COUNT],
    buses: Vec<LazyChannel>,
    /// Each bus's `/bus/<bus>/line`, made on its first mark: a run without
    /// noise or collisions has none.
    lines: Vec<LazyChannel>,
    event_channel: LazyChannel,
}

/// A channel of the recording made on its first message (its schema comes
/// from that message), then written without a lookup.
#[derive(Debug)]
pub struct LazyChannel {
    /// What the channel belongs to: a module, bus, link or node name.
    owner: String,
    topic: String,
    id: Option<ChannelId>,
}

impl LazyChannel {
    pub fn new(owner: &str, topic: String) -> Self {
        Self {
            owner: owner.to_string(),
            topic,
            id: None,
        }
    }

    /// Write `message` at `time`, making the channel on first use.
    pub fn write<T: Serialize>(
        &mut self,
        recorder: &mut SimRecorder,
        time: SimTime,
        message: &T,
    ) -> Result<(), WriteError> {
        let id = self.id(recorder, message)?;
        recorder.write_to(id, time.as_secs_f64(), message)
    }

    /// [`LazyChannel::write`] for a message that writes its own protobuf.
    pub fn write_typed<T: Serialize + Protobuf>(
        &mut self,
        recorder: &mut SimRecorder,
        time: SimTime,
        message: &T,
    ) -> Result<(), WriteError> {
        let id = self.id(recorder, message)?;
        recorder.write_typed(id, time.as_secs_f64(), message)
    }

    /// Write a plant sample at `time`, serialised by the writer thread.
    pub fn write_sensors(
        &mut self,
        recorder: &mut SimRecorder,
        time: SimTime,
        sensors: &plant::Sensors,
    ) -> Result<(), WriteError> {
        let sample = PlantSample(*sensors);
        let id = self.id(recorder, &sample)?;
        recorder.write_deferred(id, time.as_secs_f64(), sample)
    }

    /// The channel's id, made from `sample` on first use.
    fn id<T: Serialize>(
        &mut self,
        recorder: &mut SimRecorder,
        sample: &T,
    ) -> Result<ChannelId, WriteError> {
        if let Some(id) = self.id {
            return Ok(id);
        }
        let id = match recorder.channel(&self.topic) {
            Some(id) => id,
            None => recorder.add_channel(&self.topic, sample)?,
        };
        Ok(*self.id.insert(id))
    }
}

/// The channel of `owner` in `channels`, added (topic from `topic`) if new.
fn channel_of<'c>(
    channels: &'c mut Vec<LazyChannel>,
    owner: &str,
    topic: fn(&str) -> String,
) -> &'c mut LazyChannel {
    let index = match channels.iter().position(|c| c.owner == owner) {
        Some(index) => index,
        None => {
            channels.push(LazyChannel::new(owner, topic(owner)));
            channels.len() - 1
        }
    };
    &mut channels[index]
}

/// Which of [`McapObserver`]'s lists holds a payload's channels: one per
/// kind, so a message finds its channel among the few its kind has.
#[derive(Debug, Clone, Copy)]
pub enum Kind {
    Sensors,
    Actuators,
    Loop,
    Readings,
    FirmwareUart,
    FirmwareIo,
}

impl Kind {
    // The last kind's index: a kind added after it must move this along.
    const COUNT: usize = Kind::FirmwareIo as usize + 1;
}

/// What [`McapObserver::record`] writes, one channel per owner: its kind,
/// its topic and its encoding. Each keeps the encoding its channel has
/// always had, so recordings stay the same byte for byte.
pub trait Recorded {
    const KIND: Kind;
    /// The topic of `owner`'s channel.
    fn topic(owner: &str) -> String;
    fn write(
        &self,
        channel: &mut LazyChannel,
        recorder: &mut SimRecorder,
        now: SimTime,
    ) -> Result<(), WriteError>;
}

/// On `/plant/<module>/sensors`, serialised by the writer thread.
impl Recorded for plant::Sensors {
    const KIND: Kind = Kind::Sensors;
    fn topic(module: &str) -> String {
        topics::plant_sensors(module)
    }
    fn write(
        &self,
        channel: &mut LazyChannel,
        recorder: &mut SimRecorder,
        now: SimTime,
    ) -> Result<(), WriteError> {
        channel.write_sensors(recorder, now, self)
    }
}

/// What drives a module, on `/plant/<module>/actuators`, on every change.
impl Recorded for plant::Actuators {
    const KIND: Kind = Kind::Actuators;
    fn topic(module: &str) -> String {
        topics::plant_actuators(module)
    }
    fn write(
        &self,
        channel: &mut LazyChannel,
        recorder: &mut SimRecorder,
        now: SimTime,
    ) -> Result<(), WriteError> {
        channel.write(recorder, now, self)
    }
}

/// A master's loop report, on `/master/<node>/loop`: a supervisor's writes
/// its own protobuf, any other master's goes through serde.
impl Recorded for LoopReport {
    const KIND: Kind = Kind::Loop;
    fn topic(node: &str) -> String {
        topics::master_loop(node)
    }
    fn write(
        &self,
        channel: &mut LazyChannel,
        recorder: &mut SimRecorder,
        now: SimTime,
    ) -> Result<(), WriteError> {
        match self {
            LoopReport::Supervisor(typed) => channel.write_typed(recorder, now, typed),
            LoopReport::Other(_) => channel.write(recorder, now, self),
        }
    }
}

/// A module controller's readings, on `/controller/<node>/readings`.
impl Recorded for ReadingsSample {
    const KIND: Kind = Kind::Readings;
    fn topic(node: &str) -> String {
        topics::controller_readings(node)
    }
    fn write(
        &self,
        channel: &mut LazyChannel,
        recorder: &mut SimRecorder,
        now: SimTime,
    ) -> Result<(), WriteError> {
        channel.write_typed(recorder, now, self)
    }
}

/// A firmware node's UART burst, on `/firmware/<node>/uart`.
impl Recorded for UartBurst<'_> {
    const KIND: Kind = Kind::FirmwareUart;
    fn topic(node: &str) -> String {
        topics::firmware_uart(node)
    }
    fn write(
        &self,
        channel: &mut LazyChannel,
        recorder: &mut SimRecorder,
        now: SimTime,
    ) -> Result<(), WriteError> {
        channel.write(recorder, now, self)
    }
}

/// A firmware node's pins, ADC inputs and cycles, on `/firmware/<node>/io`.
impl Recorded for FirmwareIo<'_> {
    const KIND: Kind = Kind::FirmwareIo;
    fn topic(node: &str) -> String {
        topics::firmware_io(node)
    }
    fn write(
        &self,
        channel: &mut LazyChannel,
        recorder: &mut SimRecorder,
        now: SimTime,
    ) -> Result<(), WriteError> {
        channel.write(recorder, now, self)
    }
}

impl McapObserver {
    /// A firmware node's UART burst or I/O sample, each at its own time.
    pub fn record_firmware(
        &mut self,
        node: &str,
        record: FirmwareRecord<'_>,
    ) -> Result<(), WriteError> {
        match record {
            FirmwareRecord::Uart(at, burst) => self.record(at, node, &burst),
            FirmwareRecord::Io(at, io) => self.record(at, node, &io),
        }
    }
}

/// A frame's decoded fields, as [`McapObserver::record_frame`] writes them.
pub trait Decoded: Serialize {
    /// How the fields write their own protobuf, if they do; a channel that
    /// is protobuf then gets them written by hand.
    fn by_hand(&self) -> Option<&dyn DecodedProtobuf>;
}

impl Decoded for FrameFields {
    fn by_hand(&self) -> Option<&dyn DecodedProtobuf> {
        Some(self)
    }
}

impl Decoded for LinkFrameFields<'_> {
    fn by_hand(&self) -> Option<&dyn DecodedProtobuf> {
        Some(self)
    }
}

/// A PWM-capture frame's fields, which only serde writes (on a JSON channel).
impl Decoded for Value {
    fn by_hand(&self) -> Option<&dyn DecodedProtobuf> {
        None
    }
}

/// A node's event, as recorded on `/events`.
#[derive(Debug, Serialize)]
struct EventMessage<'a> {
    // In the order a `serde_json::Value` map sorted them.
    detail: &'a str,
    kind: &'a str,
    node: &'a str,
}

/// A frame's own parts, before its fields are written.
#[derive(Debug, Clone, Copy)]
struct FrameParts<'a> {
    from: &'a str,
    start: SimTime,
    end: SimTime,
    bytes: &'a [u8],
    text: Option<&'a str>,
}

impl McapObserver {
    pub fn new(recorder: SimRecorder) -> Self {
        Self {
            recorder,
            frames: 0,
            events: BTreeMap::new(),
            log_tail: VecDeque::new(),
            channels: Default::default(),
            buses: Vec::new(),
            lines: Vec::new(),
            event_channel: LazyChannel::new("", topics::EVENTS.to_string()),
        }
    }

    /// `payload` of `owner` (a module or node) at `now`, on the channel
    /// its kind gives `owner` (see [`Recorded`]).
    pub fn record<P: Recorded>(
        &mut self,
        now: SimTime,
        owner: &str,
        payload: &P,
    ) -> Result<(), WriteError> {
        let channels = &mut self.channels[P::KIND as usize];
        payload.write(
            channel_of(channels, owner, P::topic),
            &mut self.recorder,
            now,
        )
    }

    /// Write `message` to `topic`, creating its channel on first use.
    pub fn put<T: Serialize>(
        &mut self,
        topic: &str,
        time: SimTime,
        message: &T,
    ) -> Result<(), WriteError> {
        let channel = match self.recorder.channel(topic) {
            Some(channel) => channel,
            None => self.recorder.add_channel(topic, message)?,
        };
        self.recorder.write_to(channel, time.as_secs_f64(), message)
    }
}

/// A PWM-capture frame as sent and as every listener captured it: widths,
/// the values they decode to against the start width (sent, and as that
/// receiver measured it), pulses lost and values wrong.
pub fn decode_pwm_frame(link: &nodes::link::PwmBus, port_names: &[String]) -> Value {
    let coding = link.config().coding;
    let frame = link.last_frame();
    let values = |widths: &[u32]| -> Vec<Option<u16>> {
        let start = widths.first().copied().unwrap_or(0);
        widths
            .iter()
            .skip(1)
            .map(|&w| coding.decode_width(w, start).ok())
            .collect()
    };
    let receptions: Vec<Value> = frame
        .receptions
        .iter()
        .filter(|r| !r.captured.is_empty() || r.lost > 0)
        .map(|r| {
            let to = port_names.get(r.to.index()).map_or("", String::as_str);
            json!({ "to": to, "captured": r.captured, "values": values(&r.captured),
                    "lost": r.lost, "wrong": r.wrong })
        })
        .collect();
    json!({
        "protocol": "pwmcap", "period_ticks": frame.period_ticks, "widths": frame.sent,
        "values": values(&frame.sent), "receptions": receptions,
    })
}

fn secs(t: SimTime) -> f64 {
    t.as_secs_f64()
}

impl McapObserver {
    /// One frame on `channel` (`/bus/<bus>/frames`, `/link/<link>/frames`),
    /// sent by `from`, with its decoded fields.
    pub fn record_frame<D: Decoded>(
        &mut self,
        channel: &mut LazyChannel,
        from: &str,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
        decoded: &D,
    ) -> Result<(), WriteError> {
        self.record_frame_with(channel, from, start, end, bytes, decoded, decoded.by_hand())
    }

    /// A frame whose decoded fields are `decoded`, written by hand where
    /// `by_hand` can and the channel is protobuf.
    #[allow(clippy::too_many_arguments)]
    fn record_frame_with(
        &mut self,
        channel: &mut LazyChannel,
        from: &str,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
        decoded: &impl Serialize,
        by_hand: Option<&dyn DecodedProtobuf>,
    ) -> Result<(), WriteError> {
        let printable = bytes
            .iter()
            .all(|b| b.is_ascii_graphic() || *b == b'\n' || *b == b'\r');
        // Printable bytes are ASCII, so this never fails when it is used
        // (and binary frames are not checked for UTF-8 at all).
        let text = printable.then(|| std::str::from_utf8(bytes).ok()).flatten();
        let frame = FrameParts {
            from,
            start,
            end,
            bytes,
            text,
        };
        self.write_frame(channel, &frame, decoded, by_hand)
    }

    /// [`McapObserver::record_frame`] with the text worked out. A protobuf
    /// channel holds the bytes once, as `text` when they are printable
    /// (MEB) and as `hex` otherwise (the twin's readers
    /// give back both: `topics::complete_frame`); a JSON channel (a
    /// PWM-capture bus's) holds both, as it always did.
    fn write_frame(
        &mut self,
        channel: &mut LazyChannel,
        frame: &FrameParts<'_>,
        decoded: &impl Serialize,
        by_hand: Option<&dyn DecodedProtobuf>,
    ) -> Result<(), WriteError> {
        let FrameParts {
            from,
            start,
            end,
            bytes,
            text,
        } = *frame;
        let id = match channel.id {
            Some(id) => id,
            None => {
                // The channel is made from a frame with every field.
                let sample = FrameMessage {
                    from,
                    start_s: secs(start),
                    end_s: secs(end),
                    len: bytes.len(),
                    text: Some(text.unwrap_or("")),
                    hex: Some(Hex(bytes)),
                    decoded,
                };
                channel.id(&mut self.recorder, &sample)?
            }
        };
        let once = self.recorder.is_protobuf(id);
        let hex_too = !(once && text.is_some());
        let text = if once && text.is_none() {
            None
        } else {
            Some(text.unwrap_or(""))
        };
        let hex = hex_too.then_some(Hex(bytes));
        self.frames += 1;
        let time_s = start.as_secs_f64();
        let message = FrameMessage {
            from,
            start_s: secs(start),
            end_s: secs(end),
            len: bytes.len(),
            text,
            hex,
            decoded,
        };
        if let Some(fields) = by_hand.filter(|_| once) {
            let hand = message.with_decoded(fields);
            let written = self
                .recorder
                .write_protobuf(id, time_s, topics::FRAME_SCHEMA, |m| hand.write(m))?;
            if written {
                return Ok(());
            }
        }
        self.recorder.write_to(id, time_s, &message)
    }

    /// One event a node (or link) noticed.
    pub fn record_event(&mut self, node: &str, event: &NodeEvent) -> Result<(), WriteError> {
        *self.events.entry(event.kind.to_string()).or_default() += 1;
        if event.kind == "log" || event.kind == "silent" {
            if self.log_tail.len() == LOG_TAIL {
                self.log_tail.pop_front();
            }
            self.log_tail.push_back(format!(
                "[{:9.3} s] {}: {}",
                event.at.as_secs_f64(),
                node,
                event.detail
            ));
        }
        let message = EventMessage {
            detail: &event.detail,
            kind: event.kind,
            node,
        };
        self.event_channel
            .write(&mut self.recorder, event.at, &message)
    }
}

impl Observer for McapObserver {
    fn plant(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        Ok(self.record(now, &module.name, module.plant.sensors())?)
    }

    fn actuators(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        Ok(self.record(now, &module.name, &module.actuators)?)
    }

    fn frame(
        &mut self,
        bus: &BusSlot,
        from: &NodeSlot,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<()> {
        let mut channels = std::mem::take(&mut self.buses);
        let channel = channel_of(&mut channels, &bus.name, topics::bus_frames);
        let written = match bus.bus.as_pwm() {
            Some(link) => {
                let decoded = decode_pwm_frame(link, &bus.port_names);
                self.record_frame(channel, &from.name, start, end, bytes, &decoded)
            }
            None => self.record_frame(channel, &from.name, start, end, bytes, &decode_frame(bytes)),
        };
        self.buses = channels;
        Ok(written?)
    }

    fn line_mark(&mut self, bus: &BusSlot, mark: &LineMark) -> Result<()> {
        let name = |port: PortId| bus.port_names.get(port.index()).map_or("", String::as_str);
        let (kind, from, start, index, to, mask, byte) = match *mark {
            LineMark::Garbled {
                from,
                start,
                index,
                mask,
                byte,
            } => (topics::LINE_COLLISION, from, start, index, "", mask, byte),
            LineMark::Flipped {
                from,
                start,
                index,
                to,
                mask,
                byte,
            } => (topics::LINE_NOISE, from, start, index, name(to), mask, byte),
        };
        let message = LineMessage {
            kind,
            from: name(from),
            frame_start_s: secs(start),
            index,
            to,
            mask,
            byte,
        };
        let channel = channel_of(&mut self.lines, &bus.name, topics::bus_line);
        Ok(channel.write(&mut self.recorder, start, &message)?)
    }

    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<()> {
        Ok(self.record_event(&node.name, event)?)
    }

    fn telemetry(&mut self, now: SimTime, node: &NodeSlot, report: &LoopReport) -> Result<()> {
        Ok(self.record(now, &node.name, report)?)
    }

    fn readings(&mut self, now: SimTime, node: &NodeSlot, readings: &ReadingsSample) -> Result<()> {
        Ok(self.record(now, &node.name, readings)?)
    }

    fn firmware(&mut self, node: &str, record: FirmwareRecord<'_>) -> Result<()> {
        Ok(self.record_firmware(node, record)?)
    }
}

/// Two observers fed the same run, in order: the recorder and a live view.
#[derive(Debug)]
pub struct Tee<A, B> {
    pub first: A,
    pub second: B,
}

impl<A: Observer, B: Observer> Observer for Tee<A, B> {
    fn plant(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        self.first.plant(now, module)?;
        self.second.plant(now, module)
    }

    fn actuators(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        self.first.actuators(now, module)?;
        self.second.actuators(now, module)
    }

    fn frame(
        &mut self,
        bus: &BusSlot,
        from: &NodeSlot,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<()> {
        self.first.frame(bus, from, start, end, bytes)?;
        self.second.frame(bus, from, start, end, bytes)
    }

    fn line_mark(&mut self, bus: &BusSlot, mark: &LineMark) -> Result<()> {
        self.first.line_mark(bus, mark)?;
        self.second.line_mark(bus, mark)
    }

    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<()> {
        self.first.event(node, event)?;
        self.second.event(node, event)
    }

    fn telemetry(&mut self, now: SimTime, node: &NodeSlot, report: &LoopReport) -> Result<()> {
        if self.first.wants_loop_reports() {
            self.first.telemetry(now, node, report)?;
        }
        if self.second.wants_loop_reports() {
            self.second.telemetry(now, node, report)?;
        }
        Ok(())
    }

    fn wants_loop_reports(&self) -> bool {
        self.first.wants_loop_reports() || self.second.wants_loop_reports()
    }

    fn readings(&mut self, now: SimTime, node: &NodeSlot, readings: &ReadingsSample) -> Result<()> {
        self.first.readings(now, node, readings)?;
        self.second.readings(now, node, readings)
    }

    fn firmware(&mut self, node: &str, record: FirmwareRecord<'_>) -> Result<()> {
        self.first.firmware(node, record)?;
        self.second.firmware(node, record)
    }
}

/// Either observer borrowed: lets a `Tee` hold `&mut` observers.
impl<O: Observer + ?Sized> Observer for &mut O {
    fn plant(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        (**self).plant(now, module)
    }

    fn actuators(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        (**self).actuators(now, module)
    }

    fn frame(
        &mut self,
        bus: &BusSlot,
        from: &NodeSlot,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<()> {
        (**self).frame(bus, from, start, end, bytes)
    }

    fn line_mark(&mut self, bus: &BusSlot, mark: &LineMark) -> Result<()> {
        (**self).line_mark(bus, mark)
    }

    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<()> {
        (**self).event(node, event)
    }

    fn telemetry(&mut self, now: SimTime, node: &NodeSlot, report: &LoopReport) -> Result<()> {
        (**self).telemetry(now, node, report)
    }

    fn wants_loop_reports(&self) -> bool {
        (**self).wants_loop_reports()
    }

    fn readings(&mut self, now: SimTime, node: &NodeSlot, readings: &ReadingsSample) -> Result<()> {
        (**self).readings(now, node, readings)
    }

    fn firmware(&mut self, node: &str, record: FirmwareRecord<'_>) -> Result<()> {
        (**self).firmware(node, record)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use twin_recording::describe::link_frame_fields;
    use twin_recording::protobuf;

    /// What `value` reads back as from its protobuf bytes, against its JSON
    /// (an empty list is left out, and so is a null below the top level; a
    /// top-level null reads back as null).
    fn round_trip<T: Serialize>(topic: &str, value: &T) -> (Value, Value) {
        let schema = topics::proto_schema(topic).expect("a protobuf channel");
        let mut bytes = Vec::new();
        protobuf::transcode(&schema, value, &mut bytes).expect("it fits its schema");
        let back = protobuf::to_value(&schema, &bytes).expect("it reads back");
        let mut json = serde_json::to_value(value).unwrap();
        if let Value::Object(fields) = &mut json {
            fields.retain(|_, f| f.as_array().is_none_or(|a| !a.is_empty()));
            fields.values_mut().for_each(drop_nulls);
        }
        (back, json)
    }

    fn drop_nulls(v: &mut Value) {
        if let Value::Object(fields) = v {
            fields.retain(|_, f| !f.is_null() && f.as_array().is_none_or(|a| !a.is_empty()));
            fields.values_mut().for_each(drop_nulls);
        }
    }

    #[test]
    fn plant_samples_and_frames_fit_their_protobuf_schemas_field_for_field() {
        let mut sensors = plant::Sensors {
            battery_volts: 12.345678901234567,
            bms_trip: Some(plant::battery::BmsTrip::OverCurrent),
            ldr_counts: 3280,
            ..plant::Sensors::default()
        };
        sensors.shaft.encoder_count = -41;
        sensors.shaft.hall_edges = u64::from(u32::MAX) + 7;
        sensors.energy.capacitor = 0.828245;
        let (back, json) = round_trip("/plant/ev1/sensors", &sensors);
        assert_eq!(back, json);
        sensors.bms_trip = None;
        let (back, json) = round_trip("/plant/ev1/sensors", &sensors);
        assert_eq!(back, json);

        let frames: [(&str, &[u8]); 6] = [
            ("meb", b"@01EA0006FF*\n"),
            ("meb", b"@01SD0002000E000120*\n"),
            ("meb", b"@zz"),
            ("modbus-tcp", &[0, 7, 0, 0, 0, 6, 1, 4, 0, 0, 0, 10]),
            ("modbus-tcp", &[0, 7, 0]),
            ("modbus-rtu", &[1, 3, 0, 0, 0, 3, 0x05, 0xcb]),
        ];
        for (protocol, bytes) in frames {
            let message = FrameMessage {
                from: "client 3",
                start_s: 0.25,
                end_s: 0.2501,
                len: bytes.len(),
                text: Some(""),
                hex: Some(Hex(&[0])),
                decoded: &link_frame_fields(protocol, bytes),
            };
            let (back, json) = round_trip("/link/modbus-tcp/frames", &message);
            assert_eq!(back, json, "{protocol} {bytes:?}");
            let message = FrameMessage {
                from: "supervisor",
                start_s: 0.25,
                end_s: 0.2501,
                len: bytes.len(),
                text: Some(""),
                hex: Some(Hex(&[0])),
                decoded: &decode_frame(bytes),
            };
            let (back, json) = round_trip("/bus/rs485/frames", &message);
            assert_eq!(back, json, "{protocol} {bytes:?}");
        }
    }
}
