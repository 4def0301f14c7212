//! Inputs forced from the console (`force v1 30.5`): measured values
//! replaced before the firmware samples them, or input words after it
//! computed them. The plant itself is untouched.

use nodes::firmware::{RegisterImage, ea};

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
        Ok(())
    }
}

impl Forces {
    /// Whether anything is forced.
    pub fn any(&self) -> bool {
        *self != Forces::default()
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
        if let Some(c) = self.ldr {
            sensors.ldr_counts = c;
        }
    }

    pub(super) fn apply_words(&self, image: &mut RegisterImage) {
        if let Some(w) = self.rpm_m {
            image.inputs[ea::RPM_M] = w;
        }
        if let Some(w) = self.rpm_l {
            image.inputs[ea::RPM_L] = w;
        }
    }
}
