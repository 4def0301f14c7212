//! A suite played over a [`Wire`]: every check's steps in order, what went
//! each way and when, and whether the program did what the step required.
//! A check stops at its first failing step; the next check starts on a
//! quiet line.

use crate::framing::Protocol;
use crate::suite::{Step, Suite};
use crate::wire::{Wire, WireError};
use serde::Serialize;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// How long the line must stay quiet before a check starts: leftovers of
/// the one before (a late reply) are not taken for this one's.
const SETTLE: Duration = Duration::from_millis(30);

/// Which way a frame went.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Way {
    Sent,
    Received,
}

/// Bytes on the line, seconds after the link was opened.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Exchange {
    pub at: f64,
    pub way: Way,
    pub text: String,
}

/// Which part of the bus the checked program plays.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// It answers the twin's requests.
    #[default]
    Slave,
    /// It polls the twin's slaves.
    Master,
}

impl Role {
    fn is_slave(&self) -> bool {
        *self == Role::Slave
    }
}

/// Passed, or the reason it did not; or left to a person (what a
/// client shows its user), with what they are to look at.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "result", content = "why", rename_all = "lowercase")]
pub enum Outcome {
    Pass,
    Fail(String),
    #[serde(rename = "not judged")]
    NotJudged(String),
}

/// One check as it went.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CheckOutcome {
    pub name: String,
    pub requirement: String,
    pub points: u32,
    #[serde(flatten)]
    pub outcome: Outcome,
    /// From the last byte of a request to the first of its reply, ms.
    pub reply_ms: Vec<f64>,
    pub frames: Vec<Exchange>,
    /// From the check's first step to its verdict (the quiet line before
    /// it not counted).
    pub seconds: f64,
    /// Figures the check measured that hold the program to nothing (a
    /// master's poll rate, what it chose where the protocol lets it).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

/// A suite as it went against one program.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SuiteRun {
    pub suite: String,
    pub link: String,
    pub id: u8,
    #[serde(skip_serializing_if = "Role::is_slave")]
    pub role: Role,
    /// A master's slaves, the twin's (`id` is the first).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub ids: Vec<u8>,
    pub checks: Vec<CheckOutcome>,
    pub seconds: f64,
    /// Why no check could be run (the program unreachable, or it hung up):
    /// every check then fails with this.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

impl SuiteRun {
    pub fn score(&self) -> u32 {
        self.passed().map(|c| c.points).sum()
    }

    pub fn points(&self) -> u32 {
        self.checks.iter().map(|c| c.points).sum()
    }

    pub fn passed(&self) -> impl Iterator<Item = &CheckOutcome> {
        self.checks.iter().filter(|c| c.outcome == Outcome::Pass)
    }

    /// The first check that failed, if one did.
    /// The checks that failed.
    pub fn failed(&self) -> usize {
        self.checks
            .iter()
            .filter(|c| matches!(c.outcome, Outcome::Fail(_)))
            .count()
    }

    pub fn first_failure(&self) -> Option<&CheckOutcome> {
        self.checks
            .iter()
            .find(|c| matches!(c.outcome, Outcome::Fail(_)))
    }

    /// A run that never got to its checks: each fails with `why`, so the
    /// score and the reports say 0 of the suite's points.
    pub fn unreachable(suite: &Suite, link: &str, id: u8, why: String) -> Self {
        let checks = suite
            .checks
            .iter()
            .map(|check| CheckOutcome {
                name: check.name.clone(),
                requirement: check.requirement.clone(),
                points: check.points,
                outcome: Outcome::Fail(why.clone()),
                reply_ms: Vec::new(),
                frames: Vec::new(),
                seconds: 0.0,
                notes: Vec::new(),
            })
            .collect();
        SuiteRun {
            suite: suite.name.clone(),
            link: link.into(),
            id,
            role: Role::Slave,
            ids: Vec::new(),
            checks,
            seconds: 0.0,
            error: Some(why),
        }
    }
}

