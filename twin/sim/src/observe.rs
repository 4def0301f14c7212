//! What a virtual run writes to its recording. Channels (all JSON, JSON-schema):
//!
//! | topic | when | content |
//! |---|---|---|
//! | `/plant/<module>/sensors` | at the scenario's `record_hz` | every sensor, hall/encoder counts, energy ledger |
//! | `/plant/<module>/actuators` | on every change | what the firmware drives |
//! | `/bus/<bus>/frames` | every frame sent | sender, start and end time, raw bytes, decoded fields (PWM-capture: widths sent and captured per listener, values, pulses lost, values wrong) |
//! | `/events` | as they happen | node, kind (`timeout`, `bad_check`, `retry`, `log`, …), detail |
//! | `/master/<node>/loop` | every poll cycle | set point, measured rpm, error, output, counters |

use anyhow::Result;
use nodes::node::NodeEvent;
use nodes::time::SimTime;
use serde::Serialize;
use serde_json::{Value, json};
use std::collections::{BTreeMap, VecDeque};

use crate::engine::{BusSlot, ModuleSlot, NodeSlot, Observer};
use twin_recording::describe::decode_frame;
use twin_recording::record::Recorder;
use twin_recording::topics;

/// How many log lines the end-of-run summary shows.
const LOG_TAIL: usize = 12;

/// Writes a run to MCAP; topics are created on first use.
#[derive(Debug)]
pub struct McapObserver {
    pub recorder: Recorder,
    pub frames: u64,
    pub events: BTreeMap<String, u64>,
    /// The last lines the nodes logged (kind `log`), for the summary.
    pub log_tail: VecDeque<String>,
    /// A frame's hex text, reused from frame to frame.
    hex: String,
}

/// One frame on a bus, as recorded.
#[derive(Debug, Serialize)]
struct FrameMessage<'a, D> {
    from: &'a str,
    start_s: f64,
    end_s: f64,
    len: usize,
    /// The bytes as text when they are printable ASCII (MEB), hex otherwise.
    text: &'a str,
    hex: &'a str,
    decoded: D,
}

impl McapObserver {
    pub fn new(recorder: Recorder) -> Self {
        Self {
            recorder,
            frames: 0,
            events: BTreeMap::new(),
            log_tail: VecDeque::new(),
            hex: String::with_capacity(2 * nodes::node::MAX_FRAME),
        }
    }

    /// Write `message` to `topic`, creating its channel on first use.
    pub fn put<T: Serialize>(&mut self, topic: &str, time: SimTime, message: &T) -> Result<()> {
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
    /// One frame on `topic` (`/bus/<bus>/frames`, `/link/<link>/frames`),
    /// sent by `from`, with its decoded fields.
    pub fn record_frame(
        &mut self,
        topic: &str,
        from: &str,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
        decoded: impl Serialize,
    ) -> Result<()> {
        let printable = bytes
            .iter()
            .all(|b| b.is_ascii_graphic() || *b == b'\n' || *b == b'\r');
        // Printable bytes are ASCII, so this never fails when it is used.
        let text = std::str::from_utf8(bytes).ok().filter(|_| printable);
        let mut hex = std::mem::take(&mut self.hex);
        hex.clear();
        for b in bytes {
            const DIGITS: &[u8; 16] = b"0123456789abcdef";
            hex.push(char::from(DIGITS[usize::from(b >> 4)]));
            hex.push(char::from(DIGITS[usize::from(b & 0x0f)]));
        }
        let message = FrameMessage {
            from,
            start_s: secs(start),
            end_s: secs(end),
            len: bytes.len(),
            text: text.unwrap_or(""),
            hex: &hex,
            decoded,
        };
        self.frames += 1;
        let written = self.put(topic, start, &message);
        self.hex = hex;
        written
    }

    /// One event a node (or link) noticed.
    pub fn record_event(&mut self, node: &str, event: &NodeEvent) -> Result<()> {
        *self.events.entry(event.kind.to_string()).or_default() += 1;
        if event.kind == "log" {
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
        let message = json!({ "node": node, "kind": event.kind, "detail": event.detail });
        self.put(topics::EVENTS, event.at, &message)
    }
}

impl Observer for McapObserver {
    fn plant(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        self.put(
            &topics::plant_sensors(&module.name),
            now,
            module.plant.sensors(),
        )
    }

    fn actuators(&mut self, now: SimTime, module: &ModuleSlot) -> Result<()> {
        self.put(
            &topics::plant_actuators(&module.name),
            now,
            &module.actuators,
        )
    }

    fn frame(
        &mut self,
        bus: &BusSlot,
        from: &NodeSlot,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<()> {
        let topic = topics::bus_frames(&bus.name);
        let decoded = match bus.bus.as_pwm() {
            Some(link) => decode_pwm_frame(link, &bus.port_names),
            None => decode_frame(bytes),
        };
        self.record_frame(&topic, &from.name, start, end, bytes, decoded)
    }

    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<()> {
        self.record_event(&node.name, event)
    }

    fn telemetry(&mut self, now: SimTime, node: &NodeSlot, value: &Value) -> Result<()> {
        self.put(&topics::master_loop(&node.name), now, value)
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

    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<()> {
        self.first.event(node, event)?;
        self.second.event(node, event)
    }

    fn telemetry(&mut self, now: SimTime, node: &NodeSlot, value: &Value) -> Result<()> {
        self.first.telemetry(now, node, value)?;
        self.second.telemetry(now, node, value)
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

    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<()> {
        (**self).event(node, event)
    }

    fn telemetry(&mut self, now: SimTime, node: &NodeSlot, value: &Value) -> Result<()> {
        (**self).telemetry(now, node, value)
    }
}
