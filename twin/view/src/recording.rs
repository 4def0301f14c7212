//! Reading a twin recording (MCAP) into a [`RerunLogger`]: the channels of a
//! run (`docs/recordings.md`, "What a recording holds"), or of a real-time
//! session (`twin serve`, `twin supervise`: `/link/<link>/frames`,
//! `/realtime/lateness`), the layout from the `twin.run` metadata. The file is
//! read by twin-recording's streaming [`Reader`], the one reader of recordings,
//! and its topics recognised by the catalogue ([`twin_recording::topics`]). A
//! truncated file (the run killed) is read up to its last complete chunk.

use plant::PlantParams;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;
use twin_recording::read::{Item, Message, ReadError, Reader};
use twin_recording::topics::{self, EventSample, FrameSample, ReadingsSample, Topic};

use super::layout::{
    OPEN_LOOP_MODULE, SERVE_EV_MODULE, SERVE_LIGHT_NODE, SERVE_MOTOR_NODE, SUPERVISOR_NODE,
    ViewLayout, supervised_module,
};
use super::logger::{LatenessSample, PlantSample, RerunLogger};
use crate::ViewError;
use twin_sim::scenario::Scenario;

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

/// The `twin.run` metadata of the recording at `path`, if it has one (a
/// quick pass: the chunks are skipped, not decompressed).
pub fn run_metadata(path: &Path) -> Option<BTreeMap<String, String>> {
    let mut reader = Reader::open(path).ok()?.metadata_only();
    loop {
        match reader.next() {
            Ok(Some(Item::Metadata { name, fields })) if name == topics::RUN_METADATA => {
                return Some(fields.clone());
            }
            Ok(Some(_)) => {}
            Ok(None) | Err(_) => return None,
        }
    }
}

/// The view layout the recording at `path` was made with: its scenario's,
/// or the open loop's preset.
pub fn layout_of(path: &Path) -> Result<ViewLayout, ViewError> {
    let path_buf = || path.to_path_buf();
    match Reader::open(path) {
        Err(ReadError::NotMcap { .. }) => return Err(ViewError::NotMcap { path: path_buf() }),
        Err(e) => return Err(e.into()),
        Ok(_) => {}
    }
    let Some(meta) = run_metadata(path) else {
        return Err(ViewError::NoRunMetadata { path: path_buf() });
    };
    match meta.get("kind").map(String::as_str) {
        Some("scenario") => {
            let Some(text) = meta.get("scenario_toml") else {
                return Err(ViewError::NoScenarioToml { path: path_buf() });
            };
            let origin = format!("{} (its stored scenario)", path.display());
            let scenario = Scenario::parse(text, &origin)?;
            Ok(ViewLayout::of_scenario(&scenario)?)
        }
        Some("open-loop") => {
            let preset = meta.get("preset").map_or("vemodule", String::as_str);
            let params = match meta.get("params_toml") {
                Some(text) => toml::from_str::<PlantParams>(text).map_err(|source| {
                    ViewError::StoredParams {
                        path: path_buf(),
                        source,
                    }
                })?,
                None => PlantParams::preset(preset).ok_or_else(|| ViewError::UnknownPreset {
                    path: path_buf(),
                    preset: preset.to_string(),
                })?,
            };
            Ok(ViewLayout::open_loop(&params))
        }
        Some("serve") => {
            // `twin serve` stores its links as `--meb tcp://… --modbus8 /dev/…`.
            let links = meta.get("links").map_or("", String::as_str);
            let options: Vec<&str> = links.split_whitespace().step_by(2).collect();
            let controller_network = options.contains(&"--modbus8");
            let ev = options.iter().any(|o| *o != "--modbus8");
            let params = match meta.get("params") {
                Some(text) => toml::from_str::<PlantParams>(text).map_err(|source| {
                    ViewError::StoredParams {
                        path: path_buf(),
                        source,
                    }
                })?,
                None => PlantParams::preset("vemodule").unwrap_or_default(),
            };
            // Recorded since the choice was given; before, always fixed.
            let light_adaptive = meta.get("light_detector").is_some_and(|d| d == "adaptive");
            Ok(ViewLayout::of_serve(
                &params,
                ev || !controller_network,
                controller_network,
                light_adaptive,
            ))
        }
        Some("supervise") => {
            // Stored as `[1, 2]`.
            let text = meta.get("slaves").map_or("[1]", String::as_str);
            let slaves: Vec<u8> = text
                .trim_matches(|c| c == '[' || c == ']')
                .split(',')
                .filter(|s| !s.trim().is_empty())
                .map(|s| s.trim().parse::<u8>())
                .collect::<Result<_, _>>()
                .map_err(|source| ViewError::NotSlaveIds {
                    path: path_buf(),
                    text: text.to_string(),
                    source,
                })?;
            Ok(ViewLayout::of_supervise(&slaves))
        }
        Some("check") => {
            // A `twin check` run: its link's frames as a text log, the
            // checked slave (or, for a master, the twin's first) its module.
            let id = meta
                .get("id")
                .and_then(|id| id.parse::<u8>().ok())
                .unwrap_or(1);
            Ok(ViewLayout::of_supervise(&[id]))
        }
        other => Err(ViewError::UnknownKind {
            path: path_buf(),
            kind: other.unwrap_or("(none)").to_string(),
        }),
    }
}

