//! A VCD trace of chosen pins (`twin-avr run --vcd FILE --vcd-pins D9,D2`),
//! written from the pins' own edges with the exact cycle of each: the
//! trace GTKWave, PulseView or a Python VCD reader opens, as `simavr -t`
//! users expect. Time is in picoseconds (a 16 MHz cycle is 62 500 ps, so
//! every edge falls on its cycle exactly).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::wiring::Pin;

/// An open trace.
#[derive(Debug)]
pub struct VcdTrace {
    out: BufWriter<File>,
    path: PathBuf,
    clock_hz: u32,
    /// Per pin index: its identifier character in the file.
    ids: [Option<u8>; 24],
    /// Bit per pin index traced.
    pub mask: u32,
    /// The time of the last `#` line written, in ps.
    written: Option<u64>,
    /// The last cycle the core reached (the trace's end).
    last_cycle: u64,
    failed: Option<String>,
}

impl VcdTrace {
    /// Creates `path` with `pins` at their levels at cycle 0 (`level(index)`).
    pub fn create(
        path: &Path,
        pins: &[Pin],
        clock_hz: u32,
        board: &str,
        level: impl Fn(u8) -> bool,
    ) -> Result<Self> {
        let file = File::create(path)
            .with_context(|| format!("--vcd {}: cannot create it", path.display()))?;
        let mut out = BufWriter::new(file);
        let mut ids = [None; 24];
        let mut mask = 0u32;
        let mut head = String::new();
        head.push_str("$date simulated $end\n");
        head.push_str(&format!(
            "$version twin-avr {} (simavr) $end\n",
            env!("CARGO_PKG_VERSION")
        ));
        head.push_str(&format!(
            "$comment {board}: ATmega328P pins at {} MHz, one cycle = {} ps $end\n",
            f64::from(clock_hz) / 1e6,
            1e12 / f64::from(clock_hz)
        ));
        head.push_str("$timescale 1 ps $end\n");
        head.push_str(&format!("$scope module {board} $end\n"));
        for (n, pin) in pins.iter().enumerate() {
            // Printable identifiers from `!`.
            let id = b'!' + n as u8;
            ids[usize::from(pin.index)] = Some(id);
            mask |= 1 << pin.index;
            head.push_str(&format!(
                "$var wire 1 {} {} $end\n",
                char::from(id),
                pin.name
            ));
        }
        head.push_str("$upscope $end\n$enddefinitions $end\n#0\n$dumpvars\n");
        for pin in pins {
            let id = ids[usize::from(pin.index)].unwrap_or(b'!');
            head.push_str(&format!(
                "{}{}\n",
                u8::from(level(pin.index)),
                char::from(id)
            ));
        }
        head.push_str("$end\n");
        out.write_all(head.as_bytes())
            .with_context(|| format!("--vcd {}: cannot write it", path.display()))?;
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
        let mut line = [0u8; 48];
        let mut n = 0;
        if self.written != Some(t) {
            n = format_time(&mut line, t);
            self.written = Some(t);
        }
        line[n] = if level { b'1' } else { b'0' };
        line[n + 1] = id;
        line[n + 2] = b'\n';
        if let Err(e) = self.out.write_all(&line[..n + 3]) {
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

/// `#<t>\n` into `buf`; returns its length.
fn format_time(buf: &mut [u8; 48], t: u64) -> usize {
    let mut digits = [0u8; 20];
    let mut v = t;
    let mut k = 0;
    loop {
        digits[k] = b'0' + (v % 10) as u8;
        v /= 10;
        k += 1;
        if v == 0 {
            break;
        }
    }
    buf[0] = b'#';
    for i in 0..k {
        buf[1 + i] = digits[k - 1 - i];
    }
    buf[1 + k] = b'\n';
    k + 2
}

impl Drop for VcdTrace {
    fn drop(&mut self) {
        // The trace ends where the run did, so a viewer shows the last level.
        let end = self.ps(self.last_cycle);
        if self.failed.is_none() && self.written.is_none_or(|w| w < end) {
            let _ = writeln!(self.out, "#{end}");
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
        assert!(text.contains("$var wire 1 ! D9 $end"), "{text}");
        assert!(text.contains("$var wire 1 \" D2 $end"), "{text}");
        let body = text.split("$end\n").last().unwrap();
        assert_eq!(body, "#1000000\n1!\n1\"\n#2062500\n0!\n#6250000\n");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
