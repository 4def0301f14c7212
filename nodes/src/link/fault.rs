//! A node that misbehaves on purpose, as smoltcp's `FaultInjector` wraps a
//! device: [`FaultyNode`] wraps any [`Node`] and, while a fault is active,
//! spoils the check bytes of what it sends, loses or delays its frames,
//! refuses every request, answers as another slave, splits its replies in
//! two, sends junk with them, or takes it off the bus altogether.
//!
//! A fault is active when set by hand ([`FaultyNode::set_fault`], which wins)
//! or when the instant falls in a [`FaultWindow`] of the schedule. It is judged
//! when a frame leaves the inner node and when bytes reach it, so the wrapper
//! needs no wake-ups of its own beyond releasing delayed frames.
//!
//! Buffers are allocated at construction; a frame is never allocated.

use std::collections::VecDeque;

use super::fault_bytes::{self, Junk, JunkSource};
use crate::firmware::Refusal;
use crate::node::{MAX_FRAME, Node, NodeEvent};
use protocols::time::{SimDuration, SimTime};

/// Frames that can be held back at once by [`Fault::DelayReply`]; one more is
/// dropped (and recorded), as a firmware's full transmit queue would.
const HELD_FRAMES: usize = 4;
/// Events kept until polled; more are counted in [`FaultStats::events_lost`].
const MAX_EVENTS: usize = 64;
/// Frames pulled from the inner node in one [`Node::poll_transmit`] call while
/// its frames are dropped: bounds the work if the inner node never stops.
const MAX_PULLS: usize = 16;

/// Where a protocol keeps the check bytes that [`Fault::BadCheck`] spoils.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CheckKind {
    /// MEB: the two FCS hex characters before `*\n` (or `*\r\n`).
    Meb,
    /// The Controller_network project's 8-byte Modbus: bytes 6 and 7.
    Modbus8,
    /// Modbus RTU: the last two bytes.
    ModbusRtu,
}

/// One way to misbehave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// Send every frame with its check value plus one (read in wire byte
    /// order), as the Controller_network project's own test did on both
    /// master and slave (`0xaada` received, `0xaad9` calculated). Everything
    /// else in the frame is intact.
    BadCheck,
    /// Lose every frame on its way out: the node hears, acts and believes it
    /// answered (its `transmit_done` comes at once), but nothing reaches the wire.
    DropReply,
    /// Hand every frame to the link this much later than the node produced it.
    DelayReply(SimDuration),
    /// Off the bus: bytes for the node are lost and its frames too.
    Silent,
    /// Every request for the node refused with this (MEB `ER`, a Modbus
    /// exception, the Controller_network project's exception frame), as
    /// `twin serve`'s `fault exception`; nothing is stored. A node that
    /// serves no requests (a master) is not changed.
    Exception(Refusal),
    /// Every frame sent as slave `id` (`None`: the id next to its own), its
    /// check made good again: a well-formed reply from the wrong slave.
    WrongId(Option<u8>),
    /// Every frame sent in two writes: its first `first` bytes (`None`:
    /// half), then, after `gap` of quiet line from the end of the first
    /// write, the rest.
    SplitReply {
        first: Option<u16>,
        gap: SimDuration,
    },
    /// Junk bytes sent with every frame, in the same write.
    Junk(Junk),
}

/// A fault active from `from` (included) until `until` (excluded).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FaultWindow {
    /// First instant of the fault.
    pub from: SimTime,
    /// First instant without it.
    pub until: SimTime,
    /// The fault.
    pub fault: Fault,
}

impl FaultWindow {
    /// Whether `now` falls in the window.
    pub fn contains(&self, now: SimTime) -> bool {
        self.from <= now && now < self.until
    }
}

