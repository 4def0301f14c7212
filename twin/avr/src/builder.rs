//! How `twin-avr` builds a scenario's `firmware` nodes (registered with
//! `twin_sim::external` before anything runs).

use anyhow::{Context, Result, bail};
use nodes::time::SimDuration;
use plant::PlantParams;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use twin_sim::engine::SimNode;
use twin_sim::external::FirmwareBuilder;
use twin_sim::scenario::{BusSpec, NodeSpec};

use crate::node::{AvrNode, Board};
use crate::wiring::Wiring;

/// The builder of firmware nodes.
#[derive(Debug, Default)]
pub struct AvrBuilder;

impl FirmwareBuilder for AvrBuilder {
    fn build(
        &self,
        spec: &NodeSpec,
        module: Option<&PlantParams>,
        bus: &BusSpec,
    ) -> Result<(Box<dyn SimNode + Send>, SimDuration)> {
        let NodeSpec::Firmware {
            name,
            elf,
            wiring,
            mcu,
            clock_hz,
            ..
        } = spec
        else {
            bail!("node `{}` is not a firmware node", spec.name());
        };
        let Some(params) = module else {
            bail!("firmware node `{name}` needs a module")
        };
        if !(1_000_000..=32_000_000).contains(clock_hz) {
            bail!(
                "firmware node `{name}`: clock_hz {clock_hz}: give the board's clock, 1 to 32 MHz"
            );
        }
        let wiring = Wiring::load(wiring)
            .with_context(|| format!("firmware node `{name}`, field `wiring`"))?;
        let board = Board {
            name,
            elf: Path::new(elf),
            mcu,
            clock_hz: *clock_hz,
            bus_baud: bus.baud,
            bus_bits: bus.bits_per_char,
        };
        let node = AvrNode::start(board, wiring, params.sensing.clone())
            .with_context(|| format!("firmware node `{name}`, field `elf`"))?;
        Ok((Box::new(node), SimDuration::ZERO))
    }
}

static INLINE: AtomicBool = AtomicBool::new(false);

/// Whether firmware nodes built from now on run ahead on threads of their
/// own (the default) or all on the engine's thread. The run is the same to
/// the byte either way; one thread is for measuring what the others buy.
pub fn set_threaded(threaded: bool) {
    INLINE.store(!threaded, Ordering::Relaxed);
}

/// See [`set_threaded`].
pub fn threaded() -> bool {
    !INLINE.load(Ordering::Relaxed)
}

/// Lets this process's scenarios hold firmware nodes.
pub fn register() {
    twin_sim::external::register(Box::new(AvrBuilder));
}
