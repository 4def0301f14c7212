//! The EV module controller (as in the M3CVME tool): register image, MEB and Modbus RTU slave front ends, and the firmware loop.
//!
//! [`EvController`] is both a [`Node`] (a slave on the bus: requests in,
//! replies out) and a [`Firmware`] (the loop that samples the module's
//! sensors and drives its pins). The two halves meet in one
//! [`RegisterImage`]: a write is stored and acknowledged as soon as its
//! request has arrived, and the loop applies everything stored at its next
//! tick, so all words of one write reach the pins together, one loop period
//! at most after the acknowledgement.

mod estimators;
mod frontend;
mod image;
mod meb_map;
mod meb_slave;
mod modbus_slave;
mod readings;

use std::collections::VecDeque;

use plant::battery::BmsTrip;
use plant::params::SensingParams;
use plant::{Actuators, PlantParams, Sensors};

use crate::node::{Firmware, MAX_FRAME, Node, NodeEvent};
use protocols::meb::{MebDecodeError, MebDecoder, MebRepr};
use protocols::modbus::Adu;
use protocols::modbus::MAX_PDU_LEN;
use protocols::modbus::rtu::{self, Direction, RtuDecoder};
use protocols::modbus::serial::{Timing, standard_rtu_silence};
use protocols::time::{SimDuration, SimTime};

pub use estimators::{HallRpm, LightDetectorConfig, LightRpm};
pub use frontend::{Framing, FrontendStats, SlaveFrontend};
pub use image::{EA_WORDS, Protection, Refusal, RegisterImage, Settings, WriteSet, ea, sd, status};
pub use meb_map::{MapError, MebMap, TAGS, block_name};
pub use modbus_slave::{COILS, DISCRETE_INPUTS, HOLDING_REGISTERS, INPUT_REGISTERS};
pub use readings::Readings;

/// Events kept for [`Node::poll_event`] before the oldest is dropped, so an
/// engine that never drains them cannot make the controller grow.
const MAX_PENDING_EVENTS: usize = 64;

/// Which protocol the controller's serial port speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SlaveProtocol {
    /// MEB (`docs/protocols/meb.md`).
    #[default]
    Meb,
    /// Modbus RTU with the map of `docs/protocols/modbus-map.md`.
    ModbusRtu,
}

/// The converters behind the analog words (`docs/protocols/meb.md`, "default scaling").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MebScaling {
    /// ADC resolution (bits): the range of `LDR_TH`.
    pub adc_bits: u8,
    /// DAC resolution (bits): the range of `VEL`.
    pub dac_bits: u8,
    /// DAC output at full scale (V).
    pub dac_full_scale_volts: f64,
}

impl Default for MebScaling {
    /// 12-bit ADC and DAC, 0–5 V (paper, Fig. 7).
    fn default() -> Self {
        Self {
            adc_bits: 12,
            dac_bits: 12,
            dac_full_scale_volts: 5.0,
        }
    }
}

/// Everything the controller is configured with.
#[derive(Debug, Clone, PartialEq)]
pub struct EvControllerConfig {
    /// MEB slave number or Modbus unit id.
    pub slave_id: u8,
    /// What the serial port speaks.
    pub protocol: SlaveProtocol,
    /// Time between loop ticks.
    pub loop_period: SimDuration,
    /// Converter ranges.
    pub scaling: MebScaling,
    /// Light dip detector, including `LDR_TH` and `LDR_ADAPT` at power-up.
    pub light: LightDetectorConfig,
    /// `RPM_WIN` at power-up (ms).
    pub rpm_window_ms: u16,
    /// Motor pole pairs: 6 hall edges per pole pair per motor turn.
    pub pole_pairs: u32,
    /// Motor turns per wheel turn.
    pub gear_ratio: f64,
    /// No hall edge for this long and RPM_M reads 0.
    pub hall_timeout: SimDuration,
    /// Enabled with VEL > 0 and RPM_M = 0 for longer than this: stalled.
    pub stall_after: SimDuration,
    /// After an over-current trip, the cause persists while the winding
    /// current is above this (A): the back-EMF is driving current through the
    /// freewheeling diodes.
    pub over_current_release_amps: f64,
    /// The line silence that ends a Modbus RTU frame.
    pub modbus_silence: SimDuration,
    /// The dividers and sensors in front of the ADC: how V1, V2 and I
    /// counts convert to volts and amperes ([`EvController::readings`]).
    pub sensing: SensingParams,
}

