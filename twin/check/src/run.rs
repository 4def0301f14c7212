//! A suite played over a [`Wire`]: every check's steps in order, what went
//! each way and when, and whether the program did what the step required.
//! A check stops at its first failing step; the next check starts on a
//! quiet line.

use crate::suite::{Step, Suite};
use crate::wire::{Wire, WireError};
use serde::Serialize;
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

/// Passed, or the reason it did not.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "result", content = "why", rename_all = "lowercase")]
pub enum Outcome {
    Pass,
    Fail(String),
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
}

/// A suite as it went against one program.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SuiteRun {
    pub suite: String,
    pub link: String,
    pub id: u8,
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
    pub fn first_failure(&self) -> Option<&CheckOutcome> {
        self.checks.iter().find(|c| c.outcome != Outcome::Pass)
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
            })
            .collect();
        SuiteRun {
            suite: suite.name.clone(),
            link: link.into(),
            id,
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
    for check in &suite.checks {
        let mut play = Play {
            wire: &mut *wire,
            id,
            timeout_ms: suite.timeout_ms,
            frames: Vec::new(),
            pending: Vec::new(),
            pending_since: None,
            last_body: String::new(),
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
        checks.push(CheckOutcome {
            name: check.name.clone(),
            requirement: check.requirement.clone(),
            points: check.points,
            outcome,
            reply_ms: play.reply_ms,
            frames: play.frames,
            seconds,
        });
    }
    Ok(SuiteRun {
        suite: suite.name.clone(),
        link: wire.link().to_string(),
        id,
        checks,
        seconds: wire.now() - started,
        error: None,
    })
}

struct Play<'a> {
    wire: &'a mut Wire,
    id: u8,
    /// A reply's deadline where a step sets none.
    timeout_ms: u64,
    frames: Vec<Exchange>,
    /// Received and not yet taken as a reply, and when its first byte came.
    pending: Vec<u8>,
    pending_since: Option<f64>,
    /// The last frame sent, up to its FCS.
    last_body: String,
    /// When the last request's last byte went out.
    sent_at: Option<Instant>,
    reply_ms: Vec<f64>,
}

/// A step's verdict: `Err(why)` when the program did not do what it required.
type Verdict = Result<(), String>;

