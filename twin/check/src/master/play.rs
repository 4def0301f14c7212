//! The twin's slaves on the master's line, situation after situation: every
//! request the master sends is taken apart, answered as the situation says
//! (or not), and kept with its time and the twin's answer for [`judge`].
//!
//! A request whose only fault is its check bytes (MEB's FCS, a Modbus
//! CRC) is answered as if they were right:
//! the fault is the first check's to report, and answering lets every
//! other situation still be tried on that master.

use super::dialect::{self, Slaves};
use super::heard::{Answer, Heard, Phase};
use super::judge::{self, Normal};
use super::{Behaviour, MasterSuite};
use crate::framing::Protocol;
use crate::run::{Exchange, HungUp, Role, SuiteRun, Way, hang_up_words};
use crate::wire::{Wire, WireError};
use protocols::time::{SimDuration, SimTime};
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// What the check is told besides the suite.
#[derive(Debug, Clone)]
pub struct MasterOptions {
    /// The slaves the twin plays; the situations happen to the first.
    pub ids: Vec<u8>,
    /// How long to wait for the master's first request.
    pub wait: Duration,
}

struct Scheduled {
    at: Instant,
    bytes: Vec<u8>,
    phase: usize,
    request: usize,
    last: bool,
    /// Not the slave's normal reply (a spoilt one or an error reply).
    spoilt: bool,
    /// The good reply, held back after a spoilt one.
    good: Option<Vec<u8>>,
    rescue: bool,
}

/// How long the line stays quiet before bytes whose length cannot be
/// told are taken as a request.
const QUIET: Duration = Duration::from_millis(50);

struct Play<'a> {
    wire: &'a mut Wire,
    protocol: Protocol,
    ids: Vec<u8>,
    slaves: Slaves,
    /// When the master's last byte came.
    last_byte: Instant,
    timeout: Duration,
    phases: Vec<Phase>,
    pending: Vec<u8>,
    queue: VecDeque<Scheduled>,
    /// The good reply held back after a spoilt one, and when to send it.
    rescue: Option<Scheduled>,
}

/// Plays `suite` against the master on `wire`: each situation for its
/// seconds, then the verdicts. Errors only when the link fails.
pub fn run_master(
    suite: &MasterSuite,
    wire: &mut Wire,
    options: &MasterOptions,
) -> Result<SuiteRun, WireError> {
    let started = wire.now();
    let mut play = Play {
        wire,
        protocol: suite.protocol,
        ids: options.ids.clone(),
        slaves: Slaves::new(suite.protocol, &options.ids),
        last_byte: Instant::now(),
        timeout: Duration::from_millis(suite.timeout_ms),
        phases: Vec::new(),
        pending: Vec::new(),
        queue: VecDeque::new(),
        rescue: None,
    };
    play.phases.push(Phase::default());
    let first_by = Instant::now() + options.wait;
    while play.phases[0].heard.is_empty() && Instant::now() < first_by {
        play.turn(&Behaviour::Answers, first_by)?;
    }
    if play.phases[0].heard.is_empty() {
        let why = format!(
            "no request came within {} s: is the master running, on {}?",
            options.wait.as_secs(),
            play.wire.link()
        );
        return Ok(unreachable(suite, play.wire.link(), &options.ids, why));
    }
    // The first request only opened the line; the first check starts now.
    play.phases[0] = Phase::default();
    // A link that fails mid-run (the master hung up, or stopped reading
    // its replies) ends the run; the checks before keep their verdicts.
    let mut broke: Option<(usize, WireError)> = None;
    'checks: for (i, situation) in suite.checks.iter().enumerate() {
        if i > 0 {
            play.phases.push(Phase::default());
        }
        let began = Instant::now();
        let at = play.wire.now();
        play.phase().began = at;
        let end = began + Duration::from_secs_f64(situation.seconds);
        while Instant::now() < end {
            if let Err(e) = play.turn(&situation.slave, end) {
                broke = Some((i, e));
                break 'checks;
            }
        }
        if let Some(phase) = play.phases.last_mut() {
            phase.seconds = began.elapsed().as_secs_f64();
        }
    }
    // Replies still owed go out, so the last check's are whole.
    let flush = Instant::now() + play.timeout;
    while broke.is_none() && !play.queue.is_empty() && Instant::now() < flush {
        let last = suite
            .checks
            .last()
            .map_or(Behaviour::Answers, |c| c.slave.clone());
        if let Err(e) = play.turn(&last, flush) {
            broke = Some((suite.checks.len().saturating_sub(1), e));
        }
    }
    let hung_up = broke.as_ref().map(|(i, e)| HungUp {
        at: play.wire.now(),
        how: hang_up_words(e),
        check: suite
            .checks
            .get(*i)
            .map_or_else(String::new, |c| c.name.clone()),
    });
    // The checks keep their evidence; the recording, every frame.
    let transcript = play.phases.iter().map(|p| p.frames.clone()).collect();
    let mut normal = Normal::default();
    let mut phases = std::mem::take(&mut play.phases).into_iter();
    let checks = suite
        .checks
        .iter()
        .enumerate()
        .map(|(i, situation)| match (&broke, &hung_up) {
            (Some((at, _)), Some(gone)) if i == *at => judge::failed(
                situation,
                format!("the program hung up at {:.3} s ({})", gone.at, gone.how),
            ),
            (Some((at, _)), Some(gone)) if i > *at => judge::failed(
                situation,
                format!(
                    "not run: the program hung up at {:.3} s, during `{}`",
                    gone.at, gone.check
                ),
            ),
            _ => {
                let phase = phases.next().unwrap_or_default();
                judge::judge(situation, phase, &options.ids, suite, &mut normal)
            }
        })
        .collect();
    Ok(SuiteRun {
        suite: suite.name.clone(),
        link: play.wire.link().to_string(),
        id: options.ids.first().copied().unwrap_or(1),
        role: Role::Master,
        protocol: suite.protocol,
        ids: options.ids.clone(),
        checks,
        seconds: play.wire.now() - started,
        bench: None,
        patience: 1.0,
        error: None,
        hung_up,
        transcript,
    })
}

