//! Every parameter of the bench in one serde struct, its two presets, and
//! loading from TOML with errors that name the file, line and field.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use toml::Spanned;
use toml::de::DeValue;

use crate::battery::{BatteryParams, BmsParams, ChargerParams};
use crate::converter::ConverterParams;
use crate::light::LightParams;
use crate::motor::MotorParams;
use crate::toml_errors;
use crate::wheel::{GearboxParams, WheelParams};

/// How the module's controller board scales V1, V2 and I onto its 0–5 V ADC
/// pins (the M3CVME paper, Fig. 7: "Min=0V. Max=5V. ADC=12 bits").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SensingParams {
    /// Battery-voltage divider ratio (pack volts per pin volt): 10:1 puts a
    /// full 42 V pack at 4.2 V.
    pub battery_divider: f64,
    /// Bus-voltage divider ratio: 11:1 keeps the 48 V boosted bus under 5 V.
    pub bus_divider: f64,
    /// Hall current sensor on the inverter input (V per A), ACS712-20A class.
    pub current_volts_per_amp: f64,
    /// Current-sensor output at 0 A (V): offset so regenerative current reads.
    pub current_zero_volts: f64,
    /// ADC resolution (bits) and reference (V).
    pub adc_bits: u32,
    pub adc_reference_volts: f64,
}

impl Default for SensingParams {
    fn default() -> Self {
        Self {
            battery_divider: 10.0,
            bus_divider: 11.0,
            current_volts_per_amp: 0.1,
            current_zero_volts: 2.5,
            adc_bits: 12,
            adc_reference_volts: 5.0,
        }
    }
}

impl SensingParams {
    /// Counts for a pin voltage, clamped to the converter's range.
    pub fn counts(&self, pin_volts: f64) -> u16 {
        let full = f64::from((1u32 << self.adc_bits.min(16)) - 1);
        (pin_volts / self.adc_reference_volts * full)
            .round()
            .clamp(0.0, full) as u16
    }
}

/// The whole bench. Defaults are the `vemodule` preset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlantParams {
    pub battery: BatteryParams,
    pub bms: BmsParams,
    pub charger: ChargerParams,
    pub converter: ConverterParams,
    pub motor: MotorParams,
    pub gearbox: GearboxParams,
    pub wheel: WheelParams,
    pub light: LightParams,
    pub sensing: SensingParams,
    /// Longest electrical sub-step (s). The RL and RC states are advanced
    /// exactly, so this only bounds how stale the bus voltage and shaft speed
    /// are inside a sub-step, and the timestamp resolution of nothing: edges
    /// are interpolated.
    pub electrical_step_s: f64,
}

impl Default for PlantParams {
    fn default() -> Self {
        Self {
            battery: BatteryParams::default(),
            bms: BmsParams::default(),
            charger: ChargerParams::default(),
            converter: ConverterParams::default(),
            motor: MotorParams::default(),
            gearbox: GearboxParams::default(),
            wheel: WheelParams::default(),
            light: LightParams::default(),
            sensing: SensingParams::default(),
            electrical_step_s: 1.0e-3,
        }
    }
}

/// Names of the built-in presets, for help texts.
pub const PRESETS: [&str; 2] = ["vemodule", "controller-network"];

impl PlantParams {
    /// The M3CVME tool's EV module: 36 V pack, buck-boost, BLDC, 12-bit ADC.
    pub fn vemodule() -> Self {
        Self::default()
    }

    /// The Controller_network bench: 12 V supply, geared DC motor with a 7-pulse
    /// encoder, ≈ 100:1 gearbox, light sensor on a 10-bit ADC.
    pub fn controller_network() -> Self {
        Self {
            battery: BatteryParams::bench_supply_12v(),
            bms: BmsParams::bench_supply_12v(),
            charger: ChargerParams::bench_supply_12v(),
            converter: ConverterParams {
                regulated_bus_volts: 12.0,
                ..Default::default()
            },
            motor: MotorParams::controller_network(),
            gearbox: GearboxParams { ratio: 100.0 },
            wheel: WheelParams::controller_network(),
            light: LightParams::controller_network(),
            sensing: SensingParams {
                battery_divider: 3.0,
                bus_divider: 3.0,
                current_volts_per_amp: 0.185,
                current_zero_volts: 2.5,
                adc_bits: 10,
                adc_reference_volts: 5.0,
            },
            ..Self::default()
        }
    }

