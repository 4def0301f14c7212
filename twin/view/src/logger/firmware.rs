//! A compiled firmware node beside the plant it drives: the bursts on its
//! UART (`/firmware/<node>/uart`) and, every 10 ms, its pins' levels and
//! duty, the ADC inputs fed to it and its cycle count
//! (`/firmware/<node>/io`), as entities under the node's name:
//!
//! | entity | from | one sample per |
//! |---|---|---|
//! | `<node>/firmware/uart` | each burst, `rx`/`tx`, as text or hex, with its baud and cycle | burst |
//! | `<node>/firmware/pins/<pin> <signal>/duty`, `…/level` | each wired output and PWM pin | 10 ms |
//! | `<node>/firmware/adc/<pin> <signal>` | each analog input, in ADC counts | 10 ms |
//! | `<node>/firmware/cycles` | CPU cycles run, in millions | 10 ms |
//!
//! The view reads the recording only: it knows nothing of simavr.

use rerun::components::TextLogLevel;
use rerun::{Scalars, TextLog};
use serde::Deserialize;

use super::RerunLogger;

/// A UART burst as the view reads it.
#[derive(Debug, Deserialize)]
pub struct UartBurst {
    pub dir: String,
    pub baud: f64,
    pub start_s: f64,
    pub end_s: f64,
    #[serde(default)]
    pub text: String,
    pub hex: String,
    #[serde(default)]
    pub cycles: Vec<u64>,
}

/// A pins/ADC/cycles sample as the view reads it.
#[derive(Debug, Deserialize)]
pub struct FirmwareIo {
    pub cycles: u64,
    #[serde(default)]
    pub pins: Vec<PinState>,
    #[serde(default)]
    pub adc: Vec<AdcInput>,
}

#[derive(Debug, Deserialize)]
pub struct PinState {
    pub pin: String,
    pub signal: String,
    pub level: bool,
    pub duty: f64,
}

#[derive(Debug, Deserialize)]
pub struct AdcInput {
    pub pin: String,
    pub signal: String,
    pub counts: u16,
}

/// The entity of a firmware node's `what`.
pub fn firmware_path(node: &str, what: &str) -> String {
    format!("{node}/firmware/{what}")
}

impl RerunLogger {
    /// One burst on a firmware node's UART.
    pub fn firmware_uart(&mut self, node: &str, b: &UartBurst) {
        self.at(b.start_s);
        let shown = if b.text.is_empty() {
            b.hex
                .as_bytes()
                .chunks(2)
                .map(|c| std::str::from_utf8(c).unwrap_or("??"))
                .collect::<Vec<_>>()
                .join(" ")
        } else {
            b.text.trim_end().to_string()
        };
        let arrow = if b.dir == "rx" {
            "→ firmware"
        } else {
            "firmware →"
        };
        let line = format!(
            "{arrow}: {shown}   ({} bytes at {:.0} baud, {:.3} ms, from cycle {})",
            b.hex.len() / 2,
            b.baud,
            (b.end_s - b.start_s) * 1e3,
            b.cycles.first().copied().unwrap_or(0)
        );
        let path = firmware_path(node, "uart");
        let _ = self.rec.log(
            path.as_str(),
            &TextLog::new(line).with_level(TextLogLevel::INFO),
        );
        *self.samples.entry(path).or_default() += 1;
    }

    /// One pins/ADC/cycles sample of a firmware node at `t`.
    pub fn firmware_io(&mut self, node: &str, t: f64, io: &FirmwareIo) {
        self.at(t);
        let mut log = |path: String, value: f64| {
            let _ = self.rec.log(path.as_str(), &Scalars::single(value));
            *self.samples.entry(path).or_default() += 1;
        };
        for p in &io.pins {
            let pin = format!("pins/{} {}", p.pin, p.signal);
            log(firmware_path(node, &format!("{pin}/duty")), p.duty);
            log(
                firmware_path(node, &format!("{pin}/level")),
                f64::from(u8::from(p.level)),
            );
        }
        for a in &io.adc {
            log(
                firmware_path(node, &format!("adc/{} {}", a.pin, a.signal)),
                f64::from(a.counts),
            );
        }
        log(firmware_path(node, "cycles"), io.cycles as f64 / 1e6);
    }
}

#[cfg(test)]
mod tests {
    use crate::logger::RerunLogger;
    use crate::recording::{layout_of, replay_into};
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
