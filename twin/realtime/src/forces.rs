//! Inputs forced by hand, from the console (`force v1 30.5`) or the panel's
//! sliders and switches, as the M3CVME tool's simulator lets one set every
//! input: measured values replaced before the firmware samples them, or
//! input words after it computed them. The plant itself is untouched.
//!
//! [`Input`] names each input once, with its unit and the range it takes,
//! so the console and the panel check a value alike and say its range in
//! the same words.

use nodes::firmware::{RegisterImage, ea};
use std::ops::RangeInclusive;

/// An input that can be forced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Input {
    V1,
    V2,
    I,
    RpmM,
    RpmL,
    Ldr,
    /// The hall sensors' code, ED0 bits 0–2.
    Hall,
    /// The photoresistor sees the paper flag (dark), ED0 bit 3.
    Flag,
    /// The motor driver reports a fault (the inverter's protection trips).
    DriverFault,
}

/// What kind of control sets an input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputKind {
    /// A measured value or a word: a number in a range.
    Analog,
    /// A code of a few bits (the hall code).
    Code,
    /// On or off.
    Switch,
}

impl Input {
    /// Every input, in the order the console's help and the panel show them.
    pub const ALL: [Input; 9] = [
        Input::V1,
        Input::V2,
        Input::I,
        Input::RpmM,
        Input::RpmL,
        Input::Ldr,
        Input::Hall,
        Input::Flag,
        Input::DriverFault,
    ];

    /// Its name in commands (`force v1 30`, `{"input": "v1"}`).
    pub fn name(self) -> &'static str {
        match self {
            Input::V1 => "v1",
            Input::V2 => "v2",
            Input::I => "i",
            Input::RpmM => "rpm_m",
            Input::RpmL => "rpm_l",
            Input::Ldr => "ldr",
            Input::Hall => "hall",
            Input::Flag => "flag",
            Input::DriverFault => "driver_fault",
        }
    }

    /// The input named `name` (any case).
    pub fn parse(name: &str) -> Result<Input, ForceError> {
        let lower = name.trim().to_ascii_lowercase();
        Input::ALL
            .into_iter()
            .find(|i| i.name() == lower)
            .ok_or_else(|| ForceError::Unknown(name.to_string()))
    }

    /// What it is, in the lab's words.
    pub fn label(self) -> &'static str {
        match self {
            Input::V1 => "V1 battery voltage",
            Input::V2 => "V2 DC-bus voltage",
            Input::I => "I inverter current",
            Input::RpmM => "RPM_M word (hall rpm)",
            Input::RpmL => "RPM_L word (light rpm)",
            Input::Ldr => "LDR word (photoresistor)",
            Input::Hall => "hall code (ED0 bits 0-2: A, B, C)",
            Input::Flag => "flag in the beam (ED0 bit 3, photoresistor dark)",
            Input::DriverFault => "motor driver fault (inverter trips)",
        }
    }

    pub fn kind(self) -> InputKind {
        match self {
            Input::Hall => InputKind::Code,
            Input::Flag | Input::DriverFault => InputKind::Switch,
            _ => InputKind::Analog,
        }
    }

    /// Its unit, as the range is said.
    pub fn unit(self) -> &'static str {
        match self {
            Input::V1 | Input::V2 => "V",
            Input::I => "A",
            Input::RpmM | Input::RpmL => "rpm",
            Input::Ldr => "counts",
            Input::Hall => "code",
            Input::Flag | Input::DriverFault => "",
        }
    }

    /// The values it takes (a switch: 0 off, 1 on).
    pub fn range(self) -> RangeInclusive<f64> {
        match self {
            Input::V1 | Input::V2 => 0.0..=100.0,
            Input::I => -100.0..=100.0,
            Input::RpmM | Input::RpmL | Input::Ldr => 0.0..=65535.0,
            Input::Hall => 0.0..=7.0,
            Input::Flag | Input::DriverFault => 0.0..=1.0,
        }
    }

    /// The smallest change that means something: a word's count, a code.
    pub fn step(self) -> f64 {
        match self {
            Input::V1 | Input::V2 | Input::I => 0.1,
            _ => 1.0,
        }
    }

    /// What it takes, in words: `V1 takes 0 to 100 V`.
    pub fn takes(self) -> String {
        let name = self.name().to_ascii_uppercase();
        match self.kind() {
            InputKind::Switch => format!("{name} takes on or off (1 or 0)"),
            InputKind::Code => {
                format!("{name} takes a code from 0 to 7 (bit 0 A, bit 1 B, bit 2 C)")
            }
            InputKind::Analog => {
                let r = self.range();
                format!("{name} takes {} to {} {}", r.start(), r.end(), self.unit())
            }
        }
    }

    /// `value` checked against the input's range.
    pub fn value(self, value: f64) -> Result<Forced, ForceError> {
        if !value.is_finite() || !self.range().contains(&value) {
            let shown = match self.unit() {
                "" | "code" => format!("{value}"),
                unit => format!("{value} {unit}"),
            };
            return Err(ForceError::OutOfRange {
                value: shown,
                takes: self.takes(),
            });
        }
        let word = value.round() as u16;
        Ok(match self {
            Input::V1 => Forced::V1(value),
            Input::V2 => Forced::V2(value),
            Input::I => Forced::I(value),
            Input::RpmM => Forced::RpmM(word),
            Input::RpmL => Forced::RpmL(word),
            Input::Ldr => Forced::Ldr(word),
            Input::Hall => Forced::Hall(word as u8),
            Input::Flag => Forced::Flag(word != 0),
            Input::DriverFault => Forced::DriverFault(word != 0),
        })
    }

    /// A value typed on the console: a number, or for a switch `on`/`off`.
    pub fn value_text(self, text: &str) -> Result<Forced, ForceError> {
        let number = match text.trim().to_ascii_lowercase().as_str() {
            "on" | "true" if self.kind() == InputKind::Switch => 1.0,
            "off" | "false" if self.kind() == InputKind::Switch => 0.0,
            t => t.parse::<f64>().map_err(|_| ForceError::NotANumber {
                text: text.to_string(),
                takes: self.takes(),
            })?,
        };
        self.value(number)
    }
}

