//! A simulated RS-485 bus: half duplex, multi-drop, at a fixed baud.
//!
//! Sans-IO like the nodes: [`SimBus::send`] puts a frame on the line, and the
//! engine drains timed arrivals with [`SimBus::poll_timeout`] /
//! [`SimBus::poll_event`]. Every byte arrives at the exact instant its stop bit
//! ends, `start + (i + 1) × bits_per_char / baud`, computed from the frame's
//! start each time so no rounding accumulates (exact in ticks for every
//! standard baud, see [`crate::time`]).
//!
//! The physics that matter to a master's timing and error handling:
//! - **Turnaround**: a port's frame starts a fixed delay after the instant it
//!   is handed to the bus (the firmware's reply latency).
//! - **Collisions**: RS-485 drivers do not listen before they talk. Bytes whose
//!   wire time overlaps another port's frame are garbled, the same way for every
//!   listener, and flagged `corrupted`.
//! - **Noise**: each data bit flips independently at the configured rate, at
//!   each receiver (a seeded stream consumed in delivery order).
//!
//! Where the line differs from what a port sent (a character a collision
//! garbled, bits noise flipped at a listener) is kept as a [`LineMark`] when
//! asked ([`SimBus::keep_line_marks`]), for a recording to say where.
//!
//! Buffers are allocated when ports are added; the pool of in-flight frames
//! grows only when more frames overlap than ever before, never per byte.
//! Nothing here panics on any input.

use std::collections::VecDeque;

use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;
use thiserror::Error;

use super::noise::BitNoise;
use crate::node::MAX_FRAME;
use protocols::time::{SimDuration, SimTime, TICKS_PER_SECOND};

/// Added to the seed for the collision-garbling stream, so noise statistics do
/// not depend on how many collisions happened.
const COLLISION_STREAM: u64 = 0x9E37_79B9_7F4A_7C15;

/// A port on the bus: ports are numbered 0, 1, 2… in the order they are added.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct PortId(pub u16);

impl PortId {
    /// The port's position in the order ports were added.
    pub fn index(self) -> usize {
        usize::from(self.0)
    }
}

/// Who hears whom.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Wiring {
    /// One pair shared by all: every port hears every other.
    #[default]
    MultiDrop,
    /// As in the Controller_network project: the master hears every slave, a
    /// slave hears only the master (slaves never hear each other).
    MasterSlaves {
        /// The port of the master.
        master: PortId,
    },
}

impl Wiring {
    /// Whether `listener` hears what `talker` sends. Nobody hears itself: its
    /// receiver is off while it drives the line.
    pub fn hears(self, listener: PortId, talker: PortId) -> bool {
        listener != talker
            && match self {
                Wiring::MultiDrop => true,
                Wiring::MasterSlaves { master } => listener == master || talker == master,
            }
    }
}

/// Line parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BusConfig {
    /// Bits per second.
    pub baud: u32,
    /// Bit times per character: 10 for 8N1, 11 for 8E1 or 8N2, 12 for 8E2.
    pub bits_per_char: u32,
    /// Probability that noise flips one data bit, 0 to 1.
    pub bit_error_rate: f64,
    /// Seeds the noise and the collision garbling.
    pub seed: u64,
    /// Who hears whom.
    pub wiring: Wiring,
}

impl Default for BusConfig {
    /// The lab's bus: 115200 baud 8N1, no noise, multi-drop.
    fn default() -> Self {
        BusConfig {
            baud: 115_200,
            bits_per_char: 10,
            bit_error_rate: 0.0,
            seed: 0,
            wiring: Wiring::MultiDrop,
        }
    }
}

/// A line configuration the bus cannot simulate.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
pub enum BusConfigError {
    /// The baud rate is zero.
    #[error("baud rate must be above zero")]
    ZeroBaud,
    /// A character is 10 to 12 bit times (start, 8 data, optional parity, 1–2 stop).
    #[error("{0} bits per character; a UART character with 8 data bits is 10 to 12")]
    BitsPerChar(u32),
    /// The bit-error rate is not a probability.
    #[error("bit-error rate {0} is not between 0 and 1")]
    BitErrorRate(f64),
}

