//! The link end of compiled firmware (`twin-avr serve --firmware`): the
//! link's bytes go to the sketches' UARTs as over a bus, their replies come
//! back when their cores have written them, and two things a real link
//! needs from a program that answers on its own time:
//!
//! - **One request at a time on TCP.** A TCP client may send its next
//!   request before the sketch has answered the last (a pipelining client,
//!   or one whose timeout ran out). A sketch on a serial line would see the
//!   two run together; here requests wait in order and each goes to the
//!   sketch once it has answered the one before (or its firmware has run
//!   [`REPLY_WAIT`] without answering), so the client gets every answer, in
//!   order.
//! - **A watchdog for a board that never answers.** Requests for a board's
//!   id that it has not answered while its firmware ran for [`WATCHDOG`]
//!   (two or more, valid, not broadcast; the second of them unanswered for
//!   [`REPLY_WAIT`]) mark the board dead: the node says where its program is
//!   ([`twin_sim::engine::SimNode::not_answering`]), the server keeps serving
//!   the others, and the master sees timeouts as on the bench.
//!
//! A sketch's core runs with its pins, on the engine's ticks. Between two
//! 1 ms ticks it would stand still, so a request that came mid-tick would
//! reach it early and its reply, written mid-tick, would wait for the next
//! tick: while a board owes a reply (and while bytes wait for the core to
//! reach their arrival), the endpoint asks the engine to run the firmware
//! on its own loop period ([`Endpoint::follow`]), so the bytes reach the
//! core when they came and the reply leaves when it is written.

use std::collections::VecDeque;

use nodes::node::{MAX_FRAME, NodeEvent};
use protocols::meb::MebFrame;
use protocols::modbus8::{CrcOrder, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};

use super::device::Device;
use super::endpoint::Endpoint;

/// How requests are cut from the link's bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RequestFraming {
    /// `@` … `*\n`; the id is the two digits after `@`.
    Meb,
    /// Eight bytes; the id is the first.
    Modbus8,
}

/// How long a queued request waits for the sketch's answer to the one
/// before it (TCP): far longer than any sketch of ours takes, well inside a
/// master's patience for a few requests.
pub const REPLY_WAIT: SimDuration = SimDuration::from_millis(500);
/// How long a board may leave requests for it unanswered before it is
/// marked dead.
pub const WATCHDOG: SimDuration = SimDuration::from_secs(1);
/// Unanswered requests before the watchdog may bite: one lost request is a
/// timeout, as on the bench.
const WATCHDOG_REQUESTS: u32 = 2;
/// Quiet that drops a partial 8-byte frame (a pty's bytes carry no timing).
const SILENCE: SimDuration = SimDuration::from_millis(5);
/// Requests held for a TCP client before more are dropped.
const QUEUE_MAX: usize = 256;
/// How long after a request a board that owes its reply is followed on its
/// loop period: far longer than any sketch of ours takes to answer; a board
/// still silent then (a mute sketch, a student's that waits a second for
/// bytes that never come) goes back to the engine's 1 ms ticks, so it does
/// not keep the engine waking ten times a millisecond.
const FOLLOW_FOR: SimDuration = SimDuration::from_millis(50);
/// Bytes held for the cores to reach their arrival before more are
/// dropped: far more than a link brings in a millisecond.
const HELD_MAX: usize = QUEUE_MAX * MAX_FRAME;

/// One board the watchdog keeps an eye on.
#[derive(Debug, Clone)]
struct Watch {
    device: usize,
    id: u8,
    /// When the oldest request it has not answered came, and how many since.
    since: Option<SimTime>,
    asked: u32,
    /// When the second of them came: a request a sketch left unanswered
    /// long ago (one a student's bug spoilt) must not condemn it the
    /// moment the next request comes.
    second: Option<SimTime>,
    fired: bool,
    /// When the latest request for it came (the board is followed for
    /// [`FOLLOW_FOR`] after it while a reply is owed).
    last: SimTime,
}