/// Why a force was refused, in the user's words.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ForceError {
    #[error("cannot force `{0}`: v1, v2, i, rpm_m, rpm_l, ldr, hall, flag or driver_fault")]
    Unknown(String),
    #[error("{value} is out of range: {takes}")]
    OutOfRange { value: String, takes: String },
    #[error("`{text}` is not a value: {takes}")]
    NotANumber { text: String, takes: String },
}

/// One input's forced value, checked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Forced {
    V1(f64),
    V2(f64),
    I(f64),
    RpmM(u16),
    RpmL(u16),
    Ldr(u16),
    Hall(u8),
    Flag(bool),
    DriverFault(bool),
}

impl Forced {
    pub fn input(self) -> Input {
        match self {
            Forced::V1(_) => Input::V1,
            Forced::V2(_) => Input::V2,
            Forced::I(_) => Input::I,
            Forced::RpmM(_) => Input::RpmM,
            Forced::RpmL(_) => Input::RpmL,
            Forced::Ldr(_) => Input::Ldr,
            Forced::Hall(_) => Input::Hall,
            Forced::Flag(_) => Input::Flag,
            Forced::DriverFault(_) => Input::DriverFault,
        }
    }
}

impl std::fmt::Display for Forced {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let on = |b: bool| if b { "on" } else { "off" };
        match *self {
            Forced::V1(v) | Forced::V2(v) | Forced::I(v) => write!(f, "{v}"),
            Forced::RpmM(w) | Forced::RpmL(w) | Forced::Ldr(w) => write!(f, "{w}"),
            Forced::Hall(c) => write!(f, "{c} (0b{c:03b})"),
            Forced::Flag(b) | Forced::DriverFault(b) => f.write_str(on(b)),
        }
    }
}

/// The flag forced: in the beam or not, and the photoresistor's reading
/// for it (the plant's steady shaded or lit level, worked out when forced).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FlagForce {
    pub in_beam: bool,
    /// The divider's volts (a sketch's analog pin) and their ADC counts.
    pub ldr_millivolts: u16,
    pub ldr_counts: u16,
}

/// Inputs forced by hand: measured values replaced before the firmware
/// samples them (`force v1 30.5`), or input words after it computed them.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Forces {
    /// Battery voltage V1 (V).
    pub v1: Option<f64>,
    /// DC-bus voltage V2 (V).
    pub v2: Option<f64>,
    /// Inverter current I (A).
    pub i: Option<f64>,
    /// RPM_M, RPM_L and LDR words (counts).
    pub rpm_m: Option<u16>,
    pub rpm_l: Option<u16>,
    pub ldr: Option<u16>,
    /// The hall sensors' code (bit 0 A, bit 1 B, bit 2 C).
    pub hall: Option<u8>,
    /// The paper flag in the photoresistor's beam, or out of it.
    pub flag: Option<FlagForce>,
    /// The motor driver's fault line.
    pub driver_fault: Option<bool>,
}

