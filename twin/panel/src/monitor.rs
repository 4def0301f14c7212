//! The frame monitor's side of the producer: each frame decoded, its sender
//! and receiver named, and counted per link (with the recent errors the
//! links' lamps show).
//!
//! Every panel names the parties the same way: `twin` is this process,
//! the other party is who it talks with on that link. A session's sink only
//! knows "the twin sent it" or "connection N sent it"; which of the two is
//! a client and which a slave depends on the panel's role and the link (a
//! supervisor's `bus` is the one link where the twin is the master).

use serde_json::{Value, json};
use std::collections::{BTreeMap, VecDeque};

use crate::PanelRole;
use crate::hub::Hub;
use twin_recording::describe::link_frame_fields;

/// How long an error keeps a link's lamp from green, s.
pub const RECENT_S: f64 = 5.0;

/// What the producer keeps per link.
#[derive(Debug, Default)]
struct LinkStats {
    frames_in: u64,
    frames_out: u64,
    errors: u64,
    last_t: Option<f64>,
    /// The end of the last frame received that passed its check.
    last_good_t: Option<f64>,
    /// The end of the last frame received, good or not: on `twin serve`, a
    /// client's last request (the class's index shows it).
    last_in_t: Option<f64>,
    /// Errors per whole second of session time, the last few seconds only
    /// (a noisy line makes thousands: one entry per second, not per error).
    recent: VecDeque<(i64, u64)>,
    /// The slave the twin last sent a request to, as a master on this link.
    last_asked: String,
}

impl LinkStats {
    fn error_at(&mut self, t: f64) {
        let second = t.floor() as i64;
        match self.recent.back_mut() {
            Some((s, n)) if *s == second => *n += 1,
            _ => self.recent.push_back((second, 1)),
        }
    }

    fn errors_since(&self, since: f64) -> u64 {
        self.recent
            .iter()
            .filter(|(s, _)| (*s as f64) + 1.0 > since)
            .map(|(_, n)| n)
            .sum()
    }

    fn forget_before(&mut self, since: f64) {
        while self
            .recent
            .front()
            .is_some_and(|(s, _)| (*s as f64) + 1.0 <= since)
        {
            self.recent.pop_front();
        }
    }
}

/// Shown bytes: the text of an ASCII frame (MEB, Modbus ASCII), else hex.
pub fn shown(bytes: &[u8]) -> String {
    if is_text(bytes) {
        String::from_utf8_lossy(bytes).trim_end().to_string()
    } else {
        hex(bytes)
    }
}

/// Whether a frame is shown as its text: printable ASCII and line ends.
fn is_text(bytes: &[u8]) -> bool {
    !bytes.is_empty()
        && bytes
            .iter()
            .all(|&b| b == b'\r' || b == b'\n' || (0x20..0x7f).contains(&b))
}