/// A frame handed to the bus that it cannot send.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum BusError {
    /// No port with this id was added.
    #[error("no port {} on this bus", .0.index())]
    UnknownPort(PortId),
    /// The frame cannot be put on this medium (a PWM frame that is not a
    /// whole number of widths, or a width the timer cannot make).
    #[error("malformed frame: {0}")]
    Malformed(&'static str),
}

/// How one port drives the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PortConfig {
    /// From the instant a frame is handed to the bus to its first start bit
    /// (the firmware's reply latency; 0 allowed).
    pub turnaround: SimDuration,
}

impl Default for PortConfig {
    /// The lab's default turnaround of 1 ms.
    fn default() -> Self {
        PortConfig {
            turnaround: SimDuration::from_millis(1),
        }
    }
}

/// Where a frame went on the wire, for the recording.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameInfo {
    /// The port that sent it.
    pub from: PortId,
    /// Its first start bit.
    pub start: SimTime,
    /// The end of its last stop bit.
    pub end: SimTime,
}

/// Something that happened on the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BusEvent {
    /// A byte reached a port.
    Byte {
        /// The listener.
        to: PortId,
        /// The end of the byte's stop bit.
        at: SimTime,
        /// The byte as received.
        byte: u8,
        /// Garbled by a collision or flipped by noise: differs from what was sent.
        corrupted: bool,
        /// The sender, the byte's place in its frame, and whether it is the
        /// frame's last byte: what a receiver-side check tally needs.
        from: PortId,
        index: usize,
        last: bool,
    },
    /// A port's frame has left the wire (the end of its last stop bit).
    TransmitDone {
        /// The sender.
        port: PortId,
        /// The end of the frame's last stop bit.
        at: SimTime,
    },
}

impl BusEvent {
    /// When the event happens.
    pub fn at(&self) -> SimTime {
        match *self {
            BusEvent::Byte { at, .. } | BusEvent::TransmitDone { at, .. } => at,
        }
    }
}

/// Where the line differs from what a port sent: what a recording keeps so
/// that a logic analyzer's picture of the bus shows it where it happened.
/// A frame is named by its sender and its first start bit ([`FrameInfo`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LineMark {
    /// A character garbled on the wire by a collision: every listener gets
    /// it so.
    Garbled {
        from: PortId,
        /// The frame's first start bit.
        start: SimTime,
        /// The character's place in its frame.
        index: usize,
        /// The data bits changed (bit 0 is the first on the wire).
        mask: u8,
        /// The character as it is on the wire.
        byte: u8,
    },
    /// Data bits that noise flipped at one listener.
    Flipped {
        from: PortId,
        start: SimTime,
        index: usize,
        /// The listener.
        to: PortId,
        mask: u8,
        /// The character as the listener got it.
        byte: u8,
    },
}

/// Line marks held between two [`SimBus::poll_line_mark`] calls before the
/// queue grows: a frame's worth of garbled characters.
const MARKS_RESERVED: usize = 2 * MAX_FRAME;

/// What the bus has carried so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BusStats {
    /// Frames handed to [`SimBus::send`].
    pub frames_sent: u64,
    /// Bytes handed to [`SimBus::send`].
    pub bytes_sent: u64,
    /// Byte arrivals at listeners (a byte heard by three ports counts three times).
    pub bytes_delivered: u64,
    /// Byte arrivals with at least one bit flipped by noise.
    pub bytes_corrupted_by_noise: u64,
    /// Bits flipped by noise.
    pub bits_flipped: u64,
    /// Pairs of frames that overlapped on the wire.
    pub collisions: u64,
    /// Bytes on the wire garbled by a collision (counted once, not per listener).
    pub bytes_garbled_by_collision: u64,
}

#[derive(Debug, Clone, Copy)]
struct Port {
    config: PortConfig,
    /// Its own transmitter is busy until then: a second frame queues behind.
    transmitting_until: SimTime,
}

