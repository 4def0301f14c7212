//! What a view needs to know about a run: its modules, the bus nodes that
//! speak for each one, and how each module's light detector is set up.

use anyhow::Result;
use nodes::firmware::LightDetectorConfig;
use plant::PlantParams;
use std::collections::BTreeMap;

use crate::scenario::{NodeSpec, Scenario};

/// The module an open-loop recording's `/plant/sensors` belongs to.
pub const OPEN_LOOP_MODULE: &str = "bench";

/// One bench module as the view shows it.
#[derive(Debug, Clone)]
pub struct ModuleView {
    pub name: String,
    /// The firmware's light detector for this module's sensor.
    pub light: LightDetectorConfig,
    /// Volts per ADC count of the photoresistor's converter.
    pub volts_per_count: f64,
}

impl ModuleView {
    pub fn new(name: &str, params: &PlantParams) -> Self {
        let light = &params.light;
        let bits = light.adc_bits.clamp(1, 16);
        Self {
            name: name.to_string(),
            light: LightDetectorConfig::for_sensor(light),
            volts_per_count: light.adc_reference_volts / f64::from(1u32 << bits),
        }
    }

    /// The fixed dark threshold, in volts at the divider.
    pub fn threshold_volts(&self) -> f64 {
        f64::from(self.light.threshold_counts) * self.volts_per_count
    }
}

/// Modules, and which node or (master, slave id) stands for which module.
#[derive(Debug, Clone, Default)]
pub struct ViewLayout {
    pub modules: Vec<ModuleView>,
    /// Slave node name → module index (its replies carry the module's rpm).
    node_module: BTreeMap<String, usize>,
    /// (master node name, slave id) → module index (its loop's set point).
    slave_module: BTreeMap<(String, u8), usize>,
    /// The seed-002 network's nodes: name → module index and which one.
    seed002: BTreeMap<String, (usize, Seed002Role)>,
}

/// Which seed-002 node a reply comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Seed002Role {
    /// Motor node: its register 5 is the motor shaft's rpm.
    Motor,
    /// Light-sensor node: its register 6 is the wheel rpm × 100.
    Light,
}

impl ViewLayout {
    /// The layout of a scenario run.
    pub fn of_scenario(scenario: &Scenario) -> Result<Self> {
        let mut layout = Self::default();
        for m in &scenario.modules {
            let params = scenario.module_params(m)?;
            layout.modules.push(ModuleView::new(&m.name, &params));
        }
        let index = |name: &str| layout.modules.iter().position(|m| m.name == name);
        let mut node_module = BTreeMap::new();
        let mut seed002 = BTreeMap::new();
        // Per bus: slave id → module, for the masters on that bus.
        let mut bus_slaves: BTreeMap<(&str, u8), usize> = BTreeMap::new();
        for node in &scenario.nodes {
            match node {
                NodeSpec::EvController {
                    name,
                    bus,
                    module,
                    id,
                    ..
                } => {
                    if let Some(m) = index(module) {
                        node_module.insert(name.clone(), m);
                        bus_slaves.insert((bus.as_str(), *id), m);
                    }
                }
                NodeSpec::MotorNode { name, module, .. } => {
                    if let Some(m) = index(module) {
                        seed002.insert(name.clone(), (m, Seed002Role::Motor));
                    }
                }
                NodeSpec::LightNode { name, module, .. } => {
                    if let Some(m) = index(module) {
                        seed002.insert(name.clone(), (m, Seed002Role::Light));
                    }
                }
                NodeSpec::Supervisor { .. } | NodeSpec::Seed002Master { .. } => {}
            }
        }
        let mut slave_module = BTreeMap::new();
        for node in &scenario.nodes {
            if let NodeSpec::Supervisor {
                name, bus, slaves, ..
            } = node
            {
                for id in slaves {
                    if let Some(&m) = bus_slaves.get(&(bus.as_str(), *id)) {
                        slave_module.insert((name.clone(), *id), m);
                    }
                }
            }
        }
        layout.node_module = node_module;
        layout.slave_module = slave_module;
        layout.seed002 = seed002;
        Ok(layout)
    }

    /// The layout of an open-loop run: one module, no bus.
    pub fn open_loop(params: &PlantParams) -> Self {
        Self {
            modules: vec![ModuleView::new(OPEN_LOOP_MODULE, params)],
            ..Self::default()
        }
    }

    pub fn module_index(&self, name: &str) -> Option<usize> {
        self.modules.iter().position(|m| m.name == name)
    }

    /// The module whose controller board is node `name`.
    pub fn module_of_node(&self, name: &str) -> Option<usize> {
        self.node_module.get(name).copied()
    }

    /// The module that master `node` reaches as slave `id`.
    pub fn module_of_slave(&self, node: &str, id: u8) -> Option<usize> {
        // A handful of entries: a scan needs no key allocation.
        self.slave_module
            .iter()
            .find(|((master, slave), _)| master == node && *slave == id)
            .map(|(_, &m)| m)
    }

    /// The seed-002 node `name`: its module and role.
    pub fn seed002_node(&self, name: &str) -> Option<(usize, Seed002Role)> {
        self.seed002.get(name).copied()
    }

    /// Whether module `m` is run by seed-002 nodes (it then has a motor-shaft view).
    pub fn has_seed002(&self, m: usize) -> bool {
        self.seed002.values().any(|&(i, _)| i == m)
    }

    /// The module of the seed-002 motor node (the master's set point is its).
    pub fn seed002_motor_module(&self) -> Option<usize> {
        self.seed002
            .values()
            .find(|(_, role)| *role == Seed002Role::Motor)
            .map(|&(m, _)| m)
    }
}
