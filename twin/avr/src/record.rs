//! What a firmware node keeps for its recording: the bursts on its UART in
//! both directions with the cycle of every byte, and every 10 ms its pins
//! (level, duty, edges), the ADC inputs fed to it and its cycle count
//! (`/firmware/<node>/uart`, `/firmware/<node>/io` in
//! `twin_recording::topics`). Every buffer is made once, at the node's
//! start, and reused: nothing is allocated per byte or per edge.

use protocols::time::{SimDuration, SimTime};
use twin_recording::topics::{AdcInput, FirmwareIo, PinEdge, PinState, UartBurst};
use twin_sim::engine::{FirmwareRecord, ObserveError};

/// Bytes a burst holds before it is recorded even if the line stays busy.
const BURST_BYTES: usize = 1024;
/// Edges listed per pin and sample (10 ms): every edge of a line that
/// changes up to a kilohertz (the enable lines, a software PWM). A faster
/// PWM (the EV sketch's 15.6 kHz on D9) is described by its duty, period
/// and edge count instead: its every edge is a VCD trace's job.
pub const EDGES_LISTED: u16 = 20;
/// Edges kept between two samples.
const EDGES: usize = 24 * EDGES_LISTED as usize;

/// Bytes on the wire in one direction, one after another.
#[derive(Debug)]
struct Burst {
    dir: &'static str,
    bytes: Vec<u8>,
    cycles: Vec<u64>,
    start: SimTime,
    end: SimTime,
    baud: f64,
}

impl Burst {
    fn new(dir: &'static str) -> Self {
        Self {
            dir,
            bytes: Vec::with_capacity(BURST_BYTES),
            cycles: Vec::with_capacity(BURST_BYTES),
            start: SimTime::ZERO,
            end: SimTime::ZERO,
            baud: 0.0,
        }
    }

    fn clear(&mut self) {
        self.bytes.clear();
        self.cycles.clear();
    }
}

/// One direction of the UART: the burst on the line, and the one before it
/// if it has not been recorded yet.
#[derive(Debug)]
struct Direction {
    current: Burst,
    done: Burst,
}

impl Direction {
    fn new(dir: &'static str) -> Self {
        Self {
            current: Burst::new(dir),
            done: Burst::new(dir),
        }
    }

    /// A byte on the wire from `start` to `end`, started at CPU `cycle`; a
    /// line quiet for `gap` before it starts a new burst.
    fn push(
        &mut self,
        byte: u8,
        cycle: u64,
        start: SimTime,
        end: SimTime,
        baud: f64,
        gap: SimDuration,
    ) {
        let c = &mut self.current;
        let quiet = !c.bytes.is_empty() && start > c.end + gap;
        let full = c.bytes.len() >= BURST_BYTES;
        if full && !self.done.bytes.is_empty() {
            // Nobody drains this log (a real-time session records no
            // firmware channels): keep it bounded.
            self.done.clear();
        }
        if (quiet || full) && self.done.bytes.is_empty() {
            std::mem::swap(&mut self.current, &mut self.done);
            self.current.clear();
        }
        let c = &mut self.current;
        if c.bytes.is_empty() {
            c.start = start;
        }
        c.bytes.push(byte);
        c.cycles.push(cycle);
        c.end = end;
        c.baud = baud;
    }
}

/// An output pin the recording follows.
#[derive(Debug, Clone, Copy)]
pub struct Followed {
    pub index: u8,
    pub pin: &'static str,
    pub signal: &'static str,
}

/// An analog input the recording follows.
#[derive(Debug, Clone, Copy)]
pub struct FollowedInput {
    pub channel: u8,
    pub pin: &'static str,
    pub signal: &'static str,
}

/// A firmware node's recording, between two drains.
#[derive(Debug)]
pub struct FirmwareLog {
    rx: Direction,
    tx: Direction,
    hex: String,
    text: String,
    /// Pins followed, and per pin (cycle, cycles high, edges) at the last sample.
    pub followed: Vec<Followed>,
    last: Vec<(u64, u64, u64)>,
    pub inputs: Vec<FollowedInput>,
    /// Pin index → name, for the edges.
    names: [&'static str; 24],
    /// Bit per pin index whose edges are recorded.
    pub mask: u32,
    edges: Vec<PinEdge>,
    /// Per pin index, in this sample period: edges listed, rising edges,
    /// and the cycles of the first and last rising edge.
    listed: [u16; 24],
    rises: [u32; 24],
    first_rise: [u64; 24],
    last_rise: [u64; 24],
    clock_hz: u32,
    pins: Vec<PinState>,
    adc: Vec<AdcInput>,
    cycles: u64,
    /// A sample is ready, taken at this time.
    sample_at: Option<SimTime>,
}

impl FirmwareLog {
    pub fn new(followed: Vec<Followed>, inputs: Vec<FollowedInput>, clock_hz: u32) -> Self {
        let mut names = [""; 24];
        let mut mask = 0u32;
        for f in &followed {
            names[usize::from(f.index)] = f.pin;
            mask |= 1 << f.index;
        }
        Self {
            rx: Direction::new("rx"),
            tx: Direction::new("tx"),
            hex: String::with_capacity(2 * BURST_BYTES),
            text: String::with_capacity(BURST_BYTES),
            last: vec![(0, 0, 0); followed.len()],
            pins: Vec::with_capacity(followed.len()),
            adc: Vec::with_capacity(inputs.len()),
            followed,
            inputs,
            names,
            mask,
            edges: Vec::with_capacity(EDGES),
            listed: [0; 24],
            rises: [0; 24],
            first_rise: [0; 24],
            last_rise: [0; 24],
            clock_hz: clock_hz.max(1),
            cycles: 0,
            sample_at: None,
        }
    }

