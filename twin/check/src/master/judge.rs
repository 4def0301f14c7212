//! What a master must do in each situation, and what it may choose. The
//! verdicts are read off the requests alone, the only thing of a master's
//! a slave can see:
//!
//! - it answers: every request well-formed (the page's frame, FCS, upper
//!   case, `*\n`), to a slave on the line, and none while a reply is owed;
//!   every slave polled. Its poll rate is a figure, not a grade: the page
//!   sets none.
//! - a slow reply: nothing sent before it, and it goes on after it as
//!   after a prompt one.
//! - a split reply, junk before a reply: it goes on after it as after a
//!   prompt one (a master that lost the reply waits out its timeout).
//! - an error reply: it keeps polling (retrying the request or not is its
//!   choice).
//! - a bad FCS, another slave's id (MEB): not taken as the reply. It may
//!   retry at once, or wait out its timeout; going straight on to its next
//!   request as after a good reply is taking it.
//! - a bad CRC, another slave's id, junk before a reply (Modbus): the
//!   serial line specification lets a master that finds a frame error go
//!   on at once, retry or wait out its timeout, so its requests cannot show
//!   whether it took the reply: it must keep polling, and what it chose is
//!   said.
//! - a slave that does not answer: it gives up within its timeout and a
//!   poll period, and polls the other slaves meanwhile; retrying first is
//!   its choice.

use super::heard::{Heard, Phase};
use super::{Behaviour, MasterSuite, Situation};
use crate::framing::Protocol;
use crate::run::{CheckOutcome, Exchange, Outcome};
use std::collections::BTreeSet;

/// How the master went on in the first check, where the slaves answered:
/// the yardstick of the others.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct Normal {
    /// From a reply's last byte to the next request, ms (median).
    pub after_reply_ms: f64,
    /// From one request to the first slave to its next, ms (median).
    pub period_ms: f64,
    /// It sent nothing while a reply was owed. One that does not is not
    /// waiting for replies at all, so what it does after a spoilt one
    /// shows nothing (the first check reports it).
    pub waits: bool,
}

/// The verdict on one situation.
pub(crate) fn judge(
    situation: &Situation,
    phase: Phase,
    ids: &[u8],
    suite: &MasterSuite,
    normal: &mut Normal,
) -> CheckOutcome {
    let timeout = suite.timeout_ms as f64;
    let protocol = suite.protocol;
    let mut notes = Vec::new();
    let result = if phase.heard.is_empty() {
        Err((
            format!(
                "no request came in these {:.0} s: the master stopped polling",
                situation.seconds
            ),
            None,
        ))
    } else {
        match &situation.slave {
            Behaviour::Answers => {
                let result = answers(&phase, ids, protocol, &mut notes);
                *normal = Normal {
                    after_reply_ms: median(gaps_after_replies(&phase.heard)).unwrap_or(0.0),
                    period_ms: median(periods(&phase.heard, ids[0])).unwrap_or(timeout),
                    waits: !phase.heard.iter().any(|h| h.owed),
                };
                result
            }
            Behaviour::Slow(ms) => waits(&phase, *ms, protocol)
                .and_then(|()| carries_on(&phase, normal, timeout, &mut notes)),
            Behaviour::Junk(..) if !protocol.is_text() => {
                goes_on(&phase, normal, timeout, protocol, Passed::Junk, &mut notes)
            }
            Behaviour::Split(_) | Behaviour::Junk(..) => {
                carries_on(&phase, normal, timeout, &mut notes)
            }
            Behaviour::Error(_) => {
                goes_on(&phase, normal, timeout, protocol, Passed::Error, &mut notes)
            }
            Behaviour::BadFcs | Behaviour::WrongId if !protocol.is_text() => goes_on(
                &phase,
                normal,
                timeout,
                protocol,
                Passed::Spoilt,
                &mut notes,
            ),
            Behaviour::BadFcs | Behaviour::WrongId => discards(&phase, normal, timeout, &mut notes),
            Behaviour::Silent => gives_up(&phase, ids, normal, timeout, protocol, &mut notes),
        }
    };
    let (outcome, around) = match result {
        Ok(()) => (Outcome::Pass, None),
        Err((why, at)) => (Outcome::Fail(why), at),
    };
    CheckOutcome {
        name: situation.name.clone(),
        requirement: situation.requirement.clone(),
        points: situation.points,
        outcome,
        reply_ms: Vec::new(),
        frames: evidence(phase.frames, around),
        at: phase.began,
        seconds: phase.seconds,
        notes,
    }
}