/// What the wrapper did so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// Frames sent unchanged and on time.
    pub frames_passed: u64,
    /// Frames sent with a spoiled check.
    pub frames_bad_check: u64,
    /// Frames lost (dropped, silent, or the delay queue full).
    pub frames_dropped: u64,
    /// Frames held back.
    pub frames_delayed: u64,
    /// Received bytes not passed on while silent.
    pub bytes_ignored: u64,
    /// Events not kept because nobody polled them.
    pub events_lost: u64,
    /// Frames sent while every request was refused (exceptions, `ER`s).
    pub frames_refused: u64,
    /// Frames sent under another slave's id.
    pub frames_wrong_id: u64,
    /// Frames sent in two writes.
    pub frames_split: u64,
    /// Frames sent with junk bytes.
    pub frames_junk: u64,
}

/// The rest of a split frame: waiting for the first write to end, or for
/// its instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Rest {
    None,
    /// The first write is on the wire; the rest follows `gap` after it ends.
    AfterFirst {
        len: usize,
        gap: SimDuration,
    },
    /// The rest goes out at `release`.
    Due {
        len: usize,
        release: SimTime,
    },
}

/// A frame held back, and when it may go.
#[derive(Debug, Clone, Copy)]
struct Held {
    release: SimTime,
    len: usize,
}

/// A [`Node`] wrapper that injects faults. See the module documentation.
#[derive(Debug)]
pub struct FaultyNode<N: Node> {
    inner: N,
    check: CheckKind,
    manual: Option<Fault>,
    schedule: Vec<FaultWindow>,
    /// Held frames, oldest first; their bytes in `held_bytes`, one
    /// [`MAX_FRAME`] slot each, at slot `(held_head + k) % HELD_FRAMES`.
    held: VecDeque<Held>,
    held_bytes: Vec<u8>,
    held_head: usize,
    events: VecDeque<NodeEvent>,
    stats: FaultStats,
    /// The refusal the inner node was last told to give.
    refusing: Option<Refusal>,
    /// The rest of a split frame, its bytes in `rest_bytes`.
    rest: Rest,
    rest_bytes: Vec<u8>,
    /// What the link adds before every write (the port's turnaround): taken
    /// off a split's gap, so the quiet line is the gap asked for.
    turnaround: SimDuration,
    junk: JunkSource,
}

impl<N: Node> FaultyNode<N> {
    /// Wraps `inner`, whose frames keep their check bytes where `check` says.
    /// No fault is active until one is set or scheduled.
    pub fn new(inner: N, check: CheckKind) -> Self {
        FaultyNode {
            inner,
            check,
            manual: None,
            schedule: Vec::new(),
            held: VecDeque::with_capacity(HELD_FRAMES),
            held_bytes: vec![0; HELD_FRAMES * MAX_FRAME],
            held_head: 0,
            events: VecDeque::with_capacity(MAX_EVENTS),
            stats: FaultStats::default(),
            refusing: None,
            rest: Rest::None,
            rest_bytes: vec![0; MAX_FRAME],
            turnaround: SimDuration::ZERO,
            junk: JunkSource::new(0),
        }
    }