/// One frame on the wire and how far its delivery has got.
#[derive(Debug, Clone)]
struct Transmission {
    /// Order of sending: breaks ties between frames whose events coincide.
    seq: u64,
    from: PortId,
    start: SimTime,
    end: SimTime,
    /// The bytes as they are on the wire (collision garbling applied).
    bytes: Vec<u8>,
    garbled: Vec<bool>,
    /// When each byte's stop bit ends at the listeners.
    arrivals: Vec<SimTime>,
    /// A stream (see [`SimBus::stream_byte`]) still taking bytes: its end
    /// is not known yet.
    open: bool,
    /// When a stream was ended: its end is not reported before.
    closed_at: SimTime,
    /// Next byte to deliver; `bytes.len()` once all are delivered.
    next_byte: usize,
    /// Listener of the next delivery.
    next_listener: u16,
    /// When the next event (byte arrival or end of frame) happens: kept up
    /// to date as delivery advances, because the engine asks for it after
    /// every event and recomputing it takes a 128-bit division per frame.
    next_at: SimTime,
    active: bool,
}

impl Transmission {
    fn empty() -> Self {
        Transmission {
            seq: 0,
            from: PortId(0),
            start: SimTime::ZERO,
            end: SimTime::ZERO,
            bytes: Vec::with_capacity(MAX_FRAME),
            garbled: Vec::with_capacity(MAX_FRAME),
            arrivals: Vec::with_capacity(MAX_FRAME),
            open: false,
            closed_at: SimTime::ZERO,
            next_byte: 0,
            next_listener: 0,
            next_at: SimTime::ZERO,
            active: false,
        }
    }
}

/// The simulated bus. See the module documentation.
#[derive(Debug, Clone)]
pub struct SimBus {
    config: BusConfig,
    ports: Vec<Port>,
    /// Pool of frames; the active ones are on the wire or awaiting delivery.
    slots: Vec<Transmission>,
    next_seq: u64,
    noise: BitNoise,
    collision_rng: Pcg64,
    /// The latest event handed out: no frame may start before it, or it could
    /// collide with bytes already delivered intact.
    delivered_up_to: SimTime,
    busy_until: SimTime,
    stats: BusStats,
    /// The frame whose event comes next and when: rescanned only when a
    /// frame starts, moves to its next byte or ends, since most deliveries
    /// only pass the same byte on to the next listener.
    next: Option<(usize, SimTime)>,
    /// Line marks not yet polled; `None` unless asked for, so a bus whose
    /// marks nobody reads keeps none.
    marks: Option<VecDeque<LineMark>>,
}

impl SimBus {
    /// A bus with no ports yet.
    pub fn new(config: BusConfig) -> Result<Self, BusConfigError> {
        if config.baud == 0 {
            return Err(BusConfigError::ZeroBaud);
        }
        if !(10..=12).contains(&config.bits_per_char) {
            return Err(BusConfigError::BitsPerChar(config.bits_per_char));
        }
        if !(0.0..=1.0).contains(&config.bit_error_rate) {
            return Err(BusConfigError::BitErrorRate(config.bit_error_rate));
        }
        Ok(SimBus {
            config,
            ports: Vec::new(),
            slots: Vec::new(),
            next_seq: 0,
            noise: BitNoise::new(config.bit_error_rate, config.seed),
            collision_rng: Pcg64::seed_from_u64(config.seed.wrapping_add(COLLISION_STREAM)),
            delivered_up_to: SimTime::ZERO,
            busy_until: SimTime::ZERO,
            stats: BusStats::default(),
            next: None,
            marks: None,
        })
    }

    /// Connects a port; ids count up from 0. Also reserves room for two frames
    /// in flight per port, so sending does not allocate.
    pub fn add_port(&mut self, config: PortConfig) -> PortId {
        let id = PortId(u16::try_from(self.ports.len()).unwrap_or(u16::MAX));
        self.ports.push(Port {
            config,
            transmitting_until: SimTime::ZERO,
        });
        self.slots.push(Transmission::empty());
        self.slots.push(Transmission::empty());
        id
    }

