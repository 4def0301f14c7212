//! A waveform as a VCD file: one 1-bit wire per line, named like
//! `bus.rs485.ev1.tx`, in one scope, on a 1 ns timescale (sigrok's VCD
//! input takes its sample rate from it). Only edges are written, each at
//! its tick rounded to the nanosecond, at the run's time; the file starts
//! at the window's start with every line's level there and ends at its end.
//! A window with an idle lead-in starts that much earlier, every line idle;
//! when that would be before the run's 0 s, every time is shifted by what
//! is missing, and a comment says by how much.

use std::io::{self, Write};

use protocols::time::TICKS_PER_SECOND;
use vcd::{IdCode, SimulationCommand, TimescaleUnit, Value};

use crate::wave::{Edges, Parity, Waveform};

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
    let parity = match wave.format.parity {
        Parity::None => "none",
        Parity::Even => "even",
        Parity::Odd => "odd",
    };
    out.comment(&format!(
        "{}: {} baud, 8 data bits, parity {parity}, {} stop bit(s); {how}",
        wave.name, wave.format.baud, wave.format.stop_bits
    ))?;
    // Idle line before the window; before the run's 0 s, times move later.
    let shift = wave.lead_in.saturating_sub(wave.from);
    let start = (wave.from + shift) - wave.lead_in;
    let at_ns = |ticks: u64| ns(ticks + shift);
    if wave.lead_in > 0 {
        let lead_us = wave.lead_in as f64 * 1e6 / TICKS_PER_SECOND as f64;
        let mut note = format!(
            "the window starts with {lead_us:.3} us of idle line added, so a decoder sees the first start bit"
        );
        if shift > 0 {
            note.push_str(&format!("; every time is the run's plus {} ns", ns(shift)));
        }
        out.comment(&note)?;
    }
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
    let mut levels: Vec<bool> = Vec::with_capacity(lines.len());
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
        levels.push(level);
    }
    let mut last = ns(start);
    out.timestamp(last)?;
    out.begin(SimulationCommand::Dumpvars)?;
    for (i, line) in lines.iter().enumerate() {
        let level = if wave.lead_in > 0 {
            Waveform::idle(line.kind)
        } else {
            levels[i]
        };
        out.change_scalar(ids[i], Value::from(level))?;
    }
    out.end()?;
    if wave.lead_in > 0 {
        let mut stamped = false;
        for (i, line) in lines.iter().enumerate() {
            if levels[i] != Waveform::idle(line.kind) {
                if !stamped {
                    last = at_ns(wave.from);
                    out.timestamp(last)?;
                    stamped = true;
                }
                out.change_scalar(ids[i], Value::from(levels[i]))?;
            }
        }
    }
    let mut written = Written {
        lines: lines.len(),
        edges: 0,
    };
    while let Some((i, (at, level))) = heads
        .iter()
        .enumerate()
        .filter_map(|(i, h)| h.map(|h| (i, h)))
        .min_by_key(|&(i, (at, _))| (at, i))
    {
        if at >= wave.to {
            break;
        }
        let t = at_ns(at);
        if t != last {
            out.timestamp(t)?;
            last = t;
        }
        out.change_scalar(ids[i], Value::from(level))?;
        written.edges += 1;
        heads[i] = edges[i].next();
    }
    if at_ns(wave.to) > last {
        out.timestamp(at_ns(wave.to))?;
    }
    out.flush()?;
    Ok(written)
}
