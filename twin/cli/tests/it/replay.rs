//! `twin replay`, `twin compare` and `twin export` as a user runs them: the
//! real binary on real recordings, read back with the `mcap` crate's own
//! reader where a count is checked. The verdicts of recordings a run makes
//! as it is (no bytes cut or flipped) are the case
//! `tests/cmd/replay-verdicts.trycmd`.

use crate::support;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;
use support::{text, twin};

fn scratch(name: &str) -> PathBuf {
    support::scratch("replay-cli", name)
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// One 3-second ev-meb run shared by the tests (set point 1000 rpm at 0.5 s).
fn ev_meb() -> &'static Path {
    static RUN: OnceLock<PathBuf> = OnceLock::new();
    RUN.get_or_init(|| {
        let out = scratch("ev-meb.mcap");
        let o = twin(&["run", "ev-meb", "--duration", "3", "--out", s(&out)]);
        assert!(o.status.success(), "{}", text(&o));
        out
    })
}

/// Per topic, the messages' (log time, JSON), read with the `mcap` crate.
fn messages(path: &Path) -> Vec<(String, u64, serde_json::Value)> {
    let bytes = std::fs::read(path).expect("recording exists");
    mcap::MessageStream::new(&bytes)
        .expect("valid MCAP")
        .map(|m| m.expect("valid message"))
        .map(|m| {
            (
                m.channel.topic.clone(),
                m.log_time,
                twin_recording::read::value_of(&m.channel, &m.data).expect("a message that reads"),
            )
        })
        .collect()
}