/// Plays `suite` against the program on `wire`, as slave `id`. Errors only
/// when the link itself fails (a connection closed): the checks run so far
/// are lost with it, so the caller says which link and why.
pub fn run_suite(suite: &Suite, wire: &mut Wire, id: u8) -> Result<SuiteRun, WireError> {
    let started = wire.now();
    let mut checks = Vec::with_capacity(suite.checks.len());
    let mut next_transaction = 1;
    for check in &suite.checks {
        let mut play = Play {
            wire: &mut *wire,
            protocol: suite.protocol,
            id,
            timeout_ms: suite.timeout_ms,
            frames: Vec::new(),
            pending: Vec::new(),
            pending_since: None,
            unanswered: VecDeque::new(),
            last_request: (Vec::new(), 0),
            next_transaction,
            sent_at: None,
            reply_ms: Vec::new(),
        };
        play.settle()?;
        let began = play.wire.now();
        let mut outcome = Outcome::Pass;
        for step in &check.steps {
            if let Err(why) = play.step(step)? {
                // What comes after the failure is part of its story (a
                // reply too late), and must not be taken for the next
                // check's.
                let late = play.late(Duration::from_millis(3 * suite.timeout_ms.max(100)))?;
                outcome = Outcome::Fail(why + &late);
                break;
            }
        }
        let seconds = play.wire.now() - began;
        next_transaction = play.next_transaction;
        checks.push(CheckOutcome {
            name: check.name.clone(),
            requirement: check.requirement.clone(),
            points: check.points,
            outcome,
            reply_ms: play.reply_ms,
            frames: play.frames,
            seconds,
            notes: Vec::new(),
        });
    }
    Ok(SuiteRun {
        suite: suite.name.clone(),
        link: wire.link().to_string(),
        id,
        role: Role::Slave,
        ids: Vec::new(),
        checks,
        seconds: wire.now() - started,
        error: None,
    })
}

struct Play<'a> {
    wire: &'a mut Wire,
    protocol: Protocol,
    id: u8,
    /// A reply's deadline where a step sets none.
    timeout_ms: u64,
    frames: Vec<Exchange>,
    /// Received and not yet taken as a reply, and when its first byte came.
    pending: Vec<u8>,
    pending_since: Option<f64>,
    /// The requests sent and not yet answered, oldest first: each one's
    /// body (MEB's text up to the FCS, a binary frame's bytes before its
    /// CRC) and its Modbus TCP transaction id.
    unanswered: VecDeque<(Vec<u8>, u16)>,
    /// The last request a reply was taken for, for a step expecting more.
    last_request: (Vec<u8>, u16),
    /// The next Modbus TCP transaction id (counted over the whole run).
    next_transaction: u16,
    /// When the last request's last byte went out.
    sent_at: Option<Instant>,
    reply_ms: Vec<f64>,
}

/// A step's verdict: `Err(why)` when the program did not do what it required.
type Verdict = Result<(), String>;