impl Play<'_> {
    fn fill(&self, text: &str) -> String {
        let other = if self.id == 99 { 98 } else { self.id + 1 };
        text.replace("{id}", &format!("{:02}", self.id))
            .replace("{other}", &format!("{other:02}"))
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
        self.frames.push(Exchange {
            at: self.wire.now(),
            way: Way::Sent,
            text: shown(bytes),
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
        self.frames.push(Exchange {
            at,
            way: Way::Received,
            text: shown(bytes),
        });
    }

    fn step(&mut self, step: &Step) -> Result<Verdict, WireError> {
        match step {
            Step::Send {
                body,
                bad_fcs,
                ending,
            } => {
                let body = self.fill(body);
                let fcs = fcs(body.as_bytes()).wrapping_add(u8::from(*bad_fcs));
                let frame = format!("{body}{fcs:02X}{ending}");
                self.last_body = body;
                self.pending.clear();
                self.pending_since = None;
                self.send(frame.as_bytes())?;
                Ok(Ok(()))
            }
            Step::Raw(text) => {
                let text = self.fill(text);
                self.pending.clear();
                self.pending_since = None;
                self.send(text.as_bytes())?;
                Ok(Ok(()))
            }
            Step::Expect {
                pattern,
                words,
                within_ms,
            } => {
                let pattern = self.fill(pattern);
                self.expect(&pattern, *words, within_ms.unwrap_or(self.timeout_ms))
            }
            Step::Error { code, within_ms } => {
                let addr = self.last_body.get(5..7).unwrap_or("##").to_string();
                let pattern = format!("@{:02}ER{addr}01{code:04X}", self.id);
                self.expect(&pattern, 0, within_ms.unwrap_or(self.timeout_ms))
            }
            Step::Silence { ms } => {
                let until = Instant::now() + Duration::from_millis(*ms);
                while Instant::now() < until {
                    self.receive(until)?;
                }
                if self.pending.is_empty() {
                    return Ok(Ok(()));
                }
                let got = std::mem::take(&mut self.pending);
                self.note_received(&got);
                Ok(Err(format!(
                    "answered `{}` where it must stay silent for {ms} ms",
                    shown(&got)
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
        Ok(match came {
            Some(after) => format!(
                "; then `{}` came, {:.0} ms after the request",
                shown(&got),
                after.as_secs_f64() * 1e3
            ),
            None => format!("; then `{}` came", shown(&got)),
        })
    }

    /// The next frame, held to `pattern` and `words` data words.
    fn expect(&mut self, pattern: &str, words: u8, within_ms: u64) -> Result<Verdict, WireError> {
        let deadline = self.sent_at.unwrap_or_else(Instant::now) + Duration::from_millis(within_ms);
        let wanted = format!("`{pattern}`{}", data_words(words));
        loop {
            if let Some(end) = frame_end(&self.pending) {
                let frame: Vec<u8> = self.pending.drain(..end).collect();
                self.note_received(&frame);
                return Ok(judge(&frame, pattern, words)
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
                return Ok(Err(format!(
                    "`{}` came, no whole frame (`*\\n` missing) within {within_ms} ms; expected {wanted}",
                    shown(&got)
                )));
            }
        }
    }
}

fn data_words(words: u8) -> String {
    match words {
        0 => String::new(),
        1 => " and one data word".into(),
        n => format!(" and {n} data words"),
    }
}

/// Where the first frame in `bytes` ends (after its `\n`), if one is whole.
fn frame_end(bytes: &[u8]) -> Option<usize> {
    bytes.iter().position(|&b| b == b'\n').map(|i| i + 1)
}

/// Whether `frame` is a well-formed reply matching `pattern` (`#`: any
/// upper-case hex digit) and then `words` words of data.
fn judge(frame: &[u8], pattern: &str, words: u8) -> Result<(), String> {
    let text = String::from_utf8_lossy(frame);
    let Some(start) = text.find('@') else {
        return Err(format!("`{}` is no frame (no @)", shown(frame)));
    };
    if start > 0 {
        return Err(format!(
            "{start} bytes before the reply's @ (`{}`)",
            shown(&frame[..start])
        ));
    }
    let Some(head) = text.strip_suffix("*\n") else {
        return Err(format!(
            "`{}` does not end in *\\n (the MEB page: replies end *\\n)",
            shown(frame)
        ));
    };
    if head.len() < 3 {
        return Err(format!("`{}` is too short for a frame", shown(frame)));
    }
    let (body, fcs_text) = head.split_at(head.len() - 2);
    let computed = fcs(body.as_bytes());
    match u8::from_str_radix(fcs_text, 16) {
        Ok(given) if given == computed && fcs_text == fcs_text.to_uppercase() => {}
        Ok(_) if fcs_text != fcs_text.to_uppercase() => {
            return Err(format!(
                "its FCS `{fcs_text}` is lower case (replies are upper case)"
            ));
        }
        _ => {
            return Err(format!(
                "its FCS is `{fcs_text}`; its bytes give {computed:02X}"
            ));
        }
    }
    let expected_len = pattern.len() + 4 * usize::from(words);
    let hex = |c: char| c.is_ascii_digit() || ('A'..='F').contains(&c);
    let fits = body.len() == expected_len
        && body
            .chars()
            .zip(pattern.chars())
            .all(|(c, p)| if p == '#' { hex(c) } else { c == p })
        && body.chars().skip(pattern.len()).all(hex);
    if fits {
        Ok(())
    } else {
        Err(format!("the reply was `{body}`"))
    }
}

/// The MEB check: XOR of every byte from `@` to the last before the FCS.
fn fcs(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0, |x, b| x ^ b)
}

/// Bytes as a report shows them: text with `\r` and `\n` spelt out, other
/// control bytes in hex.
pub fn shown(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len() + 4);
    for &b in bytes {
        match b {
            b'\n' => out.push_str("\\n"),
            b'\r' => out.push_str("\\r"),
            0x20..=0x7e => out.push(char::from(b)),
            _ => out.push_str(&format!("\\x{b:02X}")),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replies_are_judged_by_form_fcs_and_pattern() {
        assert_eq!(judge(b"@01EA000643*\n", "@01EA0006", 0), Ok(()));
        let read = b"@01EA00020BD608004F*\n";
        assert_eq!(judge(read, "@01EA0002", 2), Ok(()));
        assert_eq!(judge(read, "@##EA0002", 2), Ok(()));
        assert!(
            judge(read, "@01EA0002", 1)
                .unwrap_err()
                .contains("the reply was")
        );
        assert!(
            judge(b"@01EA000644*\n", "@01EA0006", 0)
                .unwrap_err()
                .contains("its bytes give 43")
        );
        assert!(
            judge(b"@01EA000643*\r\n", "@01EA0006", 0)
                .unwrap_err()
                .contains("does not end")
        );
        assert!(
            judge(b"xx@01EA000643*\n", "@01EA0006", 0)
                .unwrap_err()
                .contains("2 bytes before")
        );
    }

    #[test]
    fn control_bytes_are_spelt_out() {
        assert_eq!(shown(b"@01\r\n\x01"), "@01\\r\\n\\x01");
    }
}
