//! The whole bench: [`EvModule`] wires the parts together and keeps the
//! energy ledger.

use serde::Serialize;

use crate::battery::{Battery, BmsTrip};
use crate::converter::Converter;
use crate::light::LightSensor;
use crate::motor::{Drive, Motor};
use crate::params::PlantParams;
use crate::shaft::{ShaftReading, ShaftSensors};
use crate::wheel::Wheel;

const RPM_PER_RAD_S: f64 = 60.0 / std::f64::consts::TAU;

/// What the controller board drives, as functions rather than pin levels: the
/// pins are active low, and turning pin words into these is the firmware's job
/// ([`Actuators::from_pins`] does the module's default mapping).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Actuators {
    /// `VEL`: speed command at the controller's input (V, 0–5).
    pub vel_volts: f64,
    /// `EN`: inverter enabled.
    pub enable: bool,
    /// `BRK`: brake applied.
    pub brake: bool,
    /// `PRO`: converter regulating (boost) instead of passing the battery through.
    pub boost: bool,
    /// `DES`: bleeder across the DC bus.
    pub discharge: bool,
    /// `FR`: turning counter-clockwise.
    pub reverse: bool,
    /// `CHG`: charger connected to the pack.
    pub charger: bool,
}

impl Actuators {
    /// The module's pins (MEB `SD0`, `SD1`, active low) and `VEL` in volts.
    pub fn from_pins(sd0: u16, sd1: u16, vel_volts: f64) -> Self {
        let active = |word: u16, bit: u8| word & (1 << bit) == 0;
        Self {
            vel_volts,
            enable: active(sd0, 0),
            brake: active(sd0, 1),
            boost: active(sd0, 2),
            discharge: active(sd0, 3),
            // FR: 0 = clockwise, 1 = counter-clockwise (not active low).
            reverse: !active(sd0, 4),
            charger: active(sd1, 0),
        }
    }
}

/// Energy that crossed each boundary since power-up (J). Every loss is
/// integrated from its own model; none is a residual.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct EnergyLedger {
    /// Taken from the battery terminals (negative while charging it).
    pub battery_out: f64,
    pub converter_loss: f64,
    pub bleeder_loss: f64,
    pub copper_loss: f64,
    pub friction_loss: f64,
    pub brake_loss: f64,
    /// Stored now: wheel and rotor kinetic energy, bus capacitor, winding.
    pub kinetic: f64,
    pub capacitor: f64,
    pub magnetic: f64,
}

impl EnergyLedger {
    /// Energy in minus losses minus the change in storage: zero for a perfect
    /// model, the discretisation error otherwise.
    pub fn residual(&self, initial_stored: f64) -> f64 {
        self.battery_out
            - self.converter_loss
            - self.bleeder_loss
            - self.copper_loss
            - self.friction_loss
            - self.brake_loss
            - (self.kinetic + self.capacitor + self.magnetic - initial_stored)
    }
}

/// Everything a sensor on the bench shows, after a step.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Sensors {
    /// Simulated time (s).
    pub time_s: f64,
    /// V1: battery terminal voltage (V).
    pub battery_volts: f64,
    /// V2: DC-bus voltage at the inverter's input (V).
    pub bus_volts: f64,
    /// I: inverter input current (A), mean over the last sub-step.
    pub inverter_current: f64,
    /// Battery current, positive discharging (A).
    pub battery_current: f64,
    /// State of charge, 0–1.
    pub soc: f64,
    pub charging: bool,
    /// Why the BMS holds the pack open, if it does.
    pub bms_trip: Option<BmsTrip>,
    /// V1, V2 and I as the controller's ADC reads them.
    pub battery_counts: u16,
    pub bus_counts: u16,
    pub current_counts: u16,
    /// Motor winding current (A, signed).
    pub motor_current: f64,
    /// The inverter's over-current protection holds the gates off.
    pub motor_tripped: bool,
    /// Motor shaft speed (rpm, signed: positive clockwise).
    pub motor_rpm: f64,
    /// Hall sensors and encoder.
    pub shaft: ShaftReading,
    /// Wheel speed (rpm, signed) and unwrapped angle (rad).
    pub wheel_rpm: f64,
    pub wheel_angle: f64,
    pub brake_applied: bool,
    /// Photoresistor divider (V), its ADC counts, and the true flag position.
    pub ldr_volts: f64,
    pub ldr_counts: u16,
    pub flag_in_beam: bool,
    pub energy: EnergyLedger,
}