/// The sketches behind one link (see the module's documentation).
#[derive(Debug, Clone)]
pub struct FirmwareEndpoint {
    devices: Vec<usize>,
    framing: RequestFraming,
    one_at_a_time: bool,
    watches: Vec<Watch>,
    partial: Vec<u8>,
    last_rx: SimTime,
    /// Requests waiting for the sketch (TCP): their bytes, and each length.
    queued: Vec<u8>,
    lengths: VecDeque<usize>,
    /// The request handed over last, waiting for its answer since then.
    outstanding: Option<SimTime>,
    /// A queued request on its way to the sketch (kept, not allocated each time).
    next: Vec<u8>,
    /// Bytes that came before the engine had run the sketches to their
    /// arrival, back to back, and each chunk's arrival and length.
    held: Vec<u8>,
    held_chunks: VecDeque<(SimTime, usize)>,
}

impl FirmwareEndpoint {
    /// The nodes `devices` (engine indices) behind one link cut by
    /// `framing`; `boards` pairs each firmware device with its slave id for
    /// the watchdog; `one_at_a_time` on TCP.
    pub fn new(
        devices: Vec<usize>,
        boards: &[(usize, u8)],
        framing: RequestFraming,
        one_at_a_time: bool,
    ) -> Self {
        Self {
            devices,
            framing,
            one_at_a_time,
            watches: boards
                .iter()
                .map(|&(device, id)| Watch {
                    device,
                    id,
                    since: None,
                    asked: 0,
                    second: None,
                    fired: false,
                    last: SimTime::ZERO,
                })
                .collect(),
            partial: Vec::with_capacity(MAX_FRAME),
            last_rx: SimTime::ZERO,
            queued: Vec::new(),
            lengths: VecDeque::new(),
            outstanding: None,
            next: Vec::with_capacity(MAX_FRAME),
            held: Vec::with_capacity(MAX_FRAME),
            held_chunks: VecDeque::new(),
        }
    }

    /// Whether every sketch of the link has run to `at` (its next loop
    /// tick is there or beyond): bytes that came at `at` may reach it.
    fn reached(&self, devices: &[Device], at: SimTime) -> bool {
        self.devices
            .iter()
            .filter_map(|&d| devices.get(d)?.next_tick)
            .all(|tick| tick >= at)
    }

    /// The link's bytes at `now`, the sketches run to `now`: to the cores
    /// (as over a bus) and cut into requests.
    fn deliver(&mut self, devices: &mut [Device], now: SimTime, bytes: &[u8]) {
        if !self.one_at_a_time {
            for &d in &self.devices {
                if let Some(device) = devices.get_mut(d) {
                    // As in `hand_over`: the core stays with its pins.
                    let at = firmware_time(device, now);
                    device.node.handle_bytes(at, bytes);
                }
            }
        }
        self.frame(devices, now, bytes);
    }

    /// Hands over the held bytes whose arrival the sketches have reached.
    fn release(&mut self, devices: &mut [Device]) {
        let mut held = std::mem::take(&mut self.held);
        let mut taken = 0;
        while let Some(&(at, len)) = self.held_chunks.front()
            && self.reached(devices, at)
        {
            self.held_chunks.pop_front();
            let end = (taken + len).min(held.len());
            let chunk = held.get(taken..end).unwrap_or_default();
            self.deliver(devices, at, chunk);
            taken = end;
        }
        held.drain(..taken);
        self.held = held;
    }

    /// The slave id a whole, valid request is for; `None` for a broadcast
    /// or a frame no slave answers (MEB: one shaped like a reply).
    fn addressed(&self, frame: &[u8]) -> Option<u8> {
        match self.framing {
            RequestFraming::Meb => {
                let frame = MebFrame::new_checked(frame).ok()?;
                // A frame shaped like a reply (an error reply, a read
                // carrying data) is never answered: no request at all.
                (frame.id() != 0 && !frame.shape().is_reply()).then_some(frame.id())
            }
            RequestFraming::Modbus8 => Modbus8Repr::parse(frame, CrcOrder::HighFirst)
                .ok()
                .map(|f| f.id),
        }
    }

    /// Cuts whole requests from `bytes` and hands each to `on_frame`.
    fn frame(&mut self, devices: &mut [Device], now: SimTime, bytes: &[u8]) {
        if self.framing == RequestFraming::Modbus8 && now.saturating_since(self.last_rx) > SILENCE {
            self.partial.clear();
        }
        self.last_rx = now;
        for &b in bytes {
            match self.framing {
                RequestFraming::Meb => {
                    if b == b'@' {
                        self.partial.clear();
                    }
                    if self.partial.is_empty() && b != b'@' {
                        continue;
                    }
                    if self.partial.len() >= MAX_FRAME {
                        self.partial.clear();
                        continue;
                    }
                    self.partial.push(b);
                    if b != b'\n' {
                        continue;
                    }
                }
                RequestFraming::Modbus8 => {
                    self.partial.push(b);
                    if self.partial.len() < 8 {
                        continue;
                    }
                }
            }
            let frame = std::mem::take(&mut self.partial);
            self.on_frame(devices, now, &frame);
            self.partial = frame;
            self.partial.clear();
        }
    }