    /// Draws random junk from `seed` (a scenario's seed, derived per node).
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.junk = JunkSource::new(seed);
        self
    }

    /// The link waits `turnaround` before each write: a split's second
    /// write is asked for that much earlier, so the line is quiet for the
    /// gap asked for (or the turnaround, if that is longer).
    pub fn with_turnaround(mut self, turnaround: SimDuration) -> Self {
        self.turnaround = turnaround;
        self
    }

    /// Wraps `inner` with a schedule of fault windows (the first window that
    /// contains an instant applies).
    pub fn with_schedule(inner: N, check: CheckKind, schedule: Vec<FaultWindow>) -> Self {
        let mut node = Self::new(inner, check);
        node.schedule = schedule;
        node
    }

    /// Sets (or with `None` clears) a fault that applies from now on,
    /// overriding the schedule.
    pub fn set_fault(&mut self, fault: Option<Fault>) {
        self.manual = fault;
    }

    /// Replaces the schedule.
    pub fn set_schedule(&mut self, schedule: Vec<FaultWindow>) {
        self.schedule = schedule;
    }

    /// The fault in force at `now`: the one set by hand, else the schedule's.
    pub fn active_fault(&self, now: SimTime) -> Option<Fault> {
        self.manual.or_else(|| {
            self.schedule
                .iter()
                .find(|w| w.contains(now))
                .map(|w| w.fault)
        })
    }

    /// What the wrapper did so far.
    pub fn stats(&self) -> &FaultStats {
        &self.stats
    }

    /// The wrapped node.
    pub fn inner(&self) -> &N {
        &self.inner
    }

    /// The wrapped node, to reconfigure it.
    pub fn inner_mut(&mut self) -> &mut N {
        &mut self.inner
    }

    /// Unwraps the node.
    pub fn into_inner(self) -> N {
        self.inner
    }

    fn record(&mut self, at: SimTime, kind: &'static str, detail: String) {
        if self.events.len() >= MAX_EVENTS {
            self.stats.events_lost += 1;
            return;
        }
        self.events.push_back(NodeEvent { at, kind, detail });
    }

    /// Holds `frame` until `release` (kept behind frames already held, so
    /// order is preserved). Returns false if the queue is full.
    fn hold(&mut self, release: SimTime, frame: &[u8]) -> bool {
        if self.held.len() >= HELD_FRAMES {
            return false;
        }
        let slot = (self.held_head + self.held.len()) % HELD_FRAMES;
        let len = frame.len().min(MAX_FRAME);
        let Some(dst) = self
            .held_bytes
            .get_mut(slot * MAX_FRAME..slot * MAX_FRAME + len)
        else {
            return false;
        };
        dst.copy_from_slice(frame.get(..len).unwrap_or_default());
        let release = self.held.back().map_or(release, |b| release.max(b.release));
        self.held.push_back(Held { release, len });
        true
    }

    /// Tells the inner node whether to refuse every request, when that changes.
    fn sync_refusal(&mut self, now: SimTime) {
        let want = match self.active_fault(now) {
            Some(Fault::Exception(refusal)) => Some(refusal),
            _ => None,
        };
        if want != self.refusing {
            self.inner.force_refusal(want);
            self.refusing = want;
        }
    }

    /// Moves the rest of a split frame into `buf` if it is due at `now`.
    fn release_rest(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        let Rest::Due { len, release } = self.rest else {
            return None;
        };
        if release > now {
            return None;
        }
        self.rest = Rest::None;
        let src = self.rest_bytes.get(..len)?;
        let dst = buf.get_mut(..len)?;
        dst.copy_from_slice(src);
        Some(len)
    }

    /// Applies a fault that changes the bytes of a frame on its way out
    /// (the first `len` of `buf`); returns the length to send now.
    fn reshape(&mut self, now: SimTime, fault: Fault, buf: &mut [u8], len: usize) -> usize {
        match fault {
            Fault::WrongId(id) => {
                let frame = buf.get_mut(..len).unwrap_or_default();
                let id = id.or_else(|| {
                    fault_bytes::frame_id(self.check, frame)
                        .map(|own| fault_bytes::other_id(self.check, own))
                });
                if let Some(id) = id
                    && fault_bytes::set_id(self.check, frame, id)
                {
                    self.stats.frames_wrong_id += 1;
                    self.record(
                        now,
                        "fault",
                        format!("fault: {len}-byte frame sent as id {id}"),
                    );
                } else {
                    self.stats.frames_passed += 1;
                }
                len
            }
            Fault::SplitReply { first, gap } => {
                let Some(at) = fault_bytes::split_point(len, first) else {
                    self.stats.frames_passed += 1;
                    return len;
                };
                let rest = len - at;
                if let (Some(dst), Some(src)) = (self.rest_bytes.get_mut(..rest), buf.get(at..len))
                {
                    dst.copy_from_slice(src);
                }
                self.rest = Rest::AfterFirst { len: rest, gap };
                self.stats.frames_split += 1;
                self.record(
                    now,
                    "fault",
                    format!(
                        "fault: {len}-byte frame split after byte {at}, the rest {:.0} us later",
                        gap.as_secs_f64() * 1e6
                    ),
                );
                at
            }
            Fault::Junk(junk) => {
                let sent = self.junk.apply(&junk, buf, len);
                self.stats.frames_junk += 1;
                self.record(
                    now,
                    "fault",
                    format!(
                        "fault: {len}-byte frame sent with {} junk byte(s)",
                        sent - len
                    ),
                );
                sent
            }
            Fault::Exception(_) => {
                self.stats.frames_refused += 1;
                len
            }
            _ => len,
        }
    }

    /// Moves the oldest held frame into `buf` if it is due at `now`.
    fn release(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        let front = *self.held.front().filter(|h| h.release <= now)?;
        self.held.pop_front();
        let slot = self.held_head;
        self.held_head = (self.held_head + 1) % HELD_FRAMES;
        let src = self
            .held_bytes
            .get(slot * MAX_FRAME..slot * MAX_FRAME + front.len)?;
        match buf.get_mut(..front.len) {
            Some(dst) => {
                dst.copy_from_slice(src);
                Some(front.len)
            }
            None => {
                self.stats.frames_dropped += 1;
                self.record(
                    now,
                    "dropped",
                    "delayed frame larger than the link's buffer".into(),
                );
                None
            }
        }
    }
}