/// One EV bench module.
#[derive(Debug)]
pub struct EvModule {
    params: PlantParams,
    battery: Battery,
    converter: Converter,
    motor: Motor,
    shaft: ShaftSensors,
    wheel: Wheel,
    light: LightSensor,
    time: f64,
    /// Current mechanical interval: its index, and the wheel's speed and
    /// angle at its start and end (already stepped: sub-steps interpolate).
    wheel_interval: u64,
    wheel_from: (f64, f64),
    wheel_to: (f64, f64),
    /// Torque impulse the motor produced but the wheel has not received yet:
    /// carried into the next interval so no momentum is lost.
    torque_impulse_owed: f64,
    torque_impulse_this_interval: f64,
    enable_was: bool,
    last_bus_current: f64,
    last_battery_current: f64,
    ledger: EnergyLedger,
    initial_stored: f64,
    sensors: Sensors,
}

impl EvModule {
    /// A module at rest at power-up; `seed` drives every random draw.
    pub fn new(params: &PlantParams, seed: u64) -> Self {
        let ratio = params.gearbox.ratio;
        let reflected = params.motor.rotor_inertia * ratio * ratio;
        let wheel = Wheel::new(&params.wheel, reflected);
        let battery = Battery::new(&params.battery, &params.bms, &params.charger);
        let bus = if params.converter.precharged {
            battery.source_voltage()
        } else {
            0.0
        };
        let mut module = Self {
            converter: Converter::new(&params.converter, bus),
            battery,
            motor: Motor::new(&params.motor),
            shaft: ShaftSensors::new(
                params.motor.pole_pairs,
                params.motor.encoder_pulses_per_turn,
                0.0,
            ),
            light: LightSensor::new(&params.light, seed),
            wheel,
            params: params.clone(),
            time: 0.0,
            wheel_interval: 0,
            wheel_from: (0.0, 0.0),
            wheel_to: (0.0, 0.0),
            torque_impulse_owed: 0.0,
            torque_impulse_this_interval: 0.0,
            enable_was: false,
            last_bus_current: 0.0,
            last_battery_current: 0.0,
            ledger: EnergyLedger::default(),
            initial_stored: 0.0,
            sensors: Sensors::default(),
        };
        module.initial_stored = module.stored_energy();
        module.start_wheel_interval(false);
        module.refresh_sensors(false);
        module
    }

    pub fn params(&self) -> &PlantParams {
        &self.params
    }

    /// The latest sensor readings.
    pub fn sensors(&self) -> &Sensors {
        &self.sensors
    }

    /// Energy stored at power-up (J), for [`EnergyLedger::residual`].
    pub fn initial_stored_energy(&self) -> f64 {
        self.initial_stored
    }

    fn stored_energy(&self) -> f64 {
        self.wheel.kinetic_energy() + self.converter.stored_energy() + self.motor.stored_energy()
    }

    /// Advance the bench by `dt` seconds with the actuators held constant.
    pub fn step(&mut self, dt: f64, actuators: &Actuators) -> &Sensors {
        if actuators.enable && !self.enable_was {
            // Re-applying EN resets the gate driver's and the pack's latches.
            self.motor.reset_trip();
            self.battery.reset_trip();
        }
        self.enable_was = actuators.enable;
        let end = self.time + dt.max(0.0);
        let wheel_h = self.params.wheel.step_s;
        while end - self.time > 1e-12 {
            let interval_end = (self.wheel_interval + 1) as f64 * wheel_h;
            if interval_end - self.time <= 1e-12 {
                self.wheel_interval += 1;
                self.start_wheel_interval(actuators.brake);
                continue;
            }
            let h = (end - self.time)
                .min(interval_end - self.time)
                .min(self.params.electrical_step_s);
            self.electrical_substep(h, actuators);
            self.time += h;
        }
        self.refresh_sensors(actuators.brake);
        &self.sensors
    }

