//! A recording's JSON messages as named signals: every numeric (and boolean)
//! field of a channel's messages, flattened into `TOPIC.field.sub` names —
//! `/plant/ev1/sensors.wheel_rpm`, `/plant/ev1/sensors.energy.battery_out`,
//! `/master/supervisor/loop.loops.0.measured_rpm` (array items by index) —
//! sampled at the messages' log times.
//!
//! The plant's sensor channels (`…/sensors`) are sampled at a fixed rate and
//! read between samples by linear interpolation. Every other channel is a
//! stream of events (an actuator change, a frame, a poll cycle): its value
//! holds from one message to the next.
//!
//! [`Signals::read`] streams the recording and keeps only the numbers: a time
//! and a value column of `f64` per signal.

use serde_json::Value;
use std::collections::BTreeMap;
use std::path::Path;

use super::Recording;
use crate::read::ReadError;
use crate::topics::Topic;

/// One signal: its samples (time in seconds, value), in file order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Signal {
    pub times: Vec<f64>,
    pub values: Vec<f64>,
    /// The value holds until the next sample (events) instead of moving
    /// linearly to it (sampled channels).
    pub hold: bool,
}

impl Signal {
    pub fn len(&self) -> usize {
        self.times.len()
    }
    pub fn is_empty(&self) -> bool {
        self.times.is_empty()
    }
    /// The value at `t`, linearly interpolated between neighbouring samples
    /// (held flat outside them). `None` for an empty signal.
    pub fn at(&self, t: f64) -> Option<f64> {
        let n = self.times.len();
        if n == 0 {
            return None;
        }
        let i = self.times.partition_point(|&x| x <= t);
        if i == 0 {
            return Some(self.values[0]);
        }
        if i == n || self.hold {
            return Some(self.values[i - 1]);
        }
        let (t0, t1) = (self.times[i - 1], self.times[i]);
        let (v0, v1) = (self.values[i - 1], self.values[i]);
        if t1 <= t0 {
            return Some(v1);
        }
        Some(v0 + (v1 - v0) * (t - t0) / (t1 - t0))
    }
}

/// A leaf's number, if it has one: numbers as they are, booleans as 0 and 1.
pub fn number(value: &Value) -> Option<f64> {
    match value {
        Value::Number(n) => n.as_f64(),
        Value::Bool(b) => Some(f64::from(u8::from(*b))),
        _ => None,
    }
}

/// Call `visit(path, leaf)` for every scalar leaf of `value` (strings and
/// nulls included), with `path` the dotted field path (empty for a scalar
/// message). `path` is a reused buffer.
pub fn leaves(value: &Value, path: &mut String, visit: &mut dyn FnMut(&str, &Value)) {
    let mut descend = |key: &str, child: &Value, path: &mut String| {
        let len = path.len();
        if !path.is_empty() {
            path.push('.');
        }
        path.push_str(key);
        leaves(child, path, visit);
        path.truncate(len);
    };
    match value {
        Value::Object(fields) => {
            for (k, v) in fields {
                descend(k, v, path);
            }
        }
        Value::Array(items) => {
            for (i, v) in items.iter().enumerate() {
                descend(&i.to_string(), v, path);
            }
        }
        leaf => visit(path, leaf),
    }
}

/// The full name of a field of a topic's messages.
pub fn signal_name(topic: &str, path: &str) -> String {
    if path.is_empty() {
        topic.to_string()
    } else {
        format!("{topic}.{path}")
    }
}

/// Whether a topic's messages are samples at a fixed rate (the plant's
/// sensors) rather than events.
pub fn is_sampled(topic: &str) -> bool {
    Topic::parse(topic).is_sampled()
}

/// A recording's numeric signals, read in one pass.
#[derive(Debug, Clone, PartialEq)]
pub struct Signals {
    /// What the pass found (metadata, channels, extent, a cut).
    pub recording: Recording,
    /// Every numeric signal, by name.
    pub by_name: BTreeMap<String, Signal>,
}

impl Signals {
    /// Read every numeric signal of the recording at `path`.
    pub fn read(path: &Path) -> Result<Self, ReadError> {
        // Per channel (by index): field path to signal, so that the topic
        // prefix is put on once, at the end.
        let mut per_channel: Vec<BTreeMap<String, Signal>> = Vec::new();
        let mut buf = String::new();
        let recording = Recording::scan(path, |m| {
            let value: Value = m.json()?;
            if per_channel.len() <= m.channel {
                per_channel.resize_with(m.channel + 1, BTreeMap::new);
            }
            let local = &mut per_channel[m.channel];
            let t = m.time_s();
            buf.clear();
            leaves(&value, &mut buf, &mut |p, leaf| {
                if let Some(v) = number(leaf) {
                    let s = match local.get_mut(p) {
                        Some(s) => s,
                        None => local.entry(p.to_string()).or_default(),
                    };
                    s.times.push(t);
                    s.values.push(v);
                }
            });
            Ok(())
        })?;
        let mut by_name = BTreeMap::new();
        for (channel, local) in recording.channels.iter().zip(per_channel) {
            let hold = !is_sampled(&channel.topic);
            for (p, mut s) in local {
                s.hold = hold;
                s.times.shrink_to_fit();
                s.values.shrink_to_fit();
                by_name.insert(signal_name(&channel.topic, &p), s);
            }
        }
        Ok(Self { recording, by_name })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn nested_fields_and_arrays_get_dotted_names() {
        let mut seen = Vec::new();
        let v = json!({"a": 1, "b": {"c": true, "d": "x"}, "e": [{"f": 2.5}], "g": null});
        leaves(&v, &mut String::new(), &mut |p, leaf| {
            seen.push((p.to_string(), number(leaf)))
        });
        assert_eq!(
            seen,
            vec![
                ("a".into(), Some(1.0)),
                ("b.c".into(), Some(1.0)),
                ("b.d".into(), None),
                ("e.0.f".into(), Some(2.5)),
                ("g".into(), None),
            ]
        );
    }

    #[test]
    fn interpolation_between_and_beyond_samples() {
        let s = Signal {
            times: vec![0.0, 1.0, 2.0],
            values: vec![0.0, 10.0, 0.0],
            hold: false,
        };
        assert_eq!(s.at(-1.0), Some(0.0));
        assert_eq!(s.at(0.25), Some(2.5));
        assert_eq!(s.at(1.5), Some(5.0));
        assert_eq!(s.at(3.0), Some(0.0));
        assert_eq!(Signal::default().at(0.0), None);
        let events = Signal { hold: true, ..s };
        assert_eq!(events.at(0.25), Some(0.0));
        assert_eq!(events.at(1.0), Some(10.0));
        assert_eq!(events.at(1.99), Some(10.0));
    }
}
