//! The gearbox and the wheel: a rapier3d rigid body on a revolute joint.
//!
//! Bearing friction with stiction comes from the joint's velocity motor with
//! target 0 and a torque cap (rapier's solver holds the wheel still while the
//! drive torque stays under the cap and lets it slip with the cap's torque
//! against it above), viscous drag is applied as a torque, and the brake
//! (`BRK`) raises the cap. The motor's rotor is reflected to the wheel through
//! the gearbox (`J_rotor·N²`) and added to the body's inertia.
//!
//! rapier integrates with symplectic Euler (`ω₁ = ω₀ + Δt·τ/J`, then
//! `θ₁ = θ₀ + Δt·ω₁`), so the work of each torque over a step is its impulse
//! times the mean speed `(ω₀ + ω₁)/2`: that is how every mechanical energy term
//! below is computed. Two rapier pitfalls are handled: its default angular
//! speed cap (π/4 rad per step) is lifted with `allow_fast_rotation`, and the
//! body never sleeps.

use rapier3d::prelude::*;
use serde::{Deserialize, Serialize};

/// The reduction between motor and wheel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GearboxParams {
    /// Motor turns per wheel turn: 1 on the EV module (direct drive), 100 on
    /// the Controller_network bench (≈ 10 000 motor rpm for ≈ 98 wheel rpm in its log).
    pub ratio: f64,
}

impl Default for GearboxParams {
    fn default() -> Self {
        Self { ratio: 1.0 }
    }
}

/// The wheel, its bearings and brake, all referred to the wheel shaft.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WheelParams {
    /// Wheel radius (m): a 20 cm aluminium flywheel disc on the EV module bench.
    pub radius_m: f64,
    /// Wheel mass (kg): 6 mm aluminium disc of 20 cm, about 0.5 kg.
    pub mass_kg: f64,
    /// Coulomb bearing friction (N·m): two 6001 ball bearings with seals.
    pub coulomb_friction_nm: f64,
    /// Viscous drag (N·m per rad/s): bearing grease and air.
    pub viscous_friction_nms: f64,
    /// Brake torque when `BRK` is applied (N·m): enough to stop the wheel
    /// against the motor's current-limited torque.
    pub brake_torque_nm: f64,
    /// Mechanical step (s): the wheel is stepped at this rate, with the motor
    /// torque averaged over the step. 5 ms is under a tenth of the
    /// electromechanical time constant on both presets.
    pub step_s: f64,
}

impl Default for WheelParams {
    fn default() -> Self {
        Self {
            radius_m: 0.1,
            mass_kg: 0.5,
            coulomb_friction_nm: 0.02,
            viscous_friction_nms: 5.0e-5,
            brake_torque_nm: 2.0,
            step_s: 0.005,
        }
    }
}

impl WheelParams {
    /// The Controller_network bench: a 65 mm robot wheel on the gearbox output shaft.
    pub fn controller_network() -> Self {
        Self {
            radius_m: 0.0325,
            mass_kg: 0.05,
            // Gearbox and bearing drag referred to the output shaft, fitted
            // to the bench's step response (the datasheet's no-load current
            // of a JGB37-520, ≈ 0.12 A, times k times N gives 0.1).
            coulomb_friction_nm: 0.0357,
            viscous_friction_nms: 1.0e-3,
            brake_torque_nm: 5.0,
            step_s: 0.002,
        }
    }

    /// Moment of inertia of the wheel alone (kg·m²), a uniform disc.
    pub fn inertia(&self) -> f64 {
        0.5 * self.mass_kg * self.radius_m * self.radius_m
    }
}

/// What one mechanical step did; energies in joules.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct WheelStep {
    pub speed_start: f64,
    pub speed_end: f64,
    pub angle_start: f64,
    pub angle_end: f64,
    /// Work of the drive torque.
    pub drive_work: f64,
    /// Heat in the bearings (Coulomb and viscous) and in the brake.
    pub friction_loss: f64,
    pub brake_loss: f64,
}