    /// A byte the firmware received.
    pub fn received(
        &mut self,
        byte: u8,
        cycle: u64,
        start: SimTime,
        end: SimTime,
        baud: f64,
        gap: SimDuration,
    ) {
        self.rx.push(byte, cycle, start, end, baud, gap);
    }

    /// A byte the firmware sent.
    pub fn sent(
        &mut self,
        byte: u8,
        cycle: u64,
        start: SimTime,
        end: SimTime,
        baud: f64,
        gap: SimDuration,
    ) {
        self.tx.push(byte, cycle, start, end, baud, gap);
    }

    /// An edge of a watched pin, if it is one the recording follows.
    pub fn edge(&mut self, cycle: u64, index: u8, level: bool) {
        if self.mask >> index & 1 == 0 {
            return;
        }
        let i = usize::from(index);
        if level {
            if self.rises[i] == 0 {
                self.first_rise[i] = cycle;
            }
            self.rises[i] += 1;
            self.last_rise[i] = cycle;
        }
        if self.listed[i] < EDGES_LISTED {
            self.listed[i] += 1;
            self.edges.push(PinEdge {
                cycle,
                pin: self.names[i],
                level,
            });
        }
    }

    /// Takes the sample of `now`: per followed pin its level, and from
    /// `pin_output(index)` = (level, edges, cycles high) its duty since the
    /// last sample; the ADC inputs as `millivolts(channel)` gives them.
    pub fn sample(
        &mut self,
        now: SimTime,
        cycle: u64,
        pin_output: impl Fn(u8) -> (bool, u64, u64),
        level: impl Fn(u8) -> bool,
        millivolts: impl Fn(u8) -> u32,
    ) {
        if self.sample_at.is_some() {
            // The last sample was never drained (a real-time session):
            // its edges go with it, so the buffer stays bounded.
            self.edges.clear();
        }
        self.pins.clear();
        for (i, f) in self.followed.iter().enumerate() {
            let (_, edges, high) = pin_output(f.index);
            let (last_cycle, last_high, last_edges) = self.last[i];
            let span = cycle.saturating_sub(last_cycle);
            let on = level(f.index);
            let duty = if edges == last_edges || span == 0 {
                f64::from(u8::from(on))
            } else {
                high.saturating_sub(last_high) as f64 / span as f64
            };
            let p = usize::from(f.index);
            let period_us = if self.rises[p] >= 2 {
                let cycles =
                    (self.last_rise[p] - self.first_rise[p]) as f64 / f64::from(self.rises[p] - 1);
                (cycles / f64::from(self.clock_hz) * 1e9).round() / 1e3
            } else {
                0.0
            };
            self.pins.push(PinState {
                pin: f.pin,
                signal: f.signal,
                level: on,
                // To a part in a million: enough for a duty, and no
                // floating-point noise in the file.
                duty: (duty * 1e6).round() / 1e6,
                period_us,
                edges: u32::try_from(edges - last_edges).unwrap_or(u32::MAX),
            });
            self.last[i] = (cycle, high, edges);
            self.listed[p] = 0;
            self.rises[p] = 0;
        }
        self.adc.clear();
        for a in &self.inputs {
            let mv = millivolts(a.channel);
            self.adc.push(AdcInput {
                pin: a.pin,
                signal: a.signal,
                millivolts: mv,
                counts: (u64::from(mv) * 1024 / 5000).min(1023) as u16,
            });
        }
        self.cycles = cycle;
        self.sample_at = Some(now);
    }