impl Play<'_> {
    fn fill(&self, text: &str) -> String {
        self.protocol.fill(text, self.id)
    }

    fn shown(&self, bytes: &[u8]) -> String {
        self.protocol.shown(bytes)
    }

    /// The request the next reply answers: the oldest unanswered one.
    fn answered(&mut self) -> (Vec<u8>, u16) {
        if let Some(request) = self.unanswered.pop_front() {
            self.last_request = request;
        }
        self.last_request.clone()
    }

    /// Waits until the line has been quiet for [`SETTLE`].
    fn settle(&mut self) -> Result<(), WireError> {
        let mut junk = Vec::new();
        let give_up = Instant::now() + Duration::from_secs(2);
        while self.wire.receive(&mut junk, Instant::now() + SETTLE)? > 0 {
            if Instant::now() > give_up {
                break;
            }
        }
        Ok(())
    }

    fn send(&mut self, bytes: &[u8]) -> Result<(), WireError> {
        let text = self.shown(bytes);
        self.frames.push(Exchange {
            at: self.wire.now(),
            way: Way::Sent,
            text,
        });
        self.wire.send(bytes)?;
        self.sent_at = Some(Instant::now());
        Ok(())
    }

    /// Receives until `deadline`; true when something came.
    fn receive(&mut self, deadline: Instant) -> Result<bool, WireError> {
        let before = self.pending.len();
        if self.wire.receive(&mut self.pending, deadline)? == 0 {
            return Ok(false);
        }
        if before == 0 {
            self.pending_since = Some(self.wire.now());
            if let Some(sent) = self.sent_at.take() {
                self.reply_ms.push(sent.elapsed().as_secs_f64() * 1e3);
            }
        }
        Ok(true)
    }

    /// `bytes`, taken from the front of what came, as received when the
    /// first of them came.
    fn note_received(&mut self, bytes: &[u8]) {
        let at = self.pending_since.take().unwrap_or_else(|| self.wire.now());
        if !self.pending.is_empty() {
            self.pending_since = Some(self.wire.now());
        }
        let text = self.shown(bytes);
        self.frames.push(Exchange {
            at,
            way: Way::Received,
            text,
        });
    }

    fn step(&mut self, step: &Step) -> Result<Verdict, WireError> {
        match step {
            Step::Send {
                body,
                spoil,
                ending,
            } => {
                let body = self.fill(body);
                let transaction = self.next_transaction;
                self.next_transaction = transaction.wrapping_add(1);
                let frame = self.protocol.request(&body, *spoil, ending, transaction);
                self.unanswered
                    .push_back((self.protocol.body(&body), transaction));
                self.pending.clear();
                self.pending_since = None;
                self.send(&frame)?;
                Ok(Ok(()))
            }
            Step::Raw(text) => {
                let bytes = self.protocol.raw(&self.fill(text));
                self.pending.clear();
                self.pending_since = None;
                self.send(&bytes)?;
                Ok(Ok(()))
            }
            Step::Expect {
                pattern,
                data,
                within_ms,
            } => {
                let pattern = self.fill(pattern);
                let (_, transaction) = self.answered();
                let within_ms = within_ms.unwrap_or(self.timeout_ms);
                self.expect(&pattern, *data, transaction, within_ms)
            }
            Step::Error { code, within_ms } => {
                let (request, transaction) = self.answered();
                let pattern = self.protocol.error_pattern(&request, self.id, *code);
                let within_ms = within_ms.unwrap_or(self.timeout_ms);
                self.expect(&pattern, 0, transaction, within_ms)
            }
            Step::Silence { ms } => {
                let until = Instant::now() + Duration::from_millis(*ms);
                while Instant::now() < until {
                    self.receive(until)?;
                }
                // What went unanswered is not waited for by a later step.
                self.unanswered.clear();
                if self.pending.is_empty() {
                    return Ok(Ok(()));
                }
                let got = std::mem::take(&mut self.pending);
                self.note_received(&got);
                Ok(Err(format!(
                    "answered `{}` where it must stay silent for {ms} ms",
                    self.shown(&got)
                )))
            }
            Step::Wait { ms } => {
                let until = Instant::now() + Duration::from_millis(*ms);
                while Instant::now() < until {
                    self.receive(until)?;
                }
                Ok(Ok(()))
            }
        }
    }

    /// Whatever comes within `wait` of now, noted as received: `""`, or
    /// how long after the last request it came.
    fn late(&mut self, wait: Duration) -> Result<String, WireError> {
        let sent = self.sent_at;
        let until = Instant::now() + wait;
        let mut came = None;
        while Instant::now() < until {
            if self.receive(until)? && came.is_none() {
                came = sent.map(|s| s.elapsed());
            }
        }
        if self.pending.is_empty() {
            return Ok(String::new());
        }
        let got = std::mem::take(&mut self.pending);
        self.note_received(&got);
        let got = self.shown(&got);
        Ok(match came {
            Some(after) => format!(
                "; then `{got}` came, {:.0} ms after the request",
                after.as_secs_f64() * 1e3
            ),
            None => format!("; then `{got}` came"),
        })
    }

    /// The next frame, held to `pattern` and `data` data words (MEB) or
    /// bytes; over TCP, answering `transaction`.
    fn expect(
        &mut self,
        pattern: &str,
        data: u16,
        transaction: u16,
        within_ms: u64,
    ) -> Result<Verdict, WireError> {
        let deadline = self.sent_at.unwrap_or_else(Instant::now) + Duration::from_millis(within_ms);
        let wanted = format!("`{pattern}`{}", self.data(data));
        loop {
            if let Some(end) = self.protocol.frame_end(&self.pending) {
                let frame: Vec<u8> = self.pending.drain(..end).collect();
                self.note_received(&frame);
                return Ok(self
                    .protocol
                    .judge(&frame, pattern, data, transaction)
                    .map_err(|why| format!("{why}; expected {wanted}")));
            }
            if !self.receive(deadline)? {
                if self.pending.is_empty() {
                    return Ok(Err(format!(
                        "no reply within {within_ms} ms; expected {wanted}"
                    )));
                }
                let got = std::mem::take(&mut self.pending);
                self.note_received(&got);
                let missing = if self.protocol.is_text() {
                    " (`*\\n` missing)"
                } else {
                    ""
                };
                return Ok(Err(format!(
                    "`{}` came, no whole frame{missing} within {within_ms} ms; expected {wanted}",
                    self.shown(&got)
                )));
            }
        }
    }

    /// " and N data words/bytes", or nothing for none.
    fn data(&self, count: u16) -> String {
        let (one, many) = self.protocol.data_unit();
        match count {
            0 => String::new(),
            1 => format!(" and one {one}"),
            n => format!(" and {n} {many}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::framing::Protocol;

    #[test]
    fn control_bytes_are_spelt_out() {
        assert_eq!(Protocol::Meb.shown(b"@01\r\n\x01"), "@01\\r\\n\\x01");
        assert_eq!(Protocol::ModbusRtu.shown(&[1, 0x83, 2]), "01 83 02");
    }
}
