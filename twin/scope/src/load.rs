//! A recording's bus (or link) as a [`Waveform`]: its frames, where the
//! line differed from them (the characters collisions garbled and the bits
//! noise flipped, which a virtual run records only where they happened),
//! its line format from the scenario the recording carries (or, for a
//! real-time session, from the link's options), and the window chosen.

use std::collections::BTreeMap;
use std::path::Path;

use protocols::time::TICKS_PER_SECOND;
use twin_recording::read::Recording;
use twin_recording::topics::{FrameSample, LINE_COLLISION, LineSample, Topic};
use twin_sim::scenario::{Scenario, WiringSpec};

use crate::ScopeError;
use crate::wave::{Flip, Garble, Hearing, LineFormat, LineFrame, Parity, Waveform};

/// Which part of the recording to show.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Window {
    /// Everything.
    All,
    /// From, to (s); either open.
    Span(Option<f64>, Option<f64>),
    /// One frame (numbered from 0 in the bus's order) with a little idle
    /// line on either side.
    Frame(usize),
}

/// What to show.
#[derive(Debug, Clone, PartialEq)]
pub struct Choice {
    /// A bus or link name; `None` when the recording has one.
    pub bus: Option<String>,
    pub window: Window,
    /// For a real-time link whose options the recording does not hold.
    pub baud: Option<u32>,
}

/// Frames of one channel, as read: sender, first start bit (s), bytes;
/// and where the line differed from them.
#[derive(Debug, Default)]
struct Channel {
    frames: Vec<(String, f64, Vec<u8>)>,
    marks: Vec<LineSample>,
}