    fn on_frame(&mut self, devices: &mut [Device], now: SimTime, frame: &[u8]) {
        if !self.one_at_a_time {
            // The bytes went to the sketches as they came: only counted.
            self.asked(devices, now, frame);
            return;
        }
        if self.outstanding.is_some() || !self.lengths.is_empty() {
            if self.lengths.len() < QUEUE_MAX {
                self.queued.extend_from_slice(frame);
                self.lengths.push_back(frame.len());
            }
            return;
        }
        self.hand_over(devices, now, frame);
    }

    /// Gives `frame` to the sketches; waits for its answer if one is due.
    fn hand_over(&mut self, devices: &mut [Device], now: SimTime, frame: &[u8]) {
        for &d in &self.devices {
            if let Some(device) = devices.get_mut(d) {
                // Where the engine's ticks have brought the core: at the
                // wall's `now` the core would run ahead of its pins, and
                // the encoder edges of that stretch would never reach it (a
                // counting window read as 0 after a stall).
                let at = firmware_time(device, now);
                device.node.handle_bytes(at, frame);
            }
        }
        if self.asked(devices, now, frame) {
            // Timed on the firmware's own clock, as the watchdog: a machine
            // too busy to run the sketch must not hand it the next request
            // while its answer to this one is still to come (the client
            // would take that answer for the next one's).
            self.outstanding = Some(self.firmware_now(devices, now));
        }
    }

    /// Counts a request for a watched board; whether one of the link's
    /// boards is due to answer it.
    fn asked(&mut self, devices: &[Device], now: SimTime, frame: &[u8]) -> bool {
        let Some(id) = self.addressed(frame) else {
            return false;
        };
        match self.watches.iter_mut().find(|w| w.id == id) {
            Some(w) => {
                let at = devices.get(w.device).map_or(now, |d| firmware_time(d, now));
                w.since.get_or_insert(at);
                w.last = at;
                w.asked += 1;
                if w.asked == WATCHDOG_REQUESTS {
                    w.second = Some(at);
                }
                true
            }
            // A Rust node on the same line answers at once.
            None => false,
        }
    }

    /// The next queued request, once the last is answered or given up.
    fn next_request(&mut self, devices: &mut [Device], now: SimTime) {
        self.outstanding = None;
        if let Some(len) = self.lengths.pop_front() {
            let mut frame = std::mem::take(&mut self.next);
            frame.clear();
            frame.extend(self.queued.drain(..len.min(self.queued.len())));
            self.hand_over(devices, now, &frame);
            self.next = frame;
        }
    }

    /// How far the link's (first) sketch has run.
    fn firmware_now(&self, devices: &[Device], now: SimTime) -> SimTime {
        self.devices
            .first()
            .and_then(|&d| devices.get(d))
            .map_or(now, |d| firmware_time(d, now))
    }

    fn watchdog_due(w: &Watch) -> Option<SimTime> {
        let (since, second) = (w.since?, w.second?);
        (!w.fired && w.asked >= WATCHDOG_REQUESTS)
            .then(|| (since + WATCHDOG).max(second + REPLY_WAIT))
    }

    /// Marks dead the boards whose firmware has run [`WATCHDOG`] past the
    /// oldest request it has not answered. Looked at once the link has
    /// taken every reply there was ([`Endpoint::poll_transmit`] finding
    /// none), not on a deadline of its own: the firmware's time may lag the
    /// wall clock's, and a deadline the firmware has not reached yet would
    /// only make the engine spin. A board whose reply is still being
    /// written (its node waits for the line to go quiet) has answered: after
    /// a stall of the machine the sketch's loop catches up in one step, and
    /// the reply it wrote in that step comes out with the watchdog's mark
    /// already passed.
    fn bite(&mut self, devices: &mut [Device], now: SimTime) {
        for w in &mut self.watches {
            let Some(device) = devices.get_mut(w.device) else {
                continue;
            };
            if device.node.poll_timeout().is_none()
                && Self::watchdog_due(w).is_some_and(|due| due <= firmware_time(device, now))
                && let Some(since) = w.since
            {
                w.fired = true;
                device.node.not_answering(now, since, w.asked);
            }
        }
    }
}

