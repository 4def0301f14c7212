//! Reading a twin recording (MCAP) into a [`RerunLogger`]: the channels of
//! README "What a recording holds", the layout from the `twin.run` metadata.
//! A truncated file (the run killed) is read up to its last complete chunk.

use anyhow::{Context, Result, bail};
use mcap::read::{ChunkFlattener, LinearReader, Options};
use mcap::records::Record;
use plant::PlantParams;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;

use super::layout::{OPEN_LOOP_MODULE, ViewLayout};
use super::logger::{PlantSample, RerunLogger};
use crate::scenario::Scenario;

/// What a recording's messages came to.
#[derive(Debug, Clone, Default)]
pub struct ReadSummary {
    /// Messages read per topic.
    pub messages: BTreeMap<String, u64>,
    /// Simulated time of the last message (s).
    pub end_s: f64,
    /// Why reading stopped early, if it did (a truncated file).
    pub stopped_early: Option<String>,
    /// Messages that could not be read (topic, reason), counted per topic.
    pub skipped: BTreeMap<String, u64>,
}

/// The `twin.run` metadata of a recording, if it has one.
pub fn run_metadata(bytes: &[u8]) -> Option<BTreeMap<String, String>> {
    let reader = LinearReader::new_with_options(bytes, Options::IgnoreEndMagic.into()).ok()?;
    for record in reader {
        match record {
            Ok(Record::Metadata(m)) if m.name == "twin.run" => return Some(m.metadata),
            Ok(_) => {}
            Err(_) => return None,
        }
    }
    None
}

/// The view layout a recording was made with: its scenario's, or the open
/// loop's preset.
pub fn layout_of(bytes: &[u8], path: &Path) -> Result<ViewLayout> {
    if !bytes.starts_with(mcap::MAGIC) {
        bail!(
            "{} is not an MCAP recording (it does not start with the MCAP magic bytes)",
            path.display()
        );
    }
    let Some(meta) = run_metadata(bytes) else {
        bail!(
            "{} has no `twin.run` metadata record: it was not written by `twin run`",
            path.display()
        );
    };
    match meta.get("kind").map(String::as_str) {
        Some("scenario") => {
            let Some(text) = meta.get("scenario_toml") else {
                bail!(
                    "{}: the `twin.run` metadata has no `scenario_toml`",
                    path.display()
                );
            };
            let origin = format!("{} (its stored scenario)", path.display());
            let scenario = Scenario::parse(text, &origin)?;
            ViewLayout::of_scenario(&scenario)
        }
        Some("open-loop") => {
            let preset = meta.get("preset").map_or("vemodule", String::as_str);
            let params = match meta.get("params_toml") {
                Some(text) => toml::from_str::<PlantParams>(text)
                    .with_context(|| format!("{}: the stored plant parameters", path.display()))?,
                None => PlantParams::preset(preset)
                    .with_context(|| format!("{}: unknown preset `{preset}`", path.display()))?,
            };
            Ok(ViewLayout::open_loop(&params))
        }
        other => bail!(
            "{}: unknown recording kind {:?} in its `twin.run` metadata",
            path.display(),
            other.unwrap_or("(none)")
        ),
    }
}

/// One frame as recorded on `/bus/<bus>/frames`.
#[derive(Debug, Deserialize)]
struct FrameMessage {
    from: String,
    start_s: f64,
    end_s: f64,
    hex: String,
}

/// One event as recorded on `/events`.
#[derive(Debug, Deserialize)]
struct EventMessage {
    node: String,
    kind: String,
    detail: String,
}

fn unhex(hex: &str) -> Option<Vec<u8>> {
    if !hex.len().is_multiple_of(2) {
        return None;
    }
    (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(hex.get(i..i + 2)?, 16).ok())
        .collect()
}

/// Feed every message of the recording `bytes` to `logger`.
pub fn replay_into(bytes: &[u8], logger: &mut RerunLogger) -> Result<ReadSummary> {
    let mut summary = ReadSummary::default();
    let mut topics: BTreeMap<u16, String> = BTreeMap::new();
    let reader = ChunkFlattener::new_with_options(bytes, Options::IgnoreEndMagic.into())
        .context("not an MCAP file")?;
    for record in reader {
        let record = match record {
            Ok(r) => r,
            Err(e) => {
                summary.stopped_early = Some(e.to_string());
                break;
            }
        };
        match record {
            Record::Channel(c) => {
                topics.insert(c.id, c.topic);
            }
            Record::Message { header, data } => {
                let Some(topic) = topics.get(&header.channel_id) else {
                    continue;
                };
                let t = header.log_time as f64 * 1e-9;
                summary.end_s = summary.end_s.max(t);
                *summary.messages.entry(topic.clone()).or_default() += 1;
                if let Err(e) = feed(logger, topic, t, &data) {
                    *summary.skipped.entry(format!("{topic}: {e}")).or_default() += 1;
                }
            }
            Record::DataEnd(_) => break,
            _ => {}
        }
    }
    Ok(summary)
}

/// One message to the logger, by topic.
fn feed(logger: &mut RerunLogger, topic: &str, t: f64, data: &[u8]) -> Result<()> {
    let parts: Vec<&str> = topic.trim_start_matches('/').split('/').collect();
    match parts.as_slice() {
        ["plant", "sensors"] => {
            let s: PlantSample = serde_json::from_slice(data)?;
            logger.plant(OPEN_LOOP_MODULE, t, &s);
        }
        ["plant", module, "sensors"] => {
            let s: PlantSample = serde_json::from_slice(data)?;
            logger.plant(module, t, &s);
        }
        ["bus", bus, "frames"] => {
            let f: FrameMessage = serde_json::from_slice(data)?;
            let Some(bytes) = unhex(&f.hex) else {
                bail!("field `hex` is not hexadecimal");
            };
            logger.frame(bus, &f.from, f.start_s, f.end_s, &bytes);
        }
        ["events"] => {
            let e: EventMessage = serde_json::from_slice(data)?;
            logger.event(&e.node, t, &e.kind, &e.detail);
        }
        ["master", node, "loop"] => {
            let report: serde_json::Value = serde_json::from_slice(data)?;
            logger.master_loop(node, t, &report);
        }
        // Actuator changes are in the frames that caused them.
        _ => {}
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::unhex;

    #[test]
    fn hex_round_trips_and_refuses_garbage() {
        assert_eq!(unhex("40a0ff"), Some(vec![0x40, 0xa0, 0xff]));
        assert_eq!(unhex("4"), None);
        assert_eq!(unhex("zz"), None);
        assert_eq!(unhex(""), Some(vec![]));
    }
}