    /// The line parameters.
    pub fn config(&self) -> &BusConfig {
        &self.config
    }

    /// Ports added so far.
    pub fn port_count(&self) -> usize {
        self.ports.len()
    }

    /// A port's configuration.
    pub fn port_config(&self, port: PortId) -> Option<PortConfig> {
        self.ports.get(port.index()).map(|p| p.config)
    }

    /// The time one character occupies the line (rounded down to a tick when
    /// the baud does not divide 72 GHz; byte arrivals never accumulate it).
    pub fn char_time(&self) -> SimDuration {
        self.wire_time(1)
    }

    /// The time `chars` back-to-back characters occupy the line.
    pub fn wire_time(&self, chars: usize) -> SimDuration {
        let ticks =
            chars as u128 * u128::from(self.config.bits_per_char) * u128::from(TICKS_PER_SECOND)
                / u128::from(self.config.baud);
        SimDuration(u64::try_from(ticks).unwrap_or(u64::MAX))
    }

    /// When the last frame handed to the bus so far leaves the wire.
    pub fn busy_until(&self) -> SimTime {
        self.busy_until
    }

    /// What the bus has carried so far.
    pub fn stats(&self) -> &BusStats {
        &self.stats
    }

    /// From now on, keep a [`LineMark`] wherever the line differs from
    /// what was sent, for [`SimBus::poll_line_mark`]. The caller must poll
    /// them: they queue until it does.
    pub fn keep_line_marks(&mut self) {
        if self.marks.is_none() {
            self.marks = Some(VecDeque::with_capacity(MARKS_RESERVED));
        }
    }

    /// The oldest line mark not yet polled (collisions are marked when the
    /// frame that collides is sent, noise when the byte is delivered).
    pub fn poll_line_mark(&mut self) -> Option<LineMark> {
        self.marks.as_mut()?.pop_front()
    }

    /// Puts `bytes` on the line from `from`, handed over at `now`.
    ///
    /// The first start bit begins at `now + turnaround`, or later if the port
    /// is still sending an earlier frame (its UART queues) or if events after
    /// that instant were already delivered (an engine must not send into the
    /// past). Bytes go back to back. Any overlap with another port's frame
    /// garbles the overlapping bytes of both and counts a collision.
    pub fn send(
        &mut self,
        now: SimTime,
        from: PortId,
        bytes: &[u8],
    ) -> Result<FrameInfo, BusError> {
        let port = self
            .ports
            .get(from.index())
            .ok_or(BusError::UnknownPort(from))?;
        let start = (now + port.config.turnaround)
            .max(port.transmitting_until)
            .max(self.delivered_up_to);
        let end = start + self.wire_time(bytes.len());
        let slot = self.free_slot();
        let first_listener = self.next_listener(from, 0);
        let seq = self.next_seq;
        self.next_seq += 1;
        if let Some(t) = self.slots.get_mut(slot) {
            t.seq = seq;
            t.from = from;
            t.start = start;
            t.end = end;
            t.bytes.clear();
            t.bytes.extend_from_slice(bytes);
            t.garbled.clear();
            t.garbled.resize(bytes.len(), false);
            t.arrivals.clear();
            t.open = false;
            t.closed_at = SimTime::ZERO;
            t.next_byte = if first_listener.is_some() {
                0
            } else {
                bytes.len()
            };
            t.next_listener = first_listener.unwrap_or(0);
        }
        for i in 0..bytes.len() {
            let at = start + self.wire_time(i + 1);
            if let Some(t) = self.slots.get_mut(slot) {
                t.arrivals.push(at);
            }
        }
        self.refresh_next_at(slot);
        self.collide(slot, start, end);
        if let Some(t) = self.slots.get_mut(slot) {
            t.active = true;
        }
        self.next = self.next_slot();
        if let Some(p) = self.ports.get_mut(from.index()) {
            p.transmitting_until = end;
        }
        self.busy_until = self.busy_until.max(end);
        self.stats.frames_sent += 1;
        self.stats.bytes_sent += bytes.len() as u64;
        Ok(FrameInfo { from, start, end })
    }

