//! The PWM-capture paper's link in scenario files, and the parallel
//! modules that use it:
//!
//! ```toml
//! [[bus]]
//! name = "pwm"
//! medium = "pwmcap"           # serial (default) | pwmcap
//! [bus.pwmcap]                # every field optional; these are the defaults
//! clock_hz = 150000000        # PWM and capture counter
//! data_bits = 8
//! dummy_bits = 2
//! start_ticks = 200
//! guard_ticks = 0             # extra OFF ticks per symbol (the paper has none)
//! duplex = "half"             # half (one pair, enable signal) | full (two pairs)
//! cable_m = 10.0
//! added_series_ohm = 0.0
//! added_shunt_nf = 0.0
//! noise_mv = 0.5              # comparator input noise, rms
//! calibrate = false           # true: find start and guard at initialisation
//! cable_model = "lumped"      # lumped | elmore (distributed RC, Elmore-delay pole)
//!
//! [[node]]
//! kind = "parallel-master"    # the master module: speed loop on its own wheel, VEL to the slaves
//! name = "master"
//! bus = "pwm"
//! module = "ev1"
//! link = "pwmcap-designated"  # pwmcap-broadcast | pwmcap-designated | modbus-rtu
//! slaves = [2, 3]
//! kp = 0.45
//! ki = 2.5
//! set_points = [[0.2, 1500.0]]
//!
//! [[node]]
//! kind = "pwm-slave"          # a slave module's controller on the PWM link
//! name = "ev2"
//! bus = "pwm"
//! module = "ev2"
//! id = 2
//! addressing = "designated"   # broadcast | designated, as the master sends
//! ```

use nodes::link::{PortId, PwmBusConfig, PwmDuplex, PwmLineParams};
use protocols::pwmcap::PwmCoding;
use serde::{Deserialize, Serialize};

/// What a `[[bus]]` is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MediumSpec {
    /// The simulated RS-485 serial bus.
    #[default]
    Serial,
    /// The PWM-capture paper's link.
    Pwmcap,
}

impl MediumSpec {
    pub fn is_serial(&self) -> bool {
        *self == MediumSpec::Serial
    }
}

/// Half or full duplex.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DuplexSpec {
    #[default]
    Half,
    Full,
}

/// The `[bus.pwmcap]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PwmcapSpec {
    pub clock_hz: u32,
    pub data_bits: u8,
    pub dummy_bits: u8,
    pub start_ticks: u32,
    pub guard_ticks: u32,
    pub duplex: DuplexSpec,
    pub cable_m: f64,
    pub added_series_ohm: f64,
    pub added_shunt_nf: f64,
    pub noise_mv: f64,
    /// Find the start width and guard gap the line needs at initialisation
    /// (training frames through the line, `PwmCalibration::find`) and use
    /// them instead of `start_ticks` and `guard_ticks`.
    pub calibrate: bool,
    /// `lumped` (default) or `elmore`: the cable as a distributed RC line.
    pub cable_model: CableModelSpec,
}

/// How the cable's R and C make the line's pole.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CableModelSpec {
    #[default]
    Lumped,
    Elmore,
}

impl Default for PwmcapSpec {
    fn default() -> Self {
        let coding = PwmCoding::PAPER;
        let line = PwmLineParams::DEFAULT;
        PwmcapSpec {
            clock_hz: coding.clock_hz(),
            data_bits: coding.data_bits(),
            dummy_bits: coding.dummy_bits(),
            start_ticks: coding.start_ticks(),
            guard_ticks: 0,
            duplex: DuplexSpec::Half,
            cable_m: line.cable_length_m,
            added_series_ohm: line.added_series_ohm,
            added_shunt_nf: line.added_shunt_farad * 1e9,
            noise_mv: line.noise_volts_rms * 1e3,
            calibrate: false,
            cable_model: CableModelSpec::Lumped,
        }
    }
}

impl PwmcapSpec {
    /// The coding, or what is wrong with it as (field, message).
    pub fn coding(&self) -> Result<PwmCoding, (String, String)> {
        if self.clock_hz == 0
            || !protocols::time::TICKS_PER_SECOND.is_multiple_of(u64::from(self.clock_hz))
        {
            return Err((
                "clock_hz".into(),
                format!(
                    "{} does not divide 72 GHz: use e.g. 150000000 or 100000000",
                    self.clock_hz
                ),
            ));
        }
        let coding = PwmCoding::new(self.clock_hz, self.data_bits, self.dummy_bits, self.start_ticks)
            .map_err(|_| {
                (
                    "data_bits".into(),
                    "with dummy_bits must be 8–16 data bits, at most 24 in all, and start_ticks at least 1".into(),
                )
            })?;
        if coding.data_bits() < 8 {
            return Err((
                "data_bits".into(),
                "must be at least 8 to carry VEL in two symbols".into(),
            ));
        }
        Ok(coding)
    }

    /// The link's configuration (master port for full duplex), or what is wrong.
    pub fn bus_config(
        &self,
        seed: u64,
        master: Option<usize>,
    ) -> Result<PwmBusConfig, (String, String)> {
        let coding = self.coding()?;
        let mut line = PwmLineParams::DEFAULT;
        line.cable_length_m = self.cable_m;
        line.added_series_ohm = self.added_series_ohm;
        line.added_shunt_farad = self.added_shunt_nf * 1e-9;
        line.noise_volts_rms = self.noise_mv * 1e-3;
        line.cable_model = match self.cable_model {
            CableModelSpec::Lumped => nodes::link::CableModel::Lumped,
            CableModelSpec::Elmore => nodes::link::CableModel::Elmore,
        };
        let field = |name: &str| match name {
            "cable_length_m" => "cable_m",
            "added_shunt_farad" => "added_shunt_nf",
            "noise_volts_rms" => "noise_mv",
            "added_series_ohm" => "added_series_ohm",
            _ => "cable_m",
        };
        if let Err(nodes::link::PwmLineError::InvalidParameter(name)) = line.validate() {
            return Err((
                field(name).into(),
                "must be a finite number, not negative".into(),
            ));
        }
        let duplex = match (self.duplex, master) {
            (DuplexSpec::Half, _) => PwmDuplex::Half,
            (DuplexSpec::Full, Some(m)) => PwmDuplex::Full {
                master: PortId(m as u16),
            },
            (DuplexSpec::Full, None) => {
                return Err((
                    "duplex".into(),
                    "full needs a parallel-master node on the bus".into(),
                ));
            }
        };
        Ok(PwmBusConfig {
            coding,
            guard_ticks: self.guard_ticks,
            line,
            duplex,
            seed,
        })
    }
}

/// How a parallel master reaches its slaves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ParallelLinkSpec {
    PwmcapBroadcast,
    PwmcapDesignated,
    ModbusRtu,
}

impl ParallelLinkSpec {
    pub fn is_pwm(self) -> bool {
        self != ParallelLinkSpec::ModbusRtu
    }
}

/// Which frames a PWM slave expects.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AddressingSpec {
    Broadcast,
    Designated,
}