/// Which program wrote the recording: the senders of a real-time
/// session's link frames are named from that program's side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Session {
    /// `twin run`: frames name their sending node.
    Virtual,
    /// `twin serve`: `twin` is the slave(s) answering, `client N` a master.
    Serve,
    /// `twin supervise`: on the `bus` link `twin` is the supervisor polling
    /// and `slave NN` the slave answering (`client N` in older recordings).
    Supervise,
}

impl Session {
    /// The session that wrote a recording, by its `twin.run` metadata.
    pub fn of(run: Option<&BTreeMap<String, String>>) -> Self {
        match run.and_then(|m| m.get("kind")) {
            Some(k) if k == "serve" => Self::Serve,
            Some(k) if k == "supervise" => Self::Supervise,
            _ => Self::Virtual,
        }
    }

    /// The node of the layout that sent `bytes` on `link`, recorded as
    /// `from` (`twin`, `client N` or `slave NN` for the other side).
    pub fn sender(self, link: &str, from: &str, bytes: &[u8]) -> String {
        let name = match (self, link, from) {
            (Self::Serve, _, "twin") if link.starts_with("modbus8") => match bytes.first() {
                Some(1) => SERVE_MOTOR_NODE,
                Some(2) => SERVE_LIGHT_NODE,
                _ => from,
            },
            (Self::Serve, _, "twin") => SERVE_EV_MODULE,
            (Self::Supervise, _, "twin") => SUPERVISOR_NODE,
            // Several slaves may share the supervisor's bus: the reply names its own.
            (Self::Supervise, "bus", _) => {
                return reply_id(bytes).map_or_else(|| from.to_string(), supervised_module);
            }
            _ => from,
        };
        name.to_string()
    }
}

/// The slave id a reply on a supervisor's bus carries: MEB `@NN…`, or a
/// Modbus RTU frame's first byte.
fn reply_id(bytes: &[u8]) -> Option<u8> {
    match bytes {
        [b'@', rest @ ..] => {
            let digits = std::str::from_utf8(rest.get(..2)?).ok()?;
            u8::from_str_radix(digits, 16).ok()
        }
        [id, _, ..] => Some(*id),
        _ => None,
    }
}

fn unhex(digits: &str) -> Option<Vec<u8>> {
    hex::decode(digits).ok()
}

/// Feed every message of the recording at `path` to `logger`.
pub fn replay_into(path: &Path, logger: &mut RerunLogger) -> Result<ReadSummary, ReadError> {
    let mut summary = ReadSummary::default();
    let session = Session::of(run_metadata(path).as_ref());
    let mut reader = Reader::open(path)?;
    while let Some(item) = reader.next()? {
        // A message on a channel never declared has no topic to show it by.
        let Item::Message(m) = item else {
            continue;
        };
        let t = m.time_s();
        summary.end_s = summary.end_s.max(t);
        match summary.messages.get_mut(m.topic) {
            Some(n) => *n += 1,
            None => {
                summary.messages.insert(m.topic.to_string(), 1);
            }
        }
        if let Err(e) = feed(logger, session, &m, t) {
            *summary
                .skipped
                .entry(format!("{}: {e}", m.topic))
                .or_default() += 1;
        }
    }
    // A file that ends between two chunks, without its summary, ends
    // without complaint: everything it holds was shown.
    summary.stopped_early = reader
        .recording()
        .truncated
        .as_ref()
        .and_then(|cut| cut.error())
        .map(str::to_string);
    Ok(summary)
}