/// A check that could not be played.
pub(crate) fn failed(situation: &Situation, why: String) -> CheckOutcome {
    CheckOutcome {
        name: situation.name.clone(),
        requirement: situation.requirement.clone(),
        points: situation.points,
        outcome: Outcome::Fail(why),
        reply_ms: Vec::new(),
        frames: Vec::new(),
        at: 0.0,
        seconds: 0.0,
        notes: Vec::new(),
    }
}

/// Why it failed, and when (the frames around then are the evidence).
type Verdict = Result<(), (String, Option<f64>)>;

fn answers(phase: &Phase, ids: &[u8], protocol: Protocol, notes: &mut Vec<String>) -> Verdict {
    let shown_ids = ids_text(ids);
    for (i, heard) in phase.heard.iter().enumerate() {
        let text = protocol.shown(&heard.bytes);
        let fault = |why: String| Err((why, Some(heard.at)));
        if !heard.junk.is_empty() {
            return fault(format!(
                "{} bytes before the request's @ (`{}`)",
                heard.junk.len(),
                protocol.shown(&heard.junk)
            ));
        }
        if let Some(why) = &heard.seen.fault {
            return fault(why.clone());
        }
        if let Some(id) = heard.seen.id
            && !heard.seen.broadcast
            && !ids.contains(&id)
        {
            return fault(format!(
                "`{text}` is for slave {id:02}, which is not on this line (slaves {shown_ids})"
            ));
        }
        if heard.owed
            && let Some(before) = i.checked_sub(1).and_then(|j| phase.heard.get(j))
        {
            return fault(format!(
                "`{text}` came {:.0} ms after `{}`, before its reply: a master waits for each reply (or its timeout) before the next request",
                (heard.at - before.at) * 1e3,
                protocol.shown(&before.bytes)
            ));
        }
    }
    let polled: BTreeSet<u8> = phase
        .heard
        .iter()
        .filter(|h| h.seen.fault.is_none())
        .filter_map(|h| h.seen.id)
        .collect();
    if let Some(missing) = ids.iter().find(|id| !polled.contains(id)) {
        return Err((
            format!(
                "slave {missing:02} was never polled (the master was given slaves {shown_ids})"
            ),
            None,
        ));
    }
    let refused: Vec<&Heard> = phase
        .heard
        .iter()
        .filter(|h| h.seen.refused.is_some())
        .collect();
    if let Some(first) = refused.first() {
        // A master's configuration (which registers to read) is its
        // user's: said, not graded.
        notes.push(format!(
            "{} of the requests asked for what the slave does not have, and got exception {:02} (e.g. `{}`): see the slave's register map",
            refused.len(),
            first.seen.refused.unwrap_or(0),
            protocol.shown(&first.bytes)
        ));
    }
    let count = phase.heard.len();
    notes.push(format!(
        "{count} requests in {:.1} s ({:.0} a second): {}",
        phase.seconds,
        count as f64 / phase.seconds.max(1e-3),
        blocks(&phase.heard)
    ));
    if let Some(period) = median(periods(&phase.heard, ids[0])) {
        notes.push(format!(
            "slave {:02} polled every {period:.1} ms (median)",
            ids[0]
        ));
    }
    let gaps = gaps_after_replies(&phase.heard);
    let shortest = gaps.iter().copied().reduce(f64::min);
    if let Some(after) = median(gaps) {
        notes.push(format!(
            "the next request came {after:.1} ms after a reply (median)"
        ));
    }
    if let (Some(shortest), false) = (shortest, protocol.is_text()) {
        notes.push(format!(
            "the shortest silence between a reply and the next request: {shortest:.1} ms"
        ));
    }
    Ok(())
}

