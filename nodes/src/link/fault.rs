//! A node that misbehaves on purpose, as smoltcp's `FaultInjector` wraps a
//! device: [`FaultyNode`] wraps any [`Node`] and, while a fault is active,
//! spoils the check bytes of what it sends, loses or delays its frames, or
//! takes it off the bus altogether.
//!
//! A fault is active when set by hand ([`FaultyNode::set_fault`], which wins)
//! or when the instant falls in a [`FaultWindow`] of the schedule. It is judged
//! when a frame leaves the inner node and when bytes reach it, so the wrapper
//! needs no wake-ups of its own beyond releasing delayed frames.
//!
//! Buffers are allocated at construction; a frame is never allocated.

use std::collections::VecDeque;

use crate::node::{MAX_FRAME, Node, NodeEvent};
use crate::time::{SimDuration, SimTime};

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
        }
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
        self.inner.handle_bytes(now, bytes);
    }

    fn handle_timeout(&mut self, now: SimTime) {
        // The wrapper's own wake-ups (releasing held frames) are not the
        // inner node's: pass on only the instants it asked for.
        if self.inner.poll_timeout().is_some_and(|t| t <= now) {
            self.inner.handle_timeout(now);
        }
    }

    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
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
            };
            if delay == SimDuration::ZERO && self.held.is_empty() {
                if fault.is_none() {
                    self.stats.frames_passed += 1;
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
        let release = self.held.front().map(|h| h.release);
        match (self.inner.poll_timeout(), release) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    fn transmit_done(&mut self, now: SimTime) {
        self.inner.transmit_done(now);
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
