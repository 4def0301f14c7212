//! What a view needs to know about a run: its modules, the bus nodes that
//! speak for each one, and how each module's light detector is set up.

use nodes::firmware::LightDetectorConfig;
use plant::PlantParams;
use std::collections::BTreeMap;

use twin_sim::scenario::{NodeSpec, Scenario};

/// The module an open-loop recording's `/plant/sensors` belongs to.
pub const OPEN_LOOP_MODULE: &str = "bench";

/// The names `twin serve` gives its modules and nodes.
pub const SERVE_EV_MODULE: &str = "ev1";
pub const SERVE_CONTROLLER_NETWORK_MODULE: &str = "bench";
pub const SERVE_MOTOR_NODE: &str = "motor";
pub const SERVE_LIGHT_NODE: &str = "sensor";
/// The node name of `twin supervise`'s master in its loop reports.
pub const SUPERVISOR_NODE: &str = "supervisor";

/// The view's name for slave `id` of a `twin supervise` session.
pub fn supervised_module(id: u8) -> String {
    format!("slave{id:02}")
}

/// One bench module as the view shows it.
#[derive(Debug, Clone)]
pub struct ModuleView {
    pub name: String,
    /// The firmware's light detector for this module's sensor.
    pub light: LightDetectorConfig,
    /// Volts per ADC count of the photoresistor's converter.
    pub volts_per_count: f64,
    /// Whether the recording holds this module's plant (a supervisor's
    /// session sees only what its slave answers).
    pub has_plant: bool,
}

