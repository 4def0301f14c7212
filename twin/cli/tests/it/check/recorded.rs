//! A check's recording: read by the Python `mcap` package (a reader we
//! did not write) it holds every frame of the report, in order, each in
//! its check, the verdicts, the suite and the score; `twin export` reads
//! it, and `twin replay` says what it is instead of failing obscurely. A
//! class records each student beside their reports.

use super::{check_slave, student};
use crate::support::{folder, text, twin};
use std::path::Path;
use std::process::Command;

/// The recording as the Python reader gives it back.
pub(super) fn read(path: &Path) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/check_recording.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(path)
        .output()
        .expect("python3 runs");
    assert!(out.status.success(), "{}", text(&out));
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Bytes spelt as the report spells them (`\n`, `\r`, `\x00`).
pub(super) fn spelt(raw: &str) -> String {
    raw.chars()
        .map(|c| match c {
            '\n' => "\\n".to_string(),
            '\r' => "\\r".to_string(),
            ' '..='~' => c.to_string(),
            _ => format!("\\x{:02X}", u32::from(c)),
        })
        .collect()
}

/// What a run's report and its recording agree on, whatever the role: the
/// checks' frame counts add up to every frame recorded, and every frame the
/// report cites (a hang-up is none) is recorded at its time, on the topic
/// and from the sender that `place` gives for its side (the report's first
/// column) and way (`true`: the twin sent it). Returns how many it cites.
pub(super) fn cited_frames_recorded(
    report: &serde_json::Value,
    recorded: &serde_json::Value,
    place: impl Fn(&str, bool) -> (&'static str, String),
) -> usize {
    let frames = recorded["frames"].as_array().unwrap();
    let counted: u64 = recorded["checks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["frames"].as_u64().unwrap())
        .sum();
    assert_eq!(counted as usize, frames.len());
    let mut cited = 0;
    for check in report["checks"].as_array().unwrap() {
        for f in check["frames"].as_array().unwrap() {
            let text = f["text"].as_str().unwrap();
            let (side, bytes) = (text[..8].trim(), &text[10..]);
            if bytes == "(hangs up)" {
                continue;
            }
            let (topic, from) = place(side, f["way"] == "sent");
            let at = f["at"].as_f64().unwrap();
            let found = frames.iter().any(|r| {
                r["topic"] == topic
                    && r["from"] == from.as_str()
                    && spelt(r["text"].as_str().unwrap()) == bytes
                    && (r["time_s"].as_f64().unwrap() - at).abs() < 1e-6
            });
            assert!(found, "`{}`: {text} at {at} not recorded", check["name"]);
            cited += 1;
        }
    }
    cited
}

#[test]
fn the_recording_holds_every_frame_of_the_report_in_its_check() {
    let dir = folder("check", "recorded");
    let (mcap, json) = (dir.join("run.mcap"), dir.join("run.json"));
    let slave = student("recorded", &["answers-broadcast"]);
    let out = check_slave(
        &slave.link,
        &[
            "--record",
            mcap.to_str().unwrap(),
            "--json",
            json.to_str().unwrap(),
        ],
    );
    let shown = text(&out);
    assert_eq!(out.status.code(), Some(1), "{shown}");
    assert!(
        shown.contains(&format!("recorded to {}\n", mcap.display())),
        "{shown}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let recorded = read(&mcap);

    assert_eq!(recorded["run"]["kind"], "check");
    assert_eq!(recorded["run"]["suite"], "MEB slave");
    assert_eq!(recorded["run"]["id"], "01");
    assert!(
        recorded["run"]["suite_toml"]
            .as_str()
            .unwrap()
            .contains("name = \"MEB slave\""),
        "{recorded}"
    );
    assert_eq!(recorded["check"]["score"], "30");
    assert_eq!(recorded["check"]["checks_passed"], "24");
    assert_eq!(
        recorded["attachments"],
        serde_json::json!(["check-run.json"])
    );

    // Every frame of the report, in order, each where its check says.
    let checks = recorded["checks"].as_array().unwrap();
    let reported = report["checks"].as_array().unwrap();
    assert_eq!(checks.len(), reported.len());
    let frames = recorded["frames"].as_array().unwrap();
    let mut next = 0;
    for (check, expected) in checks.iter().zip(reported) {
        assert_eq!(check["name"], expected["name"]);
        assert_eq!(check["result"], expected["result"]);
        let n = check["frames"].as_u64().unwrap() as usize;
        let own = &frames[next..next + n];
        next += n;
        let want = expected["frames"].as_array().unwrap();
        assert_eq!(own.len(), want.len(), "{}", check["name"]);
        for (got, want) in own.iter().zip(want) {
            assert_eq!(spelt(got["text"].as_str().unwrap()), want["text"]);
            let from = if want["way"] == "sent" {
                "twin"
            } else {
                "slave 01"
            };
            assert_eq!(got["from"], from);
            assert_eq!(got["topic"], "/link/slave/frames");
            // Decoded as every frame of the twin is: MEB where it parses
            // (garbage and spoilt frames are `unknown`, with why): the
            // first check's request and reply are whole.
            if check["index"] == 0 {
                assert_eq!(got["protocol"], "meb", "{got}");
                assert_eq!(got["cmd"], "EA", "{got}");
            }
            let at = want["at"].as_f64().unwrap();
            assert!((got["time_s"].as_f64().unwrap() - at).abs() < 1e-6, "{got}");
        }
    }
    assert_eq!(next, frames.len(), "no frame outside a check");
    assert!(frames.len() > 40, "{}", frames.len());
    let broadcast = checks
        .iter()
        .find(|c| c["result"] == "fail")
        .expect("the planted bug");
    assert_eq!(
        broadcast["name"],
        "a broadcast write (id 00) is not answered"
    );
    assert!(
        broadcast["why"]
            .as_str()
            .unwrap()
            .starts_with("answered `@01SD000157*\\n`"),
        "{broadcast}"
    );
    let times: Vec<f64> = frames
        .iter()
        .map(|f| f["time_s"].as_f64().unwrap())
        .collect();
    assert!(times.windows(2).all(|w| w[0] <= w[1]), "{times:?}");

    // The twin's own readers.
    let csv = dir.join("csv");
    let out = twin(&[
        "export",
        mcap.to_str().unwrap(),
        "--csv",
        csv.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out));
    let rows = std::fs::read_to_string(csv.join("link_slave_frames.csv")).unwrap();
    // A row starts with its time; a frame's `\n` continues its row on the
    // next line, inside quotes.
    let starts = rows
        .lines()
        .filter(|l| l.starts_with(|c: char| c.is_ascii_digit()))
        .count();
    assert_eq!(starts, frames.len(), "{rows}");
    let rrd = dir.join("run.rrd");
    let out = twin(&[
        "view",
        mcap.to_str().unwrap(),
        "--save",
        rrd.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(rrd.is_file(), "{}", text(&out));
    let out = twin(&["replay", mcap.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("is a `twin check` run: it checked a live program over its link"),
        "{}",
        text(&out)
    );
}

#[test]
fn by_default_a_run_is_recorded_in_the_folder_named_by_its_start() {
    let dir = folder("check", "record-dir");
    let slave = student("record-dir", &[]);
    let out = check_slave(&slave.link, &["--record-dir", dir.to_str().unwrap()]);
    let shown = text(&out);
    assert!(out.status.success(), "{shown}");
    let line = shown
        .lines()
        .find_map(|l| l.strip_prefix("recorded to "))
        .expect("says where");
    let name = Path::new(line).file_name().unwrap().to_str().unwrap();
    assert!(
        name.starts_with("check-slave-20") && name.ends_with(".mcap"),
        "{name}"
    );
    assert!(Path::new(line).starts_with(&dir), "{line}");
    assert_eq!(read(Path::new(line))["check"]["score"], "32");
    let out = check_slave(&slave.link, &["--no-record"]);
    assert!(!text(&out).contains("recorded to"), "{}", text(&out));
}
