//! `twin view` and `twin run --view` as a user runs them: the real binary,
//! a real MCAP recording, and the `.rrd` files read back by rerun's own CLI
//! (`rerun rrd print`, from PyPI `rerun-sdk==0.36.3`).

use crate::support;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use support::twin;

fn scratch(name: &str) -> PathBuf {
    support::scratch("view-cli", name)
}

pub(crate) fn ok(o: &Output) -> String {
    assert!(
        o.status.success(),
        "failed: {}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Messages per topic, and the EV controller's `EA` replies (they carry
/// RPM_M and RPM_L), read with the mcap crate.
fn mcap_counts(path: &Path) -> (BTreeMap<String, u64>, u64) {
    let bytes = std::fs::read(path).expect("recording exists");
    let mut counts = BTreeMap::new();
    let mut ea_replies = 0;
    for m in mcap::MessageStream::new(&bytes).expect("valid MCAP") {
        let m = m.expect("valid message");
        *counts.entry(m.channel.topic.clone()).or_default() += 1;
        if m.channel.topic == "/bus/rs485/frames" {
            let v: serde_json::Value = twin_recording::read::value_of(&m.channel, &m.data).unwrap();
            let d = &v["decoded"];
            if v["from"] == "ev1" && d["cmd"] == "EA" && d["data"].as_array().unwrap().len() == 6 {
                ea_replies += 1;
            }
        }
    }
    (counts, ea_replies)
}

/// Rows per entity of the recording (not the blueprint) in an `.rrd`, as
/// `rerun rrd print` lists its chunks.
pub(crate) fn rrd_rows(path: &Path) -> BTreeMap<String, u64> {
    let o = Command::new("rerun")
        .args(["rrd", "print"])
        .arg(path)
        .output()
        .expect("the rerun CLI runs: pip install rerun-sdk==0.36.3");
    let text = ok(&o);
    let mut rows = BTreeMap::new();
    // Chunk(chunk_…) with 2001 rows (40.1 KiB) - /ev1/speed/wheel_rpm - data columns: [Scalars:scalars]
    for line in text.lines().filter(|l| l.starts_with("Chunk(")) {
        let Some((_, rest)) = line.split_once(" with ") else {
            continue;
        };
        let n: u64 = rest.split(' ').next().unwrap().parse().unwrap();
        let parts: Vec<&str> = line.split(" - ").collect();
        let (entity, columns) = (parts[1], parts[2]);
        if columns.contains("Scalars:scalars") || columns.contains("TextLog:text") {
            *rows.entry(entity.to_string()).or_default() += n;
        }
    }
    rows
}

#[test]
fn the_rerun_recording_of_the_default_run_holds_every_channel_sample() {
    let mcap = scratch("ev-meb.mcap");
    let live = scratch("live.rrd");
    let rrd = scratch("ev-meb.rrd");
    ok(&twin(&[
        "run",
        "--duration",
        "3",
        "--out",
        mcap.to_str().unwrap(),
        "--view",
        live.to_str().unwrap(),
    ]));
    let out = ok(&twin(&[
        "view",
        mcap.to_str().unwrap(),
        "--save",
        rrd.to_str().unwrap(),
    ]));
    assert!(out.contains("rerun recording:"), "{out}");
    assert!(out.contains("pip install rerun-sdk==0.36.3"), "{out}");

    let (messages, ea_replies) = mcap_counts(&mcap);
    let sensors = messages["/plant/ev1/sensors"];
    let readings = messages["/controller/ev1/readings"];
    let loops = messages["/master/supervisor/loop"];
    let frames = messages["/bus/rs485/frames"];
    assert_eq!(sensors, 601, "3 s at 200 Hz, both ends");
    assert_eq!(
        readings, sensors,
        "the controller's readings beside each sample"
    );
    assert!(loops > 250 && ea_replies > 250, "{loops} {ea_replies}");

    let rows = rrd_rows(&rrd);
    let mut expected = BTreeMap::new();
    for entity in [
        "speed/wheel_rpm",
        "voltage/V1",
        "voltage/V2",
        "current/I",
        "soc/SOC",
        "photoresistor/divider",
        "flag/in_beam",
        "flag/detector_dark",
    ] {
        expected.insert(format!("/ev1/{entity}"), sensors);
    }
    expected.insert("/ev1/speed/set_point".into(), loops);
    // The speed plot's hall and light rpm: the controller's readings.
    expected.insert("/ev1/speed/hall_rpm".into(), readings);
    expected.insert("/ev1/speed/light_rpm".into(), readings);
    expected.insert("/bus/rs485/frames".into(), frames);
    // The adaptive detector has no fixed threshold to draw. Run on the
    // recorded 200 Hz samples it finds some of the flag's short dips (a
    // sample lands in a 5 ms dip at 1000 rpm now and then): one marker each.
    let dips = rows.get("/ev1/photoresistor/dips").copied().unwrap_or(0);
    assert!(dips > 0, "{rows:?}");
    expected.insert("/ev1/photoresistor/dips".into(), dips);
    assert_eq!(rows, expected, "entities and samples of `twin view`");

    // The live stream of the same run holds the same samples.
    assert_eq!(
        rrd_rows(&live),
        expected,
        "entities and samples of `--view`"
    );

    let verify = Command::new("rerun")
        .args(["rrd", "verify"])
        .arg(&rrd)
        .output()
        .expect("rerun runs");
    ok(&verify);
}

#[test]
fn a_truncated_recording_is_shown_up_to_its_last_complete_chunk() {
    let mcap = scratch("long.mcap");
    ok(&twin(&["run", "--out", mcap.to_str().unwrap()]));
    let bytes = std::fs::read(&mcap).unwrap();
    // The run killed mid-way: the file ends inside its last chunk.
    let cut = scratch("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let rrd = scratch("cut.rrd");
    let out = ok(&twin(&[
        "view",
        cut.to_str().unwrap(),
        "--save",
        rrd.to_str().unwrap(),
    ]));
    assert!(out.contains("the recording ends early"), "{out}");
    let rows = rrd_rows(&rrd);
    let wheel = rows["/ev1/speed/wheel_rpm"];
    assert!(wheel > 100 && wheel < 2001, "{wheel} samples of 2001");
}

// A file that is not a recording refused with its name, one not there said
// to be missing: tests/cmd/view-refusals.trycmd.

#[test]
fn run_view_without_a_viewer_says_so_and_still_records() {
    let mcap = scratch("no-viewer.mcap");
    let o = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["run", "--duration", "1", "--view", "--out"])
        .arg(&mcap)
        .env("PATH", "/nonexistent")
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .expect("twin runs");
    let out = ok(&o);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("no rerun viewer"), "{err}");
    assert!(err.contains("pip install rerun-sdk==0.36.3"), "{err}");
    assert!(out.contains("recording:"), "{out}");
    let (messages, _) = mcap_counts(&mcap);
    assert_eq!(messages["/plant/ev1/sensors"], 201);
}

#[test]
fn below_the_light_sensors_limit_every_flag_pass_is_a_detected_dip() {
    // The geared bench at full VEL: the wheel turns at about 113 rpm, well
    // under the fixed threshold's 248 rpm.
    let mcap = scratch("geared.mcap");
    ok(&twin(&[
        "run",
        "--open-loop",
        "--preset",
        "controller-network",
        "--vel",
        "1",
        "--duration",
        "5",
        "--out",
        mcap.to_str().unwrap(),
    ]));
    let rrd = scratch("geared.rrd");
    ok(&twin(&[
        "view",
        mcap.to_str().unwrap(),
        "--save",
        rrd.to_str().unwrap(),
    ]));
    // The flag's entries into the beam, from the plant's own flag bit.
    let bytes = std::fs::read(&mcap).unwrap();
    let mut passes = 0;
    let mut in_beam = false;
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == "/plant/sensors" {
            let v: serde_json::Value = twin_recording::read::value_of(&m.channel, &m.data).unwrap();
            let now = v["flag_in_beam"].as_bool().unwrap();
            passes += u64::from(now && !in_beam);
            in_beam = now;
        }
    }
    let rows = rrd_rows(&rrd);
    let dips = rows["/bench/photoresistor/dips"];
    // The cell lags the flag: a pass in the run's last moments may end it
    // before the divider falls below the threshold.
    assert!(
        passes >= 5 && (passes - 1..=passes).contains(&dips),
        "{dips} dips for {passes} flag passes"
    );
    assert_eq!(rows["/bench/speed/wheel_rpm"], 5001);
}