    /// A free frame slot; the pool grows once when more frames overlap than
    /// ever before.
    fn free_slot(&mut self) -> usize {
        match self.slots.iter().position(|s| !s.active) {
            Some(free) => free,
            None => {
                self.slots.push(Transmission::empty());
                self.slots.len() - 1
            }
        }
    }

    /// Garbles what frame `slot`, on the wire during `[start, end)`, overlaps
    /// of the other frames, and they of it.
    fn collide(&mut self, slot: usize, start: SimTime, end: SimTime) {
        for other in 0..self.slots.len() {
            let Some(t) = self.slots.get(other) else {
                continue;
            };
            if other == slot || !t.active {
                continue;
            }
            let (from_time, until) = (t.start.max(start), t.end.min(end));
            if from_time < until {
                self.stats.collisions += 1;
                self.garble(other, from_time, until);
                self.garble(slot, from_time, until);
            }
        }
    }

    /// Puts one byte on the line from `from` as a UART that writes its bytes
    /// one at a time does (compiled firmware): on the wire during
    /// `[start, end)` at the sender's own bit time, handed over at `now`,
    /// which may be after `start` (the engine found the byte when it ran the
    /// firmware). It arrives at `end`, or at `now` if that has passed. The
    /// bytes of one port make one frame until [`SimBus::end_stream`]; each
    /// is delivered as it arrives, never marked `last`.
    pub fn stream_byte(
        &mut self,
        now: SimTime,
        from: PortId,
        byte: u8,
        start: SimTime,
        end: SimTime,
    ) -> Result<(), BusError> {
        if self.ports.get(from.index()).is_none() {
            return Err(BusError::UnknownPort(from));
        }
        let at = end.max(now).max(self.delivered_up_to);
        let open = self
            .slots
            .iter()
            .position(|t| t.active && t.open && t.from == from);
        let slot = match open {
            Some(slot) => slot,
            None => {
                let slot = self.free_slot();
                let first_listener = self.next_listener(from, 0);
                let seq = self.next_seq;
                self.next_seq += 1;
                if let Some(t) = self.slots.get_mut(slot) {
                    t.seq = seq;
                    t.from = from;
                    t.start = start;
                    t.bytes.clear();
                    t.garbled.clear();
                    t.arrivals.clear();
                    t.open = true;
                    t.closed_at = SimTime::ZERO;
                    t.next_byte = 0;
                    t.next_listener = first_listener.unwrap_or(0);
                    t.active = true;
                }
                self.stats.frames_sent += 1;
                slot
            }
        };
        let heard = self.next_listener(from, 0).is_some();
        let Some(t) = self.slots.get_mut(slot) else {
            return Ok(());
        };
        if t.bytes.len() >= MAX_FRAME {
            return Ok(());
        }
        t.bytes.push(byte);
        t.garbled.push(false);
        let at = t.arrivals.last().map_or(at, |last| at.max(*last));
        t.arrivals.push(at);
        t.end = at;
        if !heard {
            t.next_byte = t.bytes.len();
        }
        self.collide(slot, start, at);
        self.refresh_next_at(slot);
        self.next = self.next_slot();
        if let Some(p) = self.ports.get_mut(from.index()) {
            p.transmitting_until = p.transmitting_until.max(at);
        }
        self.busy_until = self.busy_until.max(at);
        self.stats.bytes_sent += 1;
        Ok(())
    }

    /// Ends the stream of bytes `from` is sending: its frame leaves the wire
    /// with its last byte. Returns where the frame was on the wire and its
    /// bytes, and whether every byte has reached its listeners already
    /// (none of them was marked `last`). `None` if no stream was open.
    pub fn end_stream(&mut self, now: SimTime, from: PortId) -> Option<(FrameInfo, &[u8], bool)> {
        let slot = self
            .slots
            .iter()
            .position(|t| t.active && t.open && t.from == from)?;
        let t = self.slots.get_mut(slot)?;
        t.open = false;
        t.closed_at = now;
        t.end = t.end.max(t.start);
        let info = FrameInfo {
            from,
            start: t.start,
            end: t.end,
        };
        self.refresh_next_at(slot);
        self.next = self.next_slot();
        let t = self.slots.get(slot)?;
        Some((info, &t.bytes, t.next_byte >= t.bytes.len()))
    }