/// What is forced, as the console's `force` command names it:
/// `v1 30.0 V, rpm_m 1200`.
impl std::fmt::Display for Forces {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let measured = [
            ("v1", self.v1, "V"),
            ("v2", self.v2, "V"),
            ("i", self.i, "A"),
        ];
        let words = [
            ("rpm_m", self.rpm_m),
            ("rpm_l", self.rpm_l),
            ("ldr", self.ldr),
            ("hall", self.hall.map(u16::from)),
        ];
        let switches = [
            ("flag", self.flag.map(|f| f.in_beam)),
            ("driver_fault", self.driver_fault),
        ];
        let mut first = true;
        let mut sep = |f: &mut std::fmt::Formatter<'_>| {
            let s = if first { "" } else { ", " };
            first = false;
            f.write_str(s)
        };
        for (name, value, unit) in measured {
            if let Some(v) = value {
                sep(f)?;
                write!(f, "{name} {v:.2} {unit}")?;
            }
        }
        for (name, value) in words {
            if let Some(v) = value {
                sep(f)?;
                write!(f, "{name} {v}")?;
            }
        }
        for (name, value) in switches {
            if let Some(v) = value {
                sep(f)?;
                write!(f, "{name} {}", if v { "on" } else { "off" })?;
            }
        }
        Ok(())
    }
}

impl Forces {
    /// Whether anything is forced.
    pub fn any(&self) -> bool {
        *self != Forces::default()
    }

    /// Forces `value`; `light` is the module's photoresistor (the flag's
    /// levels come from it; without one the flag changes only ED0 bit 3).
    pub fn force(&mut self, value: Forced, light: Option<&plant::light::LightParams>) {
        match value {
            Forced::V1(v) => self.v1 = Some(v),
            Forced::V2(v) => self.v2 = Some(v),
            Forced::I(v) => self.i = Some(v),
            Forced::RpmM(w) => self.rpm_m = Some(w),
            Forced::RpmL(w) => self.rpm_l = Some(w),
            Forced::Ldr(w) => self.ldr = Some(w),
            Forced::Hall(c) => self.hall = Some(c & 0b111),
            Forced::Flag(in_beam) => {
                let volts = light.map_or(0.0, |p| {
                    if in_beam {
                        p.shaded_volts()
                    } else {
                        p.lit_volts()
                    }
                });
                self.flag = Some(FlagForce {
                    in_beam,
                    ldr_millivolts: (volts * 1000.0).round().clamp(0.0, 65535.0) as u16,
                    ldr_counts: light.map_or(0, |p| p.adc_counts_for(volts)),
                });
            }
            Forced::DriverFault(on) => self.driver_fault = Some(on),
        }
    }

    /// Returns `input` to the plant.
    pub fn release(&mut self, input: Input) {
        match input {
            Input::V1 => self.v1 = None,
            Input::V2 => self.v2 = None,
            Input::I => self.i = None,
            Input::RpmM => self.rpm_m = None,
            Input::RpmL => self.rpm_l = None,
            Input::Ldr => self.ldr = None,
            Input::Hall => self.hall = None,
            Input::Flag => self.flag = None,
            Input::DriverFault => self.driver_fault = None,
        }
    }

    pub(super) fn apply_sensors(
        &self,
        sensors: &mut plant::Sensors,
        s: &plant::params::SensingParams,
    ) {
        if let Some(v) = self.v1 {
            sensors.battery_volts = v;
            sensors.battery_counts = s.counts(v / s.battery_divider);
        }
        if let Some(v) = self.v2 {
            sensors.bus_volts = v;
            sensors.bus_counts = s.counts(v / s.bus_divider);
        }
        if let Some(a) = self.i {
            sensors.inverter_current = a;
            sensors.current_counts = s.counts(s.current_zero_volts + a * s.current_volts_per_amp);
        }
        if let Some(flag) = self.flag {
            // The detector then sees the flag come and go as a wheel would
            // show it: toggled by hand, RPM_L follows.
            sensors.flag_in_beam = flag.in_beam;
            sensors.ldr_volts = f64::from(flag.ldr_millivolts) / 1000.0;
            sensors.ldr_counts = flag.ldr_counts;
        }
        // LDR forced by its own word wins over the flag's level.
        if let Some(c) = self.ldr {
            sensors.ldr_counts = c;
        }
        if let Some(fault) = self.driver_fault {
            sensors.motor_tripped = fault;
        }
    }