impl<N: Node> Node for FaultyNode<N> {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        if self.active_fault(now) == Some(Fault::Silent) {
            self.stats.bytes_ignored += bytes.len() as u64;
            return;
        }
        self.sync_refusal(now);
        self.inner.handle_bytes(now, bytes);
    }

    fn handle_timeout(&mut self, now: SimTime) {
        // The wrapper's own wake-ups (releasing held frames) are not the
        // inner node's: pass on only the instants it asked for.
        if self.inner.poll_timeout().is_some_and(|t| t <= now) {
            self.sync_refusal(now);
            self.inner.handle_timeout(now);
        }
    }

    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        if let Some(len) = self.release_rest(now, buf) {
            return Some(len);
        }
        // A split frame's rest goes before anything else.
        if self.rest != Rest::None {
            return None;
        }
        if let Some(len) = self.release(now, buf) {
            return Some(len);
        }
        for _ in 0..MAX_PULLS {
            let len = self.inner.poll_transmit(now, buf)?.min(buf.len());
            let frame = buf.get_mut(..len)?;
            let fault = self.active_fault(now);
            let delay = match fault {
                None => SimDuration::ZERO,
                Some(Fault::DropReply | Fault::Silent) => {
                    self.stats.frames_dropped += 1;
                    let why = if fault == Some(Fault::Silent) {
                        "silent"
                    } else {
                        "dropped"
                    };
                    self.record(
                        now,
                        "dropped",
                        format!("fault: {len}-byte frame lost ({why})"),
                    );
                    self.inner.transmit_done(now);
                    continue;
                }
                Some(Fault::BadCheck) => {
                    if spoil_check(self.check, frame) {
                        self.stats.frames_bad_check += 1;
                        self.record(
                            now,
                            "fault",
                            format!("fault: {len}-byte frame sent with a bad check"),
                        );
                    } else {
                        self.stats.frames_passed += 1;
                    }
                    SimDuration::ZERO
                }
                Some(Fault::DelayReply(delay)) => delay,
                Some(
                    Fault::Exception(_)
                    | Fault::WrongId(_)
                    | Fault::SplitReply { .. }
                    | Fault::Junk(_),
                ) => SimDuration::ZERO,
            };
            if delay == SimDuration::ZERO && self.held.is_empty() {
                match fault {
                    None => self.stats.frames_passed += 1,
                    Some(fault) => return Some(self.reshape(now, fault, buf, len)),
                }
                return Some(len);
            }
            let frame = buf.get(..len)?;
            if self.hold(now + delay, frame) {
                if delay > SimDuration::ZERO {
                    self.stats.frames_delayed += 1;
                    self.record(
                        now,
                        "fault",
                        format!(
                            "fault: {len}-byte frame delayed by {} us",
                            delay.as_secs_f64() * 1e6
                        ),
                    );
                } else if fault.is_none() {
                    self.stats.frames_passed += 1;
                }
            } else {
                self.stats.frames_dropped += 1;
                self.record(
                    now,
                    "dropped",
                    format!("fault: {len}-byte frame lost (delay queue full)"),
                );
                self.inner.transmit_done(now);
            }
            if let Some(len) = self.release(now, buf) {
                return Some(len);
            }
        }
        None
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        let release = match self.rest {
            Rest::Due { release, .. } => Some(release),
            _ => self.held.front().map(|h| h.release),
        };
        match (self.inner.poll_timeout(), release) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    fn transmit_done(&mut self, now: SimTime) {
        // The first write of a split frame is not the end of the frame the
        // node sent: its rest is timed from here, and the node hears of the
        // end when the rest has gone.
        if let Rest::AfterFirst { len, gap } = self.rest {
            let ahead = SimDuration(gap.0.saturating_sub(self.turnaround.0));
            self.rest = Rest::Due {
                len,
                release: now + ahead,
            };
            return;
        }
        self.inner.transmit_done(now);
    }

    fn force_refusal(&mut self, refusal: Option<Refusal>) -> bool {
        self.refusing = refusal;
        self.inner.force_refusal(refusal)
    }

    fn poll_event(&mut self) -> Option<NodeEvent> {
        self.events.pop_front().or_else(|| self.inner.poll_event())
    }
}