    /// Garbles the bytes of frame `slot` on the wire during `[from, until)`.
    fn garble(&mut self, slot: usize, from: SimTime, until: SimTime) {
        let Some(t) = self.slots.get(slot) else {
            return;
        };
        let start = t.start;
        for i in 0..t.bytes.len() {
            let byte_start = start + self.wire_time(i);
            let byte_end = start + self.wire_time(i + 1);
            if byte_start >= until {
                break;
            }
            if byte_end <= from {
                continue;
            }
            let mask = self.collision_rng.random_range(1..=u8::MAX);
            let Some(t) = self.slots.get_mut(slot) else {
                return;
            };
            if let (Some(byte), Some(flag)) = (t.bytes.get_mut(i), t.garbled.get_mut(i))
                && !*flag
            {
                *byte ^= mask;
                *flag = true;
                self.stats.bytes_garbled_by_collision += 1;
                if let Some(marks) = &mut self.marks {
                    marks.push_back(LineMark::Garbled {
                        from: t.from,
                        start: t.start,
                        index: i,
                        mask,
                        byte: *byte,
                    });
                }
            }
        }
    }

    /// The first port at or after `from_index` that hears `talker`.
    fn next_listener(&self, talker: PortId, from_index: usize) -> Option<u16> {
        (from_index..self.ports.len())
            .filter_map(|i| u16::try_from(i).ok())
            .find(|&i| self.config.wiring.hears(PortId(i), talker))
    }

    /// Recomputes when frame `slot`'s next event happens: its next byte's
    /// stop bit, or the frame's end once every byte is delivered.
    fn refresh_next_at(&mut self, slot: usize) {
        let Some(t) = self.slots.get(slot) else {
            return;
        };
        let at = match t.arrivals.get(t.next_byte) {
            Some(&at) => at,
            // A stream waits for its next byte, or its end.
            None if t.open => SimTime(u64::MAX),
            None => t.end.max(t.closed_at),
        };
        if let Some(t) = self.slots.get_mut(slot) {
            t.next_at = at;
        }
    }

    /// The frame whose next event comes first: earliest time, then earliest sent.
    fn next_slot(&self) -> Option<(usize, SimTime)> {
        let mut best: Option<(usize, SimTime, u64)> = None;
        for (i, t) in self.slots.iter().enumerate() {
            let waiting = t.open && t.next_byte >= t.bytes.len();
            if t.active
                && !waiting
                && best.is_none_or(|(_, at, seq)| (t.next_at, t.seq) < (at, seq))
            {
                best = Some((i, t.next_at, t.seq));
            }
        }
        best.map(|(i, at, _)| (i, at))
    }

    /// The instant of the next byte arrival or end of a frame.
    pub fn poll_timeout(&self) -> Option<SimTime> {
        self.next.map(|(_, at)| at)
    }

