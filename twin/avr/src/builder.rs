//! How `twin-avr` builds a scenario's `firmware` nodes (registered with
//! `twin_sim::external` before anything runs).

use plant::PlantParams;
use protocols::time::SimDuration;
use std::path::Path;
use twin_sim::engine::SimNode;
use twin_sim::external::FirmwareBuilder;
use twin_sim::nodes_build::BuildError;
use twin_sim::scenario::{BusSpec, NodeSpec};

use crate::debug::DebugError;
use crate::node::{AvrNode, Board, StartError};
use crate::vcd::VcdError;
use crate::wiring::{Wiring, WiringError};

/// Why a scenario's firmware node cannot be built: the node and the field
/// at fault, the cause (the wiring map's or the firmware file's own error)
/// as its source.
#[derive(Debug, thiserror::Error)]
pub enum FirmwareError {
    #[error("node `{node}` is not a firmware node")]
    NotFirmware { node: String },
    #[error("firmware node `{node}` needs a module")]
    NoModule { node: String },
    #[error("firmware node `{node}`: clock_hz {clock_hz}: give the board's clock, 1 to 32 MHz")]
    Clock { node: String, clock_hz: u32 },
    #[error("firmware node `{node}`, field `wiring`")]
    Wiring {
        node: String,
        #[source]
        source: Box<WiringError>,
    },
    /// A replay's map, out of the recording.
    #[error("firmware node `{node}`, the wiring map its recording stored")]
    StoredWiring {
        node: String,
        #[source]
        source: Box<WiringError>,
    },
    /// The ELF or Intel HEX file refused, or simavr could not start it.
    #[error("firmware node `{node}`, field `elf`")]
    Start {
        node: String,
        #[source]
        source: StartError,
    },
    #[error(transparent)]
    Debug(#[from] DebugError),
    #[error(transparent)]
    Vcd(#[from] VcdError),
}

/// The builder of firmware nodes.
#[derive(Debug, Default)]
pub struct AvrBuilder;

impl FirmwareBuilder for AvrBuilder {
    fn build(
        &self,
        spec: &NodeSpec,
        module: Option<&PlantParams>,
        bus: &BusSpec,
    ) -> Result<(Box<dyn SimNode + Send>, SimDuration), BuildError> {
        self.build_node(spec, module, bus)
            .map_err(|e| BuildError::Firmware(e.into()))
    }
}

impl AvrBuilder {
    fn build_node(
        &self,
        spec: &NodeSpec,
        module: Option<&PlantParams>,
        bus: &BusSpec,
    ) -> Result<(Box<dyn SimNode + Send>, SimDuration), FirmwareError> {
        let NodeSpec::Firmware {
            name,
            elf,
            wiring,
            mcu,
            clock_hz,
            boot_ms,
            ..
        } = spec
        else {
            return Err(FirmwareError::NotFirmware {
                node: spec.name().into(),
            });
        };
        let Some(params) = module else {
            return Err(FirmwareError::NoModule { node: name.clone() });
        };
        if !(1_000_000..=32_000_000).contains(clock_hz) {
            return Err(FirmwareError::Clock {
                node: name.clone(),
                clock_hz: *clock_hz,
            });
        }
        // A replay runs the file and map its recording stored.
        let stored = crate::replay::stored(name);
        let wiring = match &stored {
            Some(s) => Wiring::parse(&s.wiring_text, &s.wiring_origin).map_err(|source| {
                FirmwareError::StoredWiring {
                    node: name.clone(),
                    source: Box::new(source),
                }
            })?,
            None => Wiring::load(wiring).map_err(|source| FirmwareError::Wiring {
                node: name.clone(),
                source: Box::new(source),
            })?,
        };
        let board = Board {
            name,
            elf: stored.as_ref().map_or(Path::new(elf), |s| s.elf.as_path()),
            mcu,
            clock_hz: *clock_hz,
            bus_baud: bus.baud,
            bus_bits: bus.bits_per_char,
        };
        let shown = stored
            .as_ref()
            .map_or(Path::new(elf), |s| Path::new(&s.recorded_file));
        let mut node =
            AvrNode::start_as(board, wiring, params.sensing.clone(), shown).map_err(|source| {
                FirmwareError::Start {
                    node: name.clone(),
                    source,
                }
            })?;
        node.hold_in_boot(SimDuration::from_secs_f64(boot_ms / 1000.0));
        if let Some(debug) = crate::debug::for_node(name)? {
            if let Some(path) = &debug.vcd {
                node.trace_vcd(path, &debug.pins()?)?;
                eprintln!(
                    "twin-avr: tracing {} of `{name}` to {}",
                    debug.vcd_pins.join(", "),
                    path.display()
                );
            }
            if let Some(port) = debug.gdb {
                node.debug_gdb(port)?;
                eprintln!(
                    "twin-avr: `{name}` waits for a debugger on port {port}: avr-gdb {} -ex 'target remote :{port}'",
                    shown.display()
                );
            }
        }
        Ok((Box::new(node), SimDuration::ZERO))
    }
}

pub use crate::stepper::{set_threaded, threaded};

/// Lets this process's scenarios hold firmware nodes.
pub fn register() {
    twin_sim::external::register(Box::new(AvrBuilder));
}
