//! A suite played over a [`Wire`]: every check's steps in order, what went
//! each way and when, and whether the program did what the step required.
//! A check stops at its first failing step; the next check starts on a
//! quiet line.

use crate::bench::{Bench, PlantState};
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
    /// The bytes themselves, for the recording (`text` spells some out,
    /// and on a check of two links names the side first); empty for a
    /// mark that is no frame (a client hanging up).
    #[serde(skip)]
    pub bytes: Vec<u8>,
    /// The link and the sender, where a check watches more than one link
    /// (a server's bus and its clients, a client's connections); `None`:
    /// the run's one link, between the twin and the checked program.
    #[serde(skip)]
    pub peer: Option<Peer>,
}

/// Which of a check's links a frame went on, and who sent it: the
/// recording puts it on `/link/<link>/frames` with that `from`.
#[derive(Debug, Clone, PartialEq)]
pub struct Peer {
    /// The link's name in the recording: `bus`, `server`, `client`.
    pub link: &'static str,
    /// The frame's sender as the recording's `from` says it: `client 1`,
    /// `supervisor`, `slave 01`, `twin`.
    pub from: String,
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
/// client shows its user), with what they are to look at; or not
/// applicable to this run (a bench check without a bench), with why.
/// Neither of the last two is a failure, and a check not applicable is
/// not scored either.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "result", content = "why", rename_all = "lowercase")]
pub enum Outcome {
    Pass,
    Fail(String),
    #[serde(rename = "not judged")]
    NotJudged(String),
    #[serde(rename = "not applicable")]
    NotApplicable(String),
}

/// Why a bench check is not applicable without a bench.
pub const NO_BENCH: &str =
    "a bench check: give --bench URL, the panel of the twin session the slave is wired to";

/// One check as it went.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CheckOutcome {
    pub name: String,
    pub requirement: String,
    pub points: u32,
    #[serde(flatten)]
    pub outcome: Outcome,
    /// When its first step began, seconds after the link was opened.
    pub at: f64,
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
    /// What its frames are: a recording decodes them by it.
    #[serde(skip)]
    pub protocol: Protocol,
    /// A master's slaves, the twin's (`id` is the first).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub ids: Vec<u8>,
    pub checks: Vec<CheckOutcome>,
    pub seconds: f64,
    /// The panel of the bench the slave was checked on, if it was.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bench: Option<String>,
    /// How many times as long the suite's waits were (`--patience`; 1:
    /// as written). Its timing checks kept theirs.
    #[serde(skip_serializing_if = "as_written")]
    pub patience: f64,
    /// Why no check could be run (the program unreachable): every check
    /// then fails with this.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The program hung up in the middle of the run: the checks before
    /// keep their verdicts, the one running and those after it fail.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hung_up: Option<HungUp>,
    /// Every frame of each check, in the checks' order, where a check
    /// keeps only those that show its verdict (a master's: a few of its
    /// seconds of polling); empty where the checks' frames are all. What
    /// the recording holds.
    #[serde(skip)]
    pub transcript: Vec<Vec<Exchange>>,
}

fn as_written(patience: &f64) -> bool {
    *patience == 1.0
}

/// When and how the program hung up, and in which check.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HungUp {
    /// Seconds after the link was opened.
    pub at: f64,
    /// What the link said: `closed the connection`, `reset the connection`.
    pub how: String,
    /// The check that was running.
    pub check: String,
}

impl SuiteRun {
    pub fn score(&self) -> u32 {
        self.passed().map(|c| c.points).sum()
    }

    /// The points of the checks that apply (not those not applicable).
    pub fn points(&self) -> u32 {
        self.applicable().map(|c| c.points).sum()
    }

    /// The checks that apply to this run.
    pub fn applicable(&self) -> impl Iterator<Item = &CheckOutcome> {
        self.checks
            .iter()
            .filter(|c| !matches!(c.outcome, Outcome::NotApplicable(_)))
    }

