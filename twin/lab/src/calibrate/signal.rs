//! The twin's signals a measured column (or a recording's signal) can be
//! compared with, and their units.

use super::CalibrateError;

/// A signal of the twin, as a master read it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TwinSignal {
    /// The Controller_network motor node's register 0005 (encoder rpm).
    MotorRpmRead,
    /// The Controller_network light node's register 0006 (wheel rpm × 100).
    SensorValueRead,
    /// The speed an MEB supervisor read to close its loop (the EV module's
    /// `RPM_M` or `RPM_L`), once per poll cycle.
    SupervisorRpm,
    /// The `VEL` (DAC counts) an MEB supervisor's PI wrote, once per poll cycle.
    SupervisorVel,
}

/// The names a calibration file uses.
const NAMES: [(&str, TwinSignal); 4] = [
    ("motor-rpm-read", TwinSignal::MotorRpmRead),
    ("sensor-value-read", TwinSignal::SensorValueRead),
    ("supervisor-rpm", TwinSignal::SupervisorRpm),
    ("supervisor-vel", TwinSignal::SupervisorVel),
];

impl TwinSignal {
    pub fn from_name(name: &str) -> Result<Self, CalibrateError> {
        match NAMES.iter().find(|(n, _)| *n == name) {
            Some((_, s)) => Ok(*s),
            None => {
                let known: Vec<&str> = NAMES.iter().map(|(n, _)| *n).collect();
                Err(CalibrateError::UnknownSignal {
                    name: name.to_string(),
                    known: known.join(", "),
                })
            }
        }
    }

    pub fn name(self) -> &'static str {
        NAMES
            .iter()
            .find(|(_, s)| *s == self)
            .map_or("?", |(n, _)| n)
    }

    /// Whether it is a speed, in the set point's unit: a step's figures
    /// (rise, overshoot, the set point's levels) are a speed's.
    pub fn is_speed(self) -> bool {
        !matches!(self, TwinSignal::SupervisorVel)
    }

    /// In the lab's words, for reports and plots.
    pub fn describe(self) -> &'static str {
        match self {
            TwinSignal::MotorRpmRead => "motor rpm (register 0005, as the master read it)",
            TwinSignal::SensorValueRead => "light sensor (register 0006, as the master read it)",
            TwinSignal::SupervisorRpm => "speed the supervisor's loop read (RPM_M or RPM_L)",
            TwinSignal::SupervisorVel => "VEL the supervisor's loop wrote (DAC counts)",
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
    pub fn parse(text: &str, signal: TwinSignal) -> Result<Unit, CalibrateError> {
        let speeds: &[(&str, f64)] = match signal {
            TwinSignal::MotorRpmRead | TwinSignal::SupervisorRpm => &[
                ("rpm", 1.0),
                ("rps", 60.0),
                ("rad/s", 60.0 / std::f64::consts::TAU),
            ],
            TwinSignal::SensorValueRead => &[("rpm*100", 1.0), ("rpm×100", 1.0), ("rpm", 100.0)],
            // 12 bits over the DAC's 0–5 V.
            TwinSignal::SupervisorVel => &[("counts", 1.0), ("V", 4095.0 / 5.0)],
        };
        if let Some((name, factor)) = speeds.iter().find(|(n, _)| *n == text) {
            return Ok(Unit {
                name,
                factor: *factor,
            });
        }
        let known: Vec<&str> = speeds.iter().map(|(n, _)| *n).collect();
        let kind = match (text, signal) {
            (_, TwinSignal::SupervisorVel) => "",
            ("V" | "mV" | "A" | "mA" | "W" | "counts" | "%", _) => " is not a speed, and",
            _ => "",
        };
        Err(CalibrateError::Unit {
            unit: text.to_string(),
            kind,
            signal: signal.describe(),
            known: known.join(", "),
        })
    }

    /// A value of this unit in the twin's.
    pub fn to_twin(self, v: f64) -> f64 {
        v * self.factor
    }
}