/// Bytes in hex, as the monitor shows a binary frame: `01 06 00 01`.
fn hex(bytes: &[u8]) -> String {
    bytes
        .iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Frames one message carries at most; the rest are counted as skipped.
const FRAMES_PER_MESSAGE: usize = 400;

/// Frames decoded and counted per link.
#[derive(Debug)]
pub struct Monitor {
    role: PanelRole,
    stats: BTreeMap<String, LinkStats>,
    pub protocols: BTreeMap<String, &'static str>,
    pub cut: u64,
}

impl Monitor {
    pub fn new(role: PanelRole) -> Self {
        Self {
            role,
            stats: BTreeMap::new(),
            protocols: BTreeMap::new(),
            cut: 0,
        }
    }

    /// Whether the twin is the master on `link` (its frames are requests
    /// to slaves, what it receives their replies).
    fn twin_is_master(&self, link: &str) -> bool {
        match self.role {
            PanelRole::Supervise => link == "bus",
            PanelRole::Client => true,
            PanelRole::Serve => false,
        }
    }

    /// The frames and events held since the last message.
    pub fn take(
        &mut self,
        hub: &Hub,
    ) -> (Vec<Value>, Vec<crate::hub::HeldEvent>, Option<(f64, f64)>) {
        let mut frames = Vec::new();
        let (events, lateness) = hub.take(|f| {
            let protocol = self.protocols.get(&f.link).copied().unwrap_or("meb");
            let decoded =
                serde_json::to_value(link_frame_fields(protocol, &f.bytes)).unwrap_or(Value::Null);
            let bad = decoded.get("error").is_some();
            let out = f.from == "twin";
            let master = self.twin_is_master(&f.link);
            let s = self.stats.entry(f.link.clone()).or_default();
            // The parties come with the frame; only a reply too garbled to
            // carry its id is put down to the slave the twin last asked.
            if master && out {
                s.last_asked.clone_from(&f.to);
            }
            let unnamed = |party: &str| party.is_empty() || party == "a slave";
            let peer = match (out, master) {
                (true, true) if f.to.is_empty() => "a slave".to_string(),
                (true, false) if f.to.is_empty() => "a client".to_string(),
                (true, _) => f.to.clone(),
                (false, true) if unnamed(&f.from) && !s.last_asked.is_empty() => {
                    s.last_asked.clone()
                }
                (false, _) => f.from.clone(),
            };
            if out {
                s.frames_out += 1;
            } else {
                s.frames_in += 1;
                s.last_in_t = Some(f.end);
            }
            if bad {
                s.errors += 1;
                s.error_at(f.end);
            } else if !out {
                // Only what the twin hears: its own frames are always well formed.
                s.last_good_t = Some(f.end);
            }
            s.last_t = Some(f.end);
            if frames.len() < FRAMES_PER_MESSAGE {
                let (from, to) = if out {
                    ("twin".to_string(), peer)
                } else {
                    (peer, "twin".to_string())
                };
                let mut frame = json!({
                    "link": f.link, "from": from, "to": to, "dir": if out { "out" } else { "in" },
                    "t": crate::seconds(f.start), "end": crate::seconds(f.end),
                    "decoded": decoded, "bad": bad,
                });
                // A text frame's bytes too (its text is trimmed of its line
                // end): the scope draws every byte that went on the line.
                if is_text(&f.bytes) {
                    frame["hex"] = Value::String(hex(&f.bytes));
                }
                frame["text"] = Value::String(shown(&f.bytes));
                frames.push(frame);
            } else {
                self.cut += 1;
            }
        });
        (frames, events, lateness)
    }

    /// Per link: clients, frames, errors (all, and of the last
    /// [`RECENT_S`]), ages of the last frame and of the last good one
    /// received at `now`.
    pub fn links<'a>(
        &mut self,
        links: impl Iterator<Item = (&'a str, usize)>,
        now: f64,
    ) -> BTreeMap<&'a str, Value> {
        links
            .map(|(name, clients)| {
                let s = self.stats.get_mut(name);
                let age = |t: Option<f64>| t.map(|t| crate::seconds((now - t).max(0.0)));
                let value = match s {
                    Some(s) => {
                        s.forget_before(now - RECENT_S);
                        json!({
                            "clients": clients,
                            "frames_in": s.frames_in,
                            "frames_out": s.frames_out,
                            "errors": s.errors,
                            "errors_recent": s.errors_since(now - RECENT_S),
                            "last_frame_age_s": age(s.last_t),
                            "last_good_age_s": age(s.last_good_t),
                            "last_in_age_s": age(s.last_in_t),
                        })
                    }
                    None => json!({
                        "clients": clients, "frames_in": 0, "frames_out": 0, "errors": 0,
                        "errors_recent": 0, "last_frame_age_s": null, "last_good_age_s": null,
                        "last_in_age_s": null,
                    }),
                };
                (name, value)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recent_errors_are_forgotten_after_their_window() {
        let mut s = LinkStats::default();
        for i in 0..700 {
            s.error_at(10.0 + f64::from(i) / 1000.0);
        }
        s.error_at(12.5);
        assert_eq!(s.errors_since(12.6 - RECENT_S), 701);
        s.forget_before(16.0 - RECENT_S);
        assert_eq!(s.errors_since(16.0 - RECENT_S), 1);
        assert_eq!(s.recent.len(), 1);
    }
}