/// A run that never got to its checks: each fails with `why`.
pub fn unreachable(suite: &MasterSuite, link: &str, ids: &[u8], why: String) -> SuiteRun {
    let checks = suite
        .checks
        .iter()
        .map(|c| judge::failed(c, why.clone()))
        .collect();
    SuiteRun {
        suite: suite.name.clone(),
        link: link.into(),
        id: ids.first().copied().unwrap_or(1),
        role: Role::Master,
        protocol: suite.protocol,
        ids: ids.to_vec(),
        checks,
        seconds: 0.0,
        hung_up: None,
        bench: None,
        patience: 1.0,
        error: Some(why),
        transcript: Vec::new(),
    }
}

impl Play<'_> {
    fn phase(&mut self) -> &mut Phase {
        let last = self.phases.len() - 1;
        &mut self.phases[last]
    }

    /// Sends what is due, then listens until the next thing is due or
    /// `end`; every whole request heard is answered as `slave` says.
    fn turn(&mut self, slave: &Behaviour, end: Instant) -> Result<(), WireError> {
        self.send_due()?;
        let mut until = end;
        if let Some(s) = self.queue.front() {
            until = until.min(s.at);
        }
        if let Some(r) = &self.rescue {
            until = until.min(r.at);
        }
        if !self.pending.is_empty() && !self.protocol.is_text() {
            // Binary bytes of no known length wait for the line to go
            // quiet (MEB's wait for their line feed).
            until = until.min(self.last_byte + QUIET);
        }
        let before = self.pending.len();
        if self.wire.receive(&mut self.pending, until)? > 0 {
            self.last_byte = Instant::now();
        }
        let quiet = self.last_byte.elapsed() >= QUIET;
        if before == self.pending.len() && !quiet {
            return Ok(());
        }
        while let Some((junk, bytes)) =
            dialect::take_request(self.protocol, &mut self.pending, quiet)
        {
            self.heard(junk, bytes, slave);
        }
        if self.pending.len() > dialect::max_request(self.protocol) {
            let junk = std::mem::take(&mut self.pending);
            self.note(Way::Received, &junk);
        }
        Ok(())
    }

    fn send_due(&mut self) -> Result<(), WireError> {
        let now = Instant::now();
        if self.rescue.as_ref().is_some_and(|r| r.at <= now)
            && let Some(r) = self.rescue.take()
        {
            self.queue.push_back(r);
        }
        while self.queue.front().is_some_and(|s| s.at <= now) {
            let Some(s) = self.queue.pop_front() else {
                break;
            };
            self.wire.send(&s.bytes)?;
            let at = self.wire.now();
            self.note(Way::Sent, &s.bytes);
            let timeout = self.timeout;
            let Some(heard) = self
                .phases
                .get_mut(s.phase)
                .and_then(|p| p.heard.get_mut(s.request))
            else {
                continue;
            };
            let answer = heard.answer.get_or_insert_with(|| Answer {
                spoilt: s.spoilt,
                ..Answer::default()
            });
            answer.end = at;
            if s.rescue {
                answer.rescued = true;
            } else if s.last
                && let Some(good) = s.good
            {
                // Held back: sent if the master neither retries nor goes
                // on within three of its timeouts.
                self.rescue = Some(Scheduled {
                    at: Instant::now() + 3 * timeout,
                    bytes: good,
                    phase: s.phase,
                    request: s.request,
                    last: true,
                    spoilt: true,
                    good: None,
                    rescue: true,
                });
            }
        }
        Ok(())
    }

    fn note(&mut self, way: Way, bytes: &[u8]) {
        let at = self.wire.now();
        let text = self.protocol.shown(bytes);
        self.phase().frames.push(Exchange {
            at,
            way,
            text,
            bytes: bytes.to_vec(),
            peer: None,
        });
    }

    /// A request the master sent (`junk`: bytes before it that belong to
    /// no frame), answered as `slave` says.
    fn heard(&mut self, junk: Vec<u8>, bytes: Vec<u8>, slave: &Behaviour) {
        let mut all = junk.clone();
        all.extend_from_slice(&bytes);
        self.note(Way::Received, &all);
        if bytes.is_empty() {
            return;
        }
        let seen = dialect::examine(self.protocol, &bytes);
        let owed = !self.queue.is_empty();
        // Whatever the master sends next ends the wait for a retry.
        self.rescue = None;
        let phase_index = self.phases.len() - 1;
        let request = self.phase().heard.len();
        let at = self.wire.now();
        self.phase().heard.push(Heard {
            at,
            bytes: bytes.clone(),
            junk,
            seen,
            owed,
            answer: None,
        });
        let Some(good) = self.good_reply(&bytes) else {
            return;
        };
        let protocol = self.protocol;
        if let Some(code) = dialect::exception_of(protocol, &good)
            && let Some(heard) = self.phase().heard.last_mut()
        {
            heard.seen.refused = Some(code);
        }
        let first = self.ids.first().copied();
        let target = dialect::reply_id(protocol, &good);
        let behaviour = if target == first {
            slave.clone()
        } else {
            Behaviour::Answers
        };
        let now = Instant::now();
        let keep = good.clone();
        let mut schedule = |at: Instant, bytes: Vec<u8>, last: bool, spoilt: bool| {
            self.queue.push_back(Scheduled {
                at,
                bytes,
                phase: phase_index,
                request,
                last,
                spoilt,
                good: (last && spoilt).then(|| keep.clone()),
                rescue: false,
            });
        };
        match behaviour {
            Behaviour::Answers => schedule(now, good, true, false),
            Behaviour::Slow(ms) => schedule(now + Duration::from_millis(ms), good, true, false),
            Behaviour::Split(ms) => {
                let half = good.len() / 2;
                schedule(now, good[..half].to_vec(), false, false);
                schedule(
                    now + Duration::from_millis(ms),
                    good[half..].to_vec(),
                    true,
                    false,
                );
            }
            Behaviour::Junk(junk, gap_ms) => {
                if gap_ms == 0 {
                    let mut bytes = junk;
                    bytes.extend_from_slice(&good);
                    schedule(now, bytes, true, false);
                } else {
                    // On a binary line a silence sets the junk apart, as
                    // noise between frames would be.
                    schedule(now, junk, false, false);
                    schedule(now + Duration::from_millis(gap_ms), good, true, false);
                }
            }
            Behaviour::Error(code) => {
                if let Some(reply) = dialect::refusal(protocol, &good, code) {
                    // An error reply is an answer: nothing is held back.
                    self.queue.push_back(Scheduled {
                        at: now,
                        bytes: reply,
                        phase: phase_index,
                        request,
                        last: true,
                        spoilt: true,
                        good: None,
                        rescue: false,
                    });
                }
            }
            Behaviour::BadFcs => {
                if let Some(reply) = dialect::spoil_check(protocol, &good) {
                    schedule(now, reply, true, true);
                }
            }
            Behaviour::WrongId => {
                let other = (1..=99).find(|id| !self.ids.contains(id)).unwrap_or(0);
                if let Some(reply) = dialect::with_id(protocol, &good, other) {
                    schedule(now, reply, true, true);
                }
            }
            Behaviour::Silent => {}
        }
    }

    /// The slave's own reply to `bytes` (its check bytes repaired if that
    /// was its only fault), if it is addressed to one of the twin's slaves
    /// and gets a reply.
    fn good_reply(&mut self, bytes: &[u8]) -> Option<Vec<u8>> {
        let request = dialect::repaired(self.protocol, bytes)?;
        let id = dialect::examine(self.protocol, &request).id?;
        let now = SimTime::ZERO + SimDuration::from_secs_f64(self.wire.now());
        self.slaves.reply(now, id, &request)
    }
}