/// Nothing sent while the slow reply was owed.
fn waits(phase: &Phase, slow_ms: u64, protocol: Protocol) -> Verdict {
    for pair in phase.heard.windows(2) {
        let [before, heard] = pair else { continue };
        if heard.owed {
            return Err((
                format!(
                    "`{}` came {:.0} ms after `{}`, before its reply (due {slow_ms} ms after it, within the timeout): a master waits for the reply",
                    protocol.shown(&heard.bytes),
                    (heard.at - before.at) * 1e3,
                    protocol.shown(&before.bytes)
                ),
                Some(heard.at),
            ));
        }
    }
    Ok(())
}

/// After each reply it went on about as soon as after a prompt reply in
/// the first check, not after waiting out a timeout.
fn carries_on(phase: &Phase, normal: &Normal, timeout: f64, notes: &mut Vec<String>) -> Verdict {
    let gaps = gaps_after_replies(&phase.heard);
    let Some(after) = median(gaps.clone()) else {
        notes.push(not_judged());
        return Ok(());
    };
    notes.push(format!(
        "the next request came {after:.1} ms after a reply (median; {:.1} ms in the first check)",
        normal.after_reply_ms
    ));
    let limit = normal.after_reply_ms + timeout / 2.0;
    if after <= limit {
        return Ok(());
    }
    let at = phase
        .heard
        .iter()
        .zip(&gaps)
        .find(|(_, g)| **g > limit)
        .map(|(h, _)| h.at);
    Err((
        format!(
            "the master went on {after:.0} ms after each reply (median), against {:.0} ms in the first check: it did not take the reply, and waited out its timeout",
            normal.after_reply_ms
        ),
        at,
    ))
}

/// What the slave sent that a master goes on after.
#[derive(Clone, Copy)]
enum Passed {
    Error,
    /// A Modbus reply with a bad CRC or another slave's id.
    Spoilt,
    /// Junk, a silence, then the reply (Modbus).
    Junk,
}

/// Error replies (Modbus: also replies to discard) and the polls go on;
/// what the master did after each is said.
fn goes_on(
    phase: &Phase,
    normal: &Normal,
    timeout: f64,
    protocol: Protocol,
    passed: Passed,
    notes: &mut Vec<String>,
) -> Verdict {
    let limit = give_up_limit(normal, timeout);
    let (mut refused, mut retried) = (0, 0);
    let mut gaps = Vec::new();
    let first = phase.heard.first().map(|h| h.seen.id);
    for (i, heard) in phase.heard.iter().enumerate() {
        let Some(answer) = heard.answer.as_ref() else {
            continue;
        };
        let counts = match passed {
            Passed::Error | Passed::Spoilt => answer.spoilt,
            Passed::Junk => first.is_some_and(|id| id == heard.seen.id),
        };
        if !counts {
            continue;
        }
        refused += 1;
        match phase.heard.get(i + 1) {
            Some(next) => {
                gaps.push((next.at - answer.end) * 1e3);
                retried += usize::from(next.bytes == heard.bytes);
            }
            None if (phase.began + phase.seconds - heard.at) * 1e3 > quiet_limit(limit) => {
                let what = match passed {
                    Passed::Error => "the error reply",
                    Passed::Spoilt => "the reply to discard",
                    Passed::Junk => "the junk and the reply",
                };
                return Err((
                    format!(
                        "nothing came after {what} to `{}`: a master goes on polling",
                        protocol.shown(&heard.bytes)
                    ),
                    Some(heard.at),
                ));
            }
            None => {}
        }
    }
    let what = match passed {
        Passed::Error => "requests refused",
        Passed::Spoilt => "replies to discard",
        Passed::Junk => "replies after junk",
    };
    let after = median(gaps).map_or(String::new(), |ms| {
        format!(", and went on {ms:.0} ms after them (median)")
    });
    notes.push(format!(
        "{refused} {what}; the next request was the same one after {retried} of them (a retry, or the same poll again: its choice){after}"
    ));
    Ok(())
}

