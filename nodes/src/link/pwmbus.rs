//! The PWM-capture paper's link as a medium beside [`super::SimBus`]:
//! pulse widths in, captured widths out, in time.
//!
//! A node hands the link one frame as the compare values its PWM timer will
//! send: ON widths in counter ticks, start symbol first, each a `u32`
//! little-endian (4 bytes per symbol). The timer sends one pulse every
//! `S + C_max + guard` ticks (the coding's period plus an optional guard gap
//! of OFF ticks). Every listener has its own cable ([`PwmLine`]: RC low-pass,
//! noisy comparator, seeded per port) and capture unit; each pulse it
//! captures is delivered as a 4-byte record — the captured ON width, `u32`
//! little-endian — at the instant its falling edge crossed the threshold,
//! which is when the capture interrupt reads it. A pulse the line swallowed
//! or merged is simply not delivered. Framing, start-width compensation and
//! the dummy bits are the receiver's software, not the link's.
//!
//! Duplex, as in the paper's Fig. 6:
//! - **half**: one PWM/capture pair shared by all. The enable signal says who
//!   drives it: a port raises it when its frame starts and drops it when the
//!   frame ends; a frame handed over while another port holds the enable
//!   waits for it to drop (the slave "waits in the low state").
//! - **full**: two pairs. The master's frames go down one to every slave; the
//!   slaves' frames go up the other to the master only. No enable between
//!   master and slaves; slaves sharing the return pair still take turns.
//!
//! Nothing here reads a clock or panics; buffers are allocated when ports
//! are added and grow only when more pulses are in flight than ever before.

use protocols::pwmcap::PwmCoding;
use protocols::time::{SimDuration, SimTime};

use super::pwmline::{PWM_LINE_MAX_SYMBOLS, PwmCapture, PwmLine, PwmLineError, PwmLineParams};
use super::simbus::{BusError, BusEvent, BusStats, FrameInfo, PortConfig, PortId};

/// Bytes per symbol in a frame handed to the link, and per capture record delivered.
pub const PWM_RECORD_BYTES: usize = 4;

/// How the PWM/capture channels are wired.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PwmDuplex {
    /// One pair for both directions, with an enable signal.
    #[default]
    Half,
    /// A pair each way; `master` sends down one, everyone else up the other.
    Full {
        /// The master's port.
        master: PortId,
    },
}

/// A PWM-capture link's configuration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PwmBusConfig {
    /// Counter clock, data and dummy bits, start width.
    pub coding: PwmCoding,
    /// OFF ticks added to every symbol period (0: the paper's `S + C_max`).
    pub guard_ticks: u32,
    /// Every listener's cable, comparator and noise.
    pub line: PwmLineParams,
    /// Half or full duplex.
    pub duplex: PwmDuplex,
    /// Seeds every listener's noise and counter phase.
    pub seed: u64,
}

impl Default for PwmBusConfig {
    /// The paper's coding on the twin's default 10 m line, half duplex.
    fn default() -> Self {
        PwmBusConfig {
            coding: PwmCoding::PAPER,
            guard_ticks: 0,
            line: PwmLineParams::DEFAULT,
            duplex: PwmDuplex::Half,
            seed: 0,
        }
    }
}

/// What the link has carried so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PwmStats {
    /// Frames handed to the link.
    pub frames_sent: u64,
    /// Symbols in them, start symbols included.
    pub symbols_sent: u64,
    /// Frames that waited for another port's enable (half) or frame (full) to end.
    pub frames_deferred: u64,
    /// Frame receptions, one per listener.
    pub receptions: u64,
    /// Receptions in which every pulse arrived and decodes to what was sent.
    pub receptions_clean: u64,
    /// Pulses the listeners captured.
    pub pulses_captured: u64,
    /// Pulses sent but not captured (swallowed or merged by the line).
    pub pulses_lost: u64,
    /// Captured data pulses that decode to another value than was sent
    /// (against the captured start, as the receiver decodes them).
    pub symbols_wrong: u64,
}

/// One listener's view of the last frame, for the recording.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PwmReception {
    /// The listener.
    pub to: PortId,
    /// The ON widths its capture unit measured, in order.
    pub captured: Vec<u32>,
    /// Sent pulses it did not capture.
    pub lost: usize,
    /// Captured data pulses that decode wrong.
    pub wrong: usize,
}

/// The last frame sent, as sent and as every listener captured it.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct PwmFrameRecord {
    /// The ON widths sent, start first.
    pub sent: Vec<u32>,
    /// The symbol period, ticks.
    pub period_ticks: u32,
    /// Per listener, in port order.
    pub receptions: Vec<PwmReception>,
}