impl Default for EvControllerConfig {
    fn default() -> Self {
        Self {
            slave_id: 1,
            protocol: SlaveProtocol::Meb,
            loop_period: SimDuration::from_millis(1),
            scaling: MebScaling::default(),
            light: LightDetectorConfig::default(),
            rpm_window_ms: 100,
            pole_pairs: 4,
            gear_ratio: 1.0,
            hall_timeout: SimDuration::from_millis(250),
            stall_after: SimDuration::from_millis(500),
            over_current_release_amps: 1.0,
            modbus_silence: standard_rtu_silence(115_200, 10),
            sensing: SensingParams::default(),
        }
    }
}

impl EvControllerConfig {
    /// The defaults, with the motor, gearbox and light sensor of `params`.
    pub fn for_plant(params: &PlantParams) -> Self {
        Self {
            pole_pairs: params.motor.pole_pairs,
            gear_ratio: params.gearbox.ratio,
            light: LightDetectorConfig::for_sensor(&params.light),
            sensing: params.sensing.clone(),
            ..Self::default()
        }
    }
}

/// The EV module's controller board: an MEB or Modbus RTU slave and the loop
/// that drives the module.
#[derive(Debug)]
pub struct EvController {
    config: EvControllerConfig,
    image: RegisterImage,
    /// What the loop applied at its last tick.
    applied: Settings,
    meb: MebDecoder,
    rtu: RtuDecoder,
    /// The reply waiting for [`Node::poll_transmit`]; one at a time, as a
    /// single UART transmit buffer holds.
    tx: [u8; MAX_FRAME],
    tx_len: usize,
    hall: HallRpm,
    light: LightRpm,
    stalled_since: Option<SimTime>,
    events: VecDeque<NodeEvent>,
    /// Every request refused with this (an injected fault).
    forced: Option<Refusal>,
}

