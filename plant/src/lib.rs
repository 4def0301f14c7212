//! Physics of the EV lab bench, pure and deterministic: no I/O, no clock, no
//! unseeded randomness. Time comes in as `dt`, randomness as a seed.
//!
//! [`EvModule::step`] composes the battery and its BMS ([`battery`]), the
//! buck-boost converter and DC bus ([`converter`]), the inverter and BLDC motor
//! ([`motor`]) with its hall sensors and encoder ([`shaft`]), the gearbox and
//! the rapier3d wheel ([`wheel`]) and the photoresistor that sees the paper flag
//! on the wheel ([`light`]). Parameters live in one serde struct ([`params`]).
//!
//! Each part is stepped at the rate its own dynamics need: the RC and RL states
//! with exact exponential updates in electrical sub-steps (1 ms by default),
//! the wheel at its mechanical rate (5 ms on the EV module) with the motor
//! torque averaged over the step, and the shaft sensors and light sensor with
//! the wheel angle interpolated between mechanical steps, so every edge gets
//! its exact time whatever the step.

pub mod battery;
pub mod converter;
pub mod light;
mod module;
pub mod motor;
pub mod params;
pub mod shaft;
pub mod toml_errors;
pub mod wheel;

pub use module::{Actuators, EnergyLedger, EvModule, Sensors};
pub use params::{ParamsError, PlantParams};