/// Reads `path` and builds the chosen bus's waveform.
pub fn load(path: &Path, choice: &Choice) -> Result<Waveform, ScopeError> {
    let mut buses: BTreeMap<(bool, String), Channel> = BTreeMap::new();
    let recording = Recording::scan(path, |m| {
        match Topic::parse(m.topic) {
            Topic::BusFrames(b) | Topic::LinkFrames(b) => {
                let link = matches!(Topic::parse(m.topic), Topic::LinkFrames(_));
                let f: FrameSample = m.json()?;
                let bytes = hex_bytes(&f.hex);
                let channel = buses.entry((link, b.to_string())).or_default();
                channel.frames.push((f.from, f.start_s, bytes));
            }
            Topic::BusLine(b) => {
                let mark: LineSample = m.json()?;
                buses
                    .entry((false, b.to_string()))
                    .or_default()
                    .marks
                    .push(mark);
            }
            _ => {}
        }
        Ok(())
    })
    .map_err(|source| ScopeError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    buses.retain(|_, c| !c.frames.is_empty());
    let names = || {
        buses
            .keys()
            .map(|(link, n)| format!("{} {n}", if *link { "link" } else { "bus" }))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let key = match &choice.bus {
        Some(want) => buses
            .keys()
            .find(|(_, n)| n == want)
            .cloned()
            .ok_or_else(|| ScopeError::NoSuchBus {
                path: path.to_path_buf(),
                bus: want.clone(),
                have: names(),
            })?,
        None => {
            if buses.len() > 1 {
                return Err(ScopeError::WhichBus {
                    path: path.to_path_buf(),
                    have: names(),
                });
            }
            buses
                .keys()
                .next()
                .cloned()
                .ok_or_else(|| ScopeError::NoFrames {
                    path: path.to_path_buf(),
                })?
        }
    };
    let (link, name) = key.clone();
    let channel = buses.remove(&key).unwrap_or_default();
    let (format, nodes, hearing) = if link {
        let format = link_format(&recording, &name, choice.baud);
        let mut nodes: Vec<String> = Vec::new();
        for (from, _, _) in &channel.frames {
            if !nodes.contains(from) {
                nodes.push(from.clone());
            }
        }
        (format, nodes, Hearing::All)
    } else {
        bus_setup(&recording, path, &name)?
    };
    let node_of = |from: &str, nodes: &mut Vec<String>| match nodes.iter().position(|n| n == from) {
        Some(i) => i,
        None => {
            nodes.push(from.to_string());
            nodes.len() - 1
        }
    };
    let mut nodes = nodes;
    let mut frames: Vec<LineFrame> = Vec::with_capacity(channel.frames.len());
    for (number, (from, start_s, bytes)) in channel.frames.into_iter().enumerate() {
        let node = node_of(&from, &mut nodes);
        frames.push(LineFrame {
            number,
            node,
            start: ticks(start_s),
            bytes,
        });
    }
    frames.sort_by_key(|f| (f.start, f.number));
    if link {
        // A pseudo-terminal or a socket hands over a frame's bytes at once,
        // faster than the baud: laid out at the baud, a frame whose byte
        // times put it on the line before the one before it has ended (and
        // 3.5 characters of silence, what a Modbus RTU receiver needs to
        // tell two frames apart) follows it after that silence.
        let silence = format.bit_offset(u64::from(format.bits_per_char()) * 7 / 2);
        let mut free = 0;
        for f in &mut frames {
            f.start = f.start.max(free);
            free = f.end(&format) + silence;
        }
    }
    let (from, to) = window(&frames, &format, choice.window, path)?;
    // A frame whose first start bit opens the window (one at 0 s) needs
    // idle line before it, or a decoder sees no falling edge.
    let char_ticks = format.bit_offset(u64::from(format.bits_per_char()));
    let lead_in = if frames
        .iter()
        .any(|f| f.start >= from && f.start - from < char_ticks)
    {
        char_ticks
    } else {
        0
    };
    frames.retain(|f| f.end(&format) > from && f.start < to);
    let (flips, garbled) = marks(&channel.marks, &frames, &mut nodes);
    Ok(Waveform {
        name: format!(
            "{}.{}",
            if link { "link" } else { "bus" },
            crate::wave::wire_name(&name)
        ),
        format,
        nodes,
        hearing,
        frames,
        flips,
        garbled,
        from,
        to,
        lead_in,
        reconstructed: link,
    })
}

/// The recorded line marks as flips and garbled characters of `frames`
/// (those of frames outside the window left out), each list sorted.
fn marks(
    marks: &[LineSample],
    frames: &[LineFrame],
    nodes: &mut Vec<String>,
) -> (Vec<Flip>, Vec<Garble>) {
    let (mut flips, mut garbled) = (Vec::new(), Vec::new());
    if marks.is_empty() {
        return (flips, garbled);
    }
    // A frame is its sender and its first start bit.
    let index: BTreeMap<(usize, u64), usize> = frames
        .iter()
        .enumerate()
        .map(|(i, f)| ((f.node, f.start), i))
        .collect();
    let node = |name: &str, nodes: &mut Vec<String>| match nodes.iter().position(|n| n == name) {
        Some(i) => i,
        None => {
            nodes.push(name.to_string());
            nodes.len() - 1
        }
    };
    for m in marks {
        let from = node(&m.from, nodes);
        let Some(&frame) = index.get(&(from, ticks(m.frame_start_s))) else {
            continue;
        };
        if m.kind == LINE_COLLISION {
            garbled.push(Garble {
                frame,
                index: m.index,
                byte: m.byte,
            });
        } else {
            flips.push(Flip {
                frame,
                index: m.index,
                to: node(&m.to, nodes),
                mask: m.mask,
            });
        }
    }
    flips.sort_unstable();
    garbled.sort_unstable();
    garbled.dedup_by_key(|g| (g.frame, g.index));
    (flips, garbled)
}

/// Seconds as engine ticks.
fn ticks(s: f64) -> u64 {
    (s * TICKS_PER_SECOND as f64).round().max(0.0) as u64
}

fn hex_bytes(digits: &str) -> Vec<u8> {
    (0..digits.len() / 2)
        .filter_map(|i| u8::from_str_radix(digits.get(2 * i..2 * i + 2)?, 16).ok())
        .collect()
}

/// The window in ticks.
fn window(
    frames: &[LineFrame],
    format: &LineFormat,
    window: Window,
    path: &Path,
) -> Result<(u64, u64), ScopeError> {
    let char_ticks = format.bit_offset(u64::from(format.bits_per_char()));
    let first = frames.first().map_or(0, |f| f.start);
    let last = frames.iter().map(|f| f.end(format)).max().unwrap_or(0);
    match window {
        Window::All => Ok((first.saturating_sub(2 * char_ticks), last + 2 * char_ticks)),
        Window::Span(from, to) => {
            let from = from.map_or(first.saturating_sub(2 * char_ticks), ticks);
            let to = to.map_or(last + 2 * char_ticks, ticks);
            if to <= from {
                return Err(ScopeError::EmptyWindow {
                    from: from as f64 / TICKS_PER_SECOND as f64,
                    to: to as f64 / TICKS_PER_SECOND as f64,
                });
            }
            Ok((from, to))
        }
        Window::Frame(n) => {
            let f = frames
                .iter()
                .find(|f| f.number == n)
                .ok_or(ScopeError::NoSuchFrame {
                    path: path.to_path_buf(),
                    frame: n,
                    frames: frames.len(),
                })?;
            Ok((
                f.start.saturating_sub(2 * char_ticks),
                f.end(format) + 2 * char_ticks,
            ))
        }
    }
}

/// A simulated bus's format, nodes (in the scenario's order) and wiring.
fn bus_setup(
    recording: &Recording,
    path: &Path,
    bus: &str,
) -> Result<(LineFormat, Vec<String>, Hearing), ScopeError> {
    let toml = recording
        .run_field("scenario_toml")
        .ok_or_else(|| ScopeError::NoScenario {
            path: path.to_path_buf(),
        })?;
    let scenario =
        Scenario::parse(toml, &format!("{}, its scenario", path.display())).map_err(|e| {
            ScopeError::Scenario {
                path: path.to_path_buf(),
                why: e.to_string(),
            }
        })?;
    let spec = scenario.buses.iter().find(|b| b.name == bus);
    let (baud, bits, wiring) = spec.map_or((115_200, 10, WiringSpec::MultiDrop), |b| {
        (b.baud, b.bits_per_char, b.wiring)
    });
    let on_bus: Vec<_> = scenario.nodes.iter().filter(|n| n.bus() == bus).collect();
    let nodes = on_bus.iter().map(|n| n.name().to_string()).collect();
    let master = on_bus
        .iter()
        .position(|n| twin_sim::nodes_build::is_master(n));
    let hearing = match (wiring, master) {
        (WiringSpec::MasterSlaves, Some(master)) => Hearing::MasterSlaves { master },
        _ => Hearing::All,
    };
    Ok((LineFormat::from_bits_per_char(baud, bits), nodes, hearing))
}

/// A real-time link's format: its options in the session's `links` (as
/// `--meb /dev/ttyV0?baud=9600&parity=E`), else `baud` or the lab's 115200 8N1.
fn link_format(recording: &Recording, link: &str, baud: Option<u32>) -> LineFormat {
    let mut format = LineFormat {
        baud: 115_200,
        parity: Parity::None,
        stop_bits: 1,
    };
    let option = match link {
        "modbus-tcp" => "--modbus".to_string(),
        other => format!("--{other}"),
    };
    let links = recording.run_field("links").unwrap_or("");
    let mut words = links.split_whitespace();
    while let Some(word) = words.next() {
        if word != option {
            continue;
        }
        let Some((_, query)) = words.next().and_then(|spec| spec.split_once('?')) else {
            break;
        };
        for pair in query.split('&') {
            match pair.split_once('=') {
                Some(("baud", v)) => format.baud = v.parse().unwrap_or(format.baud),
                Some(("parity", "E" | "e")) => format.parity = Parity::Even,
                Some(("parity", "O" | "o")) => format.parity = Parity::Odd,
                Some(("stop", "2")) => format.stop_bits = 2,
                _ => {}
            }
        }
        break;
    }
    if let Some(baud) = baud {
        format.baud = baud;
    }
    format
}

#[cfg(test)]
mod tests {
    use super::*;
    use twin_recording::topics::RUN_METADATA;

    fn session(links: &str) -> Recording {
        Recording {
            path: "serve.mcap".into(),
            metadata: BTreeMap::from([(
                RUN_METADATA.to_string(),
                BTreeMap::from([("links".to_string(), links.to_string())]),
            )]),
            channels: vec![],
            chunks: 0,
            truncated: None,
            end_ns: 0,
        }
    }

    #[test]
    fn a_links_format_is_read_from_its_options() {
        let r = session("--meb /tmp/ttyV0?baud=9600&parity=E --modbus tcp://127.0.0.1:1502");
        let meb = link_format(&r, "meb", None);
        assert_eq!(
            (meb.baud, meb.parity, meb.stop_bits),
            (9600, Parity::Even, 1)
        );
        assert_eq!(meb.bits_per_char(), 11);
        // A TCP link says no baud: the lab's, or the one asked for.
        assert_eq!(link_format(&r, "modbus-tcp", None).baud, 115_200);
        assert_eq!(link_format(&r, "modbus-tcp", Some(19_200)).baud, 19_200);
    }
}
