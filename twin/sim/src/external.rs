//! Nodes another binary knows how to build. A scenario's `firmware` node is
//! a compiled sketch run in simavr, which is GPL: only `twin-avr` links it,
//! and it registers its builder here before it runs anything. `twin` has
//! none and says where to run such a scenario.

use std::sync::OnceLock;

use plant::PlantParams;
use protocols::time::SimDuration;

use crate::engine::SimNode;
use crate::nodes_build::BuildError;

type Result<T, E = BuildError> = std::result::Result<T, E>;
use crate::scenario::{BusSpec, NodeSpec};

/// Builds the nodes of kind `firmware`.
pub trait FirmwareBuilder: Send + Sync {
    /// The node for `spec` on `bus`, with its module's parameters, and its
    /// reply turnaround (the firmware's own: zero). What it refuses is
    /// [`BuildError::Firmware`], in its own words.
    fn build(
        &self,
        spec: &NodeSpec,
        module: Option<&PlantParams>,
        bus: &BusSpec,
    ) -> Result<(Box<dyn SimNode + Send>, SimDuration)>;
}

static BUILDER: OnceLock<Box<dyn FirmwareBuilder>> = OnceLock::new();

/// Installs the builder of firmware nodes for the rest of the process (the
/// first one registered stays).
pub fn register(builder: Box<dyn FirmwareBuilder>) {
    let _ = BUILDER.set(builder);
}

/// Whether a builder of firmware nodes is registered.
pub fn available() -> bool {
    BUILDER.get().is_some()
}

/// A firmware node, by the registered builder.
pub fn build_firmware(
    spec: &NodeSpec,
    module: Option<&PlantParams>,
    bus: &BusSpec,
) -> Result<(Box<dyn SimNode + Send>, SimDuration)> {
    match BUILDER.get() {
        Some(builder) => builder.build(spec, module, bus),
        None => unavailable(spec),
    }
}

/// The error for a firmware node where no builder is registered.
pub fn unavailable<T>(spec: &NodeSpec) -> Result<T> {
    Err(BuildError::FirmwareUnavailable {
        node: spec.name().to_string(),
    })
}