    /// The checks not applicable to this run.
    pub fn not_applicable(&self) -> usize {
        self.checks.len() - self.applicable().count()
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

    /// A run that never got to its checks: each fails with `why` (a
    /// bench check without a bench is still not applicable), so the
    /// score and the reports say 0 of the suite's points.
    pub fn unreachable(suite: &Suite, link: &str, id: u8, why: String) -> Self {
        let checks = suite
            .checks
            .iter()
            .map(|check| CheckOutcome {
                name: check.name.clone(),
                requirement: check.requirement.clone(),
                points: check.points,
                outcome: if check.is_bench() {
                    Outcome::NotApplicable(NO_BENCH.into())
                } else {
                    Outcome::Fail(why.clone())
                },
                at: 0.0,
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
            protocol: suite.protocol,
            ids: Vec::new(),
            checks,
            seconds: 0.0,
            bench: None,
            patience: suite.patience,
            error: Some(why),
            hung_up: None,
            transcript: Vec::new(),
        }
    }
}

/// Plays `suite` against the program on `wire`, as slave `id`. A program
/// that hangs up (a connection closed, a pseudo-terminal gone) ends the run
/// there: the checks before keep their verdicts, the one running and those
/// after it fail saying so ([`SuiteRun::hung_up`]).
pub fn run_suite(suite: &Suite, wire: &mut Wire, id: u8) -> SuiteRun {
    run_suite_on(suite, wire, id, None)
}

/// [`run_suite`] with the slave wired to `bench`: its bench checks are
/// judged there (without one they are not applicable).
pub fn run_suite_on(suite: &Suite, wire: &mut Wire, id: u8, bench: Option<&Bench>) -> SuiteRun {
    let started = wire.now();
    let mut checks = Vec::with_capacity(suite.checks.len());
    let mut hung_up: Option<HungUp> = None;
    let mut next_transaction = 1;
    for check in &suite.checks {
        let outcome_of = |outcome: Outcome, at: f64, play: Play<'_>| CheckOutcome {
            name: check.name.clone(),
            requirement: check.requirement.clone(),
            points: check.points,
            outcome,
            at,
            seconds: play.wire.now() - at,
            reply_ms: play.reply_ms,
            frames: play.frames,
            notes: Vec::new(),
        };
        if check.is_bench() && bench.is_none() {
            let at = wire.now();
            let play = Play::new(wire, suite, id, next_transaction);
            checks.push(outcome_of(
                Outcome::NotApplicable(NO_BENCH.into()),
                at,
                play,
            ));
            continue;
        }
        if let Some(gone) = &hung_up {
            let why = format!(
                "not run: the program hung up at {:.3} s, during `{}`",
                gone.at, gone.check
            );
            let at = wire.now();
            let play = Play::new(wire, suite, id, next_transaction);
            checks.push(outcome_of(Outcome::Fail(why), at, play));
            continue;
        }
        let mut play = Play::new(wire, suite, id, next_transaction);
        play.bench = bench.filter(|_| check.is_bench());
        if check.timing {
            play.stretch = 1.0;
        }
        let mut began = play.wire.now();
        let played = play.settle().and_then(|()| {
            began = play.wire.now();
            for step in &check.steps {
                if let Err(why) = play.step(step)? {
                    // What comes after the failure is part of its story (a
                    // reply too late), and must not be taken for the next
                    // check's.
                    play.verdict = Some(why.clone());
                    let wait = play.stretched(3 * suite.timeout_ms.max(100));
                    let late = play.late(Duration::from_millis(wait))?;
                    return Ok(Outcome::Fail(why + &late));
                }
            }
            Ok(Outcome::Pass)
        });
        let outcome = match played {
            Ok(outcome) => outcome,
            Err(e) => {
                let gone = HungUp {
                    at: play.wire.now(),
                    how: hang_up_words(&e),
                    check: check.name.clone(),
                };
                let hang_up = format!("the program hung up at {:.3} s ({})", gone.at, gone.how);
                hung_up = Some(gone);
                Outcome::Fail(match play.verdict.take() {
                    // The check had failed already; the hang-up came after.
                    Some(why) => format!("{why}; then {hang_up}"),
                    None => hang_up,
                })
            }
        };
        next_transaction = play.next_transaction;
        let slowest = play.reply_ms.iter().copied().fold(0.0, f64::max);
        let mut done = outcome_of(outcome, began, play);
        // Honest about what patience let through: a reply later than the
        // suite's own deadline is said, pass or not.
        if suite.patience != 1.0 && !check.timing && slowest > suite.timeout_ms as f64 {
            done.notes.push(format!(
                "a reply began {slowest:.0} ms after its request, beyond the suite's {} ms: in time only with --patience {}",
                suite.timeout_ms, suite.patience
            ));
        }
        checks.push(done);
    }
    SuiteRun {
        suite: suite.name.clone(),
        link: wire.link().to_string(),
        id,
        role: Role::Slave,
        protocol: suite.protocol,
        ids: Vec::new(),
        checks,
        seconds: wire.now() - started,
        bench: bench.map(Bench::described),
        patience: suite.patience,
        error: None,
        hung_up,
        transcript: Vec::new(),
    }
}

/// How the link went, in the words a student reads.
pub(crate) fn hang_up_words(e: &WireError) -> String {
    match e {
        WireError::Closed { .. } => "it closed the connection".into(),
        // A serial write that made no way for 2 s: the line stayed full.
        WireError::Io { why, .. } if why.kind() == std::io::ErrorKind::TimedOut => {
            "it stopped reading the twin's replies: the line stayed full for 2 s".into()
        }
        // A pseudo-terminal whose other end closed, a USB adapter pulled:
        // the port fails its next read, write or flush, whatever it says.
        WireError::Io { link, .. } if !link.starts_with("tcp://") => {
            "the serial port or pseudo-terminal went away".into()
        }
        WireError::Io { why, .. } => match why.kind() {
            std::io::ErrorKind::ConnectionReset | std::io::ErrorKind::ConnectionAborted => {
                "it reset the connection".into()
            }
            std::io::ErrorKind::BrokenPipe => "it closed the connection".into(),
            _ => format!("the link failed: {why}"),
        },
        other => other.to_string(),
    }
}

struct Play<'a> {
    wire: &'a mut Wire,
    protocol: Protocol,
    id: u8,
    /// A reply's deadline where a step sets none (as the suite says).
    timeout_ms: u64,
    /// How many times as long every wait is ([`Suite::patience`]; 1 in a
    /// timing check).
    stretch: f64,
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
    /// Why the check failed, once a step has failed it.
    verdict: Option<String>,
    /// The bench, in a bench check.
    bench: Option<&'a Bench>,
    /// The plant before the last request (in a bench check), and the
    /// last reply taken.
    plant_before: Option<PlantState>,
    last_reply: Vec<u8>,
}