/// A spoilt reply not taken: retried, or its timeout waited out.
fn discards(phase: &Phase, normal: &Normal, timeout: f64, notes: &mut Vec<String>) -> Verdict {
    if !normal.waits {
        notes.push(not_judged());
        return Ok(());
    }
    let at_once = (normal.after_reply_ms + timeout) / 2.0;
    let (mut retried, mut waited, mut rescued) = (0, 0, 0);
    for (i, heard) in phase.heard.iter().enumerate() {
        let Some(answer) = heard.answer.as_ref().filter(|a| a.spoilt) else {
            continue;
        };
        // After a retry, going on is giving up, not taking the reply.
        let is_retry = i
            .checked_sub(1)
            .and_then(|j| phase.heard.get(j))
            .is_some_and(|before| before.bytes == heard.bytes);
        if is_retry {
            continue;
        }
        if answer.rescued {
            rescued += 1;
            continue;
        }
        let Some(next) = phase.heard.get(i + 1).filter(|n| !n.owed) else {
            continue;
        };
        if next.bytes == heard.bytes {
            retried += 1;
        } else if (next.at - answer.end) * 1e3 >= at_once {
            waited += 1;
        } else {
            return Err((
                format!(
                    "`{}` came {:.0} ms after the spoilt reply to `{}`, as after a good one: the master took a reply it must discard (a retry, or waiting out its timeout, shows it did not)",
                    crate::framing::shown_text(&next.bytes),
                    (next.at - answer.end) * 1e3,
                    crate::framing::shown_text(&heard.bytes)
                ),
                Some(next.at),
            ));
        }
    }
    if retried + waited + rescued == 0 {
        notes.push(not_judged());
        return Ok(());
    }
    notes.push(format!(
        "after a reply to discard the master retried {retried} times and waited out its timeout {waited} times (either is its choice)"
    ));
    if rescued > 0 {
        notes.push(format!(
            "{rescued} times it neither retried nor went on within 3 timeouts, and the twin sent the good reply (the last check judges waiting forever)"
        ));
    }
    Ok(())
}

/// Unanswered requests given up on in time, the other slaves polled.
fn gives_up(
    phase: &Phase,
    ids: &[u8],
    normal: &Normal,
    timeout: f64,
    protocol: Protocol,
    notes: &mut Vec<String>,
) -> Verdict {
    let silent = ids[0];
    let limit = give_up_limit(normal, timeout);
    let end = phase.began + phase.seconds;
    let to = |h: &Heard| h.seen.id;
    let mut gaps = Vec::new();
    let mut retried = 0;
    let mut unanswered = 0;
    for (i, heard) in phase.heard.iter().enumerate() {
        if to(heard) != Some(silent) {
            continue;
        }
        unanswered += 1;
        match phase.heard.get(i + 1) {
            Some(next) => {
                gaps.push((next.at - heard.at) * 1e3);
                retried += usize::from(next.bytes == heard.bytes);
            }
            None if (end - heard.at) * 1e3 > quiet_limit(limit) => {
                return Err((
                    format!(
                        "nothing came for {:.1} s after `{}` went unanswered: a master gives up after its reply timeout ({timeout:.0} ms) and carries on polling",
                        end - heard.at,
                        protocol.shown(&heard.bytes)
                    ),
                    Some(heard.at),
                ));
            }
            None => {}
        }
    }
    if unanswered == 0 {
        return Err((
            format!("slave {silent:02} was not polled while it did not answer"),
            None,
        ));
    }
    if let Some(after) = median(gaps) {
        notes.push(format!(
            "the master went on {after:.0} ms after an unanswered request (median), and sent the same request again after {retried} of {unanswered} (its choice)"
        ));
        if after > limit {
            return Err((
                format!(
                    "the master went on {after:.0} ms after an unanswered request (median): more than its timeout ({timeout:.0} ms) twice and a poll period ({:.0} ms)",
                    normal.period_ms
                ),
                None,
            ));
        }
    }
    let first = phase
        .heard
        .iter()
        .find(|h| to(h) == Some(silent))
        .map_or(0.0, |h| h.at);
    for &other in &ids[1..] {
        let polled = phase
            .heard
            .iter()
            .filter(|h| h.at > first && to(h) == Some(other))
            .count();
        if polled == 0 {
            return Err((
                format!(
                    "slave {other:02} was not polled while slave {silent:02} did not answer: a master carries on with the others"
                ),
                Some(first),
            ));
        }
        notes.push(format!("slave {other:02} polled {polled} times meanwhile"));
    }
    Ok(())
}

