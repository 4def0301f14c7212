//! Where two recordings of the same scenario part: message by message, per
//! channel, the first message whose time or content differs, and in it the
//! first field. `replay` uses it after the bytes differ.

use serde_json::Value;
use std::collections::BTreeMap;

use super::signals::{leaves, signal_name};
use super::{Message, Recording};

/// The earliest place where two recordings differ.
#[derive(Debug, Clone, PartialEq)]
pub struct Departure {
    /// The signal (`TOPIC.field`), or the topic when a whole message is
    /// missing on one side or its time moved.
    pub signal: String,
    pub time_s: f64,
    /// The value as recorded and as replayed (JSON text; `absent` if none).
    pub recorded: String,
    pub replayed: String,
    /// Other fields of the same message that differ there too.
    pub other_fields: Vec<String>,
    /// Channels that depart at all.
    pub channels_departing: usize,
}

/// The first departure of `replayed` from `recorded`, or `None` when every
/// message matches. When `recorded` was cut short, only what it holds is
/// compared (each channel's first messages).
pub fn first_departure(recorded: &Recording, replayed: &Recording) -> Option<Departure> {
    let mut topics: Vec<&str> = recorded.channels.iter().map(|c| c.topic.as_str()).collect();
    for c in &replayed.channels {
        if !topics.contains(&c.topic.as_str()) {
            topics.push(&c.topic);
        }
    }
    let mut first: Option<Departure> = None;
    let mut departing = 0;
    for topic in topics {
        let (a, b) = (messages(recorded, topic), messages(replayed, topic));
        let Some(d) = channel_departure(topic, a, b, recorded.truncated.is_some()) else {
            continue;
        };
        departing += 1;
        if first.as_ref().is_none_or(|f| d.time_s < f.time_s) {
            first = Some(d);
        }
    }
    first.map(|mut d| {
        d.channels_departing = departing;
        d
    })
}

fn channel_departure(
    topic: &str,
    a: &[Message],
    b: &[Message],
    a_cut_short: bool,
) -> Option<Departure> {
    let absent = || "absent".to_string();
    for (i, ma) in a.iter().enumerate() {
        let Some(mb) = b.get(i) else {
            return Some(Departure {
                signal: topic.to_string(),
                time_s: ma.time_s(),
                recorded: format!("message {}", i + 1),
                replayed: absent(),
                other_fields: Vec::new(),
                channels_departing: 0,
            });
        };
        if ma.log_time_ns != mb.log_time_ns {
            return Some(Departure {
                signal: topic.to_string(),
                time_s: ma.time_s().min(mb.time_s()),
                recorded: format!("message {} at {:.6} s", i + 1, ma.time_s()),
                replayed: format!("at {:.6} s", mb.time_s()),
                other_fields: Vec::new(),
                channels_departing: 0,
            });
        }
        if ma.value != mb.value {
            let fa = flat(&ma.value);
            let fb = flat(&mb.value);
            let mut differing = fa
                .keys()
                .chain(fb.keys())
                .filter(|k| fa.get(*k) != fb.get(*k))
                .collect::<std::collections::BTreeSet<_>>()
                .into_iter();
            let field = differing.next().cloned().unwrap_or_default();
            let text =
                |m: &BTreeMap<String, Value>| m.get(&field).map_or_else(absent, |v| v.to_string());
            return Some(Departure {
                signal: signal_name(topic, &field),
                time_s: ma.time_s(),
                recorded: text(&fa),
                replayed: text(&fb),
                other_fields: differing.cloned().collect(),
                channels_departing: 0,
            });
        }
    }
    if a_cut_short {
        return None;
    }
    b.get(a.len()).map(|mb| Departure {
        signal: topic.to_string(),
        time_s: mb.time_s(),
        recorded: absent(),
        replayed: format!("message {}", a.len() + 1),
        other_fields: Vec::new(),
        channels_departing: 0,
    })
}

fn messages<'a>(r: &'a Recording, topic: &str) -> &'a [Message] {
    r.channel(topic).map_or(&[], |c| &c.messages)
}

fn flat(v: &Value) -> BTreeMap<String, Value> {
    let mut out = BTreeMap::new();
    leaves(v, &mut String::new(), &mut |p, leaf| {
        out.insert(p.to_string(), leaf.clone());
    });
    out
}
