//! A check's run recorded to MCAP, as every run of the twin is, so that a
//! disputed verdict can be looked at again with the twin's readers (`twin
//! view`, `twin export`, `twin scope`) or any MCAP tool: every frame on its
//! link's frame channel (the same `twin.Frame` as a `twin serve` session's,
//! `from` `twin` or the checked program: `slave 01`, `master`), one message
//! per check on `/check/checks` saying how many frames are its and its
//! verdict, the suite in `twin.run`, the score in `twin.check`, and the
//! whole run as its JSON report attached. A master's recording holds every
//! frame of its seconds of polling, where its report shows a few; a
//! server's, both its links (`/link/server/frames`, the twin's clients and
//! the supervisor's replies; `/link/bus/frames`, the supervisor's polls and
//! the twin's slave's replies), every frame of each; a client's, every
//! frame of its connections (`/link/client/frames`).
//!
//! Written once the run is over, from the [`SuiteRun`] the reports are made
//! from, so the recording and the reports cannot disagree; log time is the
//! run's time (seconds after the link was opened).

use crate::report;
use crate::run::{Exchange, Outcome, SuiteRun, Way};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use twin_recording::describe::link_frame_fields;
use twin_recording::typed::{FrameMessage, Hex};
use twin_recording::{Recorder, WriteError, topics};

/// One check as `/check/checks` holds it.
#[derive(Serialize)]
struct CheckMessage<'a> {
    index: usize,
    name: &'a str,
    requirement: &'a str,
    points: u32,
    result: &'static str,
    why: &'a str,
    at: f64,
    seconds: f64,
    /// How many of the link channels' frames are this check's: those
    /// written after its message and before the next check's.
    frames: usize,
}

/// Records `run` to `path`: `role` names the link (`/link/slave/frames`),
/// `suite_toml` is the suite as it was read.
pub fn record(
    path: &Path,
    role: &str,
    suite_toml: &str,
    run: &SuiteRun,
) -> Result<PathBuf, WriteError> {
    let mut recorder = Recorder::create(path)?;
    let fields = |pairs: &[(&str, String)]| -> BTreeMap<String, String> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.clone()))
            .collect()
    };
    recorder.write_metadata(
        topics::RUN_METADATA,
        fields(&[
            ("kind", "check".into()),
            ("twin_version", env!("CARGO_PKG_VERSION").into()),
            ("role", role.into()),
            ("suite", run.suite.clone()),
            ("suite_toml", suite_toml.into()),
            ("link", run.link.clone()),
            ("id", format!("{:02}", run.id)),
        ]),
    )?;
    // The checked program, as the frames' `from` names it.
    let program = match role {
        "slave" => format!("slave {:02}", run.id),
        other => other.to_string(),
    };
    let mut frames: BTreeMap<&str, _> = BTreeMap::new();
    let mut checks = None;
    for (index, check) in run.checks.iter().enumerate() {
        // Every frame of the check where the run kept them apart from its
        // evidence (a master's, a server's, a client's); a mark without
        // bytes (a client hanging up) is in the attached report only.
        let own: Vec<&Exchange> = run
            .transcript
            .get(index)
            .unwrap_or(&check.frames)
            .iter()
            .filter(|f| !f.bytes.is_empty())
            .collect();
        let (result, why) = match &check.outcome {
            Outcome::Pass => ("pass", ""),
            Outcome::Fail(why) => ("fail", why.as_str()),
            Outcome::NotJudged(what) => ("not judged", what.as_str()),
            Outcome::NotApplicable(why) => ("not applicable", why.as_str()),
        };
        let message = CheckMessage {
            index,
            name: &check.name,
            requirement: &check.requirement,
            points: check.points,
            result,
            why,
            at: check.at,
            seconds: check.seconds,
            frames: own.len(),
        };
        let channel = match checks {
            Some(c) => c,
            None => *checks.insert(recorder.add_channel(topics::CHECKS, &message)?),
        };
        recorder.write_to(channel, check.at, &message)?;
        for frame in own {
            let bytes = frame.bytes.as_slice();
            let text = printable(bytes);
            let decoded = link_frame_fields(run.protocol.link_name(), bytes);
            let (link, from) = match &frame.peer {
                Some(peer) => (peer.link, peer.from.as_str()),
                None => (
                    role,
                    match frame.way {
                        Way::Sent => "twin",
                        Way::Received => program.as_str(),
                    },
                ),
            };
            let mut message = FrameMessage {
                from,
                start_s: frame.at,
                end_s: frame.at,
                len: bytes.len(),
                // The channel is made from a frame with every field.
                text: Some(text.unwrap_or("")),
                hex: Some(Hex(bytes)),
                decoded: &decoded,
            };
            let channel = match frames.get(link) {
                Some(&c) => c,
                None => {
                    let c = recorder.add_channel(&topics::link_frames(link), &message)?;
                    *frames.entry(link).or_insert(c)
                }
            };
            // Protobuf holds the bytes once: as text when printable.
            if recorder.is_protobuf(channel) && text.is_some() {
                message.hex = None;
            }
            recorder.write_to(channel, frame.at, &message)?;
        }
    }
    let mut end = fields(&[
        ("score", run.score().to_string()),
        ("points", run.points().to_string()),
        ("checks", run.checks.len().to_string()),
        ("checks_passed", run.passed().count().to_string()),
        ("seconds", format!("{:.3}", run.seconds)),
    ]);
    if let Some(line) = report::hung_up(run) {
        end.insert("hung_up".into(), line);
    }
    if let Some(why) = &run.error {
        end.insert("error".into(), why.clone());
    }
    recorder.write_metadata(topics::CHECK_METADATA, end)?;
    recorder.attach(
        topics::CHECK_RUN_ATTACHMENT,
        "application/json",
        run.seconds,
        report::json(run).into_bytes(),
    )?;
    recorder.finish()
}

/// The bytes as text, when every one is printable (an MEB frame).
fn printable(bytes: &[u8]) -> Option<&str> {
    bytes
        .iter()
        .all(|b| b.is_ascii_graphic() || matches!(b, b'\r' | b'\n'))
        .then(|| std::str::from_utf8(bytes).ok())
        .flatten()
}

/// The text of the suite `name_or_path` names (a built-in one or a
/// teacher's file), for the recording; empty if the file cannot be read
/// again.
pub fn suite_toml(name_or_path: &str) -> String {
    match crate::suite::BUILT_IN
        .iter()
        .chain(crate::master::BUILT_IN)
        .find(|(n, _)| *n == name_or_path)
    {
        Some((_, text)) => (*text).to_string(),
        None => std::fs::read_to_string(name_or_path).unwrap_or_default(),
    }
}