/// How long the line may stay quiet at a check's end before the master
/// is taken to have stopped: a loaded machine may hold a program up for a
/// while, a master that waits forever holds the line for the rest.
fn quiet_limit(give_up: f64) -> f64 {
    (3.0 * give_up).max(1000.0)
}

fn not_judged() -> String {
    "not judged: every request came before the reply to the one before (the first check reports that)".into()
}

/// How long a master may take to go on after an unanswered request, ms.
fn give_up_limit(normal: &Normal, timeout: f64) -> f64 {
    2.0 * timeout + normal.period_ms
}

/// From each normal reply's last byte to the request after it, ms, where
/// that request waited for it.
fn gaps_after_replies(heard: &[Heard]) -> Vec<f64> {
    heard
        .windows(2)
        .filter_map(|pair| {
            let [h, next] = pair else { return None };
            let answer = h.answer.as_ref().filter(|a| !a.spoilt)?;
            (!next.owed).then(|| ((next.at - answer.end) * 1e3).max(0.0))
        })
        .collect()
}

/// From one request to `id` to its next, ms.
fn periods(heard: &[Heard], id: u8) -> Vec<f64> {
    let times: Vec<f64> = heard
        .iter()
        .filter(|h| h.seen.id == Some(id))
        .map(|h| h.at)
        .collect();
    times.windows(2).map(|w| (w[1] - w[0]) * 1e3).collect()
}

fn median(mut values: Vec<f64>) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    values.get(values.len() / 2).copied()
}

/// Which blocks the requests read and wrote: `reads EA 00-05, writes SA 00`.
fn blocks(heard: &[Heard]) -> String {
    let mut reads = BTreeSet::new();
    let mut writes = BTreeSet::new();
    for (read, span) in heard.iter().filter_map(|h| h.seen.block.clone()) {
        if read {
            reads.insert(span);
        } else {
            writes.insert(span);
        }
    }
    let list = |set: BTreeSet<String>| set.into_iter().collect::<Vec<_>>().join(", ");
    match (reads.is_empty(), writes.is_empty()) {
        (false, false) => format!("reads {}; writes {}", list(reads), list(writes)),
        (false, true) => format!("reads {}", list(reads)),
        (true, false) => format!("writes {}", list(writes)),
        (true, true) => "nothing well-formed".into(),
    }
}

fn ids_text(ids: &[u8]) -> String {
    ids.iter()
        .map(|id| format!("{id:02}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The frames that show a verdict: around `at` for a failure, the first
/// few for a pass.
fn evidence(frames: Vec<Exchange>, at: Option<f64>) -> Vec<Exchange> {
    match at {
        None => frames.into_iter().take(8).collect(),
        Some(at) => {
            let from = frames
                .iter()
                .rposition(|f| f.at < at - 0.3)
                .map_or(0, |i| i + 1);
            frames.into_iter().skip(from).take(14).collect()
        }
    }
}