impl EvController {
    /// A controller at power-up: outputs off, nothing sampled yet.
    pub fn new(config: EvControllerConfig) -> Self {
        let mut image = RegisterImage::new(
            config.scaling.dac_bits,
            config.scaling.adc_bits,
            config.light.threshold_counts,
            config.rpm_window_ms,
        );
        if config.light.adaptive {
            image.stored.ldr_adaptive = image::LDR_ADAPT;
        }
        Self {
            applied: image.stored,
            image,
            meb: MebDecoder::new(),
            rtu: RtuDecoder::new(Direction::Request, Timing::Silence(config.modbus_silence)),
            tx: [0; MAX_FRAME],
            tx_len: 0,
            hall: HallRpm::new(config.pole_pairs, config.gear_ratio, config.hall_timeout),
            light: LightRpm::new(config.light, config.loop_period),
            stalled_since: None,
            events: VecDeque::with_capacity(MAX_PENDING_EVENTS),
            forced: None,
            config,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &EvControllerConfig {
        &self.config
    }

    /// The register image as the slave serves it.
    pub fn image(&self) -> &RegisterImage {
        &self.image
    }

    /// The register image, lent to front ends that serve it over other links
    /// ([`SlaveFrontend`]).
    pub fn image_mut(&mut self) -> &mut RegisterImage {
        &mut self.image
    }

    /// Stores a write as a slave front end would (range and trip checks
    /// included): for a controller that gets its settings over another link
    /// than its serial port (the PWM-capture paper's link). It takes
    /// effect at the next loop tick.
    pub fn store(&mut self, set: &WriteSet) -> Result<(), Refusal> {
        self.image.store(set)
    }

    /// What the controller reads now, its words converted with its scaling.
    pub fn readings(&self) -> Readings {
        Readings::of(&self.image, &self.config.sensing)
    }

    /// The settings the loop applied at its last tick.
    pub fn applied(&self) -> &Settings {
        &self.applied
    }

    /// `VEL` counts to volts at the DAC's output.
    fn vel_volts(&self, vel: u16) -> f64 {
        let full = f64::from(self.image.dac_max().max(1));
        f64::from(vel.min(self.image.dac_max())) / full * self.config.scaling.dac_full_scale_volts
    }

    fn push_event(&mut self, at: SimTime, kind: &'static str, detail: String) {
        if self.events.len() >= MAX_PENDING_EVENTS {
            self.events.pop_front();
        }
        self.events.push_back(NodeEvent { at, kind, detail });
    }

    /// Frames dropped for bad form or check on every protocol, saturating.
    fn refresh_errs(&mut self) {
        let drops = self.rtu.drops();
        let rtu = drops.bad_check.events
            + drops.timed_out.events
            + drops.oversize.events
            + drops.malformed.events;
        let total = self.meb.stats().dropped_frames().saturating_add(rtu);
        self.image.errs = u16::try_from(total).unwrap_or(u16::MAX);
    }

    fn queue_reply(&mut self, at: SimTime, reply: Result<usize, &'static str>) {
        match reply {
            Ok(len) => self.tx_len = len,
            Err(why) => {
                self.tx_len = 0;
                self.push_event(at, "dropped", why.into());
            }
        }
    }

    fn handle_meb(&mut self, now: SimTime, bytes: &[u8]) {
        let mut rest = bytes;
        while !rest.is_empty() {
            let (used, event) = self.meb.push(now, rest);
            let event = event.map(|e| e.map(|frame| MebRepr::from_frame(&frame)));
            rest = rest.get(used..).unwrap_or_default();
            match event {
                None => {}
                Some(Ok(request)) => {
                    // A drop earlier in this chunk already shows in FA1.
                    self.refresh_errs();
                    let id = self.config.slave_id;
                    let reply = match self.forced {
                        Some(refusal) => meb_slave::refuse(id, &request, refusal),
                        None => meb_slave::serve(&mut self.image, id, &request),
                    };
                    if let Some(reply) = reply {
                        let len = reply.emit(&mut self.tx).map_err(|_| "reply too long");
                        self.queue_reply(now, len);
                    }
                }
                Some(Err(error)) => {
                    let detail = match error {
                        MebDecodeError::Malformed(kind) => kind.name(),
                        MebDecodeError::Interrupted => "interrupted",
                    };
                    self.push_event(now, "bad_check", detail.into());
                }
            }
        }
    }

    /// Serves the RTU frame the decoder just completed, if any.
    fn serve_rtu(&mut self, now: SimTime, unit: u8, pdu: &[u8]) {
        self.refresh_errs();
        let own = self.config.slave_id;
        let reply = match self.forced {
            Some(refusal) => modbus_slave::refuse(own, unit, pdu, refusal),
            None => modbus_slave::serve(&mut self.image, own, unit, pdu),
        };
        if let Some(reply) = reply {
            let len = rtu::RtuRepr {
                unit: own,
                pdu: &reply,
            }
            .emit(&mut self.tx)
            .map_err(|_| "reply too long");
            self.queue_reply(now, len);
        }
    }

    fn handle_rtu(&mut self, now: SimTime, bytes: &[u8]) {
        let mut input = bytes;
        let mut pdu = [0u8; MAX_PDU_LEN];
        loop {
            let frame = match self.rtu.decode(now, &mut input) {
                None => break,
                Some(Ok(frame)) => {
                    let len = frame.pdu().len().min(MAX_PDU_LEN);
                    pdu[..len].copy_from_slice(&frame.pdu()[..len]);
                    Some((frame.unit(), len))
                }
                Some(Err(_)) => None,
            };
            match frame {
                Some((unit, len)) => self.serve_rtu(now, unit, &pdu[..len]),
                None => self.push_event(now, "bad_check", "crc".into()),
            }
        }
    }
}

impl Node for EvController {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        match self.config.protocol {
            SlaveProtocol::Meb => self.handle_meb(now, bytes),
            SlaveProtocol::ModbusRtu => self.handle_rtu(now, bytes),
        }
        self.refresh_errs();
    }

    fn handle_timeout(&mut self, now: SimTime) {
        if self.config.protocol != SlaveProtocol::ModbusRtu {
            return;
        }
        let mut pdu = [0u8; MAX_PDU_LEN];
        let frame = match self.rtu.handle_timeout(now) {
            Some(Ok(frame)) => {
                let len = frame.pdu().len().min(MAX_PDU_LEN);
                pdu[..len].copy_from_slice(&frame.pdu()[..len]);
                Some((frame.unit(), len))
            }
            _ => None,
        };
        if let Some((unit, len)) = frame {
            self.serve_rtu(now, unit, &pdu[..len]);
        }
        self.refresh_errs();
    }

    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        let len = std::mem::take(&mut self.tx_len);
        if len == 0 {
            return None;
        }
        match (buf.get_mut(..len), self.tx.get(..len)) {
            (Some(out), Some(reply)) => {
                out.copy_from_slice(reply);
                Some(len)
            }
            _ => {
                self.push_event(now, "dropped", "transmit buffer too small".into());
                None
            }
        }
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        match self.config.protocol {
            SlaveProtocol::Meb => None,
            SlaveProtocol::ModbusRtu => self.rtu.poll_timeout(),
        }
    }

