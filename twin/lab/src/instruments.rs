//! The firmware that reads a bench's speed sensors, run beside an open-loop
//! bench: the EV controller (hall rpm, light rpm with a fixed or adaptive
//! detector) or the Controller_network motor node (encoder) and
//! light-sensor node. They are ticked at their own loop period on the
//! plant's sensors, as on the bench, and nothing they drive is applied.

use nodes::controller_network::{LightConfig, LightNode, MotorConfig, MotorNode};
use nodes::firmware::{EvController, EvControllerConfig};
use nodes::link::{CheckKind, FaultyNode};
use plant::light::fixed_threshold_max_rpm;
use plant::{PlantParams, Sensors};
use protocols::time::SimTime;

use twin_sim::engine::{SimNode, SpeedReadings};

/// A bench's speed-reading firmware and when each ticks next.
pub struct Instruments {
    nodes: Vec<Box<dyn SimNode>>,
    next_tick: Vec<SimTime>,
    gear_ratio: f64,
}

impl std::fmt::Debug for Instruments {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Instruments")
            .field("nodes", &self.nodes.len())
            .finish_non_exhaustive()
    }
}

impl Instruments {
    pub fn new(params: &PlantParams, preset: &str, adaptive: bool) -> Self {
        let nodes = instruments(params, preset, adaptive);
        Self {
            next_tick: vec![SimTime::ZERO; nodes.len()],
            nodes,
            gear_ratio: params.gearbox.ratio,
        }
    }

    /// Give every firmware whose loop is due at `now` the sensors.
    pub fn tick(&mut self, now: SimTime, sensors: &Sensors) {
        for (node, next) in self.nodes.iter_mut().zip(&mut self.next_tick) {
            if let Some(fw) = node.firmware()
                && now >= *next
            {
                fw.loop_tick(now, sensors);
                *next = now + fw.loop_period();
            }
        }
    }

    /// What they read now.
    pub fn read(&self) -> Reading {
        read_instruments(self.nodes.iter().map(|b| b.as_ref()), self.gear_ratio)
    }

    /// The longest loop period among them (s): how often the slowest samples.
    pub fn sample_period_s(&mut self) -> f64 {
        self.nodes
            .iter_mut()
            .filter_map(|n| n.firmware().map(|f| f.loop_period().as_secs_f64()))
            .fold(0.0, f64::max)
    }
}

/// The firmware that reads a bench's speed sensors: the EV controller, or
/// the Controller_network motor and light-sensor nodes.
fn instruments(params: &PlantParams, preset: &str, adaptive: bool) -> Vec<Box<dyn SimNode>> {
    if preset == "controller-network" {
        vec![
            Box::new(FaultyNode::new(
                MotorNode::new(MotorConfig::default()),
                CheckKind::Modbus8,
            )),
            Box::new(FaultyNode::new(
                LightNode::new(LightConfig::for_sensor(&params.light)),
                CheckKind::Modbus8,
            )),
        ]
    } else {
        let mut config = EvControllerConfig::for_plant(params);
        config.light.adaptive = adaptive;
        vec![Box::new(FaultyNode::new(
            EvController::new(config),
            CheckKind::Meb,
        ))]
    }
}

/// The light detector a bench's firmware runs, and the fastest speed it
/// sees by the formula of plant/src/light.rs.
pub fn light_limit(params: &PlantParams, preset: &str, adaptive: bool) -> (String, f64) {
    let light = &params.light;
    if preset == "controller-network" {
        let th = LightConfig::default().dark_below_volts;
        (
            format!("light-sensor Nano, fixed {th:.2} V, 20 ms sampling"),
            fixed_threshold_max_rpm(light, th),
        )
    } else {
        let mut config = EvControllerConfig::for_plant(params).light;
        config.adaptive = adaptive;
        (
            format!("EV controller, {}", config.describe(light)),
            config.max_rpm(light),
        )
    }
}

/// What a bench's instruments read, in wheel rpm.
#[derive(Debug, Clone, Copy)]
pub struct Reading {
    /// The motor's own sensor (hall edges, or the encoder over the gearbox).
    pub motor: f64,
    pub light: f64,
    /// The set point a node's own loop holds, if one does.
    pub set_point: Option<f64>,
}

/// Combine the instruments' readings (NaN where none reads).
pub fn read_instruments<'a>(
    instruments: impl IntoIterator<Item = &'a dyn SimNode>,
    gear_ratio: f64,
) -> Reading {
    let mut r = SpeedReadings::default();
    for i in instruments {
        let x = i.speed_readings();
        r.hall_wheel_rpm = r.hall_wheel_rpm.or(x.hall_wheel_rpm);
        r.motor_shaft_rpm = r.motor_shaft_rpm.or(x.motor_shaft_rpm);
        r.light_rpm = r.light_rpm.or(x.light_rpm);
        r.set_point_motor_rpm = r.set_point_motor_rpm.or(x.set_point_motor_rpm);
    }
    Reading {
        motor: r
            .hall_wheel_rpm
            .or(r.motor_shaft_rpm.map(|m| m / gear_ratio))
            .unwrap_or(f64::NAN),
        light: r.light_rpm.unwrap_or(f64::NAN),
        set_point: r.set_point_motor_rpm.map(|m| m / gear_ratio),
    }
}