    /// A preset by name.
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "vemodule" => Some(Self::vemodule()),
            "controller-network" => Some(Self::controller_network()),
            _ => None,
        }
    }

    /// Parameters from TOML text: the fields the text names override `base`.
    /// `file` is only used in error messages.
    pub fn from_toml(text: &str, file: &Path, base: &Self) -> Result<Self, ParamsError> {
        let root = toml_errors::parse(text).map_err(|e| ParamsError::Syntax {
            file: file.to_path_buf(),
            at: e.span.map(|s| toml_errors::line_col(text, s.start)),
            message: e.message,
        })?;
        Self::from_toml_value(&root, text, file, base)
    }

    /// The same for a table inside a larger document (a scenario's module
    /// `params`): `text` is the whole document, so errors give its lines.
    pub fn from_toml_value(
        root: &Spanned<DeValue<'_>>,
        text: &str,
        file: &Path,
        base: &Self,
    ) -> Result<Self, ParamsError> {
        let at = |span: Option<std::ops::Range<usize>>| {
            span.map(|s| toml_errors::line_col(text, s.start))
        };
        // Type-check the text against the struct first: errors carry the
        // span of the offending key or value.
        if let Err(e) = toml_errors::deserialize::<PlantParams>(root) {
            let last = e.path.rsplit('.').next().unwrap_or_default();
            let message = if last.is_empty() || e.message.contains(&format!("`{last}`")) {
                e.message
            } else {
                format!("`{}`: {}", e.path, e.message)
            };
            return Err(ParamsError::Syntax {
                file: file.to_path_buf(),
                at: at(e.span),
                message,
            });
        }
        let overrides: toml::Table =
            toml_errors::deserialize(root).map_err(|e| ParamsError::Syntax {
                file: file.to_path_buf(),
                at: at(e.span),
                message: e.message,
            })?;
        let mut merged = toml::Table::try_from(base).map_err(|e| ParamsError::Syntax {
            file: file.to_path_buf(),
            at: None,
            message: e.to_string(),
        })?;
        merge(&mut merged, overrides);
        let params: Self =
            toml::Value::Table(merged)
                .try_into()
                .map_err(|e: toml::de::Error| ParamsError::Syntax {
                    file: file.to_path_buf(),
                    at: None,
                    message: toml_errors::in_words(e.message().trim()),
                })?;
        params
            .validate()
            .map_err(|(field, message)| ParamsError::Invalid {
                file: file.to_path_buf(),
                at: at(toml_errors::span_of(root, &field)),
                field,
                message,
            })?;
        Ok(params)
    }

    /// Physical sanity: every value a model divides by or takes a log of.
    pub fn validate(&self) -> Result<(), (String, String)> {
        let positive = [
            (
                "converter.bus_capacitance_farad",
                self.converter.bus_capacitance_farad,
            ),
            ("converter.bleeder_ohm", self.converter.bleeder_ohm),
            (
                "converter.pass_through_ohm",
                self.converter.pass_through_ohm,
            ),
            (
                "converter.regulation_droop_ohm",
                self.converter.regulation_droop_ohm,
            ),
            ("converter.efficiency", self.converter.efficiency),
            ("motor.resistance_ohm", self.motor.resistance_ohm),
            ("motor.inductance_henry", self.motor.inductance_henry),
            ("motor.torque_constant", self.motor.torque_constant),
            ("gearbox.ratio", self.gearbox.ratio),
            ("wheel.mass_kg", self.wheel.mass_kg),
            ("wheel.radius_m", self.wheel.radius_m),
            ("wheel.step_s", self.wheel.step_s),
            ("electrical_step_s", self.electrical_step_s),
            (
                "sensing.adc_reference_volts",
                self.sensing.adc_reference_volts,
            ),
        ];
        for (field, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err((
                    field.into(),
                    format!("must be a positive number, got {value}"),
                ));
            }
        }
        let battery_checks = [
            ("battery", self.battery.validate()),
            ("bms", self.bms.validate()),
            ("charger", self.charger.validate()),
        ];
        for (section, check) in battery_checks {
            if let Err(e) = check {
                use crate::battery::BatteryConfigError as E;
                return Err(match e {
                    E::OutOfRange {
                        field,
                        value,
                        expected,
                    } => (
                        format!("{section}.{field}"),
                        format!("must be {expected}, got {value}"),
                    ),
                    other => (section.to_string(), other.to_string()),
                });
            }
        }
        if let Err(e) = self.light.validate() {
            let message = format!("must be {}, got {}", e.requirement, e.value);
            return Err((format!("light.{}", e.field), message));
        }
        if self.converter.efficiency > 1.0 {
            return Err(("converter.efficiency".into(), "must be at most 1".into()));
        }
        if self.motor.pole_pairs == 0 {
            return Err(("motor.pole_pairs".into(), "must be at least 1".into()));
        }
        if !(1..=16).contains(&self.sensing.adc_bits) {
            return Err(("sensing.adc_bits".into(), "must be 1 to 16".into()));
        }
        if self.wheel.step_s > 0.05 || self.electrical_step_s > 0.01 {
            return Err((
                "wheel.step_s".into(),
                "steps longer than 50 ms (wheel) or 10 ms (electrical) are not supported".into(),
            ));
        }
        Ok(())
    }

    /// Load a parameter file over `base`.
    pub fn load(path: &Path, base: &Self) -> Result<Self, ParamsError> {
        let text = std::fs::read_to_string(path).map_err(|source| ParamsError::Read {
            file: path.to_path_buf(),
            source,
        })?;
        Self::from_toml(&text, path, base)
    }
}