    /// The next event at or before `now`, in time order. Events at the same
    /// instant come frame by frame in the order the frames were sent; within a
    /// frame, a byte goes to its listeners in port order, and the frame's
    /// [`BusEvent::TransmitDone`] follows its last byte.
    pub fn poll_event(&mut self, now: SimTime) -> Option<BusEvent> {
        let (slot, at) = self.next?;
        if at > now {
            return None;
        }
        self.delivered_up_to = self.delivered_up_to.max(at);
        let t = self.slots.get(slot)?;
        let (from, index, listener, start) = (t.from, t.next_byte, t.next_listener, t.start);
        let frame_len = t.bytes.len();
        let open = t.open;
        let Some(&wire_byte) = t.bytes.get(index) else {
            // All bytes delivered: the frame is done.
            if let Some(t) = self.slots.get_mut(slot) {
                t.active = false;
            }
            self.next = self.next_slot();
            return Some(BusEvent::TransmitDone { port: from, at });
        };
        let collided = t.garbled.get(index).copied().unwrap_or(false);

        match self.next_listener(from, usize::from(listener) + 1) {
            Some(next) => {
                if let Some(t) = self.slots.get_mut(slot) {
                    t.next_listener = next;
                }
            }
            None => {
                // The byte has reached every listener: on to the next one.
                let first = self.next_listener(from, 0);
                if let Some(t) = self.slots.get_mut(slot) {
                    t.next_byte += 1;
                    t.next_listener = first.unwrap_or(0);
                }
                self.refresh_next_at(slot);
                self.next = self.next_slot();
            }
        }

        let noise = self.noise.next_byte_mask();
        self.stats.bytes_delivered += 1;
        if noise != 0 {
            self.stats.bytes_corrupted_by_noise += 1;
            self.stats.bits_flipped += u64::from(noise.count_ones());
            if let Some(marks) = &mut self.marks {
                marks.push_back(LineMark::Flipped {
                    from,
                    start,
                    index,
                    to: PortId(listener),
                    mask: noise,
                    byte: wire_byte ^ noise,
                });
            }
        }
        Some(BusEvent::Byte {
            to: PortId(listener),
            at,
            byte: wire_byte ^ noise,
            corrupted: collided || noise != 0,
            from,
            index,
            last: !open && index + 1 == frame_len,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_impossible_lines() {
        let bad = |c: BusConfig| SimBus::new(c).err();
        let base = BusConfig::default();
        assert_eq!(
            bad(BusConfig { baud: 0, ..base }),
            Some(BusConfigError::ZeroBaud)
        );
        assert_eq!(
            bad(BusConfig {
                bits_per_char: 9,
                ..base
            }),
            Some(BusConfigError::BitsPerChar(9))
        );
        assert!(matches!(
            bad(BusConfig {
                bit_error_rate: f64::NAN,
                ..base
            }),
            Some(BusConfigError::BitErrorRate(_))
        ));
        assert!(matches!(
            bad(BusConfig {
                bit_error_rate: 1.5,
                ..base
            }),
            Some(BusConfigError::BitErrorRate(_))
        ));
    }

    #[test]
    fn a_streamed_byte_arrives_when_its_stop_bit_ends_or_at_once_if_that_has_passed() {
        let mut bus = SimBus::new(BusConfig::default()).unwrap();
        let master = bus.add_port(PortConfig::default());
        let firmware = bus.add_port(PortConfig {
            turnaround: SimDuration::ZERO,
        });
        let us = |n: u64| SimTime::ZERO + SimDuration::from_micros(n);
        // Found 40 us after its stop bit ended: delivered at once.
        bus.stream_byte(us(140), firmware, 0x11, us(15), us(100))
            .unwrap();
        // Found before its stop bit ends: delivered when it ends.
        bus.stream_byte(us(150), firmware, 0x22, us(100), us(185))
            .unwrap();
        let mut got = Vec::new();
        while let Some(at) = bus.poll_timeout() {
            let Some(event) = bus.poll_event(at) else {
                break;
            };
            got.push(event);
        }
        let byte = |b: u8, at: SimTime, index: usize| BusEvent::Byte {
            to: master,
            at,
            byte: b,
            corrupted: false,
            from: firmware,
            index,
            last: false,
        };
        assert_eq!(got, vec![byte(0x11, us(140), 0), byte(0x22, us(185), 1)]);
        // The frame ends with its last byte, reported no earlier than its end.
        let (info, bytes, delivered) = bus.end_stream(us(355), firmware).unwrap();
        assert_eq!((info.start, info.end), (us(15), us(185)));
        assert_eq!(bytes, &[0x11, 0x22]);
        assert!(delivered);
        assert_eq!(bus.poll_timeout(), Some(us(355)));
        assert_eq!(
            bus.poll_event(us(355)),
            Some(BusEvent::TransmitDone {
                port: firmware,
                at: us(355)
            })
        );
        assert_eq!(bus.poll_timeout(), None);
        assert!(bus.end_stream(us(400), firmware).is_none());
    }

    /// Every event up to the end, and the marks the bus kept.
    fn drain(bus: &mut SimBus) -> (Vec<BusEvent>, Vec<LineMark>) {
        let mut events = Vec::new();
        while let Some(at) = bus.poll_timeout() {
            let Some(event) = bus.poll_event(at) else {
                break;
            };
            events.push(event);
        }
        let marks = std::iter::from_fn(|| bus.poll_line_mark()).collect();
        (events, marks)
    }

    #[test]
    fn line_marks_say_where_a_collision_garbled_and_where_noise_flipped() {
        // Without asking, no marks are kept.
        let mut quiet = SimBus::new(BusConfig {
            bit_error_rate: 0.05,
            ..BusConfig::default()
        })
        .unwrap();
        let (a, b) = (
            quiet.add_port(PortConfig::default()),
            quiet.add_port(PortConfig::default()),
        );
        quiet.send(SimTime::ZERO, a, &[0x55; 40]).unwrap();
        quiet.send(SimTime::ZERO, b, &[0x0f; 2]).unwrap();
        assert!(drain(&mut quiet).1.is_empty());

        let mut bus = SimBus::new(BusConfig {
            bit_error_rate: 0.05,
            ..BusConfig::default()
        })
        .unwrap();
        bus.keep_line_marks();
        let a = bus.add_port(PortConfig::default());
        let b = bus.add_port(PortConfig {
            turnaround: SimDuration::ZERO,
        });
        let sent_a = [0x55u8; 40];
        let info_a = bus.send(SimTime::ZERO, a, &sent_a).unwrap();
        // b talks over a's third and fourth characters.
        let over = info_a.start + bus.wire_time(2);
        let info_b = bus.send(over, b, &[0x0f; 2]).unwrap();
        assert_eq!(info_b.start, over);
        let (events, marks) = drain(&mut bus);
        let garbled: Vec<(PortId, SimTime, usize)> = marks
            .iter()
            .filter_map(|m| match *m {
                LineMark::Garbled {
                    from, start, index, ..
                } => Some((from, start, index)),
                LineMark::Flipped { .. } => None,
            })
            .collect();
        assert_eq!(
            garbled,
            vec![
                (a, info_a.start, 2),
                (a, info_a.start, 3),
                (b, info_b.start, 0),
                (b, info_b.start, 1)
            ]
        );
        // Each byte as received is what was sent with the marks' masks:
        // the collision's, then the listener's noise.
        let mut flips = 0;
        for event in &events {
            let BusEvent::Byte {
                to,
                byte,
                from,
                index,
                ..
            } = *event
            else {
                continue;
            };
            let sent = if from == a { sent_a[index] } else { 0x0f };
            let mut want = sent;
            for m in &marks {
                match *m {
                    LineMark::Garbled {
                        from: f,
                        index: i,
                        mask,
                        byte,
                        ..
                    } if (f, i) == (from, index) => {
                        assert_eq!(byte, sent ^ mask);
                        want ^= mask;
                    }
                    LineMark::Flipped {
                        from: f,
                        index: i,
                        to: t,
                        mask,
                        byte,
                        ..
                    } if (f, i, t) == (from, index, to) => {
                        want ^= mask;
                        assert_eq!(byte, want);
                        flips += 1;
                    }
                    _ => {}
                }
            }
            assert_eq!(byte, want, "byte {index} from port {}", from.index());
        }
        assert!(flips > 3, "{marks:?}");
        assert_eq!(flips, bus.stats().bytes_corrupted_by_noise);
    }

    #[test]
    fn unknown_port_is_an_error() {
        let mut bus = SimBus::new(BusConfig::default()).unwrap();
        assert_eq!(
            bus.send(SimTime::ZERO, PortId(3), b"x"),
            Err(BusError::UnknownPort(PortId(3)))
        );
    }
}