/// Adds one to the frame's check value, in place. False if the frame is too
/// short or not shaped like `kind` (then it is left as it was).
pub fn spoil_check(kind: CheckKind, frame: &mut [u8]) -> bool {
    match kind {
        CheckKind::Meb => {
            let body = if frame.ends_with(b"*\r\n") {
                frame.len() - 3
            } else if frame.ends_with(b"*\n") {
                frame.len() - 2
            } else {
                return false;
            };
            // `@` and at least the two FCS characters.
            let Some(fcs_at) = body.checked_sub(2).filter(|&at| at >= 1) else {
                return false;
            };
            let Some([hi, lo]) = frame.get_mut(fcs_at..body) else {
                return false;
            };
            // A pair that was not hex already failed; any valid pair differs.
            let old = hex_value(*hi)
                .zip(hex_value(*lo))
                .map_or(0xFF, |(h, l)| h << 4 | l);
            let new = old.wrapping_add(1);
            const HEX_UPPER: &[u8; 16] = b"0123456789ABCDEF";
            *hi = HEX_UPPER[usize::from(new >> 4)];
            *lo = HEX_UPPER[usize::from(new & 0x0F)];
            true
        }
        CheckKind::Modbus8 => match frame {
            [_, _, _, _, _, _, hi, lo] => {
                let [h, l] = u16::from_be_bytes([*hi, *lo]).wrapping_add(1).to_be_bytes();
                (*hi, *lo) = (h, l);
                true
            }
            _ => false,
        },
        CheckKind::ModbusRtu => match frame {
            [_, _, .., lo, hi] => {
                let [l, h] = u16::from_le_bytes([*lo, *hi]).wrapping_add(1).to_le_bytes();
                (*lo, *hi) = (l, h);
                true
            }
            _ => false,
        },
    }
}

fn hex_value(c: u8) -> Option<u8> {
    char::from(c)
        .to_digit(16)
        .and_then(|d| u8::try_from(d).ok())
}
