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