/// One message to the logger, by topic.
fn feed(
    logger: &mut RerunLogger,
    session: Session,
    m: &Message<'_>,
    t: f64,
) -> Result<(), ViewError> {
    match Topic::parse(m.topic) {
        Topic::PlantSensors(module) => {
            let s: PlantSample = m.json()?;
            logger.plant(module.unwrap_or(OPEN_LOOP_MODULE), t, &s);
        }
        Topic::BusFrames(bus) => {
            let f: FrameSample = m.json()?;
            let Some(bytes) = unhex(&f.hex) else {
                return Err(ViewError::NotHex);
            };
            logger.frame(bus, &f.from, f.start_s, f.end_s, &bytes);
        }
        Topic::LinkFrames(link) => {
            let f: FrameSample = m.json()?;
            let Some(bytes) = unhex(&f.hex) else {
                return Err(ViewError::NotHex);
            };
            let from = session.sender(link, &f.from, &bytes);
            logger.frame(link, &from, f.start_s, f.end_s, &bytes);
        }
        Topic::RealtimeLateness => {
            #[derive(Deserialize)]
            struct Lateness {
                window: LatenessSample,
            }
            let l: Lateness = m.json()?;
            logger.lateness(t, &l.window);
        }
        Topic::Events => {
            let e: EventSample = m.json()?;
            logger.event(&e.node, t, &e.kind, &e.detail);
        }
        Topic::MasterLoop(node) => {
            let report: serde_json::Value = m.json()?;
            logger.master_loop(node, t, &report);
        }
        Topic::ControllerReadings(node) => {
            let r: ReadingsSample = m.json()?;
            logger.readings(node, t, &r);
        }
        Topic::FirmwareUart(node) => {
            let b: crate::logger::firmware::UartBurst = m.json()?;
            logger.firmware_uart(node, &b);
        }
        Topic::FirmwareIo(node) => {
            let io: crate::logger::firmware::FirmwareIo = m.json()?;
            logger.firmware_io(node, t, &io);
        }
        // Actuator changes are in the frames that caused them.
        Topic::PlantActuators(_) | Topic::BusLine(_) | Topic::ExperimentStep | Topic::Other(_) => {}
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::{Session, reply_id, unhex};
    use crate::layout::ViewLayout;

    #[test]
    fn a_supervisors_bus_replies_are_its_slaves_by_the_id_they_carry() {
        assert_eq!(reply_id(b"@02EA00060BD6*\n"), Some(2));
        assert_eq!(reply_id(&[0x03, 0x04, 0x02, 0x00, 0x01]), Some(3));
        assert_eq!(reply_id(b"@z"), None);
        let layout = ViewLayout::of_supervise(&[1, 2]);
        assert_eq!(layout.module_of_node("slave02"), Some(1));
        assert_eq!(layout.module_of_slave("supervisor", 2), Some(1));
        assert!(!layout.modules[0].has_plant);
        // The supervisor's own requests never feed a module.
        let sender = Session::Supervise.sender("bus", "twin", b"@01EA000643*\n");
        assert_eq!(layout.module_of_node(&sender), None);
        let sender = Session::Supervise.sender("bus", "client 1", b"@02EA00060BD6*\n");
        assert_eq!(layout.module_of_node(&sender), Some(1));
        // The image server's TCP clients are not slaves.
        assert_eq!(
            Session::Supervise.sender("tcp", "client 3", b"@02"),
            "client 3"
        );
        // On `twin serve`'s --modbus8 link the reply's id names the node.
        assert_eq!(Session::Serve.sender("modbus8", "twin", &[2, 3]), "sensor");
        assert_eq!(Session::Serve.sender("modbus8", "twin", &[1, 3]), "motor");
        assert_eq!(Session::Serve.sender("meb", "twin", b"@01"), "ev1");
        assert_eq!(Session::Serve.sender("meb", "client 4", b"@01"), "client 4");
    }

    #[test]
    fn hex_round_trips_and_refuses_garbage() {
        assert_eq!(unhex("40a0ff"), Some(vec![0x40, 0xa0, 0xff]));
        assert_eq!(unhex("4"), None);
        assert_eq!(unhex("zz"), None);
        assert_eq!(unhex(""), Some(vec![]));
    }
}

#[cfg(test)]
mod firmware_tests {
    use super::{layout_of, replay_into};
    use crate::logger::RerunLogger;
    use std::collections::BTreeMap;
    use twin_recording::Recorder;
    use twin_recording::topics::{self, AdcInput, FirmwareIo, PinEdge, PinState, UartBurst};

    const SCENARIO: &str = r#"
name = "ev-meb-avr"
seed = 1
duration_s = 1.0
[[module]]
name = "ev1"
preset = "vemodule"
[[bus]]
name = "rs485"
baud = 115200
[[node]]
kind = "firmware"
name = "ev1"
bus = "rs485"
module = "ev1"
elf = "ev-controller.elf"
wiring = "ev-controller"
"#;

    /// A recording with a firmware node's channels as `twin-avr` writes
    /// them (the catalogue's own types), shown beside its module.
    #[test]
    fn a_firmware_nodes_uart_pins_adc_and_cycles_are_entities_under_its_name() {
        let dir = std::env::temp_dir().join(format!("twin-view-fw-{}", std::process::id()));
        let path = dir.join("fw.mcap");
        let mut rec = Recorder::create(&path).unwrap();
        let run = BTreeMap::from([
            ("kind".to_string(), "scenario".to_string()),
            ("scenario_toml".to_string(), SCENARIO.to_string()),
        ]);
        rec.write_metadata(topics::RUN_METADATA, run).unwrap();
        let burst = UartBurst {
            dir: "tx",
            baud: 117_647.0,
            start_s: 0.3,
            end_s: 0.3002,
            len: 2,
            text: "@0",
            hex: "4030",
            cycles: &[4_800_000, 4_801_360],
        };
        let uart = topics::firmware_uart("ev1");
        rec.add_channel(&uart, &burst).unwrap();
        rec.write(&uart, 0.3, &burst).unwrap();
        let io = FirmwareIo {
            cycles: 160_000,
            pins: &[PinState {
                pin: "D9",
                signal: "vel",
                level: true,
                duty: 0.25,
                period_us: 64.0,
                edges: 312,
            }],
            adc: &[AdcInput {
                pin: "A2",
                signal: "v1",
                millivolts: 4070,
                counts: 833,
            }],
            edges: &[PinEdge {
                cycle: 159_000,
                pin: "D9",
                level: true,
            }],
        };
        let io_topic = topics::firmware_io("ev1");
        rec.add_channel(&io_topic, &io).unwrap();
        rec.write(&io_topic, 0.01, &io).unwrap();
        rec.finish().unwrap();

        let layout = layout_of(&path).unwrap();
        assert_eq!(layout.firmware, [("ev1".to_string(), 0)]);
        // The sketch stands for the module's controller: its replies' rpm
        // words are the module's, as the Rust controller's are.
        assert_eq!(layout.module_of_node("ev1"), Some(0));
        let (stream, _storage) = rerun::RecordingStreamBuilder::new("test").memory().unwrap();
        let mut logger = RerunLogger::new(stream, layout).unwrap();
        replay_into(&path, &mut logger).unwrap();
        for entity in [
            "ev1/firmware/uart",
            "ev1/firmware/pins/D9 vel/duty",
            "ev1/firmware/pins/D9 vel/level",
            "ev1/firmware/adc/A2 v1",
            "ev1/firmware/cycles",
        ] {
            assert_eq!(
                logger.samples.get(entity),
                Some(&1),
                "{entity}: {:?}",
                logger.samples
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
