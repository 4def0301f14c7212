//! Where two recordings of the same scenario part: message by message, per
//! channel, the first message whose time or content differs, and in it the
//! first field. `replay` uses it after the bytes differ.
//!
//! Both files are streamed side by side, the one behind in simulated time
//! read next: a channel's messages wait only until the other file's
//! counterpart arrives, and none is kept once the channel has departed.

use serde_json::Value;
use std::collections::{BTreeMap, HashMap, VecDeque};

use super::Recording;
use super::read::{Encoding, Item, Message, ReadError, Reader};

type Result<T, E = ReadError> = std::result::Result<T, E>;
use super::signals::{leaves, signal_name};

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

/// A message waiting for its counterpart in the other file.
#[derive(Debug)]
struct Waiting {
    log_time_ns: u64,
    sequence: u32,
    data: Vec<u8>,
    encoding: Encoding,
}

impl Waiting {
    fn time_s(&self) -> f64 {
        self.log_time_ns as f64 * 1e-9
    }

    /// Its JSON value, whichever encoding it was recorded in (a replay of
    /// an older JSON recording is written as protobuf).
    fn value(&self, topic: &str) -> Result<Value> {
        Message {
            channel: 0,
            topic,
            sequence: self.sequence,
            log_time_ns: self.log_time_ns,
            data: &self.data,
            encoding: &self.encoding,
        }
        .value()
    }
}

/// One topic's comparison so far.
#[derive(Debug, Default)]
struct Lane {
    /// Messages matched so far.
    matched: usize,
    /// Read in one file, not yet in the other: `[recorded, replayed]`.
    waiting: [VecDeque<Waiting>; 2],
    departure: Option<Departure>,
}

/// The first departure of the recording `replayed` from `recorded`, or
/// `None` when every message matches. When `recorded` was cut short, only
/// what it holds is compared (each channel's first messages).
pub fn first_departure(recorded: &Recording, replayed: &Recording) -> Result<Option<Departure>> {
    let mut readers = [Reader::open(&recorded.path)?, Reader::open(&replayed.path)?];
    let mut done = [false; 2];
    // How far in simulated time each file has been read.
    let mut at = [0u64; 2];
    // Topics in the order their channels appear in each file.
    let mut order: [Vec<String>; 2] = [Vec::new(), Vec::new()];
    let mut lanes: HashMap<String, Lane> = HashMap::new();
    while !(done[0] && done[1]) {
        let side = if done[1] || (!done[0] && at[0] <= at[1]) {
            0
        } else {
            1
        };
        let m = match readers[side].next()? {
            None => {
                done[side] = true;
                continue;
            }
            Some(Item::Channel { topic, .. }) => {
                if !order[side].iter().any(|t| t == topic) {
                    order[side].push(topic.to_string());
                }
                continue;
            }
            Some(item) => match item.message()? {
                Some(m) => m,
                None => continue,
            },
        };
        at[side] = at[side].max(m.log_time_ns);
        let lane = match lanes.get_mut(m.topic) {
            Some(lane) => lane,
            None => lanes.entry(m.topic.to_string()).or_default(),
        };
        if lane.departure.is_some() {
            continue;
        }
        lane.waiting[side].push_back(Waiting {
            log_time_ns: m.log_time_ns,
            sequence: m.sequence,
            data: m.data.to_vec(),
            encoding: m.encoding.clone(),
        });
        while !lane.waiting[0].is_empty() && !lane.waiting[1].is_empty() {
            let (Some(a), Some(b)) = (lane.waiting[0].pop_front(), lane.waiting[1].pop_front())
            else {
                break;
            };
            if let Some(d) = message_departure(m.topic, lane.matched, &a, &b)? {
                lane.departure = Some(d);
                lane.waiting = Default::default();
                break;
            }
            lane.matched += 1;
        }
    }
    let cut_short = recorded.ends_early();
    let [mut topics, replayed_order] = order;
    for t in replayed_order {
        if !topics.contains(&t) {
            topics.push(t);
        }
    }
    let mut first: Option<Departure> = None;
    let mut departing = 0;
    for topic in &topics {
        let Some(mut lane) = lanes.remove(topic) else {
            continue;
        };
        let Some(d) = lane
            .departure
            .take()
            .or_else(|| end_departure(topic, &lane, cut_short))
        else {
            continue;
        };
        departing += 1;
        if first.as_ref().is_none_or(|f| d.time_s < f.time_s) {
            first = Some(d);
        }
    }
    Ok(first.map(|mut d| {
        d.channels_departing = departing;
        d
    }))
}