    /// Step the wheel over the next mechanical interval with the torque the
    /// motor is expected to give, plus whatever the last interval owed.
    fn start_wheel_interval(&mut self, brake: bool) {
        let h = self.params.wheel.step_s;
        let ratio = self.params.gearbox.ratio;
        self.torque_impulse_owed += self.torque_impulse_this_interval;
        self.torque_impulse_this_interval = 0.0;
        let predicted = self.params.motor.torque_constant * self.motor.current() * ratio * h;
        let applied = self.torque_impulse_owed + predicted;
        self.torque_impulse_owed = -predicted;
        let step = self.wheel.step(h, applied / h, brake);
        self.ledger.friction_loss += step.friction_loss;
        self.ledger.brake_loss += step.brake_loss;
        self.wheel_from = (step.speed_start, step.angle_start);
        self.wheel_to = (step.speed_end, step.angle_end);
    }

    /// Wheel speed and angle at time `t` inside the current interval.
    fn wheel_at(&self, t: f64) -> (f64, f64) {
        let h = self.params.wheel.step_s;
        let start = self.wheel_interval as f64 * h;
        let f = ((t - start) / h).clamp(0.0, 1.0);
        let lerp = |a: f64, b: f64| a + (b - a) * f;
        (
            lerp(self.wheel_from.0, self.wheel_to.0),
            lerp(self.wheel_from.1, self.wheel_to.1),
        )
    }

    fn electrical_substep(&mut self, h: f64, act: &Actuators) {
        let ratio = self.params.gearbox.ratio;
        let (speed_mid, _) = self.wheel_at(self.time + 0.5 * h);
        let (_, angle_a) = self.wheel_at(self.time);
        let (_, angle_b) = self.wheel_at(self.time + h);

        let drive = Drive {
            enabled: act.enable,
            duty: self.params.motor.throttle.duty(act.vel_volts),
            reverse: act.reverse,
            bus_volts: self.converter.bus_volts(),
            shaft_speed: speed_mid * ratio,
        };
        let m = self.motor.step(h, &drive);
        self.torque_impulse_this_interval += m.torque_impulse * ratio;

        let source = self.battery.output_closed().then(|| {
            (
                self.battery.source_voltage(),
                self.battery.series_resistance(),
            )
        });
        let c = self
            .converter
            .step(h, source, m.bus_current, act.boost, act.discharge);
        self.battery.step(h, c.battery_current, act.charger);

        self.shaft
            .advance(self.time, h, angle_a * ratio, angle_b * ratio);
        self.light.step(self.time, h, angle_a, angle_b);

        self.last_bus_current = m.bus_current;
        self.last_battery_current = c.battery_current;
        let l = &mut self.ledger;
        l.battery_out += c.battery_energy;
        l.converter_loss += c.converter_loss;
        l.bleeder_loss += c.bleeder_loss;
        l.copper_loss += m.copper_loss;
    }

    fn refresh_sensors(&mut self, brake: bool) {
        let s = &self.params.sensing;
        let (wheel_speed, wheel_angle) = self.wheel_at(self.time);
        let battery_volts = self.battery.terminal_voltage();
        let bus_volts = self.converter.bus_volts();
        let current = self.last_bus_current;
        self.ledger.kinetic = 0.5 * self.wheel.inertia() * wheel_speed * wheel_speed;
        self.ledger.capacitor = self.converter.stored_energy();
        self.ledger.magnetic = self.motor.stored_energy();
        self.sensors = Sensors {
            time_s: self.time,
            battery_volts,
            bus_volts,
            inverter_current: current,
            battery_current: self.last_battery_current,
            soc: self.battery.soc(),
            charging: self.battery.charging(),
            bms_trip: self.battery.trip(),
            battery_counts: s.counts(battery_volts / s.battery_divider),
            bus_counts: s.counts(bus_volts / s.bus_divider),
            current_counts: s.counts(s.current_zero_volts + current * s.current_volts_per_amp),
            motor_current: self.motor.current(),
            motor_tripped: self.motor.tripped(),
            motor_rpm: wheel_speed * self.params.gearbox.ratio * RPM_PER_RAD_S,
            shaft: self.shaft.reading(),
            wheel_rpm: wheel_speed * RPM_PER_RAD_S,
            wheel_angle,
            brake_applied: brake,
            ldr_volts: self.light.divider_voltage(),
            ldr_counts: self.light.adc_counts(),
            flag_in_beam: self.light.flag_in_beam(),
            energy: self.ledger,
        };
    }
}
