//! Reading a recording back: its metadata, its channels and their JSON
//! messages, in file order. A recording cut short (the process killed
//! mid-run) is read up to its last complete chunk and says so.

use anyhow::{Context, Result, bail};
use mcap::read::{ChunkReader, LinearReader, Options};
use mcap::records::Record;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// One message: its log time (simulated time) and its decoded JSON.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    pub log_time_ns: u64,
    pub value: Value,
}

impl Message {
    /// Log time in seconds.
    pub fn time_s(&self) -> f64 {
        self.log_time_ns as f64 * 1e-9
    }
}

/// One channel and every message it holds, in file order.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    pub topic: String,
    pub messages: Vec<Message>,
}

/// A recording read back.
#[derive(Debug, Clone)]
pub struct Recording {
    pub path: PathBuf,
    /// Metadata records by name (`twin.run`: the run's identity).
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// Channels in the order they first appear.
    pub channels: Vec<Channel>,
    /// Complete chunks read.
    pub chunks: u64,
    /// Why reading stopped early, when the file is cut short: everything up
    /// to its last complete chunk is here.
    pub truncated: Option<String>,
}

impl Recording {
    /// Read `path`. A file that is not MCAP is an error; one cut short is not.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes =
            std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        Self::from_bytes(&bytes, path)
            .with_context(|| format!("{} is not a readable recording", path.display()))
    }

    /// Read a recording held in memory; `path` names it.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self> {
        if !bytes.starts_with(mcap::MAGIC) {
            bail!("it does not start with the MCAP magic bytes");
        }
        let mut recording = Recording {
            path: path.to_path_buf(),
            metadata: BTreeMap::new(),
            channels: Vec::new(),
            chunks: 0,
            truncated: None,
        };
        // Channel id to index in `channels`.
        let mut by_id: BTreeMap<u16, usize> = BTreeMap::new();
        let reader = LinearReader::new_with_options(bytes, Options::IgnoreEndMagic.into())?;
        let mut data_end = false;
        for record in reader {
            let record = match record {
                Ok(r) => r,
                Err(e) => {
                    recording.truncated = Some(format!(
                        "the file ends early or is damaged after {} complete chunk(s) ({e}); \
                         read up to there",
                        recording.chunks
                    ));
                    break;
                }
            };
            match record {
                Record::Chunk { header, data } => {
                    // Decode the whole chunk before keeping any of it, so a
                    // damaged chunk is dropped whole.
                    let mut inner = Vec::new();
                    let mut damaged = None;
                    for r in ChunkReader::new(header, &data)? {
                        match r {
                            Ok(r) => inner.push(r),
                            Err(e) => {
                                damaged = Some(e);
                                break;
                            }
                        }
                    }
                    if let Some(e) = damaged {
                        recording.truncated =
                            Some(format!("chunk {} is damaged ({e})", recording.chunks + 1));
                        break;
                    }
                    for r in inner {
                        recording.take(r, &mut by_id)?;
                    }
                    recording.chunks += 1;
                }
                Record::DataEnd(_) => {
                    data_end = true;
                    break;
                }
                other => recording.take(other, &mut by_id)?,
            }
        }
        if !data_end && recording.truncated.is_none() {
            recording.truncated =
                Some("the file ends without its summary (the run did not finish)".into());
        }
        Ok(recording)
    }

    fn take(&mut self, record: Record<'_>, by_id: &mut BTreeMap<u16, usize>) -> Result<()> {
        match record {
            Record::Channel(c) => {
                if let std::collections::btree_map::Entry::Vacant(e) = by_id.entry(c.id) {
                    e.insert(self.channels.len());
                    self.channels.push(Channel {
                        topic: c.topic,
                        messages: Vec::new(),
                    });
                }
            }
            Record::Message { header, data } => {
                let Some(&index) = by_id.get(&header.channel_id) else {
                    bail!(
                        "message {} refers to channel {}, which was never declared",
                        header.sequence,
                        header.channel_id
                    );
                };
                let channel = &mut self.channels[index];
                let value = serde_json::from_slice(&data).with_context(|| {
                    format!(
                        "message {} on {} is not JSON",
                        header.sequence, channel.topic
                    )
                })?;
                channel.messages.push(Message {
                    log_time_ns: header.log_time,
                    value,
                });
            }
            Record::Metadata(m) => {
                self.metadata.insert(m.name, m.metadata);
            }
            _ => {}
        }
        Ok(())
    }

    /// The channel on `topic`.
    pub fn channel(&self, topic: &str) -> Option<&Channel> {
        self.channels.iter().find(|c| c.topic == topic)
    }

    /// A field of the run's identity (`twin.run` metadata).
    pub fn run_field(&self, key: &str) -> Option<&str> {
        self.metadata
            .get("twin.run")
            .and_then(|m| m.get(key))
            .map(String::as_str)
    }

    /// Messages in all channels.
    pub fn message_count(&self) -> usize {
        self.channels.iter().map(|c| c.messages.len()).sum()
    }

    /// The latest log time of any message (s).
    pub fn end_s(&self) -> f64 {
        self.channels
            .iter()
            .flat_map(|c| c.messages.iter().map(|m| m.log_time_ns))
            .max()
            .map_or(0.0, |t| t as f64 * 1e-9)
    }

    /// Every numeric field of every JSON message as a named signal (see
    /// [`crate::signals`]).
    pub fn signals(&self) -> BTreeMap<String, super::Signal> {
        super::signals::of(self)
    }

    /// Every frame on every bus, in file order.
    pub fn frames(&self) -> Vec<Frame> {
        let mut frames = Vec::new();
        for c in &self.channels {
            let Some(bus) = c
                .topic
                .strip_prefix("/bus/")
                .and_then(|t| t.strip_suffix("/frames"))
            else {
                continue;
            };
            for m in &c.messages {
                let s = |k: &str| m.value[k].as_str().unwrap_or("").to_string();
                frames.push(Frame {
                    time_s: m.time_s(),
                    bus: bus.to_string(),
                    from: s("from"),
                    end_s: m.value["end_s"].as_f64().unwrap_or(f64::NAN),
                    bytes: unhex(m.value["hex"].as_str().unwrap_or("")),
                });
            }
        }
        frames
    }

    /// Every event, in file order.
    pub fn events(&self) -> Vec<Event> {
        let Some(c) = self.channel("/events") else {
            return Vec::new();
        };
        c.messages
            .iter()
            .map(|m| {
                let s = |k: &str| m.value[k].as_str().unwrap_or("").to_string();
                Event {
                    time_s: m.time_s(),
                    node: s("node"),
                    kind: s("kind"),
                    detail: s("detail"),
                }
            })
            .collect()
    }
}

/// A frame as it went on a bus.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// When its first byte started (s).
    pub time_s: f64,
    pub end_s: f64,
    pub bus: String,
    pub from: String,
    pub bytes: Vec<u8>,
}

/// A node's event (timeout, bad check, log line, …).
#[derive(Debug, Clone, PartialEq)]
pub struct Event {
    pub time_s: f64,
    pub node: String,
    pub kind: String,
    pub detail: String,
}

fn unhex(hex: &str) -> Vec<u8> {
    hex.as_bytes()
        .chunks_exact(2)
        .filter_map(|p| {
            let d = |c: u8| (c as char).to_digit(16);
            Some((d(p[0])? * 16 + d(p[1])?) as u8)
        })
        .collect()
}
