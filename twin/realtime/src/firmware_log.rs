//! Compiled firmware's own channels in a real-time session: the UART bursts
//! (`/firmware/<node>/uart`, each byte with its CPU cycle) and the pins, ADC
//! inputs and cycle count sampled every 10 ms (`/firmware/<node>/io`), as a
//! virtual run records them.
//!
//! The node hands its records over borrowed; the engine copies them into
//! records it owns and keeps ([`OwnedRecord`]: every string and list
//! cleared and refilled, never freed), a batch per engine tick that had
//! any, sent to the sink and sent back empty once written, as the frames'
//! batches are. A steady session allocates nothing for them after its first
//! second.

use std::sync::mpsc::{Receiver, Sender, channel};

use protocols::time::SimTime;
use twin_recording::topics::{AdcInput, FirmwareIo, PinEdge, PinState, UartBurst};
use twin_sim::engine::FirmwareRecord;

/// Emptied batches kept for reuse.
const SPARES_KEPT: usize = 8;

/// A firmware record copied out of its node, with the node's name.
#[derive(Debug, Default)]
pub struct OwnedRecord {
    node: String,
    at: SimTime,
    io: bool,
    // The UART burst.
    dir: String,
    baud: f64,
    start_s: f64,
    end_s: f64,
    len: usize,
    text: String,
    hex: String,
    byte_cycles: Vec<u64>,
    // The I/O sample.
    cycles: u64,
    pins: Vec<PinState>,
    adc: Vec<AdcInput>,
    edges: Vec<PinEdge>,
}

impl OwnedRecord {
    fn fill(&mut self, node: &str, record: FirmwareRecord<'_>) {
        self.node.clear();
        self.node.push_str(node);
        match record {
            FirmwareRecord::Uart(at, b) => {
                self.at = at;
                self.io = false;
                self.dir.clear();
                self.dir.push_str(b.dir);
                self.baud = b.baud;
                self.start_s = b.start_s;
                self.end_s = b.end_s;
                self.len = b.len;
                self.text.clear();
                self.text.push_str(b.text);
                self.hex.clear();
                self.hex.push_str(b.hex);
                self.byte_cycles.clear();
                self.byte_cycles.extend_from_slice(b.cycles);
            }
            FirmwareRecord::Io(at, io) => {
                self.at = at;
                self.io = true;
                self.cycles = io.cycles;
                self.pins.clear();
                self.pins.extend_from_slice(io.pins);
                self.adc.clear();
                self.adc.extend_from_slice(io.adc);
                self.edges.clear();
                self.edges.extend_from_slice(io.edges);
            }
        }
    }

    /// The node's name and the record, as the node handed it over.
    pub fn record(&self) -> (&str, FirmwareRecord<'_>) {
        let record = if self.io {
            FirmwareRecord::Io(
                self.at,
                FirmwareIo {
                    cycles: self.cycles,
                    pins: &self.pins,
                    adc: &self.adc,
                    edges: &self.edges,
                },
            )
        } else {
            FirmwareRecord::Uart(
                self.at,
                UartBurst {
                    dir: &self.dir,
                    baud: self.baud,
                    start_s: self.start_s,
                    end_s: self.end_s,
                    len: self.len,
                    text: &self.text,
                    hex: &self.hex,
                    cycles: &self.byte_cycles,
                },
            )
        };
        (&self.node, record)
    }
}

/// Records of one engine tick, on their way to the sink.
#[derive(Debug, Default)]
pub struct FirmwareBatch {
    records: Vec<OwnedRecord>,
    used: usize,
    home: Option<Sender<FirmwareBatch>>,
}

impl FirmwareBatch {
    pub fn iter(&self) -> impl Iterator<Item = (&str, FirmwareRecord<'_>)> {
        self.records[..self.used].iter().map(OwnedRecord::record)
    }

    pub fn len(&self) -> usize {
        self.used
    }

    pub fn is_empty(&self) -> bool {
        self.used == 0
    }

    /// Empties the batch (keeping its records' room) and sends it back to
    /// the log it came from.
    pub fn recycle(mut self) {
        self.used = 0;
        if let Some(home) = self.home.take() {
            let _ = home.send(self);
        }
    }
}

/// The engine's side: the batch being filled and the emptied ones coming back.
#[derive(Debug)]
pub struct FirmwareLog {
    filling: FirmwareBatch,
    spares: Receiver<FirmwareBatch>,
    pool: Vec<FirmwareBatch>,
    home: Sender<FirmwareBatch>,
}

impl Default for FirmwareLog {
    fn default() -> Self {
        let (home, spares) = channel();
        Self {
            filling: FirmwareBatch::default(),
            spares,
            pool: Vec::with_capacity(SPARES_KEPT),
            home,
        }
    }
}

impl FirmwareLog {
    /// Copies `record` of `node` into the batch being filled.
    pub fn push(&mut self, node: &str, record: FirmwareRecord<'_>) {
        let batch = &mut self.filling;
        if batch.used == batch.records.len() {
            batch.records.push(OwnedRecord::default());
        }
        if let Some(slot) = batch.records.get_mut(batch.used) {
            slot.fill(node, record);
            batch.used += 1;
        }
    }

    /// The batch filled so far, if it holds anything; a spare takes its place.
    pub fn take(&mut self) -> Option<FirmwareBatch> {
        if self.filling.is_empty() {
            return None;
        }
        while let Ok(spare) = self.spares.try_recv() {
            if self.pool.len() < SPARES_KEPT {
                self.pool.push(spare);
            }
        }
        let next = self.pool.pop().unwrap_or_default();
        let mut batch = std::mem::replace(&mut self.filling, next);
        batch.home = Some(self.home.clone());
        Some(batch)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_batch_gives_back_what_was_pushed_and_its_room_comes_back() {
        let mut log = FirmwareLog::default();
        assert!(log.take().is_none());
        let pins = [PinState {
            pin: "D9",
            signal: "pwm",
            level: true,
            duty: 0.25,
            period_us: 1000.0,
            edges: 20,
        }];
        let io = FirmwareIo {
            cycles: 160_000,
            pins: &pins,
            adc: &[],
            edges: &[],
        };
        log.push("motor", FirmwareRecord::Io(SimTime(10), io));
        let burst = UartBurst {
            dir: "tx",
            baud: 117_647.0,
            start_s: 0.5,
            end_s: 0.6,
            len: 2,
            text: "",
            hex: "0103",
            cycles: &[1, 2],
        };
        log.push("sensor", FirmwareRecord::Uart(SimTime(20), burst));
        let batch = log.take().expect("a batch");
        let got: Vec<_> = batch.iter().collect();
        assert_eq!(got.len(), 2);
        match got[0] {
            ("motor", FirmwareRecord::Io(at, io)) => {
                assert_eq!(at, SimTime(10));
                assert_eq!(io.cycles, 160_000);
                assert_eq!(io.pins, &pins);
            }
            other => panic!("{other:?}"),
        }
        match got[1] {
            ("sensor", FirmwareRecord::Uart(_, b)) => {
                assert_eq!((b.dir, b.hex, b.cycles), ("tx", "0103", &[1u64, 2][..]));
            }
            other => panic!("{other:?}"),
        }
        batch.recycle();
        log.push("motor", FirmwareRecord::Io(SimTime(30), io));
        let second = log.take().expect("a batch");
        assert_eq!(second.len(), 1);
        log.push("motor", FirmwareRecord::Io(SimTime(40), io));
        let third = log.take().expect("a batch");
        // The first batch again, the room of its two records kept.
        assert_eq!(third.len(), 1);
        assert_eq!(third.records.len(), 2);
    }
}
