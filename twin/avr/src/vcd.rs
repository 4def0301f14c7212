//! A VCD trace of chosen pins (`twin-avr run --vcd FILE --vcd-pins D9,D2`),
//! written from the pins' own edges with the exact cycle of each: the
//! trace GTKWave, PulseView or a Python VCD reader opens, as `simavr -t`
//! users expect. Time is in picoseconds (a 16 MHz cycle is 62 500 ps, so
//! every edge falls on its cycle exactly). The file's syntax is the `vcd`
//! crate's writer, the workspace's one VCD writer.

use std::fs::File;
use std::io::{self, BufWriter};
use std::path::{Path, PathBuf};

use vcd::{IdCode, SimulationCommand, TimescaleUnit, Value};

use crate::wiring::Pin;

/// Why a trace could not be started.
#[derive(Debug, thiserror::Error)]
pub enum VcdError {
    #[error("--vcd {}: cannot create it", path.display())]
    Create {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    #[error("--vcd {}: cannot write it", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
}

/// An open trace.
pub struct VcdTrace {
    out: vcd::Writer<BufWriter<File>>,
    path: PathBuf,
    clock_hz: u32,
    /// Per pin index: its identifier in the file.
    ids: [Option<IdCode>; 24],
    /// Bit per pin index traced.
    pub mask: u32,
    /// The time of the last `#` line written, in ps.
    written: Option<u64>,
    /// The last cycle the core reached (the trace's end).
    last_cycle: u64,
    failed: Option<String>,
}

impl std::fmt::Debug for VcdTrace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // vcd::Writer has no Debug of its own.
        f.debug_struct("VcdTrace")
            .field("path", &self.path)
            .field("mask", &self.mask)
            .field("last_cycle", &self.last_cycle)
            .finish_non_exhaustive()
    }
}

impl VcdTrace {
    /// Creates `path` with `pins` at their levels at cycle 0 (`level(index)`).
    pub fn create(
        path: &Path,
        pins: &[Pin],
        clock_hz: u32,
        board: &str,
        level: impl Fn(u8) -> bool,
    ) -> Result<Self, VcdError> {
        let file = File::create(path).map_err(|source| VcdError::Create {
            path: path.to_path_buf(),
            source,
        })?;
        let mut out = vcd::Writer::new(BufWriter::new(file));
        let ids =
            header(&mut out, pins, clock_hz, board, level).map_err(|source| VcdError::Write {
                path: path.to_path_buf(),
                source,
            })?;
        let mask = pins.iter().fold(0u32, |m, pin| m | 1 << pin.index);
        Ok(Self {
            out,
            path: path.to_path_buf(),
            clock_hz,
            ids,
            mask,
            written: Some(0),
            last_cycle: 0,
            failed: None,
        })
    }

    fn ps(&self, cycle: u64) -> u64 {
        (u128::from(cycle) * 1_000_000_000_000 / u128::from(self.clock_hz)) as u64
    }

    /// An edge of pin `index` at `cycle` (ignored if the pin is not traced).
    pub fn edge(&mut self, cycle: u64, index: u8, level: bool) {
        let Some(id) = self.ids.get(usize::from(index)).copied().flatten() else {
            return;
        };
        if self.failed.is_some() {
            return;
        }
        let t = self.ps(cycle);
        let mut write = || {
            if self.written != Some(t) {
                self.out.timestamp(t)?;
                self.written = Some(t);
            }
            self.out.change_scalar(id, Value::from(level))
        };
        if let Err(e) = write() {
            self.failed = Some(format!("--vcd {}: {e}", self.path.display()));
        }
        self.last_cycle = self.last_cycle.max(cycle);
    }

    /// The core has run to `cycle`: where the trace ends if nothing follows.
    pub fn reached(&mut self, cycle: u64) {
        self.last_cycle = self.last_cycle.max(cycle);
    }

    /// Why writing stopped, if it did.
    pub fn failure(&self) -> Option<&str> {
        self.failed.as_deref()
    }
}

/// The definitions and every pin's level at time 0; returns each pin
/// index's identifier.
fn header(
    out: &mut vcd::Writer<BufWriter<File>>,
    pins: &[Pin],
    clock_hz: u32,
    board: &str,
    level: impl Fn(u8) -> bool,
) -> io::Result<[Option<IdCode>; 24]> {
    out.date("simulated")?;
    out.version(&format!("twin-avr {} (simavr)", env!("CARGO_PKG_VERSION")))?;
    out.comment(&format!(
        "{board}: ATmega328P pins at {} MHz, one cycle = {} ps",
        f64::from(clock_hz) / 1e6,
        1e12 / f64::from(clock_hz)
    ))?;
    out.timescale(1, TimescaleUnit::PS)?;
    out.add_module(board)?;
    let mut ids = [None; 24];
    for pin in pins {
        ids[usize::from(pin.index)] = Some(out.add_wire(1, pin.name)?);
    }
    out.upscope()?;
    out.enddefinitions()?;
    out.timestamp(0)?;
    out.begin(SimulationCommand::Dumpvars)?;
    for pin in pins {
        if let Some(id) = ids[usize::from(pin.index)] {
            out.change_scalar(id, Value::from(level(pin.index)))?;
        }
    }
    out.end()?;
    Ok(ids)
}

impl Drop for VcdTrace {
    fn drop(&mut self) {
        // The trace ends where the run did, so a viewer shows the last level.
        let end = self.ps(self.last_cycle);
        if self.failed.is_none() && self.written.is_none_or(|w| w < end) {
            let _ = self.out.timestamp(end);
        }
        let _ = self.out.flush();
    }
}
#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edges_land_on_their_cycles_in_picoseconds() {
        let dir = std::env::temp_dir().join(format!("twin-vcd-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.vcd");
        let pins = [
            crate::wiring::pin("D9").unwrap(),
            crate::wiring::pin("D2").unwrap(),
        ];
        {
            let mut v = VcdTrace::create(&path, &pins, 16_000_000, "ev1", |_| false).unwrap();
            v.edge(16, pins[0].index, true);
            v.edge(16, pins[1].index, true);
            v.edge(33, pins[0].index, false);
            v.edge(40, 5, true); // not traced
            v.reached(100);
        }
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("$timescale 1 ps $end"), "{text}");
        assert!(text.contains("$var wire 1 ! D9 $end"), "{text}");
        assert!(text.contains("$var wire 1 \" D2 $end"), "{text}");
        let body = text.split("$end\n").last().unwrap();
        assert_eq!(body, "#1000000\n1!\n1\"\n#2062500\n0!\n#6250000\n");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