fn absent() -> String {
    "absent".to_string()
}

/// Whether message `i` of `topic` departs: recorded `a`, replayed `b`.
fn message_departure(topic: &str, i: usize, a: &Waiting, b: &Waiting) -> Result<Option<Departure>> {
    if a.log_time_ns != b.log_time_ns {
        return Ok(Some(Departure {
            signal: topic.to_string(),
            time_s: a.time_s().min(b.time_s()),
            recorded: format!("message {} at {:.6} s", i + 1, a.time_s()),
            replayed: format!("at {:.6} s", b.time_s()),
            other_fields: Vec::new(),
            channels_departing: 0,
        }));
    }
    if a.data == b.data && a.encoding == b.encoding {
        return Ok(None);
    }
    let (va, vb) = (a.value(topic)?, b.value(topic)?);
    if va == vb {
        return Ok(None);
    }
    let fa = flat(&va);
    let fb = flat(&vb);
    // A field absent is one written as null: protobuf leaves out the
    // optional fields JSON wrote as null (a BMS that has not tripped) and
    // empty lists (no leaves either way), so a replay of an older JSON
    // recording does not depart on them.
    let given =
        |m: &BTreeMap<String, Value>, k: &String| m.get(k).filter(|v| !v.is_null()).cloned();
    let mut differing = fa
        .keys()
        .chain(fb.keys())
        .filter(|k| given(&fa, k) != given(&fb, k))
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .peekable();
    if differing.peek().is_none() {
        return Ok(None);
    }
    let field = differing.next().cloned().unwrap_or_default();
    let text = |m: &BTreeMap<String, Value>| m.get(&field).map_or_else(absent, |v| v.to_string());
    Ok(Some(Departure {
        signal: signal_name(topic, &field),
        time_s: a.time_s(),
        recorded: text(&fa),
        replayed: text(&fb),
        other_fields: differing.cloned().collect(),
        channels_departing: 0,
    }))
}

/// A departure at the end of the files: messages one file holds beyond the
/// other's (the replay's extra ones do not count when the recording was cut
/// short).
fn end_departure(topic: &str, lane: &Lane, recorded_cut_short: bool) -> Option<Departure> {
    let n = lane.matched + 1;
    if let Some(a) = lane.waiting[0].front() {
        return Some(Departure {
            signal: topic.to_string(),
            time_s: a.time_s(),
            recorded: format!("message {n}"),
            replayed: absent(),
            other_fields: Vec::new(),
            channels_departing: 0,
        });
    }
    if recorded_cut_short {
        return None;
    }
    lane.waiting[1].front().map(|b| Departure {
        signal: topic.to_string(),
        time_s: b.time_s(),
        recorded: absent(),
        replayed: format!("message {n}"),
        other_fields: Vec::new(),
        channels_departing: 0,
    })
}

fn flat(v: &Value) -> BTreeMap<String, Value> {
    let mut out = BTreeMap::new();
    leaves(v, &mut String::new(), &mut |p, leaf| {
        out.insert(p.to_string(), leaf.clone());
    });
    out
}

/// Whether two files hold the same bytes, read a block at a time.
pub fn same_bytes(a: &std::path::Path, b: &std::path::Path) -> Result<bool> {
    let cannot_read = |p: &std::path::Path| {
        let path = p.to_path_buf();
        move |source| ReadError::Io { path, source }
    };
    let open = |p: &std::path::Path| std::fs::File::open(p).map_err(cannot_read(p));
    let (mut fa, mut fb) = (open(a)?, open(b)?);
    let len = |f: &std::fs::File| f.metadata().map(|m| m.len()).map_err(ReadError::Source);
    if len(&fa)? != len(&fb)? {
        return Ok(false);
    }
    let (mut ba, mut bb) = (vec![0u8; 64 * 1024], vec![0u8; 64 * 1024]);
    loop {
        let n = fill(&mut fa, &mut ba).map_err(cannot_read(a))?;
        let m = fill(&mut fb, &mut bb).map_err(cannot_read(b))?;
        if n != m || ba[..n] != bb[..m] {
            return Ok(false);
        }
        if n == 0 {
            return Ok(true);
        }
    }
}

/// Read until `buf` is full or the file ends; the bytes read.
fn fill(file: &mut impl std::io::Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match file.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}