    pub(super) fn apply_words(&self, image: &mut RegisterImage) {
        if let Some(w) = self.rpm_m {
            image.inputs[ea::RPM_M] = w;
        }
        if let Some(w) = self.rpm_l {
            image.inputs[ea::RPM_L] = w;
        }
        if let Some(flag) = self.flag {
            // ED0 bit 3 is the detector's verdict, and the adaptive one
            // forgets a flag held still in the beam: the bit the master
            // reads is the one set by hand, as on the tool's simulator.
            let dark = u16::from(flag.in_beam) << 3;
            image.hall = (image.hall & !(1 << 3)) | dark;
        }
    }
}

/// The hall lines as the controller sees them once a code has been forced:
/// held at the code set by hand, they change only when that code does, and
/// each line that changes is an edge the controller counts (RPM_M follows
/// the hand, as on the bench's lines); released, they are the motor's again,
/// counted on from where the controller was, so no burst of the edges the
/// motor made meanwhile.
#[derive(Debug, Clone, Copy)]
pub struct HallLines {
    /// A code has been forced since power-up: the lines are counted here.
    touched: bool,
    /// The lines were held at a forced code at the last tick.
    held: bool,
    /// The code, edge count and latest edge time the controller saw last.
    code: u8,
    count: u64,
    edge_at: f64,
    /// The controller's count minus the motor's, once released (wrapping).
    offset: u64,
}

impl Default for HallLines {
    fn default() -> Self {
        Self {
            touched: false,
            held: false,
            code: 0,
            count: 0,
            edge_at: f64::NAN,
            offset: 0,
        }
    }
}