#[derive(Debug, Clone)]
struct Port {
    config: PortConfig,
    line: PwmLine,
}

/// A pulse record (or end of frame) waiting for its instant.
#[derive(Debug, Clone, Copy)]
struct Pending {
    at: SimTime,
    seq: u64,
    event: BusEvent,
}

/// The PWM-capture medium.
#[derive(Debug, Clone)]
pub struct PwmBus {
    config: PwmBusConfig,
    /// Every port's line is this one with its own seed.
    template: PwmLine,
    period_ticks: u32,
    ports: Vec<Port>,
    /// Per channel (half: one; full: down, up), when its current frame ends.
    busy_until: [SimTime; 2],
    pending: Vec<Pending>,
    seq: u64,
    stats: PwmStats,
    bus_stats: BusStats,
    last: PwmFrameRecord,
    captures: [PwmCapture; PWM_LINE_MAX_SYMBOLS],
}

impl PwmBus {
    /// A link with no ports yet; the line parameters and the period are checked.
    pub fn new(config: PwmBusConfig) -> Result<Self, PwmLineError> {
        config.line.validate()?;
        let period_ticks = config
            .coding
            .symbol_period_ticks()
            .checked_add(config.guard_ticks)
            .ok_or(PwmLineError::InvalidParameter("guard_ticks"))?;
        let template = PwmLine::new(config.line, config.coding.clock_hz(), config.seed)?;
        Ok(PwmBus {
            config,
            template,
            period_ticks,
            ports: Vec::new(),
            busy_until: [SimTime::ZERO; 2],
            pending: Vec::new(),
            seq: 0,
            stats: PwmStats::default(),
            bus_stats: BusStats::default(),
            last: PwmFrameRecord::default(),
            captures: [PwmCapture::default(); PWM_LINE_MAX_SYMBOLS],
        })
    }

    /// The configuration.
    pub fn config(&self) -> &PwmBusConfig {
        &self.config
    }

    /// Ticks from one symbol's rising edge to the next one's.
    pub fn period_ticks(&self) -> u32 {
        self.period_ticks
    }

    /// The link's own counters.
    pub fn pwm_stats(&self) -> &PwmStats {
        &self.stats
    }

    /// The counters in the serial bus' terms (bytes are 4-byte pulse
    /// records; a record that decodes wrong counts as corrupted by noise).
    pub fn stats(&self) -> &BusStats {
        &self.bus_stats
    }

    /// The last frame sent and what every listener captured of it.
    pub fn last_frame(&self) -> &PwmFrameRecord {
        &self.last
    }