/// The wheel in its rapier world.
pub struct Wheel {
    world: PhysicsWorld,
    body: RigidBodyHandle,
    joint: ImpulseJointHandle,
    params: WheelParams,
    /// Wheel plus reflected rotor inertia (kg·m²).
    inertia: f64,
    /// Unwrapped angle (rad): the joint's own angle wraps to ±π.
    angle: f64,
    speed: f64,
}

impl std::fmt::Debug for Wheel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Wheel")
            .field("inertia", &self.inertia)
            .field("angle", &self.angle)
            .field("speed", &self.speed)
            .finish_non_exhaustive()
    }
}

/// Stiff enough that the friction motor acts as a hard constraint up to its cap.
const FRICTION_MOTOR_DAMPING: f32 = 1.0e6;

impl Wheel {
    /// `extra_inertia` is the rotor's inertia reflected to the wheel.
    pub fn new(params: &WheelParams, extra_inertia: f64) -> Self {
        let mut world = PhysicsWorld::new();
        world.gravity = Vector::ZERO;
        world.integration_parameters.dt = params.step_s as f32;
        // One body on one joint: a single solver substep already meets the
        // friction cap exactly (the tests check it), and four cost 4x.
        world.integration_parameters.num_solver_iterations = 1;
        let inertia = params.inertia() + extra_inertia;
        let ground = world.bodies.insert(RigidBodyBuilder::fixed());
        let wheel = RigidBodyBuilder::dynamic()
            .additional_mass_properties(MassProperties::new(
                Vector::ZERO,
                params.mass_kg as f32,
                Vector::splat(inertia as f32),
            ))
            .allow_fast_rotation(true)
            .can_sleep(false)
            .build();
        let body = world.bodies.insert(wheel);
        let axle = RevoluteJointBuilder::new(Vector::Z)
            .motor_velocity(0.0, FRICTION_MOTOR_DAMPING)
            .motor_max_force(params.coulomb_friction_nm as f32);
        let joint = world.impulse_joints.insert(ground, body, axle, true);
        Self {
            world,
            body,
            joint,
            params: params.clone(),
            inertia,
            angle: 0.0,
            speed: 0.0,
        }
    }

    /// Unwrapped wheel angle (rad).
    pub fn angle(&self) -> f64 {
        self.angle
    }

    /// Wheel speed (rad/s, positive clockwise as seen by the light sensor).
    pub fn speed(&self) -> f64 {
        self.speed
    }

    /// Total inertia the drive sees at the wheel (kg·m²).
    pub fn inertia(&self) -> f64 {
        self.inertia
    }

    /// Kinetic energy (J).
    pub fn kinetic_energy(&self) -> f64 {
        0.5 * self.inertia * self.speed * self.speed
    }

