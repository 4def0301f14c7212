//! The wiring map: which pin of the board is wired to what on the bench
//! (TOML). The map for our EV controller sketch ships with the crate; a
//! student's sketch for the same board runs with it and no map of its own.

use std::collections::BTreeMap;

use serde::Deserialize;

type Result<T, E = WiringError> = std::result::Result<T, E>;

/// Why a wiring map is refused: each names the map (its file, or the
/// shipped map's name) and the table and pin at fault.
#[derive(Debug, thiserror::Error)]
pub enum WiringError {
    #[error("wiring map {name}: neither a shipped map ({shipped}) nor a file that can be read")]
    Unreadable {
        name: String,
        /// The shipped maps' names, listed.
        shipped: String,
        #[source]
        source: std::io::Error,
    },
    /// Not TOML, or a table or field the map has not: the TOML reader's
    /// own words (line, column and the text) are the message.
    #[error("{origin}: {error}")]
    Toml {
        origin: String,
        error: toml::de::Error,
    },
    #[error("{origin}: [{table}] {name}: no such pin on the ATmega328P (D2–D13, A0–A5)")]
    NoSuchPin {
        origin: String,
        table: &'static str,
        name: String,
    },
    #[error("{origin}: [{table}] {name} = \"{signal}\": unknown signal (known here: {known})")]
    UnknownSignal {
        origin: String,
        table: &'static str,
        name: String,
        signal: String,
        known: &'static str,
    },
    #[error("{origin}: [analog] {pin}: not an analog pin (A0–A5)")]
    NotAnalog { origin: String, pin: &'static str },
    #[error("{origin}: {pin}: D0 and D1 are the serial port (RXD, TXD)")]
    SerialPort { origin: String, pin: &'static str },
    #[error("{origin}: {pin} is wired twice")]
    WiredTwice { origin: String, pin: &'static str },
    #[error("{origin}: [board] tick_us: give 10 to 100000 µs, got {got}")]
    TickUs { origin: String, got: u32 },
    #[error("{origin}: [board] pwm_filter_ms: give 0 or more, got {got}")]
    PwmFilter { origin: String, got: f64 },
}

/// The maps that ship: name, text.
pub const SHIPPED: [(&str, &str); 3] = [
    (
        "ev-controller",
        include_str!("../wiring/ev-controller.toml"),
    ),
    ("motor-nano", include_str!("../wiring/motor-nano.toml")),
    ("light-nano", include_str!("../wiring/light-nano.toml")),
];

/// What a pin is wired to on the plant's side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Analog {
    /// V1, battery, through its divider.
    V1,
    /// V2, DC bus, through its divider.
    V2,
    /// I, inverter current, through the hall current sensor.
    I,
    /// The photoresistor divider.
    Ldr,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Input {
    HallA,
    HallB,
    HallC,
    EncoderA,
    EncoderB,
    /// The motor driver's fault line: high while the driver is healthy.
    DriverFault,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Output {
    /// MEB SD0 bits 0–4 (high = off, as the module's inputs are wired).
    En,
    Brk,
    Pro,
    Des,
    Fr,
    /// MEB SD1 bit 0.
    Chg,
    /// Read and recorded only.
    Led,
    /// The motor driver's sleep line: high = awake, the inverter enabled
    /// (the Controller_network motor Nano).
    DriverSleep,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pwm {
    /// The module's speed input VEL (0–5 V).
    Vel,
}

/// A pin of the ATmega328P: index into ports B (0–7), C (8–15), D (16–23),
/// and its ADC channel if it has one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pin {
    pub name: &'static str,
    pub index: u8,
    pub adc: Option<u8>,
}

const PIN_NAMES: [&str; 20] = [
    "D0", "D1", "D2", "D3", "D4", "D5", "D6", "D7", "D8", "D9", "D10", "D11", "D12", "D13", "A0",
    "A1", "A2", "A3", "A4", "A5",
];

/// The Arduino pin called `name` (`D9`, `A0`; `13` for D13).
pub fn pin(name: &str) -> Option<Pin> {
    let upper = name.trim().to_ascii_uppercase();
    let canonical = if upper.chars().all(|c| c.is_ascii_digit()) {
        format!("D{upper}")
    } else {
        upper
    };
    let n = PIN_NAMES.iter().position(|p| *p == canonical)?;
    let name = PIN_NAMES[n];
    let (index, adc) = match n {
        0..=7 => (16 + n as u8, None),
        8..=13 => (n as u8 - 8, None),
        _ => (8 + (n as u8 - 14), Some(n as u8 - 14)),
    };
    Some(Pin { name, index, adc })
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    #[serde(default)]
    analog: BTreeMap<String, String>,
    #[serde(default)]
    inputs: BTreeMap<String, String>,
    #[serde(default)]
    outputs: BTreeMap<String, String>,
    #[serde(default)]
    pwm: BTreeMap<String, String>,
    #[serde(default)]
    board: Board,
}

/// The board's settings beside its pins.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Board {
    /// How often the sensors reach the pins and the outputs are read (µs).
    pub tick_us: u32,
    /// RC time constant between a PWM pin and the module (ms).
    pub pwm_filter_ms: f64,
    /// Whether the outputs drive the module (false: a sensor-only board).
    pub drives_plant: bool,
}

impl Default for Board {
    fn default() -> Self {
        Self {
            tick_us: 100,
            pwm_filter_ms: 1.0,
            drives_plant: true,
        }
    }
}

/// A wiring map, checked.
#[derive(Debug, Clone)]
pub struct Wiring {
    /// Where it came from, for messages.
    pub origin: String,
    pub analog: Vec<(Pin, Analog)>,
    pub inputs: Vec<(Pin, Input)>,
    pub outputs: Vec<(Pin, Output)>,
    pub pwm: Vec<(Pin, Pwm)>,
    pub board: Board,
    /// The map as written (stored in a recording beside the firmware).
    pub text: String,
}

impl Wiring {
    /// A shipped map by name, or a TOML file.
    pub fn load(name_or_file: &str) -> Result<Self> {
        if let Some((name, text)) = SHIPPED.iter().find(|(n, _)| *n == name_or_file) {
            return Self::parse(text, &format!("wiring map {name}"));
        }
        let text = std::fs::read_to_string(name_or_file).map_err(|source| {
            let names: Vec<&str> = SHIPPED.iter().map(|(n, _)| *n).collect();
            WiringError::Unreadable {
                name: name_or_file.into(),
                shipped: names.join(", "),
                source,
            }
        })?;
        Self::parse(&text, name_or_file)
    }

    /// Parses a map; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self> {
        let file: File = toml::from_str(text).map_err(|error| WiringError::Toml {
            origin: origin.into(),
            error,
        })?;
        let analog = pins(
            origin,
            "analog",
            &file.analog,
            |s| {
                Some(match s {
                    "v1" => Analog::V1,
                    "v2" => Analog::V2,
                    "i" => Analog::I,
                    "ldr" => Analog::Ldr,
                    _ => return None,
                })
            },
            "v1, v2, i, ldr",
        )?;
        for (pin, _) in &analog {
            if pin.adc.is_none() {
                return Err(WiringError::NotAnalog {
                    origin: origin.into(),
                    pin: pin.name,
                });
            }
        }
        let inputs = pins(
            origin,
            "inputs",
            &file.inputs,
            |s| {
                Some(match s {
                    "hall_a" => Input::HallA,
                    "hall_b" => Input::HallB,
                    "hall_c" => Input::HallC,
                    "encoder_a" => Input::EncoderA,
                    "encoder_b" => Input::EncoderB,
                    "driver_fault" => Input::DriverFault,
                    _ => return None,
                })
            },
            "hall_a, hall_b, hall_c, encoder_a, encoder_b, driver_fault",
        )?;
        let outputs = pins(
            origin,
            "outputs",
            &file.outputs,
            |s| {
                Some(match s {
                    "en" => Output::En,
                    "brk" => Output::Brk,
                    "pro" => Output::Pro,
                    "des" => Output::Des,
                    "fr" => Output::Fr,
                    "chg" => Output::Chg,
                    "led" => Output::Led,
                    "driver_sleep" => Output::DriverSleep,
                    _ => return None,
                })
            },
            "en, brk, pro, des, fr, chg, led, driver_sleep",
        )?;
        let pwm = pins(
            origin,
            "pwm",
            &file.pwm,
            |s| (s == "vel").then_some(Pwm::Vel),
            "vel",
        )?;
        let mut used: BTreeMap<u8, &str> = BTreeMap::new();
        let all = analog
            .iter()
            .map(|(p, _)| p)
            .chain(inputs.iter().map(|(p, _)| p))
            .chain(outputs.iter().map(|(p, _)| p))
            .chain(pwm.iter().map(|(p, _)| p));
        for p in all {
            if p.index == 16 || p.index == 17 {
                return Err(WiringError::SerialPort {
                    origin: origin.into(),
                    pin: p.name,
                });
            }
            if used.insert(p.index, p.name).is_some() {
                return Err(WiringError::WiredTwice {
                    origin: origin.into(),
                    pin: p.name,
                });
            }
        }
        let board = file.board;
        if !(10..=100_000).contains(&board.tick_us) {
            return Err(WiringError::TickUs {
                origin: origin.into(),
                got: board.tick_us,
            });
        }
        if !(board.pwm_filter_ms.is_finite() && board.pwm_filter_ms >= 0.0) {
            return Err(WiringError::PwmFilter {
                origin: origin.into(),
                got: board.pwm_filter_ms,
            });
        }
        Ok(Self {
            origin: origin.into(),
            analog,
            inputs,
            outputs,
            pwm,
            board,
            text: text.into(),
        })
    }
}

fn pins<T>(
    origin: &str,
    table: &'static str,
    entries: &BTreeMap<String, String>,
    signal: impl Fn(&str) -> Option<T>,
    known: &'static str,
) -> Result<Vec<(Pin, T)>> {
    entries
        .iter()
        .map(|(name, what)| {
            let p = pin(name).ok_or_else(|| WiringError::NoSuchPin {
                origin: origin.into(),
                table,
                name: name.clone(),
            })?;
            let s =
                signal(&what.to_ascii_lowercase()).ok_or_else(|| WiringError::UnknownSignal {
                    origin: origin.into(),
                    table,
                    name: name.clone(),
                    signal: what.clone(),
                    known,
                })?;
            Ok((p, s))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_maps_load() {
        for (name, _) in SHIPPED {
            Wiring::load(name).unwrap_or_else(|e| panic!("{e:#}"));
        }
        let ev = Wiring::load("ev-controller").unwrap();
        assert_eq!(ev.pwm[0].0.name, "D9");
        assert_eq!(pin("D9").unwrap().index, 1); // PB1, OC1A
        assert_eq!(pin("A2").unwrap().adc, Some(2));
        assert_eq!(pin("D2").unwrap().index, 18); // PD2, INT0
        let motor = Wiring::load("motor-nano").unwrap();
        assert_eq!(motor.pwm[0].0.name, "D9");
        assert!(
            motor
                .inputs
                .contains(&(pin("D4").unwrap(), Input::DriverFault))
        );
        assert!(!Wiring::load("light-nano").unwrap().board.drives_plant);
    }

    #[test]
    fn an_unknown_pin_or_signal_names_the_file_and_the_field() {
        let err = Wiring::parse("[outputs]\nD22 = \"en\"\n", "my.toml").unwrap_err();
        assert!(
            err.to_string()
                .contains("my.toml: [outputs] D22: no such pin"),
            "{err}"
        );
        let err = Wiring::parse("[inputs]\nD2 = \"hal_a\"\n", "my.toml").unwrap_err();
        assert!(
            err.to_string()
                .contains("[inputs] D2 = \"hal_a\": unknown signal"),
            "{err}"
        );
        let err = Wiring::parse("[analog]\nD5 = \"v1\"\n", "my.toml").unwrap_err();
        assert!(err.to_string().contains("not an analog pin"), "{err}");
    }

    #[test]
    fn a_map_that_cannot_be_read_says_why_once_as_its_source() {
        let err = Wiring::load("/nonexistent/my-map.toml").unwrap_err();
        assert!(matches!(err, WiringError::Unreadable { .. }), "{err:?}");
        let top = err.to_string();
        assert!(
            top.starts_with(
                "wiring map /nonexistent/my-map.toml: neither a shipped map (ev-controller"
            ),
            "{top}"
        );
        let cause = std::error::Error::source(&err)
            .expect("the I/O error")
            .to_string();
        assert!(
            !top.contains(&cause),
            "the cause is printed by whoever walks the chain: {top}"
        );
        let err = Wiring::parse("[pwm]\nD9 = \"vel\"\nd9 = \"vel\"\n", "my.toml").unwrap_err();
        assert!(
            matches!(err, WiringError::WiredTwice { pin: "D9", .. }),
            "{err:?}"
        );
    }
}
