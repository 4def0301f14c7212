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
//! - a bad FCS, another slave's id: not taken as the reply. It may retry
//!   at once, or wait out its timeout; going straight on to its next
//!   request as after a good reply is taking it.
//! - a slave that does not answer: it gives up within its timeout and a
//!   poll period, and polls the other slaves meanwhile; retrying first is
//!   its choice.

use super::heard::{Heard, Phase, emit_request};
use super::{Behaviour, MasterSuite, Situation};
use crate::run::{CheckOutcome, Exchange, Outcome};
use nodes::proto::meb::{MebError, MebRepr};
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
                let result = answers(&phase, ids, &mut notes);
                *normal = Normal {
                    after_reply_ms: median(gaps_after_replies(&phase.heard)).unwrap_or(0.0),
                    period_ms: median(periods(&phase.heard, ids[0])).unwrap_or(timeout),
                    waits: !phase.heard.iter().any(|h| h.owed),
                };
                result
            }
            Behaviour::Slow(ms) => {
                waits(&phase, *ms).and_then(|()| carries_on(&phase, normal, timeout, &mut notes))
            }
            Behaviour::Split(_) | Behaviour::Junk(_) => {
                carries_on(&phase, normal, timeout, &mut notes)
            }
            Behaviour::Error(_) => goes_on(&phase, normal, timeout, &mut notes),
            Behaviour::BadFcs | Behaviour::WrongId => discards(&phase, normal, timeout, &mut notes),
            Behaviour::Silent => gives_up(&phase, ids, normal, timeout, &mut notes),
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

fn answers(phase: &Phase, ids: &[u8], notes: &mut Vec<String>) -> Verdict {
    let shown_ids = ids_text(ids);
    for (i, heard) in phase.heard.iter().enumerate() {
        let text = crate::framing::shown_text(&heard.bytes);
        let fault = |why: String| Err((why, Some(heard.at)));
        if !heard.junk.is_empty() {
            return fault(format!(
                "{} bytes before the request's @ (`{}`)",
                heard.junk.len(),
                crate::framing::shown_text(&heard.junk)
            ));
        }
        let frame = match &heard.frame {
            Ok(frame) => frame,
            Err(MebError::BadFcs) => {
                return fault(format!(
                    "`{text}`: its FCS is not the XOR of its bytes (the page: XOR of every byte from @ to the last before the FCS)"
                ));
            }
            Err(e) => return fault(format!("`{text}` is not a well-formed frame: {e}")),
        };
        if frame.shape().is_reply() {
            return fault(format!("`{text}` has a reply's shape, not a request's"));
        }
        if !frame.is_broadcast() && !ids.contains(&frame.id) {
            return fault(format!(
                "`{text}` is for slave {:02}, which is not on this line (slaves {shown_ids})",
                frame.id
            ));
        }
        if emit_request(frame).is_some_and(|canonical| canonical != heard.bytes) {
            return fault(format!(
                "`{text}` is not written as the page says to emit a frame (upper-case hex, ending *\\n)"
            ));
        }
        if heard.owed
            && let Some(before) = i.checked_sub(1).and_then(|j| phase.heard.get(j))
        {
            return fault(format!(
                "`{text}` came {:.0} ms after `{}`, before its reply: a master waits for each reply (or its timeout) before the next request",
                (heard.at - before.at) * 1e3,
                crate::framing::shown_text(&before.bytes)
            ));
        }
    }
    let polled: BTreeSet<u8> = phase
        .heard
        .iter()
        .filter_map(|h| h.frame.as_ref().ok().map(|f| f.id))
        .collect();
    if let Some(missing) = ids.iter().find(|id| !polled.contains(id)) {
        return Err((
            format!(
                "slave {missing:02} was never polled (the master was given slaves {shown_ids})"
            ),
            None,
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
    if let Some(after) = median(gaps_after_replies(&phase.heard)) {
        notes.push(format!(
            "the next request came {after:.1} ms after a reply (median)"
        ));
    }
    Ok(())
}

/// Nothing sent while the slow reply was owed.
fn waits(phase: &Phase, slow_ms: u64) -> Verdict {
    for pair in phase.heard.windows(2) {
        let [before, heard] = pair else { continue };
        if heard.owed {
            return Err((
                format!(
                    "`{}` came {:.0} ms after `{}`, before its reply (due {slow_ms} ms after it, within the timeout): a master waits for the reply",
                    crate::framing::shown_text(&heard.bytes),
                    (heard.at - before.at) * 1e3,
                    crate::framing::shown_text(&before.bytes)
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

/// Error replies taken as answers: the polls go on.
fn goes_on(phase: &Phase, normal: &Normal, timeout: f64, notes: &mut Vec<String>) -> Verdict {
    let limit = give_up_limit(normal, timeout);
    let (mut refused, mut retried) = (0, 0);
    for (i, heard) in phase.heard.iter().enumerate() {
        if !heard.answer.as_ref().is_some_and(|a| a.spoilt) {
            continue;
        }
        refused += 1;
        match phase.heard.get(i + 1) {
            Some(next) if next.bytes == heard.bytes => retried += 1,
            Some(_) => {}
            None if (phase.began + phase.seconds - heard.at) * 1e3 > quiet_limit(limit) => {
                return Err((
                    format!(
                        "nothing came after the error reply to `{}`: a master takes an error reply as the slave's answer and goes on",
                        crate::framing::shown_text(&heard.bytes)
                    ),
                    Some(heard.at),
                ));
            }
            None => {}
        }
    }
    notes.push(format!(
        "{refused} requests refused; the master sent the same request again after {retried} of them (its choice)"
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
    notes: &mut Vec<String>,
) -> Verdict {
    let silent = ids[0];
    let limit = give_up_limit(normal, timeout);
    let end = phase.began + phase.seconds;
    let to = |h: &Heard| h.id;
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
                        crate::framing::shown_text(&heard.bytes)
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
        .filter(|h| h.id == Some(id))
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
    for frame in heard.iter().filter_map(|h| h.frame.as_ref().ok()) {
        let span = span(frame);
        match frame.cmd.block().map(|(b, _)| b.access()) {
            Some(nodes::proto::meb::MebAccess::Read) => reads.insert(span),
            _ => writes.insert(span),
        };
    }
    let list = |set: BTreeSet<String>| set.into_iter().collect::<Vec<_>>().join(", ");
    match (reads.is_empty(), writes.is_empty()) {
        (false, false) => format!("reads {}; writes {}", list(reads), list(writes)),
        (false, true) => format!("reads {}", list(reads)),
        (true, false) => format!("writes {}", list(writes)),
        (true, true) => "nothing well-formed".into(),
    }
}

fn span(frame: &MebRepr) -> String {
    let last = u16::from(frame.addr) + u16::from(frame.cnt.max(1)) - 1;
    if frame.cnt <= 1 {
        format!("{} {:02X}", frame.cmd, frame.addr)
    } else {
        format!("{} {:02X}-{last:02X}", frame.cmd, frame.addr)
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