#[test]
fn a_modbus_rtu_controller_gives_the_same_speed_plot_as_meb() {
    // The default scenario with both ends speaking Modbus RTU: the rpm
    // words come from the FC04 replies, paired with the read they answer.
    let text = twin_sim::scenario::EMBEDDED
        .iter()
        .find(|(name, _, _)| *name == "ev-meb")
        .map(|(_, _, toml)| *toml)
        .unwrap()
        .replace("protocol = \"meb\"", "protocol = \"modbus-rtu\"");
    assert_eq!(text.matches("modbus-rtu").count(), 2, "both ends switched");
    let scenario = scratch("rtu.toml");
    std::fs::write(&scenario, text).unwrap();
    let mcap = scratch("rtu.mcap");
    ok(&twin(&[
        "run",
        scenario.to_str().unwrap(),
        "--duration",
        "2",
        "--out",
        mcap.to_str().unwrap(),
    ]));
    let rrd = scratch("rtu.rrd");
    ok(&twin(&[
        "view",
        mcap.to_str().unwrap(),
        "--save",
        rrd.to_str().unwrap(),
    ]));
    let bytes = std::fs::read(&mcap).unwrap();
    let mut fc04_replies = 0;
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == "/bus/rs485/frames" {
            let v: serde_json::Value = twin_recording::read::value_of(&m.channel, &m.data).unwrap();
            if v["from"] == "ev1" && v["decoded"]["function"] == 4 {
                fc04_replies += 1;
            }
        }
    }
    let rows = rrd_rows(&rrd);
    assert!(fc04_replies > 150, "{fc04_replies}");
    // The controller's readings give the speed plot its words, over Modbus
    // RTU as over MEB (`logger.rs` checks the replies of a recording
    // without them).
    assert_eq!(rows["/ev1/speed/hall_rpm"], rows["/ev1/speed/wheel_rpm"]);
    assert_eq!(rows["/ev1/speed/light_rpm"], rows["/ev1/speed/wheel_rpm"]);
}
