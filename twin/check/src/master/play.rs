//! The twin's slaves on the master's line, situation after situation: every
//! request the master sends is taken apart, answered as the situation says
//! (or not), and kept with its time and the twin's answer for [`judge`].
//!
//! A request whose only fault is its FCS is answered as if it were right:
//! the fault is the first check's to report, and answering lets every
//! other situation still be tried on that master.

use super::heard::{Answer, Heard, Phase, emit};
use super::judge::{self, Normal};
use super::{Behaviour, MasterSuite};
use crate::framing::shown_text as shown;
use crate::run::{Exchange, Role, SuiteRun, Way};
use crate::wire::{Wire, WireError};
use nodes::firmware::{Framing, RegisterImage, SlaveFrontend};
use nodes::proto::meb::{MebError, MebErrorCode, MebRepr};
use nodes::time::{SimDuration, SimTime};
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

struct Slave {
    id: u8,
    image: RegisterImage,
    frontend: SlaveFrontend,
}

struct Play<'a> {
    wire: &'a mut Wire,
    ids: Vec<u8>,
    slaves: Vec<Slave>,
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
    let slaves = options
        .ids
        .iter()
        .map(|&id| Slave {
            id,
            // The EV module's controller at power-up (12-bit DAC and ADC,
            // the default light threshold and speed window).
            image: RegisterImage::new(12, 12, 1933, 100),
            frontend: SlaveFrontend::new(Framing::Meb, id),
        })
        .collect();
    let mut play = Play {
        wire,
        ids: options.ids.clone(),
        slaves,
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
    for (i, situation) in suite.checks.iter().enumerate() {
        if i > 0 {
            play.phases.push(Phase::default());
        }
        let began = Instant::now();
        let at = play.wire.now();
        play.phase().began = at;
        let end = began + Duration::from_secs_f64(situation.seconds);
        while Instant::now() < end {
            play.turn(&situation.slave, end)?;
        }
        if let Some(phase) = play.phases.last_mut() {
            phase.seconds = began.elapsed().as_secs_f64();
        }
    }
    // Replies still owed go out, so the last check's are whole.
    let flush = Instant::now() + play.timeout;
    while !play.queue.is_empty() && Instant::now() < flush {
        let last = suite
            .checks
            .last()
            .map_or(Behaviour::Answers, |c| c.slave.clone());
        play.turn(&last, flush)?;
    }
    let mut normal = Normal::default();
    let checks = suite
        .checks
        .iter()
        .zip(std::mem::take(&mut play.phases))
        .map(|(situation, phase)| judge::judge(situation, phase, &options.ids, suite, &mut normal))
        .collect();
    Ok(SuiteRun {
        suite: suite.name.clone(),
        link: play.wire.link().to_string(),
        id: options.ids.first().copied().unwrap_or(1),
        role: Role::Master,
        ids: options.ids.clone(),
        checks,
        seconds: play.wire.now() - started,
        error: None,
        hung_up: None,
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
        ids: ids.to_vec(),
        checks,
        seconds: 0.0,
        hung_up: None,
        error: Some(why),
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
        let before = self.pending.len();
        if self.wire.receive(&mut self.pending, until)? == 0 && before == self.pending.len() {
            return Ok(());
        }
        while let Some(nl) = self.pending.iter().position(|&b| b == b'\n') {
            let chunk: Vec<u8> = self.pending.drain(..=nl).collect();
            self.heard(chunk, slave);
        }
        if self.pending.len() > nodes::proto::meb::MEB_MAX_FRAME_LEN {
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
        self.phase().frames.push(Exchange {
            at,
            way,
            text: shown(bytes),
            bytes: bytes.to_vec(),
        });
    }

    /// A line the master sent (up to its `\n`): the request from its last
    /// `@`, anything before that junk; answered as `slave` says.
    fn heard(&mut self, chunk: Vec<u8>, slave: &Behaviour) {
        self.note(Way::Received, &chunk);
        let start = chunk
            .iter()
            .rposition(|&b| b == b'@')
            .unwrap_or(chunk.len());
        let (junk, bytes) = chunk.split_at(start);
        if bytes.is_empty() {
            return;
        }
        let frame = MebRepr::parse(bytes);
        let id = frame.as_ref().ok().map(|f| f.id).or_else(|| {
            with_fcs(bytes, |right| right)
                .and_then(|b| MebRepr::parse(&b).ok())
                .map(|f| f.id)
        });
        let owed = !self.queue.is_empty();
        // Whatever the master sends next ends the wait for a retry.
        self.rescue = None;
        let phase_index = self.phases.len() - 1;
        let request = self.phase().heard.len();
        let at = self.wire.now();
        self.phase().heard.push(Heard {
            at,
            bytes: bytes.to_vec(),
            junk: junk.to_vec(),
            frame,
            id,
            owed,
            answer: None,
        });
        let Some(good) = self.good_reply(bytes) else {
            return;
        };
        let first = self.ids.first().copied();
        let target = MebRepr::parse(&good).map(|r| r.id).ok();
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
            Behaviour::Junk(junk) => {
                let mut bytes = junk.into_bytes();
                bytes.extend_from_slice(&good);
                schedule(now, bytes, true, false);
            }
            Behaviour::Error(code) => {
                let addr = MebRepr::parse(&good).map_or(0, |r| r.addr);
                let code =
                    MebErrorCode::from_word(code.into()).unwrap_or(MebErrorCode::DeviceFailure);
                let refusal = MebRepr::error_reply(target.unwrap_or(0), addr, code);
                if let Some(reply) = emit(&refusal) {
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
            Behaviour::BadFcs => schedule(now, spoil_fcs(&good), true, true),
            Behaviour::WrongId => {
                let other = (1..=99).find(|id| !self.ids.contains(id)).unwrap_or(0);
                let reply = MebRepr::parse(&good)
                    .ok()
                    .and_then(|r| emit(&MebRepr { id: other, ..r }));
                if let Some(reply) = reply {
                    schedule(now, reply, true, true);
                }
            }
            Behaviour::Silent => {}
        }
    }

    /// The slave's own reply to `bytes` (its FCS repaired if that was its
    /// only fault), if it is addressed to one of the twin's slaves and
    /// gets a reply.
    fn good_reply(&mut self, bytes: &[u8]) -> Option<Vec<u8>> {
        let repaired;
        let request = match MebRepr::parse(bytes) {
            Ok(_) => bytes,
            Err(MebError::BadFcs) => {
                repaired = with_fcs(bytes, |right| right)?;
                &repaired[..]
            }
            Err(_) => return None,
        };
        let id = MebRepr::parse(request).ok()?.id;
        let now = SimTime::ZERO + SimDuration::from_secs_f64(self.wire.now());
        let slave = self.slaves.iter_mut().find(|s| s.id == id)?;
        slave.frontend.handle_bytes(&mut slave.image, now, request);
        while slave.frontend.poll_event().is_some() {}
        let mut out = [0u8; 512];
        let n = slave.frontend.poll_transmit(&mut out)?;
        while slave.frontend.poll_transmit(&mut [0u8; 512]).is_some() {}
        out.get(..n).map(<[u8]>::to_vec)
    }
}

/// `frame` with its FCS replaced by `fcs(the right one)`.
fn with_fcs(frame: &[u8], fcs: impl Fn(u8) -> u8) -> Option<Vec<u8>> {
    let star = frame.iter().rposition(|&b| b == b'*')?;
    let body = frame.get(..star.checked_sub(2)?)?;
    let right = body.iter().fold(0, |x, b| x ^ b);
    let mut out = body.to_vec();
    out.extend_from_slice(format!("{:02X}", fcs(right)).as_bytes());
    out.extend_from_slice(frame.get(star..)?);
    Some(out)
}

/// The reply with a wrong FCS (every bit of the right one flipped).
fn spoil_fcs(reply: &[u8]) -> Vec<u8> {
    with_fcs(reply, |right| !right).unwrap_or_else(|| reply.to_vec())
}