    fn poll_event(&mut self) -> Option<NodeEvent> {
        self.events.pop_front()
    }

    fn force_refusal(&mut self, refusal: Option<Refusal>) -> bool {
        self.forced = refusal;
        true
    }
}

impl Firmware for EvController {
    fn loop_period(&self) -> SimDuration {
        self.config.loop_period
    }

    fn loop_tick(&mut self, now: SimTime, sensors: &Sensors) -> Actuators {
        // Everything acknowledged since the last tick takes effect together.
        let cleared = self.image.protection.take_clear();
        self.applied = self.image.stored;
        let applied = self.applied;

        let inputs = &mut self.image.inputs;
        inputs[ea::V2] = sensors.bus_counts;
        inputs[ea::I] = sensors.current_counts;
        inputs[ea::V1] = sensors.battery_counts;
        inputs[ea::LDR] = sensors.ldr_counts;
        let window = SimDuration::from_millis(u64::from(applied.rpm_window_ms));
        let rpm_m = self.hall.tick(now, window, &sensors.shaft);
        let adaptive = applied.ldr_adaptive & image::LDR_ADAPT != 0;
        let rpm_l = self
            .light
            .tick(now, sensors.ldr_counts, applied.ldr_threshold, adaptive);
        let rpm_word = |rpm: f64| rpm.round().clamp(0.0, f64::from(u16::MAX)) as u16;
        let inputs = &mut self.image.inputs;
        inputs[ea::RPM_M] = rpm_word(rpm_m);
        inputs[ea::RPM_L] = rpm_word(rpm_l);
        self.image.hall = u16::from(sensors.shaft.hall & 0b111) | u16::from(self.light.dark()) << 3;

        let was_tripped = self.image.protection.tripped();
        if cleared {
            // These sensors were sampled before the plant saw EN applied, so
            // its own latches still show: the next tick judges afresh.
            self.push_event(now, "trip", "cleared".into());
        } else {
            self.image.protection.latch(
                sensors.bms_trip.is_some(),
                sensors.motor_tripped,
                applied.enabled(),
            );
            if self.image.protection.tripped() && !was_tripped {
                let battery = sensors
                    .bms_trip
                    .map_or_else(|| "none".to_string(), |t| t.to_string());
                let inverter = if sensors.motor_tripped { "yes" } else { "no" };
                let detail =
                    format!("battery cut-off: {battery}, inverter over-current: {inverter}");
                self.push_event(now, "trip", detail);
            }
        }
        let protection = &mut self.image.protection;
        protection.cause_persists = (protection.battery
            && matches!(
                sensors.bms_trip,
                Some(BmsTrip::UnderVoltage | BmsTrip::OverVoltage)
            ))
            || (protection.over_current
                && sensors.motor_current.abs() > self.config.over_current_release_amps);

        let actuators = if self.image.protection.tripped() {
            // A trip switches every function off; FR is a direction, not a
            // function, so it stays where the master set it (and the CCW
            // flag with it).
            let off = (sd::SD0_OFF & !sd::FR) | (applied.sd0 & sd::FR);
            Actuators::from_pins(off, sd::SD1_OFF, 0.0)
        } else {
            Actuators::from_pins(applied.sd0, applied.sd1, self.vel_volts(applied.vel))
        };

        self.image.soc = (sensors.soc * 1000.0).round().clamp(0.0, 1000.0) as u16;
        let stalled = if actuators.enable && applied.vel > 0 && rpm_m == 0.0 {
            let since = *self.stalled_since.get_or_insert(now);
            now - since > self.config.stall_after
        } else {
            self.stalled_since = None;
            false
        };
        let protection = &self.image.protection;
        let flag = |on: bool, bit: u16| if on { bit } else { 0 };
        self.image.status = flag(protection.battery, status::BATTERY_CUT_OFF)
            | flag(protection.over_current, status::OVER_CURRENT)
            | flag(sensors.brake_applied, status::BRAKE)
            | flag(stalled, status::STALLED)
            | flag(sensors.charging, status::CHARGING)
            | flag(actuators.reverse, status::CCW);
        actuators
    }
}
