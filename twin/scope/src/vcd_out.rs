//! A waveform as a VCD file: one 1-bit wire per line, named like
//! `bus.rs485.ev1.tx`, in one scope, on a 1 ns timescale (sigrok's VCD
//! input takes its sample rate from it). Only edges are written, each at
//! its tick rounded to the nanosecond; the file starts at the window's
//! start with every line's level there and ends at its end.

use std::io::{self, Write};

use protocols::time::TICKS_PER_SECOND;
use vcd::{IdCode, SimulationCommand, TimescaleUnit, Value};

use crate::wave::{Edges, Waveform};

/// What was written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Written {
    pub lines: usize,
    pub edges: u64,
}

const TICKS_PER_NS: u64 = TICKS_PER_SECOND / 1_000_000_000;

fn ns(ticks: u64) -> u64 {
    (ticks + TICKS_PER_NS / 2) / TICKS_PER_NS
}

/// Writes `wave` to `out` as VCD.
pub fn write(wave: &Waveform, out: impl Write) -> io::Result<Written> {
    let mut out = vcd::Writer::new(out);
    let lines = wave.lines();
    out.version(&format!("twin scope {}", env!("CARGO_PKG_VERSION")))?;
    let how = if wave.reconstructed {
        "reconstructed from the recorded byte times"
    } else {
        "as the simulated bus carried it"
    };
    out.comment(&format!(
        "{}: {} baud, 8 data bits, parity {:?}, {} stop bit(s); {how}",
        wave.name, wave.format.baud, wave.format.parity, wave.format.stop_bits
    ))?;
    out.timescale(1, TimescaleUnit::NS)?;
    out.add_module("twin")?;
    let mut ids: Vec<IdCode> = Vec::with_capacity(lines.len());
    for line in &lines {
        ids.push(out.add_wire(1, &line.name)?);
    }
    out.upscope()?;
    out.enddefinitions()?;

    // Every line's edges, each iterator's next edge at or after the window.
    let mut edges: Vec<Edges<'_>> = lines.iter().map(|l| wave.edges(l.kind)).collect();
    let mut heads: Vec<Option<(u64, bool)>> = Vec::with_capacity(lines.len());
    out.timestamp(ns(wave.from))?;
    out.begin(SimulationCommand::Dumpvars)?;
    for (i, line) in lines.iter().enumerate() {
        let mut level = Waveform::idle(line.kind);
        let mut head = edges[i].next();
        while let Some((at, l)) = head {
            if at > wave.from {
                break;
            }
            level = l;
            head = edges[i].next();
        }
        heads.push(head);
        out.change_scalar(ids[i], Value::from(level))?;
    }
    out.end()?;
    let mut written = Written {
        lines: lines.len(),
        edges: 0,
    };
    let mut last = ns(wave.from);
    while let Some((i, (at, level))) = heads
        .iter()
        .enumerate()
        .filter_map(|(i, h)| h.map(|h| (i, h)))
        .min_by_key(|&(i, (at, _))| (at, i))
    {
        if at >= wave.to {
            break;
        }
        let t = ns(at);
        if t != last {
            out.timestamp(t)?;
            last = t;
        }
        out.change_scalar(ids[i], Value::from(level))?;
        written.edges += 1;
        heads[i] = edges[i].next();
    }
    if ns(wave.to) > last {
        out.timestamp(ns(wave.to))?;
    }
    out.flush()?;
    Ok(written)
}
