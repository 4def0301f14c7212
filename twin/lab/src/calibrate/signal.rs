//! The twin's signals a measured column can be compared with, and their units.

use anyhow::{Result, bail};

/// A signal of the twin, as a master read it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TwinSignal {
    /// The Controller_network motor node's register 0005 (encoder rpm).
    MotorRpmRead,
    /// The Controller_network light node's register 0006 (wheel rpm × 100).
    SensorValueRead,
}

/// The names a calibration file uses.
const NAMES: [(&str, TwinSignal); 2] = [
    ("motor-rpm-read", TwinSignal::MotorRpmRead),
    ("sensor-value-read", TwinSignal::SensorValueRead),
];

impl TwinSignal {
    pub fn from_name(name: &str) -> Result<Self> {
        match NAMES.iter().find(|(n, _)| *n == name) {
            Some((_, s)) => Ok(*s),
            None => {
                let known: Vec<&str> = NAMES.iter().map(|(n, _)| *n).collect();
                bail!(
                    "`twin = \"{name}\"` is no signal the twin has: {}",
                    known.join(", ")
                )
            }
        }
    }

    pub fn name(self) -> &'static str {
        NAMES
            .iter()
            .find(|(_, s)| *s == self)
            .map_or("?", |(n, _)| n)
    }

    /// In the lab's words, for reports and plots.
    pub fn describe(self) -> &'static str {
        match self {
            TwinSignal::MotorRpmRead => "motor rpm (register 0005, as the master read it)",
            TwinSignal::SensorValueRead => "light sensor (register 0006, as the master read it)",
        }
    }
}

/// A unit of a measured column, and its factor to the twin's unit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Unit {
    pub name: &'static str,
    factor: f64,
}

impl Unit {
    /// The unit `text` for `signal`: a speed for both (the light register
    /// is wheel rpm × 100, so plain wheel rpm is scaled by 100).
    pub fn parse(text: &str, signal: TwinSignal) -> Result<Unit> {
        let speeds: &[(&str, f64)] = match signal {
            TwinSignal::MotorRpmRead => &[
                ("rpm", 1.0),
                ("rps", 60.0),
                ("rad/s", 60.0 / std::f64::consts::TAU),
            ],
            TwinSignal::SensorValueRead => &[("rpm*100", 1.0), ("rpm×100", 1.0), ("rpm", 100.0)],
        };
        if let Some((name, factor)) = speeds.iter().find(|(n, _)| *n == text) {
            return Ok(Unit {
                name,
                factor: *factor,
            });
        }
        let known: Vec<&str> = speeds.iter().map(|(n, _)| *n).collect();
        let kind = match text {
            "V" | "mV" | "A" | "mA" | "W" | "counts" | "%" => " is not a speed, and",
            _ => "",
        };
        bail!(
            "unit `{text}`{kind} does not fit the twin's {}: use one of {}",
            signal.describe(),
            known.join(", ")
        )
    }

    /// A value of this unit in the twin's.
    pub fn to_twin(self, v: f64) -> f64 {
        v * self.factor
    }
}