    /// Attach a port; its cable gets its own noise stream.
    pub fn add_port(&mut self, config: PortConfig) -> PortId {
        let index = self.ports.len() as u64;
        let seed = self
            .config
            .seed
            .wrapping_add((index + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let line = self.template.reseeded(seed);
        self.ports.push(Port { config, line });
        let id = PortId(u16::try_from(self.ports.len() - 1).unwrap_or(u16::MAX));
        self.last.receptions.push(PwmReception {
            to: id,
            captured: Vec::with_capacity(PWM_LINE_MAX_SYMBOLS),
            lost: 0,
            wrong: 0,
        });
        id
    }

    /// Which channel `from` drives, and whether `listener` hears it.
    fn channel(&self, from: PortId) -> usize {
        match self.config.duplex {
            PwmDuplex::Half => 0,
            PwmDuplex::Full { master } => usize::from(from != master),
        }
    }

    fn hears(&self, listener: PortId, talker: PortId) -> bool {
        listener != talker
            && match self.config.duplex {
                PwmDuplex::Half => true,
                PwmDuplex::Full { master } => listener == master || talker == master,
            }
    }

    /// A frame of ON widths (4-byte little-endian records, start first) from
    /// `from`, handed over at `now`. A malformed frame (length not a multiple
    /// of 4, no symbol, too many, a width not below the period) is refused
    /// with [`BusError::Malformed`] and nothing is sent.
    pub fn send(
        &mut self,
        now: SimTime,
        from: PortId,
        bytes: &[u8],
    ) -> Result<FrameInfo, BusError> {
        let Some(port) = self.ports.get(from.index()) else {
            return Err(BusError::UnknownPort(from));
        };
        let turnaround = port.config.turnaround;
        let mut widths = [0u32; PWM_LINE_MAX_SYMBOLS];
        let symbols = bytes.len() / PWM_RECORD_BYTES;
        if !bytes.len().is_multiple_of(PWM_RECORD_BYTES) || symbols == 0 || symbols > widths.len() {
            return Err(BusError::Malformed(
                "a PWM frame is 1 to 18 four-byte widths",
            ));
        }
        for (width, chunk) in widths.iter_mut().zip(bytes.chunks_exact(PWM_RECORD_BYTES)) {
            *width = u32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
            if *width >= self.period_ticks || *width == 0 {
                return Err(BusError::Malformed(
                    "a PWM width must be above 0 and below the symbol period",
                ));
            }
        }
        let widths = &widths[..symbols];
        let channel = self.channel(from);
        let wanted = now + turnaround;
        let start = wanted.max(self.busy_until[channel]);
        if start > wanted {
            self.stats.frames_deferred += 1;
        }
        let hz = f64::from(self.config.coding.clock_hz());
        let end = start + ticks_to(hz, f64::from(self.period_ticks) * symbols as f64);
        self.busy_until[channel] = end;
        self.stats.frames_sent += 1;
        self.stats.symbols_sent += symbols as u64;
        self.bus_stats.frames_sent += 1;
        self.bus_stats.bytes_sent += bytes.len() as u64;
        self.last.sent.clear();
        self.last.sent.extend_from_slice(widths);
        self.last.period_ticks = self.period_ticks;

        let coding = self.config.coding;
        let hz = f64::from(coding.clock_hz());
        let sent_value = |i: usize| coding.decode_width(widths[i], widths[0]).ok();
        for l in 0..self.ports.len() {
            let listener = PortId(l as u16);
            let reception = &mut self.last.receptions[l];
            reception.captured.clear();
            reception.lost = 0;
            reception.wrong = 0;
            if !self.hears(listener, from) {
                continue;
            }
            let got = self.ports[l]
                .line
                .transmit_timed(widths, self.period_ticks, &mut self.captures)
                .map_err(|_| BusError::Malformed("width not below the period"))?;
            let captures = &self.captures[..got];
            let start_width = captures.first().map_or(0, |c| c.width);
            let reception = &mut self.last.receptions[l];
            reception.lost = symbols - got;
            for (i, c) in captures.iter().enumerate() {
                reception.captured.push(c.width);
                let wrong = i > 0
                    && (got != symbols
                        || coding.decode_width(c.width, start_width).ok() != sent_value(i));
                reception.wrong += usize::from(wrong);
                let at = start + ticks_to(hz, c.fall_at_ticks);
                for (k, byte) in c.width.to_le_bytes().into_iter().enumerate() {
                    let index = i * PWM_RECORD_BYTES + k;
                    self.seq += 1;
                    self.pending.push(Pending {
                        at,
                        seq: self.seq,
                        event: BusEvent::Byte {
                            to: listener,
                            at,
                            byte,
                            corrupted: wrong,
                            from,
                            index,
                            last: index + 1 == got * PWM_RECORD_BYTES,
                        },
                    });
                }
            }
            let (lost, wrong) = (reception.lost, reception.wrong);
            self.stats.receptions += 1;
            self.stats.receptions_clean += u64::from(lost == 0 && wrong == 0);
            self.stats.pulses_captured += got as u64;
            self.stats.pulses_lost += lost as u64;
            self.stats.symbols_wrong += wrong as u64;
            self.bus_stats.bytes_delivered += (got * PWM_RECORD_BYTES) as u64;
            self.bus_stats.bytes_corrupted_by_noise += (wrong * PWM_RECORD_BYTES) as u64;
        }
        self.seq += 1;
        self.pending.push(Pending {
            at: end,
            seq: self.seq,
            event: BusEvent::TransmitDone {
                port: from,
                at: end,
            },
        });
        Ok(FrameInfo { from, start, end })
    }

    fn earliest(&self) -> Option<usize> {
        self.pending
            .iter()
            .enumerate()
            .min_by_key(|(_, p)| (p.at, p.seq))
            .map(|(i, _)| i)
    }

    /// When the next pulse record lands or frame ends.
    pub fn poll_timeout(&self) -> Option<SimTime> {
        self.earliest().map(|i| self.pending[i].at)
    }

    /// The next delivery due at or before `now`.
    pub fn poll_event(&mut self, now: SimTime) -> Option<BusEvent> {
        let i = self.earliest()?;
        if self.pending[i].at > now {
            return None;
        }
        Some(self.pending.swap_remove(i).event)
    }
}

/// `counter_ticks` of a `hz` counter as simulated time.
fn ticks_to(hz: f64, counter_ticks: f64) -> SimDuration {
    SimDuration::from_secs_f64(counter_ticks.max(0.0) / hz)
}