    /// Hands `record` the bursts that have ended by `now` (the line quiet
    /// for `gap` after them) and the sample, if one is ready.
    pub fn drain(
        &mut self,
        now: SimTime,
        gap: SimDuration,
        record: &mut dyn FnMut(FirmwareRecord<'_>) -> Result<(), ObserveError>,
    ) -> Result<(), ObserveError> {
        for dir in [&mut self.rx, &mut self.tx] {
            if !dir.done.bytes.is_empty() {
                emit(&dir.done, &mut self.hex, &mut self.text, record)?;
                dir.done.clear();
            }
            if !dir.current.bytes.is_empty() && dir.current.end + gap <= now {
                emit(&dir.current, &mut self.hex, &mut self.text, record)?;
                dir.current.clear();
            }
        }
        if let Some(at) = self.sample_at.take() {
            record(FirmwareRecord::Io(
                at,
                FirmwareIo {
                    cycles: self.cycles,
                    pins: &self.pins,
                    adc: &self.adc,
                    edges: &self.edges,
                },
            ))?;
            self.edges.clear();
        }
        Ok(())
    }
}

fn emit(
    burst: &Burst,
    hex: &mut String,
    text: &mut String,
    record: &mut dyn FnMut(FirmwareRecord<'_>) -> Result<(), ObserveError>,
) -> Result<(), ObserveError> {
    hex.clear();
    text.clear();
    twin_recording::topics::put_hex(hex, &burst.bytes);
    if burst
        .bytes
        .iter()
        .all(|b| b.is_ascii_graphic() || matches!(b, b' ' | b'\n' | b'\r'))
    {
        text.extend(burst.bytes.iter().map(|&b| char::from(b)));
    }
    record(FirmwareRecord::Uart(
        burst.start,
        UartBurst {
            dir: burst.dir,
            baud: burst.baud.round(),
            start_s: burst.start.as_secs_f64(),
            end_s: burst.end.as_secs_f64(),
            len: burst.bytes.len(),
            text,
            hex,
            cycles: &burst.cycles,
        },
    ))
}

/// What the recording follows on a board wired by `wiring`: its outputs
/// and PWM pins, and its analog inputs.
pub fn follow(wiring: &crate::wiring::Wiring, clock_hz: u32) -> FirmwareLog {
    use crate::wiring::{Analog, Output, Pwm};
    let mut pins: Vec<Followed> = wiring
        .outputs
        .iter()
        .map(|&(p, o)| Followed {
            index: p.index,
            pin: p.name,
            signal: match o {
                Output::En => "en",
                Output::Brk => "brk",
                Output::Pro => "pro",
                Output::Des => "des",
                Output::Fr => "fr",
                Output::Chg => "chg",
                Output::Led => "led",
                Output::DriverSleep => "driver_sleep",
            },
        })
        .collect();
    pins.extend(wiring.pwm.iter().map(|&(p, Pwm::Vel)| Followed {
        index: p.index,
        pin: p.name,
        signal: "vel",
    }));
    // In the order of the Arduino's pin numbers: D0–D7 are port D, D8–D13
    // port B.
    pins.sort_by_key(|f| match f.index {
        16.. => f.index - 16,
        0..8 => f.index + 8,
        _ => f.index + 6,
    });
    let inputs = wiring
        .analog
        .iter()
        .map(|&(p, a)| FollowedInput {
            channel: p.adc.unwrap_or(0),
            pin: p.name,
            signal: match a {
                Analog::V1 => "v1",
                Analog::V2 => "v2",
                Analog::I => "i",
                Analog::Ldr => "ldr",
            },
        })
        .collect();
    FirmwareLog::new(pins, inputs, clock_hz)
}

/// SHA-256 of `bytes` in lowercase hex, as `sha256sum` prints it.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn us(v: u64) -> SimTime {
        SimTime::ZERO + SimDuration::from_micros(v)
    }

    #[test]
    fn bytes_a_quiet_line_apart_are_two_bursts_with_every_cycle() {
        let mut log = FirmwareLog::new(Vec::new(), Vec::new(), 16_000_000);
        let gap = SimDuration::from_micros(170);
        for (i, b) in b"@01".iter().enumerate() {
            let t = 85 * i as u64;
            log.sent(*b, t * 16, us(t), us(t + 85), 117_647.0, gap);
        }
        log.sent(b'X', 1000 * 16, us(1000), us(1085), 117_647.0, gap);
        let mut seen = Vec::new();
        log.drain(us(2000), gap, &mut |r| {
            if let FirmwareRecord::Uart(at, b) = r {
                seen.push((at, b.text.to_string(), b.cycles.to_vec(), b.end_s));
            }
            Ok(())
        })
        .unwrap();
        assert_eq!(seen.len(), 2, "{seen:?}");
        assert_eq!(seen[0].1, "@01");
        assert_eq!(seen[0].2, [0, 85 * 16, 170 * 16]);
        assert!((seen[0].3 - 255e-6).abs() < 1e-9);
        assert_eq!(seen[1].0, us(1000));
        assert_eq!(seen[1].1, "X");
    }
}
