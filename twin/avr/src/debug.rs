//! The debugging extras simavr users expect, for one firmware node of a
//! run: simavr's GDB stub on a port (`--gdb PORT`, the run waiting for the
//! debugger as `simavr -g` does) and a VCD trace of chosen pins (`--vcd
//! FILE --vcd-pins D9,D2`). Both stay out of the run unless asked: without
//! them the core runs simavr's plain loop.

use std::path::PathBuf;
use std::sync::Mutex;

use crate::wiring::{Pin, pin};

type Result<T, E = DebugError> = std::result::Result<T, E>;

/// Why the debugging extras cannot be given as asked.
#[derive(Debug, thiserror::Error)]
pub enum DebugError {
    #[error("--vcd-pins {name}: no such pin on the ATmega328P (D0–D13, A0–A5)")]
    NoSuchPin { name: String },
    #[error(
        "--gdb and --vcd go to one firmware node, and this scenario has two (`{first}`, \
         `{second}`): name one with --firmware-node"
    )]
    TwoNodes { first: String, second: String },
    /// simavr's GDB stub did not start; `simavr` is its last log line, if any.
    #[error("--gdb {port}: cannot listen on that port (in use?{})", said(.simavr.as_deref()))]
    GdbPort { port: u16, simavr: Option<String> },
}

fn said(simavr: Option<&str>) -> String {
    simavr.map_or_else(String::new, |l| format!("; simavr: {l}"))
}

/// `twin-avr run`'s and `replay`'s debugging options.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct DebugArgs {
    /// Start simavr's GDB stub on PORT for the firmware node: the run waits,
    /// stopped at the reset vector, until a debugger connects (`avr-gdb
    /// FIRMWARE.elf -ex 'target remote :PORT'`) and continues; it goes on
    /// when the debugger detaches.
    #[arg(long, value_name = "PORT", help_heading = "Firmware debugging")]
    pub gdb: Option<u16>,
    /// Write a VCD trace of the pins named by --vcd-pins to FILE, each edge
    /// at its exact CPU cycle (open it in GTKWave or PulseView).
    #[arg(
        long,
        value_name = "FILE",
        requires = "vcd_pins",
        help_heading = "Firmware debugging"
    )]
    pub vcd: Option<PathBuf>,
    /// The pins the VCD trace holds, by their Arduino names: D9,D2,D13,A0.
    #[arg(
        long,
        value_name = "PINS",
        value_delimiter = ',',
        requires = "vcd",
        help_heading = "Firmware debugging"
    )]
    pub vcd_pins: Vec<String>,
    /// The firmware node --gdb and --vcd attach to [default: the scenario's
    /// only one].
    #[arg(long, value_name = "NAME", help_heading = "Firmware debugging")]
    pub firmware_node: Option<String>,
}

impl DebugArgs {
    /// Whether any extra is asked for.
    pub fn any(&self) -> bool {
        self.gdb.is_some() || self.vcd.is_some()
    }

    /// The VCD pins, checked.
    pub fn pins(&self) -> Result<Vec<Pin>> {
        let mut pins: Vec<Pin> = Vec::new();
        for name in &self.vcd_pins {
            let Some(p) = pin(name) else {
                return Err(DebugError::NoSuchPin { name: name.clone() });
            };
            if !pins.contains(&p) {
                pins.push(p);
            }
        }
        Ok(pins)
    }
}

/// The options of this process's run, and the node they went to.
static DEBUG: Mutex<Option<(DebugArgs, Option<String>)>> = Mutex::new(None);

/// Sets the run's debugging options (checked here, before anything runs).
pub fn set(args: DebugArgs) -> Result<()> {
    args.pins()?;
    if let Ok(mut d) = DEBUG.lock() {
        *d = args.any().then_some((args, None));
    }
    Ok(())
}

/// What to tell the user when the options went to no node (a
/// `--firmware-node` the scenario does not have, or no firmware node).
pub fn unused() -> Option<String> {
    let d = DEBUG.lock().ok()?;
    let (args, taken) = d.as_ref()?;
    if taken.is_some() {
        return None;
    }
    Some(match &args.firmware_node {
        Some(name) => format!(
            "--firmware-node {name}: the scenario has no firmware node of that name, so --gdb and --vcd did nothing"
        ),
        None => "the scenario has no firmware node, so --gdb and --vcd did nothing".into(),
    })
}

/// The options for node `name`, if they go to it: to the node named by
/// `--firmware-node`, else to the first firmware node built (a second one
/// is an error: the user must say which).
pub fn for_node(name: &str) -> Result<Option<DebugArgs>> {
    let Ok(mut d) = DEBUG.lock() else {
        return Ok(None);
    };
    let Some((args, taken)) = d.as_mut() else {
        return Ok(None);
    };
    match (&args.firmware_node, taken.as_deref()) {
        (Some(wanted), _) if wanted != name => Ok(None),
        (Some(_), _) => {
            *taken = Some(name.to_string());
            Ok(Some(args.clone()))
        }
        (None, Some(first)) => Err(DebugError::TwoNodes {
            first: first.to_string(),
            second: name.to_string(),
        }),
        (None, None) => {
            *taken = Some(name.to_string());
            Ok(Some(args.clone()))
        }
    }
}