    /// Advance one mechanical step of `h` seconds under a mean drive torque.
    pub fn step(&mut self, h: f64, drive_torque: f64, brake: bool) -> WheelStep {
        let p = &self.params;
        let speed_start = self.speed;
        let viscous = p.viscous_friction_nms * speed_start;
        let cap = p.coulomb_friction_nm + if brake { p.brake_torque_nm } else { 0.0 };
        if let Some(joint) = self.world.impulse_joints.get_mut(self.joint, false) {
            joint.data.set_motor_max_force(JointAxis::AngX, cap as f32);
        }
        self.world.integration_parameters.dt = h as f32;
        if let Some(b) = self.world.bodies.get_mut(self.body) {
            b.reset_torques(false);
            b.add_torque(Vector::Z * (drive_torque - viscous) as f32, false);
        }
        self.world.step();
        let speed_end = self
            .world
            .bodies
            .get(self.body)
            .map_or(speed_start, |b| f64::from(b.angvel().z));
        // The bearing's (and brake's) angular impulse is what the constraint
        // added to the body's momentum beyond the applied torques. rapier keeps
        // only the last solver substep's impulse, so it is read off the motion.
        let constraint_impulse =
            self.inertia * (speed_end - speed_start) - (drive_torque - viscous) * h;
        let angle_start = self.angle;
        self.angle += speed_end * h;
        self.speed = speed_end;
        let mean_speed = 0.5 * (speed_start + speed_end);
        // The cap's impulse is shared between bearing and brake in proportion.
        let dissipated = constraint_impulse.abs() * mean_speed.abs();
        let brake_share = if brake { p.brake_torque_nm / cap } else { 0.0 };
        WheelStep {
            speed_start,
            speed_end,
            angle_start,
            angle_end: self.angle,
            drive_work: drive_torque * h * mean_speed,
            friction_loss: viscous * h * mean_speed + dissipated * (1.0 - brake_share),
            brake_loss: dissipated * brake_share,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stiction_holds_below_the_friction_torque() {
        let p = WheelParams::default();
        let mut w = Wheel::new(&p, 0.0);
        for _ in 0..200 {
            w.step(p.step_s, 0.9 * p.coulomb_friction_nm, false);
        }
        // rapier's motor constraint is slightly soft: a creep of 1e-5 rad/s
        // (1e-4 rpm) is the solver's compliance, not motion.
        assert!(w.speed().abs() < 1e-4, "{}", w.speed());
    }

    #[test]
    fn above_stiction_accelerates_with_net_torque() {
        let p = WheelParams {
            viscous_friction_nms: 0.0,
            ..Default::default()
        };
        let mut w = Wheel::new(&p, 0.0);
        let drive = 3.0 * p.coulomb_friction_nm;
        let n = 200;
        for _ in 0..n {
            w.step(p.step_s, drive, false);
        }
        let expected = (drive - p.coulomb_friction_nm) / w.inertia() * p.step_s * n as f64;
        assert!(
            (w.speed() - expected).abs() < 1e-3 * expected,
            "{} vs {expected}",
            w.speed()
        );
    }

    #[test]
    fn fast_rotation_is_not_capped() {
        let p = WheelParams::default();
        let mut w = Wheel::new(&p, 0.0);
        for _ in 0..400 {
            w.step(p.step_s, 2.0, false);
        }
        // π/4 per 5 ms step would cap the wheel at 25 turns/s = 1500 rpm.
        assert!(
            w.speed() * 60.0 / std::f64::consts::TAU > 3000.0,
            "{}",
            w.speed()
        );
    }

    #[test]
    fn slipping_bearing_dissipates_coulomb_plus_viscous_power() {
        let p = WheelParams::default();
        let mut w = Wheel::new(&p, 0.0);
        for _ in 0..100 {
            w.step(p.step_s, 0.5, false);
        }
        let s = w.step(p.step_s, 0.5, false);
        let mean = 0.5 * (s.speed_start + s.speed_end);
        let model =
            (p.coulomb_friction_nm + p.viscous_friction_nms * s.speed_start) * mean * p.step_s;
        assert!(
            (s.friction_loss - model).abs() < 1e-3 * model,
            "{} vs {model}",
            s.friction_loss
        );
    }

    #[test]
    fn brake_stops_the_wheel_and_takes_the_heat() {
        let p = WheelParams::default();
        let mut w = Wheel::new(&p, 0.0);
        let (mut input, mut friction, mut brake, mut ke_at_brake) = (0.0, 0.0, 0.0, 0.0);
        for k in 0..600 {
            if k == 450 {
                ke_at_brake = w.kinetic_energy();
            }
            let s = w.step(p.step_s, if k < 300 { 0.5 } else { 0.0 }, k >= 450);
            input += s.drive_work;
            friction += s.friction_loss;
            brake += s.brake_loss;
        }
        assert!(
            w.speed().abs() < 1e-4,
            "brake stops the wheel: {}",
            w.speed()
        );
        // The brake takes its share of the kinetic energy left when it closes.
        let share = p.brake_torque_nm / (p.brake_torque_nm + p.coulomb_friction_nm);
        assert!(
            (brake - share * ke_at_brake).abs() < 0.02 * ke_at_brake,
            "{brake} of {ke_at_brake}"
        );
        let residual = input - friction - brake - w.kinetic_energy();
        assert!(
            residual.abs() < 1e-6 * input,
            "residual {residual} J of {input} J"
        );
    }

    #[test]
    fn joint_does_not_wrap_the_angle() {
        let p = WheelParams::default();
        let mut w = Wheel::new(&p, 0.0);
        for _ in 0..1000 {
            w.step(p.step_s, 1.0, false);
        }
        assert!(w.angle() > 10.0 * std::f64::consts::TAU, "{}", w.angle());
    }
}