/// Why a parameter file was refused.
#[derive(Debug, thiserror::Error)]
pub enum ParamsError {
    // The reason is the source, which error reports print after this.
    #[error("cannot read {}", file.display())]
    Read {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{}{}: {message}", file.display(), fmt_at(*at))]
    Syntax {
        file: PathBuf,
        at: Option<(usize, usize)>,
        message: String,
    },
    #[error("{}{}: field `{field}` {message}", file.display(), fmt_at(*at))]
    Invalid {
        file: PathBuf,
        at: Option<(usize, usize)>,
        field: String,
        message: String,
    },
}

fn fmt_at(at: Option<(usize, usize)>) -> String {
    at.map_or_else(String::new, |(line, col)| format!(":{line}:{col}"))
}

/// Deep-merge `overrides` into `base`: tables merge, everything else replaces.
fn merge(base: &mut toml::Table, overrides: toml::Table) {
    for (key, value) in overrides {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(key, v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_round_trip_through_toml() {
        for name in PRESETS {
            let p = PlantParams::preset(name).expect("preset exists");
            let text = toml::to_string(&p).expect("serialises");
            let back = PlantParams::from_toml(&text, Path::new("x.toml"), &PlantParams::vemodule())
                .expect("parses");
            assert_eq!(back, p, "{name}");
        }
    }

    #[test]
    fn overrides_apply_on_top_of_the_base_preset() {
        let text = "[motor]\npole_pairs = 2\n";
        let base = PlantParams::controller_network();
        let p = PlantParams::from_toml(text, Path::new("p.toml"), &base).expect("parses");
        assert_eq!(p.motor.pole_pairs, 2);
        assert_eq!(p.gearbox.ratio, 100.0, "untouched fields keep the preset");
    }

    #[test]
    fn errors_name_file_line_and_field() {
        let text = "[wheel]\nmass_kg = 1.0\n\n[motor]\nresistance_ohms = 0.4\n";
        let e = PlantParams::from_toml(text, Path::new("bench.toml"), &PlantParams::default())
            .expect_err("unknown field");
        let msg = e.to_string();
        assert!(msg.starts_with("bench.toml:5:"), "{msg}");
        assert!(msg.contains("resistance_ohms"), "{msg}");

        let text = "[motor]\nresistance_ohm = \"low\"\n";
        let msg = PlantParams::from_toml(text, Path::new("b.toml"), &PlantParams::default())
            .expect_err("wrong type")
            .to_string();
        assert!(msg.starts_with("b.toml:2:"), "{msg}");

        assert!(
            msg.contains("`motor.resistance_ohm`: expected a number"),
            "{msg}"
        );
        assert!(!msg.contains("f64"), "{msg}");

        let text = "[motor]\npole_pairs = 2.5\n";
        let msg = PlantParams::from_toml(text, Path::new("b.toml"), &PlantParams::default())
            .expect_err("not an integer")
            .to_string();
        assert_eq!(
            msg,
            "b.toml:2:14: `motor.pole_pairs`: expected an integer of 0 or more, found 2.5"
        );

        let text = "# bench\n[wheel]\nmass_kg = -1.0\n";
        let msg = PlantParams::from_toml(text, Path::new("c.toml"), &PlantParams::default())
            .expect_err("negative mass")
            .to_string();
        assert_eq!(
            msg,
            "c.toml:3:1: field `wheel.mass_kg` must be a positive number, got -1"
        );
    }
}
