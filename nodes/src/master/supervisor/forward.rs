//! Writes a remote client asked for, forwarded on the bus between the
//! supervisor's own exchanges, and what became of them.
//!
//! A forwarded write goes out at the first moment the line is free: between
//! two transactions of a cycle, or at once while the supervisor waits for its
//! next cycle. The exchange it displaced resumes after it, and runs before
//! the next forwarded write goes out. It is retried like
//! the supervisor's own requests when the reply is missing or fails its check,
//! but not when the slave refuses it (an `ER` reply is the slave's answer and
//! goes back to the client as it is).

use std::collections::VecDeque;

use protocols::meb::{MebCmd, MebWords};
use protocols::time::SimTime;

use super::super::layout::TranslateError;
use super::super::wire::Transaction;
use super::super::{LoopMode, Protocol};
use super::{Pending, Phase, Supervisor};

/// Forwarded writes waiting for the line, at most; more are refused.
pub(super) const FORWARD_QUEUE_LEN: usize = 64;
/// Outcomes nobody took (their client went away) are forgotten past this many.
const OUTCOMES_KEPT: usize = 256;

/// Names one forwarded write, so its outcome finds the client that asked.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct WriteTicket(pub u64);

/// What the slave made of a forwarded write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WriteOutcome {
    /// The slave acknowledged it (the values are in its image).
    Acknowledged,
    /// The slave answered `ER` with this code.
    Refused(u8),
    /// No usable reply after every retry.
    NoAnswer,
}

/// Why a write cannot be forwarded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ForwardError {
    /// The bus speaks Modbus RTU; MEB writes have no form there.
    #[error("the bus does not speak MEB")]
    NotMeb,
    /// The supervisor does not poll this slave.
    #[error("slave {0} is not polled by this supervisor")]
    UnknownSlave(u8),
    /// Too many writes already wait for the line.
    #[error("too many forwarded writes waiting")]
    QueueFull,
    /// Not a write command, or the words do not match the count.
    #[error("not a write request")]
    NotAWrite,
    /// The slave's I/O map cannot take the write as it is.
    #[error("{0}")]
    Map(TranslateError),
}

#[derive(Debug, Clone)]
pub(super) struct Forward {
    pub(super) ticket: WriteTicket,
    pub(super) slave: usize,
    pub(super) cmd: MebCmd,
    pub(super) addr: u8,
    pub(super) data: MebWords,
}

/// The supervisor's forwarding state.
#[derive(Debug, Clone, Default)]
pub(super) struct Forwarding {
    pub(super) queue: VecDeque<Forward>,
    /// The write on the line now, if any.
    pub(super) current: Option<Forward>,
    /// The exchange a forwarded write displaced and when it was due.
    pub(super) resume: Option<(Pending, SimTime)>,
    /// A displaced exchange was resumed and has not run yet: the next
    /// write waits for it, or a client writing back to back would starve
    /// the polls (inputs and status words never read again).
    pub(super) owed: bool,
    pub(super) outcomes: VecDeque<(WriteTicket, WriteOutcome)>,
    pub(super) next_ticket: u64,
}

impl Supervisor {
    /// Queues a remote client's write of `data` to `cmd addr` on slave `id`;
    /// its outcome comes out of [`poll_write_outcome`](Self::poll_write_outcome).
    pub fn forward_write(
        &mut self,
        now: SimTime,
        id: u8,
        cmd: MebCmd,
        addr: u8,
        data: &[u16],
    ) -> Result<WriteTicket, ForwardError> {
        if self.protocol != Protocol::Meb {
            return Err(ForwardError::NotMeb);
        }
        let is_write = matches!(
            cmd.block().map(|(block, _)| block.access()),
            Some(protocols::meb::MebAccess::Write)
        );
        let data = MebWords::from_slice(data).ok_or(ForwardError::NotAWrite)?;
        if !is_write || data.is_empty() {
            return Err(ForwardError::NotAWrite);
        }
        let slave = self
            .slaves
            .iter()
            .position(|slave| slave.config.id == id)
            .ok_or(ForwardError::UnknownSlave(id))?;
        if self.forwarding.queue.len() >= FORWARD_QUEUE_LEN {
            return Err(ForwardError::QueueFull);
        }
        // Clients write in the protocol page's map; the slave may keep
        // its signals elsewhere.
        let Some(held) = self.slaves.get_mut(slave) else {
            return Err(ForwardError::UnknownSlave(id));
        };
        let mut switches = held.switches;
        let (addr, data) = self
            .layout
            .translate(cmd, addr, data.as_slice(), &mut switches)
            .map_err(ForwardError::Map)?;
        held.switches = switches;
        let ticket = WriteTicket(self.forwarding.next_ticket);
        self.forwarding.next_ticket += 1;
        self.forwarding.queue.push_back(Forward {
            ticket,
            slave,
            cmd,
            addr,
            data,
        });
        self.start_forward(now);
        Ok(ticket)
    }