/// How far a board's firmware has run: its loop's next tick, which the
/// engine's ticks move on (not the wall clock's `now` when they lag it: a
/// busy machine slows the firmware, it does not make it mute). A link's
/// bytes and timers reach the core there, never beyond: a core run ahead of
/// the ticks would miss its pins' edges in between.
fn firmware_time(device: &Device, now: SimTime) -> SimTime {
    device.next_tick.map_or(now, |tick| tick.min(now))
}

impl Endpoint for FirmwareEndpoint {
    fn handle_bytes(&mut self, devices: &mut [Device], now: SimTime, bytes: &[u8]) {
        if self.held_chunks.is_empty() && self.reached(devices, now) {
            self.deliver(devices, now, bytes);
        } else if self.held.len() + bytes.len() <= HELD_MAX {
            // The cores are behind the bytes' arrival (between two of the
            // engine's ticks): they get them once the engine has run them
            // there (see `follow`), not early.
            self.held.extend_from_slice(bytes);
            self.held_chunks.push_back((now, bytes.len()));
        }
    }

    fn handle_timeout(&mut self, devices: &mut [Device], now: SimTime) {
        self.release(devices);
        for &d in &self.devices {
            if let Some(device) = devices.get_mut(d) {
                let at = firmware_time(device, now);
                if device.node.poll_timeout().is_some_and(|t| t <= at) {
                    device.node.handle_timeout(at);
                }
            }
        }
        let at = self.firmware_now(devices, now);
        if self
            .outstanding
            .is_some_and(|since| since + REPLY_WAIT <= at)
        {
            self.next_request(devices, now);
        }
    }

    fn poll_timeout(&self, devices: &[Device]) -> Option<SimTime> {
        // Not before the engine has ticked the firmware there (see
        // `firmware_time`).
        self.devices
            .iter()
            .filter_map(|&d| {
                let device = devices.get(d)?;
                let t = device.node.poll_timeout()?;
                Some(device.next_tick.map_or(t, |tick| t.max(tick)))
            })
            .chain(self.outstanding.map(|since| since + REPLY_WAIT))
            // Held bytes: the engine follows the sketches there first.
            .chain(self.held_chunks.front().map(|&(at, _)| at))
            .min()
    }

    fn follow(&self, devices: &[Device]) -> Option<SimTime> {
        let owed = |w: &Watch| {
            !w.fired
                && w.since.is_some()
                && devices
                    .get(w.device)
                    .and_then(|d| d.next_tick)
                    .is_some_and(|tick| tick < w.last + FOLLOW_FOR)
        };
        if self.held_chunks.is_empty() && !self.watches.iter().any(owed) {
            return None;
        }
        self.devices
            .iter()
            .filter_map(|&d| devices.get(d)?.next_tick)
            .min()
    }

    fn poll_transmit(
        &mut self,
        devices: &mut [Device],
        now: SimTime,
        buf: &mut [u8],
    ) -> Option<usize> {
        let Some((d, len)) = self.devices.iter().find_map(|&d| {
            let device = devices.get_mut(d)?;
            let at = firmware_time(device, now);
            let len = device.node.poll_transmit(at, buf)?;
            Some((d, len))
        }) else {
            // Every reply there was is taken: what is left unanswered is.
            self.bite(devices, now);
            return None;
        };
        if let Some(w) = self.watches.iter_mut().find(|w| w.device == d) {
            w.since = None;
            w.asked = 0;
            w.second = None;
        }
        if self.one_at_a_time {
            self.next_request(devices, now);
        }
        Some(len)
    }

    fn transmit_done(&mut self, devices: &mut [Device], now: SimTime) {
        for &d in &self.devices {
            if let Some(device) = devices.get_mut(d) {
                device.node.transmit_done(now);
            }
        }
    }

    /// The engine drains the devices' own events.
    fn poll_event(&mut self, _devices: &mut [Device]) -> Option<(String, NodeEvent)> {
        None
    }

    fn pending(&self) -> usize {
        self.partial.len()
    }

    fn answers_later(&self) -> bool {
        true
    }
}
