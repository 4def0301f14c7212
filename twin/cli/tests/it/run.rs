//! `twin run` as a user runs it: the real binary, a real MCAP file read back.
//! What it prints (summaries, refusals) is checked whole by the cases
//! `tests/cmd/run-*.trycmd` and `words-*.trycmd`.

use crate::support;
use std::path::{Path, PathBuf};
use std::process::Command;
use support::twin;

fn scratch(name: &str) -> PathBuf {
    support::scratch("run-cli", name)
}

fn read_messages(path: &Path, topic: &str) -> Vec<(u64, serde_json::Value)> {
    let bytes = std::fs::read(path).expect("recording exists");
    mcap::MessageStream::new(&bytes)
        .expect("valid MCAP")
        .map(|m| m.expect("valid message"))
        .filter(|m| m.channel.topic == topic)
        .map(|m| {
            (
                m.log_time,
                twin_recording::read::value_of(&m.channel, &m.data).expect("a message that reads"),
            )
        })
        .collect()
}

/// Its printed summary is `tests/cmd/run-open-loop.trycmd`.
#[test]
fn open_loop_run_records_the_step() {
    let out = scratch("default.mcap");
    let o = twin(&["run", "--open-loop", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let sensors = read_messages(&out, "/plant/sensors");
    assert_eq!(sensors.len(), 3001, "1 kHz for 3 s plus the initial state");
    let (t_last, last) = sensors.last().unwrap();
    assert_eq!(*t_last, 3_000_000_000, "simulated time is the log time");
    // Still before the VEL step at 0.5 s, moving well after it.
    let before = &sensors[400].1;
    assert_eq!(before["wheel_rpm"].as_f64().unwrap(), 0.0);
    assert!(last["wheel_rpm"].as_f64().unwrap() > 1000.0, "{last}");
    let actuators = read_messages(&out, "/plant/actuators");
    assert_eq!(actuators.len(), 2, "the initial state and the VEL step");
    assert_eq!(actuators[1].0, 500_000_000);
    assert_eq!(actuators[1].1["vel_volts"].as_f64().unwrap(), 3.0);
}

#[test]
fn the_same_seed_gives_the_same_bytes() {
    let a = scratch("a.mcap");
    let b = scratch("b.mcap");
    for p in [&a, &b] {
        let o = twin(&[
            "run",
            "--open-loop",
            "--duration",
            "1",
            "--seed",
            "9",
            "--out",
            p.to_str().unwrap(),
        ]);
        assert!(o.status.success());
    }
    // Compared with `==`: a failing assert_eq! would print a megabyte of bytes.
    let same = std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap();
    assert!(same, "{} and {} differ", a.display(), b.display());
    let c = scratch("c.mcap");
    twin(&[
        "run",
        "--open-loop",
        "--duration",
        "1",
        "--seed",
        "10",
        "--out",
        c.to_str().unwrap(),
    ]);
    let differ = std::fs::read(&a).unwrap() != std::fs::read(&c).unwrap();
    assert!(differ, "sensor noise follows the seed");
}

#[test]
fn the_recording_opens_in_the_python_mcap_reader() {
    let out = scratch("py.mcap");
    assert!(
        twin(&[
            "run",
            "--open-loop",
            "--duration",
            "0.5",
            "--out",
            out.to_str().unwrap()
        ])
        .status
        .success()
    );
    // The plant's samples decode by field name with PyPI's protobuf support
    // for MCAP (what Foxglove's and Lichtblick's readers do in their way).
    let script = r#"
import json, sys
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from google.protobuf.json_format import MessageToDict
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f, decoder_factories=[DecoderFactory()])
    summary = reader.get_summary()
    counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
    schemas = sorted({s.encoding for s in summary.schemas.values()})
    meta = {m.name: m.metadata for m in reader.iter_metadata()}
    last = None
    for _, _, _, sample in reader.iter_decoded_messages(topics=["/plant/sensors"]):
        last = MessageToDict(sample, preserving_proto_field_name=True)
print(json.dumps({"counts": counts, "schemas": schemas, "preset": meta["twin.run"]["preset"], "last": last}))
"#;
    let o = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(&out)
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "the Python `mcap` package must read it (pip install mcap): {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["counts"]["/plant/sensors"], 501);
    assert_eq!(v["schemas"], serde_json::json!(["jsonschema", "protobuf"]));
    assert_eq!(v["preset"], "vemodule");
    // Every field by its name, as the twin's own reader reads it.
    let ours = read_messages(&out, "/plant/sensors")
        .pop()
        .expect("a sample")
        .1;
    let theirs = &v["last"];
    for (name, value) in ours.as_object().expect("fields") {
        match value {
            serde_json::Value::Null => {}
            serde_json::Value::Object(inner) => {
                for key in inner.keys() {
                    assert!(!theirs[name][key].is_null(), "{name}.{key} in {theirs}");
                }
            }
            _ => assert!(!theirs[name].is_null(), "{name} in {theirs}"),
        }
    }
    assert_eq!(
        theirs["battery_volts"].as_f64(),
        ours["battery_volts"].as_f64()
    );
    assert_eq!(theirs["battery_counts"], ours["battery_counts"]);
}

#[test]
fn the_geared_bench_runs_near_100_wheel_rpm() {
    let out = scratch("cn.mcap");
    let o = twin(&[
        "run",
        "--open-loop",
        "--preset",
        "controller-network",
        "--vel",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success());
    let last = read_messages(&out, "/plant/sensors").pop().unwrap().1;
    let rpm = last["wheel_rpm"].as_f64().unwrap();
    assert!((90.0..125.0).contains(&rpm), "{rpm}");
}

#[test]
fn the_default_scenario_closes_the_loop_over_meb_and_records_the_bus() {
    let out = scratch("ev-meb.mcap");
    let o = twin(&["run", "--duration", "2", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let frames = read_messages(&out, "/bus/rs485/frames");
    assert!(
        frames.len() > 300,
        "{} frames in 2 s at 100 Hz",
        frames.len()
    );
    let first = &frames[0].1;
    assert_eq!(first["from"], "supervisor");
    assert_eq!(first["decoded"]["protocol"], "meb");
    assert!(
        first["text"].as_str().unwrap().starts_with("@01SD"),
        "{first}"
    );
    // The slave's acknowledgement starts 1 ms (turnaround) after the request's last stop bit.
    let reply = &frames[1].1;
    assert_eq!(reply["from"], "ev1");
    let gap = reply["start_s"].as_f64().unwrap() - first["end_s"].as_f64().unwrap();
    assert!((gap - 1e-3).abs() < 1e-9, "turnaround {gap}");
    let loops = read_messages(&out, "/master/supervisor/loop");
    assert!(!loops.is_empty());
    let sensors = read_messages(&out, "/plant/ev1/sensors");
    let last = &sensors.last().unwrap().1;
    assert!(
        last["wheel_rpm"].as_f64().unwrap() > 950.0,
        "the loop drives the wheel to its 1000 rpm set point: {last}"
    );
}

/// Ctrl-C (and SIGTERM) stop a long run where it has got to, with its
/// recording finished: a summary every MCAP reader takes, and exit 130.
#[test]
fn an_interrupted_run_finishes_its_recording() {
    for (signal, said) in [("INT", "Ctrl-C"), ("TERM", "SIGTERM")] {
        let out = scratch(&format!("interrupted-{signal}.mcap"));
        let child = Command::new(env!("CARGO_BIN_EXE_twin"))
            .args(["run", "ev-meb", "--duration", "3000"])
            .arg("--out")
            .arg(&out)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .expect("twin starts");
        let started = std::time::Instant::now();
        // A chunk on disk: the run is under way.
        while std::fs::metadata(&out).map_or(0, |m| m.len()) < 8 * 1024 {
            assert!(started.elapsed().as_secs() < 120, "no chunk in 2 min");
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let killed = Command::new("kill")
            .arg(format!("-{signal}"))
            .arg(child.id().to_string())
            .status()
            .expect("kill runs");
        assert!(killed.success());
        let o = child.wait_with_output().expect("twin ends");
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(130), "{stderr}");
        assert!(stderr.contains(said), "{stderr}");
        assert!(
            stderr.contains("s of simulated time: the recording") && stderr.contains("complete"),
            "{stderr}"
        );
        // The summary is there: the `mcap` crate's indexed reader needs it.
        let bytes = std::fs::read(&out).unwrap();
        let summary = mcap::Summary::read(&bytes)
            .expect("a readable summary")
            .expect("a summary");
        let stats = summary.stats.expect("statistics");
        assert!(stats.message_count > 0);
        let mut streamed = 0u64;
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            m.expect("every message whole");
            streamed += 1;
        }
        assert_eq!(streamed, stats.message_count);
    }
}

/// A run stops before its recording fills the disk, the file closed whole:
/// here the free space to keep is set above what any disk has.
#[test]
fn a_run_stops_with_its_recording_closed_before_the_disk_is_full() {
    let out = scratch("disk-guard.mcap");
    let o = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["run", "ev-meb", "--duration", "600"])
        .arg("--out")
        .arg(&out)
        .env("TWIN_MIN_FREE_DISK_MB", "1000000000000")
        .output()
        .expect("twin runs");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(
        stderr.contains("MB free, under the 1000000000000 MB a recording leaves free")
            && stderr.contains("TWIN_MIN_FREE_DISK_MB"),
        "{stderr}"
    );
    let bytes = std::fs::read(&out).unwrap();
    let summary = mcap::Summary::read(&bytes)
        .expect("a readable summary")
        .expect("a summary");
    assert!(summary.stats.expect("statistics").message_count > 0);
    // Far from the 600 s asked for.
    assert!(bytes.len() < 1024 * 1024, "{} bytes", bytes.len());
}

/// The numbers of the summary's `speed (rpm): wheel W, motor (hall) RPM_M H,
/// light sensor RPM_L L` line.
fn summary_speeds(text: &str) -> (f64, f64, f64) {
    let line = text
        .lines()
        .find(|l| l.trim_start().starts_with("speed (rpm):"))
        .unwrap_or_else(|| panic!("no speed line in the summary: {text}"));
    let after = |label: &str| -> f64 {
        let rest = &line[line
            .find(label)
            .unwrap_or_else(|| panic!("{label} in {line}"))
            + label.len()..];
        rest.trim_start()
            .split(|c: char| c == ',' || c.is_whitespace())
            .next()
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("a number after {label} in {line}"))
    };
    (after("wheel"), after("RPM_M"), after("RPM_L"))
}

#[test]
fn the_default_run_shows_the_light_sensor_following_the_wheel_beside_the_hall_rpm() {
    let out = scratch("ev-meb-speeds.mcap");
    let o = twin(&["run", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let (wheel, hall, light) = summary_speeds(&text);
    assert!(wheel > 1000.0, "the loop drives the wheel: {text}");
    assert!(
        (hall - wheel).abs() < 0.01 * wheel,
        "hall rpm {hall}: {text}"
    );
    assert!(
        light > 0.0 && (light - wheel).abs() < 0.03 * wheel,
        "light rpm {light} against the wheel's {wheel}: {text}"
    );
    // Where the light sensor stops seeing the flag, from the physics: the
    // summary's line, in tests/cmd/run-ev-meb.trycmd.

    // The controller's readings, by name, beside every plant sample.
    let sensors = read_messages(&out, "/plant/ev1/sensors");
    let readings = read_messages(&out, "/controller/ev1/readings");
    assert_eq!(readings.len(), sensors.len());
    let mut tracked = 0;
    for ((t, plant), (t_r, r)) in sensors.iter().zip(&readings) {
        assert_eq!(t, t_r);
        let s = *t as f64 * 1e-9;
        // Settled at 1000 rpm and at 1500 rpm: one light reading per turn,
        // on the firmware's 1 ms ticks.
        if (2.5..5.0).contains(&s) || s >= 7.0 {
            let wheel = plant["wheel_rpm"].as_f64().unwrap();
            let light = r["light_rpm"].as_f64().unwrap();
            let hall = r["hall_rpm"].as_f64().unwrap();
            assert!(
                (light - wheel).abs() < 0.04 * wheel,
                "{s} s: light {light}, wheel {wheel}"
            );
            assert!(
                (hall - wheel).abs() < 0.02 * wheel,
                "{s} s: hall {hall}, wheel {wheel}"
            );
            assert_eq!(r["meb"]["RPM_L"], r["light_rpm"]);
            let v1 = r["battery_volts"].as_f64().unwrap();
            let true_v1 = plant["battery_volts"].as_f64().unwrap();
            assert!(
                (v1 - true_v1).abs() < 0.1,
                "{s} s: V1 {v1} against {true_v1}"
            );
            tracked += 1;
        }
    }
    assert!(tracked > 1000, "{tracked} samples checked");

    // Its protobuf schema names every field and describes it (the
    // descriptor's comments), for Foxglove and protoc-made tools.
    let bytes = std::fs::read(&out).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
    let channel = summary
        .channels
        .values()
        .find(|c| c.topic == "/controller/ev1/readings")
        .expect("the readings channel");
    let schema = channel.schema.as_ref().expect("a schema");
    assert_eq!(schema.encoding, "protobuf");
    assert_eq!(schema.name, "twin.ControllerReadings");
    let text = String::from_utf8_lossy(&schema.data);
    for said in [
        "light_rpm",
        "RPM_L, wheel speed from the photoresistor (rpm)",
        "STATUS",
        "FD0, bit 0 battery cut-off",
    ] {
        assert!(text.contains(said), "{said} not in {text}");
    }

    // `twin export` gives it a CSV of its own, with the named columns.
    let dir = scratch("ev-meb-speeds-csv");
    let o = twin(&[
        "export",
        out.to_str().unwrap(),
        "--csv",
        dir.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let csv = std::fs::read_to_string(dir.join("controller_ev1_readings.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    for column in [
        "time_s",
        "battery_volts",
        "hall_rpm",
        "light_rpm",
        "meb.V1",
        "meb.RPM_L",
    ] {
        assert!(header.contains(&column), "{column} in {header:?}");
    }
    assert_eq!(csv.lines().count(), readings.len() + 1);
}

#[test]
fn a_wheel_faster_than_the_light_sensors_limit_is_said_so() {
    // The fixed threshold loses the flag above 260 rpm; the wheel runs at
    // 1000 rpm from 0.5 s.
    let out = scratch("fixed-detector.mcap");
    let o = twin(&[
        "run",
        "--duration",
        "1.5",
        "--set",
        "node.ev1.light_detector=fixed",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let (wheel, _, light) = summary_speeds(&text);
    assert!(wheel > 300.0 && light == 0.0, "{text}");
    // That it says so, once: tests/cmd/run-ev-meb.trycmd.
}

#[test]
fn set_changes_a_field_of_the_scenario_before_it_runs() {
    let out = scratch("set.mcap");
    let o = twin(&[
        "run",
        "--duration",
        "3",
        "--set",
        "node.supervisor.set_points=[[0.0, 0.0], [0.5, 800.0]]",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let (wheel, hall, _) = summary_speeds(&text);
    // The scenario's own set points are 1000 and 1500 rpm; the edited one is 800.
    assert!(
        (wheel - 800.0).abs() < 0.03 * 800.0,
        "wheel {wheel}: {text}"
    );
    assert!((hall - 800.0).abs() < 0.03 * 800.0, "RPM_M {hall}: {text}");
    // A `--set` without a value, or on an item that does not exist, is
    // refused in words: tests/cmd/run-refusals.trycmd.
}

#[test]
fn set_changes_an_open_loop_setting() {
    let out = scratch("set-open-loop.mcap");
    let o = twin(&[
        "run",
        "--open-loop",
        "--set",
        "vel_fraction=0",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let wheel: f64 = text
        .lines()
        .find_map(|l| l.trim().strip_prefix("wheel speed"))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no wheel speed: {text}"));
    assert!(
        wheel.abs() < 1.0,
        "VEL 0 leaves the wheel still: {wheel} rpm"
    );
    // Checked as --vel is, a fraction of the 5 V range: tests/cmd/run-refusals.trycmd.
}

/// A node, bus or module name has a length and characters that fit where it
/// goes (topics, monitor lines, file names): a name of 100 000 characters is
/// refused with its line and its start, not accepted and printed in full;
/// so is a name with a space, and a wrong value of any field is clipped.
#[test]
fn names_have_a_sensible_length_and_character_set() {
    let dir = support::folder("run-cli", "names");
    let scenario = ev_meb_toml();
    let long = "x".repeat(100_000);
    let cases = [
        (
            "long",
            scenario.replace("name = \"supervisor\"", &format!("name = \"{long}\"")),
            "`name` \"xxxxxxxxxxxxxxxxxxxx…\" is 100000 characters long",
        ),
        (
            "space",
            scenario.replace("name = \"rs485\"", "name = \"rs 485\""),
            "`name` \"rs 485\" holds a space",
        ),
        (
            "kind",
            scenario.replace("kind = \"supervisor\"", &format!("kind = \"{long}\"")),
            "unknown variant `xxxxxxxxxxxxxxxxxxxx… (100000 characters)`",
        ),
    ];
    for (name, text, expected) in cases {
        let file = dir.join(format!("{name}.toml"));
        std::fs::write(&file, text).unwrap();
        let out = twin(&["run", file.to_str().unwrap(), "--duration", "0.1"]);
        let said = support::text(&out);
        assert!(!out.status.success(), "{name}: refused");
        assert!(said.contains(expected), "{name}: {said}");
        assert!(
            said.len() < 600,
            "{name}: a short message, {} bytes",
            said.len()
        );
        assert!(
            said.contains(&format!("{name}.toml:")),
            "{name}: the line: {said}"
        );
    }
}

/// A master polling an id no node on its bus has can only time out: the
/// summary says so, naming the ids that are there.
#[test]
fn a_master_polling_an_id_no_node_has_is_named_in_the_summary() {
    let dir = support::folder("run-cli", "unanswered");
    let scenario = ev_meb_toml();
    let file = dir.join("two.toml");
    std::fs::write(&file, scenario.replace("slaves = [1]", "slaves = [1, 2]")).unwrap();
    let recording = dir.join("two.mcap");
    let out = twin(&[
        "run",
        file.to_str().unwrap(),
        "--duration",
        "0.5",
        "--out",
        recording.to_str().unwrap(),
    ]);
    let said = support::text(&out);
    assert!(out.status.success(), "{said}");
    assert!(
        said.contains(
            "no node on bus rs485 has id 2 (ids there: 1): `supervisor` polls it and can only time out"
        ),
        "{said}"
    );
    let recording = dir.join("ev-meb.mcap");
    let out = twin(&[
        "run",
        "ev-meb",
        "--duration",
        "0.5",
        "--out",
        recording.to_str().unwrap(),
    ]);
    assert!(
        !support::text(&out).contains("no node on bus"),
        "none in the default run"
    );
}

/// What a user gives in a scenario's place by mistake gets words that say
/// what it is and what to do: a recording, or a parameter file that is not
/// there (its reason said once).
#[test]
fn a_recording_or_a_missing_file_in_place_of_a_scenario_is_named() {
    let recording =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/examples/cut-short.mcap");
    let out = twin(&["run", recording.to_str().unwrap()]);
    let said = support::text(&out);
    assert!(!out.status.success());
    assert!(said.contains("is a recording, not a scenario"), "{said}");
    assert!(said.contains("twin replay"), "{said}");
    assert!(!said.contains("UTF-8"), "{said}");
    let out = twin(&["run", "--open-loop", "--params", "no-such-params.toml"]);
    let said = support::text(&out);
    assert!(!out.status.success());
    assert_eq!(said.matches("(os error 2)").count(), 1, "{said}");
}

/// The default scenario's file, for tests that run an edited copy of it.
fn ev_meb_toml() -> String {
    std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recordings/scenarios/ev-meb.toml"),
    )
    .expect("the default scenario's file")
}