    /// What became of the forwarded write `ticket`, once it is known; each
    /// outcome is handed out once. Every client's server asks for its own
    /// tickets, so clients on different connections never take each other's.
    pub fn take_write_outcome(&mut self, ticket: WriteTicket) -> Option<WriteOutcome> {
        let outcomes = &mut self.forwarding.outcomes;
        let index = outcomes.iter().position(|(t, _)| *t == ticket)?;
        outcomes.remove(index).map(|(_, outcome)| outcome)
    }

    /// Drops the forwarded write `ticket` if it is not on the line now (its
    /// client gave up on it); a write awaiting its reply runs its course.
    /// Returns whether it was dropped.
    pub fn cancel_forward(&mut self, ticket: WriteTicket) -> bool {
        // Taken off the queue but not sent yet (or between its attempts).
        let is_current = self.forwarding.current.as_ref().map(|f| f.ticket) == Some(ticket);
        if is_current && let Phase::Waiting { .. } = self.phase {
            self.forwarding.current = None;
            if let Some((pending, at)) = self.forwarding.resume.take() {
                self.pending = pending;
                self.phase = Phase::Waiting { at };
            }
            return true;
        }
        let queue = &mut self.forwarding.queue;
        match queue.iter().position(|f| f.ticket == ticket) {
            Some(index) => queue.remove(index).is_some(),
            None => false,
        }
    }

    /// Forwarded writes waiting for the line or on it.
    pub fn forwards_in_flight(&self) -> usize {
        self.forwarding.queue.len() + usize::from(self.forwarding.current.is_some())
    }

    /// Puts the next queued write on the line if the supervisor is between
    /// exchanges (not mid-exchange, not about to retry).
    pub(super) fn start_forward(&mut self, now: SimTime) {
        let Phase::Waiting { at } = self.phase else {
            return;
        };
        if self.forwarding.current.is_some() || self.forwarding.owed || self.pending.attempt > 0 {
            return;
        }
        let Some(forward) = self.forwarding.queue.pop_front() else {
            return;
        };
        self.forwarding.resume = Some((self.pending, at));
        self.pending = Pending {
            slave: forward.slave,
            transaction: Transaction::Forward {
                cmd: forward.cmd,
                addr: forward.addr,
                cnt: forward.data.len() as u8,
            },
            attempt: 0,
        };
        self.forwarding.current = Some(forward);
        // When the line is free, but never later than the displaced exchange.
        self.phase = Phase::Waiting {
            at: now.max(self.line_free_at.min(at)),
        };
    }

    /// The forwarded write on the line is done: report it, take the next one
    /// or resume the exchange it displaced.
    pub(super) fn finish_forward(&mut self, now: SimTime, outcome: WriteOutcome) {
        if let Some(forward) = self.forwarding.current.take() {
            if outcome == WriteOutcome::Acknowledged {
                self.apply_forwarded(&forward);
            }
            let outcomes = &mut self.forwarding.outcomes;
            if outcomes.len() >= OUTCOMES_KEPT {
                outcomes.pop_front();
            }
            outcomes.push_back((forward.ticket, outcome));
        }
        let after_gap = now + self.inter_frame_gap;
        self.line_free_at = self.line_free_at.max(after_gap);
        match self.forwarding.resume.take() {
            Some((pending, at)) => {
                self.pending = pending;
                self.phase = Phase::Waiting {
                    at: at.max(self.line_free_at),
                };
                self.forwarding.owed = true;
            }
            // Only if a forward was started without a displaced exchange,
            // which `start_forward` never does.
            None => self.advance(now, None),
        }
        self.start_forward(now);
    }

    /// What an acknowledged write changes in the supervisor's own view: a
    /// `VEL` written by a client is the slave's `VEL` now, and with the loop
    /// open it becomes the manual value the supervisor holds.
    fn apply_forwarded(&mut self, forward: &Forward) {
        let Some(slave) = self.slaves.get_mut(forward.slave) else {
            return;
        };
        if forward.cmd == MebCmd::SA
            && forward.addr == 0
            && let Some(&vel) = forward.data.as_slice().first()
        {
            slave.state.vel_written = Some(vel);
            if let LoopMode::Open { .. } = slave.config.mode {
                slave.config.mode = LoopMode::Open { vel };
                slave.state.output = vel;
            }
        }
    }
}
