//! Placeholder: replaced by the full flag + lamp + CdS + divider + ADC model.
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LightParams {
    pub flag_arc_deg: f64,
    pub adc_bits: u32,
    pub lit_volts: f64,
    pub dark_volts: f64,
}
impl Default for LightParams {
    fn default() -> Self {
        Self { flag_arc_deg: 30.0, adc_bits: 12, lit_volts: 4.0, dark_volts: 1.0 }
    }
}
impl LightParams {
    pub fn controller_network() -> Self {
        Self { adc_bits: 10, ..Self::default() }
    }
}
#[derive(Debug, Clone)]
pub struct LightSensor {
    p: LightParams,
    v: f64,
    in_beam: bool,
}
impl LightSensor {
    pub fn new(params: &LightParams, _seed: u64) -> Self {
        Self { p: params.clone(), v: params.lit_volts, in_beam: false }
    }
    pub fn step(&mut self, _t: f64, _dt: f64, _angle_start: f64, angle_end: f64) {
        let deg = angle_end.to_degrees().rem_euclid(360.0);
        self.in_beam = deg < self.p.flag_arc_deg / 2.0 || deg > 360.0 - self.p.flag_arc_deg / 2.0;
        self.v = if self.in_beam { self.p.dark_volts } else { self.p.lit_volts };
    }
    pub fn divider_voltage(&self) -> f64 {
        self.v
    }
    pub fn adc_counts(&self) -> u16 {
        let full = (1u32 << self.p.adc_bits) - 1;
        ((self.v / 5.0) * full as f64).round().clamp(0.0, full as f64) as u16
    }
    pub fn flag_in_beam(&self) -> bool {
        self.in_beam
    }
    pub fn ldr_resistance(&self) -> f64 {
        0.0
    }
}
pub fn fixed_threshold_max_rpm(_params: &LightParams, _threshold_volts: f64) -> f64 {
    0.0
}