#[test]
fn replay_of_an_unchanged_scenario_is_byte_identical() {
    let out = scratch("unchanged.replay.mcap");
    let o = twin(&["replay", s(ev_meb()), "--out", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    // That it says so: tests/cmd/replay-verdicts.trycmd.
    assert_eq!(
        std::fs::read(ev_meb()).unwrap(),
        std::fs::read(&out).unwrap()
    );
}

#[test]
fn a_changed_set_point_is_reported_where_the_vel_write_departs() {
    // 800 rpm instead of 1000 at 0.5 s: the supervisor's first VEL write
    // after the step (its next poll cycle, before 0.52 s) carries a smaller
    // value; nothing departs before it.
    let out = scratch("set-point.replay.mcap");
    let o = twin(&[
        "replay",
        s(ev_meb()),
        "--out",
        s(&out),
        "--set",
        "node.supervisor.set_points=[[0.0, 0.0], [0.5, 800.0], [5.0, 1500.0]]",
    ]);
    let t = text(&o);
    assert!(!o.status.success(), "a departure must fail: {t}");
    let line = t
        .lines()
        .find(|l| l.contains("DEPARTS at"))
        .unwrap_or_else(|| panic!("no departure line: {t}"));
    assert!(
        line.contains(" on /bus/rs485/frames.decoded.data.0:"),
        "{line}"
    );
    let at: f64 = line
        .split_whitespace()
        .nth(2)
        .and_then(|v| v.parse().ok())
        .expect("a time");
    assert!((0.5..0.52).contains(&at), "{line}");
    let values: Vec<f64> = ["recorded ", "replayed "]
        .iter()
        .map(|k| {
            let rest = &line[line.find(k).expect("values") + k.len()..];
            rest.trim_end_matches(|c: char| !c.is_ascii_digit())
                .split(|c: char| c == ',' || c.is_whitespace())
                .next()
                .and_then(|v| v.parse().ok())
                .expect("a number")
        })
        .collect();
    assert!(
        values[1] < values[0],
        "a smaller VEL for a smaller set point: {line}"
    );
}

// A changed plant parameter named at the first sample, an open-loop replay
// that names the VEL step, bad changes refused with what exists, compare's
// verdicts on a recording against itself, on missing signals, unreadable
// files and bad tolerances: tests/cmd/replay-verdicts.trycmd.

/// A copy of `from` with `delta` added to one field of one topic from `after_s` on.
fn perturbed(from: &Path, to: &Path, topic: &str, field: &str, after_s: f64, delta: f64) {
    let mut rec = twin_recording::record::Recorder::create(to).expect("create");
    for (t, ns, mut v) in messages(from) {
        let time_s = ns as f64 * 1e-9;
        if t == topic && time_s >= after_s {
            let x = v[field].as_f64().expect("numeric field");
            v[field] = serde_json::json!(x + delta);
        }
        if !rec.has_channel(&t) {
            rec.add_channel(&t, &v).expect("channel");
        }
        rec.write(&t, time_s, &v).expect("write");
    }
    rec.finish().expect("finish");
}

#[test]
fn compare_fails_a_perturbed_signal_and_names_only_it() {
    let bad = scratch("perturbed.mcap");
    perturbed(ev_meb(), &bad, "/plant/ev1/sensors", "wheel_rpm", 1.0, 10.0);
    let o = twin(&["compare", s(&bad), s(ev_meb())]);
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    let failing: Vec<&str> = t.lines().filter(|l| l.ends_with("FAIL")).collect();
    assert_eq!(failing.len(), 1, "{t}");
    let cols: Vec<&str> = failing[0].split_whitespace().collect();
    assert_eq!(cols[0], "/plant/ev1/sensors.wheel_rpm", "{t}");
    assert_eq!(cols[1], "1.000", "first beyond tolerance at 1 s: {t}");
    assert_eq!(cols[5], "10", "deviation: {t}");
    assert!(
        t.contains("first /plant/ev1/sensors.wheel_rpm at 1.000 s"),
        "{t}"
    );

    // Allowed 15 rpm on that signal, it passes; 5 rpm, it does not.
    for (abs, pass) in [(15.0, true), (5.0, false)] {
        let tol = scratch(&format!("tol-{abs}.toml"));
        std::fs::write(
            &tol,
            format!("[[signal]]\npattern = \"/plant/*/sensors.wheel_rpm\"\nabs = {abs}\n"),
        )
        .unwrap();
        let o = twin(&["compare", s(&bad), s(ev_meb()), "--tolerances", s(&tol)]);
        assert_eq!(o.status.success(), pass, "abs {abs}: {}", text(&o));
    }
}

#[test]
fn export_writes_one_csv_per_channel_with_every_message() {
    let dir = scratch("csv");
    let o = twin(&["export", s(ev_meb()), "--csv", s(&dir)]);
    assert!(o.status.success(), "{}", text(&o));
    let all = messages(ev_meb());
    for (topic, file) in [
        ("/plant/ev1/sensors", "plant_ev1_sensors.csv"),
        ("/plant/ev1/actuators", "plant_ev1_actuators.csv"),
        ("/bus/rs485/frames", "bus_rs485_frames.csv"),
        ("/master/supervisor/loop", "master_supervisor_loop.csv"),
    ] {
        let csv = std::fs::read_to_string(dir.join(file)).expect(file);
        let header = csv.lines().next().unwrap();
        assert!(header.starts_with("time_s,"), "{file}: {header}");
        // Frames hold MEB text with a line break inside quotes: count records.
        let rows = csv.matches("\n").count() - 1 - csv.matches("\n\"").count();
        let expected = all.iter().filter(|(t, _, _)| t == topic).count();
        assert_eq!(rows, expected, "{file}");
    }
    let sensors = std::fs::read_to_string(dir.join("plant_ev1_sensors.csv")).unwrap();
    assert_eq!(
        sensors.lines().count(),
        1 + 601,
        "200 Hz for 3 s plus t = 0"
    );
    let header: Vec<&str> = sensors.lines().next().unwrap().split(',').collect();
    for column in [
        "wheel_rpm",
        "battery_volts",
        "energy.battery_out",
        "shaft.hall",
    ] {
        assert!(header.contains(&column), "{header:?}");
    }
    let last: Vec<&str> = sensors.lines().last().unwrap().split(',').collect();
    assert_eq!(last[0], "3.000000000");
}

/// Sensor messages at 200 Hz, one chunk per simulated second: a recording cut
/// anywhere holds a whole number of seconds of them.
fn sensor_rows(dir: &Path) -> usize {
    let csv = std::fs::read_to_string(dir.join("plant_ev1_sensors.csv")).expect("sensors csv");
    csv.lines().count() - 1
}

#[test]
fn a_truncated_recording_still_compares_and_exports_up_to_its_last_chunk() {
    let full = std::fs::read(ev_meb()).unwrap();
    let cut = scratch("cut.mcap");
    std::fs::write(&cut, &full[..full.len() * 6 / 10]).unwrap();
    let o = twin(&["compare", s(&cut), s(ev_meb())]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("the run is cut short: compared up to"),
        "{}",
        text(&o)
    );
    let dir = scratch("cut-csv");
    let o = twin(&["export", s(&cut), "--csv", s(&dir)]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("ends early"), "{}", text(&o));
    let rows = sensor_rows(&dir);
    assert!(rows > 0 && rows < 601, "{rows}");
    assert!(rows.is_multiple_of(200), "whole simulated seconds: {rows}");
}

#[test]
fn a_killed_run_leaves_a_recording_that_compares_and_exports() {
    // A long run, killed a little after its first chunk is on disk (the
    // kill lands anywhere: in a chunk or between two).
    let out = scratch("killed.mcap");
    let mut child = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["run", "ev-meb", "--duration", "600", "--out", s(&out)])
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("twin starts");
    let started = std::time::Instant::now();
    // The file opens with its header alone; a simulated second of ev-meb is
    // a chunk of about 60 kB, so 8 kB on disk means one has landed.
    while std::fs::metadata(&out).map_or(0, |m| m.len()) < 8 * 1024 {
        assert!(
            started.elapsed().as_secs() < 120,
            "no chunk written in 2 min"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    std::thread::sleep(std::time::Duration::from_millis(300));
    child.kill().expect("kill");
    child.wait().expect("reaped");
    let dir = scratch("killed-csv");
    let o = twin(&["export", s(&out), "--csv", s(&dir)]);
    assert!(o.status.success(), "{}", text(&o));
    let rows = sensor_rows(&dir);
    assert!(
        rows >= 200 && rows.is_multiple_of(200),
        "whole simulated seconds: {rows}"
    );
    // The same scenario and seed: it matches the 3 s run as far as both go.
    let o = twin(&["compare", s(&out), s(ev_meb())]);
    assert!(text(&o).contains("the run is cut short"), "{}", text(&o));
    assert!(o.status.success(), "{}", text(&o));
    // As a baseline it is refused until it is made whole.
    let o = twin(&["compare", s(&out), s(&out)]);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("twin recover"), "{}", text(&o));
    let whole = scratch("killed.recovered.mcap");
    let o = twin(&["recover", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains(s(&whole)), "{}", text(&o));
    let o = twin(&["compare", s(&out), s(&whole)]);
    assert!(o.status.success(), "{}", text(&o));
    let (counts, _) = python_mcap_counts(&whole);
    assert_eq!(counts["/plant/ev1/sensors"], rows as u64, "{counts:?}");
}

/// Per topic, the message counts in the summary of `path` and the messages
/// iterated, read by the Python `mcap` package (which needs the summary a
/// killed run never wrote).
fn python_mcap_counts(path: &Path) -> (BTreeMap<String, u64>, u64) {
    let script = r#"
import json, sys
from mcap.reader import make_reader
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f)
    summary = reader.get_summary()
    counts = {c.topic: summary.statistics.channel_message_counts.get(i, 0) for i, c in summary.channels.items()}
    n = sum(1 for _ in reader.iter_messages())
print(json.dumps({"counts": counts, "iterated": n}))
"#;
    let o = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(path)
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "the Python `mcap` package must read {} (pip install mcap): {}",
        path.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let counts = serde_json::from_value(v["counts"].clone()).unwrap();
    (counts, v["iterated"].as_u64().unwrap())
}

#[test]
fn a_recording_with_no_message_fails_every_reader() {
    // The header and metadata of a run, cut before its first chunk.
    let full = std::fs::read(ev_meb()).unwrap();
    let empty = scratch("no-messages.mcap");
    std::fs::write(&empty, &full[..1500]).unwrap();
    let said = |o: &Output| {
        assert!(!o.status.success(), "{}", text(o));
        assert!(text(o).contains("holds no messages"), "{}", text(o));
    };
    said(&twin(&["replay", s(&empty)]));
    said(&twin(&["compare", s(ev_meb()), s(&empty)]));
    said(&twin(&["compare", s(&empty), s(ev_meb())]));
    let dir = scratch("no-messages-csv");
    said(&twin(&["export", s(&empty), "--csv", s(&dir)]));
    assert!(!dir.exists(), "no folder of empty CSV files");
    let rrd = scratch("no-messages.rrd");
    let o = twin(&["view", s(&empty), "--save", s(&rrd)]);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(!rrd.exists(), "no .rrd of nothing");
    let o = twin(&["recover", s(&empty)]);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("no message"), "{}", text(&o));
    // Not MCAP at all.
    let junk = scratch("junk.mcap");
    std::fs::write(&junk, b"this is no recording").unwrap();
    for args in [
        vec!["compare", s(ev_meb()), s(&junk)],
        vec!["recover", s(&junk)],
        vec!["replay", s(&junk)],
    ] {
        let o = twin(&args);
        assert!(!o.status.success(), "{args:?}: {}", text(&o));
        assert!(text(&o).contains("MCAP magic"), "{args:?}: {}", text(&o));
    }
}

#[test]
fn recover_turns_a_cut_recording_into_one_every_reader_opens() {
    let full = std::fs::read(ev_meb()).unwrap();
    let cut = scratch("cut-for-recover.mcap");
    std::fs::write(&cut, &full[..full.len() * 6 / 10]).unwrap();
    let o = twin(&["compare", s(ev_meb()), s(&cut)]);
    assert!(!o.status.success(), "a baseline cut short: {}", text(&o));
    assert!(text(&o).contains("is not whole"), "{}", text(&o));
    let whole = scratch("cut-whole.mcap");
    let o = twin(&["recover", s(&cut), "--out", s(&whole)]);
    assert!(o.status.success(), "{}", text(&o));
    // As many messages as the twin reads up to the last complete chunk.
    let dir = scratch("cut-for-recover-csv");
    assert!(
        twin(&["export", s(&cut), "--csv", s(&dir)])
            .status
            .success()
    );
    let rows = sensor_rows(&dir) as u64;
    let (counts, iterated) = python_mcap_counts(&whole);
    assert_eq!(counts["/plant/ev1/sensors"], rows, "{counts:?}");
    assert_eq!(counts.values().sum::<u64>(), iterated);
    assert!(
        text(&o).contains(&format!("{iterated} messages")),
        "{}",
        text(&o)
    );
    // The messages themselves, byte for byte and in order, as far as the cut.
    let original = messages(ev_meb());
    let recovered = messages(&whole);
    assert_eq!(recovered.len() as u64, iterated);
    assert_eq!(recovered[..], original[..recovered.len()]);
    // More: its data are the recording's own bytes up to the last whole
    // chunk (header, metadata, chunks, message indexes), then a record of
    // the copy's own saying where the run stops, then its end.
    let copied = std::fs::read(&whole).unwrap();
    let summary = mcap::Summary::read(&copied)
        .expect("a summary")
        .expect("a summary");
    let said = summary
        .metadata_indexes
        .iter()
        .find(|m| m.name == "twin.recovered")
        .expect("the copy says the run was cut");
    let own = usize::try_from(said.offset).unwrap();
    assert!(own > full.len() / 3, "{own}");
    assert!(copied[..own] == full[..own], "the data differ");
    // A replay compares what the cut run holds, as for the cut file.
    let o = twin(&[
        "replay",
        s(&whole),
        "--out",
        s(&scratch("cut-whole.replay.mcap")),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("recovered from a run cut short")
            && text(&o).contains("every message the cut-short recording holds matches"),
        "{}",
        text(&o)
    );
    // `twin export` reads the copy as it read the cut file.
    let whole_dir = scratch("cut-whole-csv");
    assert!(
        twin(&["export", s(&whole), "--csv", s(&whole_dir)])
            .status
            .success()
    );
    for file in ["plant_ev1_sensors.csv", "bus_rs485_frames.csv"] {
        assert_eq!(
            std::fs::read(dir.join(file)).unwrap(),
            std::fs::read(whole_dir.join(file)).unwrap(),
            "{file}"
        );
    }
    // Made whole, it is a baseline again; and a complete file is copied as is.
    let o = twin(&["compare", s(&cut), s(&whole)]);
    assert!(o.status.success(), "{}", text(&o));
    let copy = scratch("copy.mcap");
    let _ = std::fs::remove_file(&copy);
    let o = twin(&["recover", s(ev_meb()), "--out", s(&copy)]);
    assert!(text(&o).contains("complete already"), "{}", text(&o));
    assert!(!text(&o).contains("replaced"), "{}", text(&o));
    assert_eq!(messages(&copy), original);
    // Written as the twin writes recordings, chunk for chunk: the same bytes.
    assert!(std::fs::read(&copy).unwrap() == full, "the copy differs");
    let o = twin(&["replay", s(&copy), "--out", s(&scratch("copy.replay.mcap"))]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("byte-identical"), "{}", text(&o));
    // A second time it says what it replaced.
    let o = twin(&["recover", s(ev_meb()), "--out", s(&copy)]);
    assert!(
        text(&o).contains("(replaced the one there before: a scenario run of ev-meb"),
        "{}",
        text(&o)
    );
    let o = twin(&["recover", s(ev_meb()), "--out", s(ev_meb())]);
    assert!(!o.status.success(), "{}", text(&o));
}

/// What `twin baseline` prints, of a missing baseline, a recorded one and
/// one checked, is tests/cmd/replay-verdicts.trycmd.
#[test]
fn baseline_record_writes_the_baseline() {
    let dir = scratch("baselines");
    std::fs::create_dir_all(&dir).expect("baselines folder");
    let o = twin(&["baseline", "ev-meb", "--record", "--dir", s(&dir)]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(dir.join("ev-meb.mcap").exists());
}

/// A damaged baseline never passes as one: bytes flipped anywhere in the
/// file either fail the comparison, or fell where no message is (an index,
/// the summary) and every message reads as it was recorded.
#[test]
fn a_corrupted_baseline_fails_unless_its_data_are_intact() {
    let full = std::fs::read(ev_meb()).unwrap();
    let csv_of = |path: &Path, name: &str| -> BTreeMap<String, String> {
        let dir = scratch(name);
        let o = twin(&["export", s(path), "--csv", s(&dir)]);
        assert!(o.status.success(), "{}", text(&o));
        std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .map(|p| {
                let name = p.file_name().unwrap().to_string_lossy().into_owned();
                (name, std::fs::read_to_string(&p).unwrap())
            })
            .collect()
    };
    let original = csv_of(ev_meb(), "corrupt-original-csv");
    let (mut failed, mut intact) = (0, 0);
    for k in 1..20 {
        let at = full.len() * k / 20;
        let mut bytes = full.clone();
        for b in &mut bytes[at..at + 16] {
            *b ^= 0xa5;
        }
        let damaged = scratch(&format!("corrupt-{k}.mcap"));
        std::fs::write(&damaged, &bytes).unwrap();
        let o = twin(&["compare", s(ev_meb()), s(&damaged)]);
        if o.status.success() {
            let csv = csv_of(&damaged, &format!("corrupt-{k}-csv"));
            assert_eq!(csv, original, "a pass on damaged data (bytes {at}..)");
            intact += 1;
        } else {
            assert!(
                text(&o).contains("is not whole") || text(&o).contains("holds no messages"),
                "{}",
                text(&o)
            );
            failed += 1;
        }
    }
    assert!(
        failed > intact,
        "most flips land in the chunks: {failed} failed, {intact} intact"
    );
}

/// A 0.3 s ev-meb recording made by the twin before a frame kept its bytes
/// once, when every protobuf frame held both `text` and `hex`.
fn frames_stored_twice() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/ev-meb-frames-stored-twice.mcap")
}

#[test]
fn replay_of_a_recording_whose_frames_stored_their_bytes_twice_matches_and_says_why_bytes_differ() {
    let out = scratch("stored-twice.replay.mcap");
    let o = twin(&["replay", s(&frames_stored_twice()), "--out", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("stored each frame's bytes twice"),
        "{}",
        text(&o)
    );
    // The bytes differ, the frames as a reader sees them do not.
    let frames = |path: &Path| -> Vec<(u64, serde_json::Value)> {
        messages(path)
            .into_iter()
            .filter(|(topic, _, _)| topic.ends_with("/frames"))
            .map(|(_, t, v)| (t, v))
            .collect()
    };
    let (old, new) = (frames(&frames_stored_twice()), frames(&out));
    assert!(old.len() > 10, "{} frames", old.len());
    assert_eq!(old, new);
    assert!(
        old.iter()
            .all(|(_, f)| f["hex"].as_str().is_some_and(|h| !h.is_empty()))
    );
    assert_ne!(
        std::fs::read(frames_stored_twice()).unwrap(),
        std::fs::read(&out).unwrap()
    );
}

/// The controller-network baseline: recorded by the twin before the
/// messages were `.proto` files, when it wrote their schemas by hand.
fn schemas_written_by_hand() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../recordings/baselines/controller-network.mcap")
}

#[test]
fn replay_of_a_recording_whose_schemas_were_written_by_hand_matches_and_says_why_bytes_differ() {
    let out = scratch("schemas-by-hand.replay.mcap");
    let o = twin(&["replay", s(&schemas_written_by_hand()), "--out", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("wrote its protobuf schemas by hand, before the .proto files"),
        "{}",
        text(&o)
    );
    // Every message reads alike; the plant's samples are the same bytes
    // too, a frame's are not (its decoded fields come in another order).
    let (old, new) = (messages(&schemas_written_by_hand()), messages(&out));
    assert!(old.len() > 300, "{} messages", old.len());
    assert_eq!(old, new);
    let raw = |path: &Path, topic: &str| -> Vec<Vec<u8>> {
        let bytes = std::fs::read(path).unwrap();
        let stream = mcap::MessageStream::new(&bytes).unwrap();
        stream
            .map(|m| m.unwrap())
            .filter(|m| m.channel.topic == topic)
            .map(|m| m.data.into_owned())
            .collect()
    };
    let samples = raw(&schemas_written_by_hand(), "/plant/bench/sensors");
    assert!(samples.len() > 100);
    assert_eq!(samples, raw(&out, "/plant/bench/sensors"));
    assert_ne!(
        raw(&schemas_written_by_hand(), "/bus/serial/frames"),
        raw(&out, "/bus/serial/frames")
    );
}

#[test]
fn compare_of_runs_of_different_lengths_says_so_first_and_how_to_match_the_baseline() {
    let dir = support::folder("replay", "lengths");
    let path = |name: &str| dir.join(name).to_str().expect("a UTF-8 path").to_string();
    let (base, run, again) = (path("base.mcap"), path("run.mcap"), path("again.mcap"));
    for args in [
        vec![
            "run",
            "--duration",
            "0.6",
            "--set",
            "record_hz=20",
            "--out",
            &base,
        ],
        vec!["run", "--duration", "0.4", "--out", &run],
    ] {
        let o = twin(&args);
        assert!(o.status.success(), "{}", text(&o));
    }
    let compared = twin(&["compare", &run, &base]);
    let printed = text(&compared);
    assert_eq!(compared.status.code(), Some(1), "{printed}");
    // Before, it said "85 within tolerance, 0 beyond", then that the run
    // departs from the baseline, and only then that the lengths differ.
    let lengths = printed
        .find("the lengths differ: the run ends at 0.40")
        .unwrap_or_else(|| panic!("the lengths are not said: {printed}"));
    let counts = printed.find(" samples compared").expect("the counts");
    assert!(
        lengths < counts,
        "the lengths come after the counts: {printed}"
    );
    assert!(
        printed.contains("compared over the first 0.40"),
        "{printed}"
    );
    assert!(!printed.contains("departs"), "{printed}");
    assert!(printed.contains("differ in length"), "{printed}");
    let advice = "`twin run ev-meb --duration 0.6 --set record_hz=20.0 --out run.mcap`";
    assert!(printed.contains(advice), "{printed}");
    // The advice, followed, makes a run that passes.
    let o = twin(&[
        "run",
        "ev-meb",
        "--duration",
        "0.6",
        "--set",
        "record_hz=20.0",
        "--out",
        &again,
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let compared = twin(&["compare", &again, &base]);
    let printed = text(&compared);
    assert!(compared.status.success(), "{printed}");
    assert!(printed.contains("PASS"), "{printed}");
}