impl ModuleView {
    pub fn new(name: &str, params: &PlantParams) -> Self {
        let light = &params.light;
        let bits = light.adc_bits.clamp(1, 16);
        Self {
            name: name.to_string(),
            light: LightDetectorConfig::for_sensor(light),
            volts_per_count: light.adc_reference_volts / f64::from(1u32 << bits),
            has_plant: true,
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
    /// The Controller_network nodes: name → module index and which one.
    controller_network: BTreeMap<String, (usize, ControllerNetworkRole)>,
    /// A real-time session (`twin serve`, `twin supervise`): its tick
    /// lateness is shown too.
    pub realtime: bool,
    /// Compiled firmware nodes (`twin-avr`) and the module each drives:
    /// their UART, pins and ADC inputs are shown beside that module.
    pub firmware: Vec<(String, usize)>,
}

/// Which Controller_network node a reply comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ControllerNetworkRole {
    /// Motor node: its register 5 is the motor shaft's rpm.
    Motor,
    /// Light-sensor node: its register 6 is the wheel rpm × 100.
    Light,
}

impl ViewLayout {
    /// The layout of a scenario run.
    pub fn of_scenario(scenario: &Scenario) -> Result<Self, twin_sim::scenario::ScenarioError> {
        let mut layout = Self::default();
        for m in &scenario.modules {
            let params = scenario.module_params(m)?;
            layout.modules.push(ModuleView::new(&m.name, &params));
        }
        let index = |name: &str| layout.modules.iter().position(|m| m.name == name);
        let mut node_module = BTreeMap::new();
        let mut controller_network = BTreeMap::new();
        // Per bus: slave id → module, for the masters on that bus.
        let mut bus_slaves: BTreeMap<(&str, u8), usize> = BTreeMap::new();
        // Per module: whether its controller's light detector is adaptive.
        let mut adaptive = Vec::new();
        for node in &scenario.nodes {
            match node {
                NodeSpec::EvController {
                    name,
                    bus,
                    module,
                    id,
                    light_detector,
                    ..
                } => {
                    if let Some(m) = index(module) {
                        node_module.insert(name.clone(), m);
                        bus_slaves.insert((bus.as_str(), *id), m);
                        adaptive.push((m, light_detector.adaptive()));
                    }
                }
                NodeSpec::MotorNode { name, module, .. } => {
                    if let Some(m) = index(module) {
                        controller_network.insert(name.clone(), (m, ControllerNetworkRole::Motor));
                    }
                }
                NodeSpec::LightNode { name, module, .. } => {
                    if let Some(m) = index(module) {
                        controller_network.insert(name.clone(), (m, ControllerNetworkRole::Light));
                    }
                }
                // Their frames carry no rpm words: the plants' own sensors
                // show the parallel modules' wheels.
                NodeSpec::Supervisor { .. }
                | NodeSpec::ControllerNetworkMaster { .. }
                | NodeSpec::ParallelMaster { .. }
                | NodeSpec::PwmSlave { .. } => {}
                NodeSpec::Firmware {
                    name,
                    bus,
                    module,
                    wiring,
                    ..
                } => {
                    if let Some(m) = index(module) {
                        layout.firmware.push((name.clone(), m));
                        // Our sketches answer as the boards they stand for
                        // (the EV controller's is MEB slave 1): their
                        // replies' rpm words go on the module's speed plot.
                        match wiring.as_str() {
                            "ev-controller" => {
                                node_module.insert(name.clone(), m);
                                bus_slaves.insert((bus.as_str(), 1), m);
                            }
                            "motor-nano" => {
                                controller_network
                                    .insert(name.clone(), (m, ControllerNetworkRole::Motor));
                            }
                            "light-nano" => {
                                controller_network
                                    .insert(name.clone(), (m, ControllerNetworkRole::Light));
                            }
                            _ => {}
                        }
                    }
                }
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
        for (m, on) in adaptive {
            layout.modules[m].light.adaptive = on;
        }
        layout.node_module = node_module;
        layout.slave_module = slave_module;
        layout.controller_network = controller_network;
        Ok(layout)
    }

    /// The layout of an open-loop run: one module, no bus.
    pub fn open_loop(params: &PlantParams) -> Self {
        Self {
            modules: vec![ModuleView::new(OPEN_LOOP_MODULE, params)],
            ..Self::default()
        }
    }

    /// The layout of a `twin serve` session: module `ev1` (the EV
    /// controller every link but `--modbus8` serves, on the plant `params`)
    /// and/or `bench`, the Controller_network nodes', with its nodes `motor` and
    /// `sensor`. The names are those `twin serve` gives them.
    pub fn of_serve(
        params: &PlantParams,
        ev: bool,
        controller_network: bool,
        light_adaptive: bool,
    ) -> Self {
        let mut layout = Self {
            realtime: true,
            ..Self::default()
        };
        if ev {
            let mut module = ModuleView::new(SERVE_EV_MODULE, params);
            module.light.adaptive = light_adaptive;
            layout.modules.push(module);
            layout.node_module.insert(SERVE_EV_MODULE.into(), 0);
        }
        if controller_network {
            let m = layout.modules.len();
            let bench = PlantParams::preset("controller-network").unwrap_or_default();
            layout
                .modules
                .push(ModuleView::new(SERVE_CONTROLLER_NETWORK_MODULE, &bench));
            layout
                .controller_network
                .insert(SERVE_MOTOR_NODE.into(), (m, ControllerNetworkRole::Motor));
            layout
                .controller_network
                .insert(SERVE_LIGHT_NODE.into(), (m, ControllerNetworkRole::Light));
        }
        layout
    }

    /// The layout of a `twin supervise` session: one module per polled
    /// slave, named [`supervised_module`], known only through its replies
    /// and the supervisor's loop (no plant in the recording).
    pub fn of_supervise(slaves: &[u8]) -> Self {
        let mut layout = Self {
            realtime: true,
            ..Self::default()
        };
        // The light detector is not run without plant samples; any preset does.
        let params = PlantParams::preset("vemodule").unwrap_or_default();
        for (m, &id) in slaves.iter().enumerate() {
            let name = supervised_module(id);
            let mut view = ModuleView::new(&name, &params);
            view.has_plant = false;
            layout.modules.push(view);
            layout.node_module.insert(name, m);
            layout.slave_module.insert((SUPERVISOR_NODE.into(), id), m);
        }
        layout
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

    /// The Controller_network node `name`: its module and role.
    pub fn controller_network_node(&self, name: &str) -> Option<(usize, ControllerNetworkRole)> {
        self.controller_network.get(name).copied()
    }

    /// Whether module `m` is run by Controller_network nodes (it then has a
    /// motor-shaft view).
    pub fn has_controller_network(&self, m: usize) -> bool {
        self.controller_network.values().any(|&(i, _)| i == m)
    }

    /// The module of the Controller_network motor node (the master's set point is its).
    pub fn controller_network_motor_module(&self) -> Option<usize> {
        self.controller_network
            .values()
            .find(|(_, role)| *role == ControllerNetworkRole::Motor)
            .map(|&(m, _)| m)
    }
}
