//! Placeholder: replaced by the full equivalent-circuit + BMS model.
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BatteryParams {
    pub capacity_ah: f64,
    pub ocv_volts: f64,
    pub r0_ohm: f64,
    pub initial_soc: f64,
}
impl Default for BatteryParams {
    fn default() -> Self {
        Self { capacity_ah: 10.0, ocv_volts: 37.0, r0_ohm: 0.15, initial_soc: 0.8 }
    }
}
impl BatteryParams {
    pub fn bench_supply_12v() -> Self {
        Self { capacity_ah: 1000.0, ocv_volts: 12.0, r0_ohm: 0.01, initial_soc: 1.0 }
    }
}
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BmsParams {}
impl BmsParams {
    pub fn bench_supply_12v() -> Self {
        Self {}
    }
}
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChargerParams {}
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum BmsTrip {
    UnderVoltage,
    OverVoltage,
    OverCurrent,
    ShortCircuit,
}
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BatteryStep {
    pub terminal_voltage: f64,
    pub charger_current: f64,
    pub net_current: f64,
    pub internal_loss: f64,
}
#[derive(Debug, Clone)]
pub struct Battery {
    p: BatteryParams,
    soc: f64,
    v: f64,
}
impl Battery {
    pub fn new(battery: &BatteryParams, _bms: &BmsParams, _charger: &ChargerParams) -> Self {
        Self { p: battery.clone(), soc: battery.initial_soc, v: battery.ocv_volts }
    }
    pub fn source_voltage(&self) -> f64 {
        self.p.ocv_volts
    }
    pub fn series_resistance(&self) -> f64 {
        self.p.r0_ohm
    }
    pub fn output_closed(&self) -> bool {
        true
    }
    pub fn step(&mut self, dt: f64, load_current: f64, _charger_connected: bool) -> BatteryStep {
        self.soc -= load_current * dt / (self.p.capacity_ah * 3600.0);
        self.v = self.p.ocv_volts - self.p.r0_ohm * load_current;
        BatteryStep {
            terminal_voltage: self.v,
            charger_current: 0.0,
            net_current: load_current,
            internal_loss: self.p.r0_ohm * load_current * load_current * dt,
        }
    }
    pub fn soc(&self) -> f64 {
        self.soc
    }
    pub fn terminal_voltage(&self) -> f64 {
        self.v
    }
    pub fn trip(&self) -> Option<BmsTrip> {
        None
    }
    pub fn charging(&self) -> bool {
        false
    }
    pub fn reset_trip(&mut self) {}
}