impl HallLines {
    /// The lines at `now` (s): the motor's in `shaft`, replaced by what the
    /// controller sees with `forced` held (or released).
    pub fn apply(&mut self, forced: Option<u8>, now: f64, shaft: &mut plant::shaft::ShaftReading) {
        if !self.touched {
            if forced.is_none() {
                return;
            }
            self.touched = true;
            self.code = shaft.hall;
            self.count = shaft.hall_edges;
            self.edge_at = shaft.last_hall_edge_at;
        }
        let to = |code: u8, lines: &mut Self| {
            let changes = u64::from((lines.code ^ code).count_ones());
            if changes > 0 {
                lines.count = lines.count.wrapping_add(changes);
                lines.edge_at = now;
                lines.code = code;
            }
        };
        match forced {
            Some(code) => {
                to(code & 0b111, self);
                self.held = true;
            }
            None => {
                if self.held {
                    // Released: each line that differs from the motor's
                    // changes once.
                    to(shaft.hall, self);
                    self.offset = self.count.wrapping_sub(shaft.hall_edges);
                    self.held = false;
                }
                self.count = shaft.hall_edges.wrapping_add(self.offset);
                self.code = shaft.hall;
                if self.edge_at.is_nan() || shaft.last_hall_edge_at > self.edge_at {
                    self.edge_at = shaft.last_hall_edge_at;
                }
            }
        }
        shaft.hall = self.code;
        shaft.hall_edges = self.count;
        shaft.last_hall_edge_at = self.edge_at;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_input_is_checked_and_says_its_range() {
        assert_eq!(Input::parse("V1"), Ok(Input::V1));
        assert!(matches!(Input::parse("v9"), Err(ForceError::Unknown(_))));
        let e = Input::V1.value(500.0).unwrap_err().to_string();
        assert_eq!(e, "500 V is out of range: V1 takes 0 to 100 V");
        let e = Input::Hall.value(8.0).unwrap_err().to_string();
        assert!(e.contains("0 to 7"), "{e}");
        assert_eq!(Input::Hall.value(5.0), Ok(Forced::Hall(5)));
        assert_eq!(Input::Flag.value_text("on"), Ok(Forced::Flag(true)));
        assert_eq!(
            Input::DriverFault.value_text("0"),
            Ok(Forced::DriverFault(false))
        );
        assert!(
            Input::RpmM
                .value(-3.0)
                .unwrap_err()
                .to_string()
                .contains("0 to 65535")
        );
        assert!(matches!(
            Input::V1.value_text("x"),
            Err(ForceError::NotANumber { .. })
        ));
    }

    #[test]
    fn digital_inputs_reach_the_sensors_and_ed0() {
        let light = plant::PlantParams::default().light;
        let mut forces = Forces::default();
        forces.force(Forced::Hall(0b101), None);
        forces.force(Forced::Flag(true), Some(&light));
        forces.force(Forced::DriverFault(true), None);
        let mut sensors = plant::Sensors::default();
        forces.apply_sensors(&mut sensors, &plant::params::SensingParams::default());
        HallLines::default().apply(forces.hall, 0.0, &mut sensors.shaft);
        assert_eq!(sensors.shaft.hall, 0b101);
        assert!(sensors.flag_in_beam && sensors.motor_tripped);
        assert_eq!(
            sensors.ldr_counts,
            light.adc_counts_for(light.shaded_volts())
        );
        assert!((sensors.ldr_volts - light.shaded_volts()).abs() < 1e-3);
        let mut image = RegisterImage::new(12, 12, 500, 100);
        forces.apply_words(&mut image);
        assert_eq!(image.hall & 0b1000, 0b1000);
        assert_eq!(forces.to_string(), "hall 5, flag on, driver_fault on");
        forces.release(Input::Flag);
        assert_eq!(forces.flag, None);
    }

    /// The motor at `code` with `edges` counted, its latest edge at `at`.
    fn shaft(code: u8, edges: u64, at: f64) -> plant::shaft::ShaftReading {
        plant::shaft::ShaftReading {
            hall: code,
            hall_edges: edges,
            last_hall_edge_at: at,
            ..Default::default()
        }
    }

    #[test]
    fn a_forced_hall_code_changes_by_hand_and_is_counted_as_edges() {
        let mut lines = HallLines::default();
        let seen = |lines: &mut HallLines, forced, now, motor| {
            let mut s = motor;
            lines.apply(forced, now, &mut s);
            (s.hall, s.hall_edges, s.last_hall_edge_at)
        };
        // Never forced: the motor's own lines.
        assert_eq!(
            seen(&mut lines, None, 0.5, shaft(1, 100, 0.4)),
            (1, 100, 0.4)
        );
        // 1 -> 3: one line changes, at the moment it is set.
        assert_eq!(
            seen(&mut lines, Some(3), 1.0, shaft(1, 100, 0.9)),
            (3, 101, 1.0)
        );
        // Held: the motor turns on, the controller sees nothing of it.
        assert_eq!(
            seen(&mut lines, Some(3), 1.5, shaft(5, 300, 1.49)),
            (3, 101, 1.0)
        );
        // 3 -> 4: three lines change.
        assert_eq!(
            seen(&mut lines, Some(4), 2.0, shaft(6, 400, 1.99)),
            (4, 104, 2.0)
        );
        // Released onto the motor's 6: one line changes, and the count goes
        // on from the controller's, not the motor's 500.
        assert_eq!(
            seen(&mut lines, None, 3.0, shaft(6, 500, 2.99)),
            (6, 105, 3.0)
        );
        assert_eq!(
            seen(&mut lines, None, 3.1, shaft(2, 501, 3.05)),
            (2, 106, 3.05)
        );
    }

    #[test]
    fn rpm_m_follows_a_hall_code_stepped_by_hand() {
        use nodes::firmware::HallRpm;
        use protocols::time::{SimDuration, SimTime};
        // One pole pair, no gear: 6 edges a turn. The sequence 1 3 2 6 4 5
        // changes one line a step; 60 steps a second is 10 turns a second.
        let mut hall = HallRpm::new(1, 1.0, SimDuration::from_millis(250));
        let mut lines = HallLines::default();
        let codes = [1, 3, 2, 6, 4, 5];
        let mut rpm = 0.0;
        for ms in 0..2000u64 {
            let now = ms as f64 / 1000.0;
            let code = codes[(ms / 16) as usize % 6];
            // The motor stands still at code 1 the whole time.
            let mut s = shaft(1, 0, f64::NAN);
            lines.apply(Some(code), now, &mut s);
            rpm = hall.tick(
                SimTime::ZERO + SimDuration::from_millis(ms),
                SimDuration::from_millis(100),
                &s,
            );
        }
        // A step every 16 ms: 62.5 edges/s, 625 rpm.
        assert!((rpm - 625.0).abs() < 25.0, "RPM_M {rpm}");
    }
}