/// A step's verdict: `Err(why)` when the program did not do what it required.
type Verdict = Result<(), String>;

impl<'a> Play<'a> {
    fn new(wire: &'a mut Wire, suite: &Suite, id: u8, next_transaction: u16) -> Self {
        Play {
            wire,
            protocol: suite.protocol,
            id,
            timeout_ms: suite.timeout_ms,
            stretch: suite.patience,
            frames: Vec::new(),
            pending: Vec::new(),
            pending_since: None,
            unanswered: VecDeque::new(),
            last_request: (Vec::new(), 0),
            next_transaction,
            sent_at: None,
            reply_ms: Vec::new(),
            verdict: None,
            bench: None,
            plant_before: None,
            last_reply: Vec::new(),
        }
    }

    fn fill(&self, text: &str) -> String {
        self.protocol.fill(text, self.id)
    }

    /// `ms` stretched by the patience asked for.
    fn stretched(&self, ms: u64) -> u64 {
        (ms as f64 * self.stretch).round() as u64
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

    /// Waits until the line has been quiet for [`SETTLE`] (stretched).
    fn settle(&mut self) -> Result<(), WireError> {
        let mut junk = Vec::new();
        let quiet = SETTLE.mul_f64(self.stretch);
        let give_up = Instant::now() + Duration::from_secs(2).mul_f64(self.stretch);
        while self.wire.receive(&mut junk, Instant::now() + quiet)? > 0 {
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
            bytes: bytes.to_vec(),
            peer: None,
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
            bytes: bytes.to_vec(),
            peer: None,
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
                if let Some(bench) = self.bench {
                    // What the plant was before the request, for the
                    // inputs its reply carries; a bench that cannot be
                    // read fails the step that needs it.
                    self.plant_before = bench.state().ok();
                }
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
                let within_ms = self.stretched(within_ms.unwrap_or(self.timeout_ms));
                self.expect(&pattern, *data, transaction, within_ms)
            }
            Step::Error { code, within_ms } => {
                let (request, transaction) = self.answered();
                let pattern = self.protocol.error_pattern(&request, self.id, *code);
                let within_ms = self.stretched(within_ms.unwrap_or(self.timeout_ms));
                self.expect(&pattern, 0, transaction, within_ms)
            }
            Step::Silence { ms } => {
                let ms = self.stretched(*ms);
                let until = Instant::now() + Duration::from_millis(ms);
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
                let until = Instant::now() + Duration::from_millis(self.stretched(*ms));
                while Instant::now() < until {
                    self.receive(until)?;
                }
                Ok(Ok(()))
            }
            Step::Bench(step) => {
                let Some(bench) = self.bench else {
                    return Ok(Err(NO_BENCH.into()));
                };
                let words = self.protocol.data_words(&self.last_reply);
                let reply = (!self.last_reply.is_empty()).then_some(words.as_slice());
                Ok(bench
                    .judge(step, reply, self.plant_before.as_ref())
                    .map_err(|why| format!("on the bench: {why}")))
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
                let verdict = self
                    .protocol
                    .judge(&frame, pattern, data, transaction)
                    .map_err(|why| format!("{why}; expected {wanted}"));
                if verdict.is_ok() {
                    self.last_reply = frame;
                }
                return Ok(verdict);
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
