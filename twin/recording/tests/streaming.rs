//! The streamed readers against small recordings written here: a replay's
//! first departure, and CSV export.

use serde_json::json;
use std::path::{Path, PathBuf};
use twin_recording::record::Recorder;
use twin_recording::{Recording, diff, export, topics};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twin-recording-streaming-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Two simulated seconds of sensors at 100 Hz and a frame every 50 ms;
/// `wheel(i)` is the wheel speed of sample `i`, `frames` how many frames.
fn write(path: &Path, wheel: impl Fn(u32) -> f64, frames: u32) {
    let mut rec = Recorder::create(path).unwrap();
    let sensors = topics::plant_sensors("ev1");
    let bus = topics::bus_frames("rs485");
    rec.add_channel(&sensors, &json!({"energy": {"out": 0.0}, "wheel_rpm": 0.0}))
        .unwrap();
    rec.add_channel(&bus, &json!({"from": "", "hex": "", "note": ""}))
        .unwrap();
    for i in 0..200 {
        let t = f64::from(i) * 0.01;
        let s = json!({"energy": {"out": t}, "wheel_rpm": wheel(i)});
        rec.write(&sensors, t, &s).unwrap();
        if i % 5 == 0 && i / 5 < frames {
            let f = json!({"from": "master", "hex": "0103", "note": "a, \"b\""});
            rec.write(&bus, t, &f).unwrap();
        }
    }
    rec.finish().unwrap();
}

#[test]
fn identical_recordings_do_not_depart() {
    let (a, b) = (scratch("same-a.mcap"), scratch("same-b.mcap"));
    write(&a, f64::from, 40);
    write(&b, f64::from, 40);
    assert!(diff::same_bytes(&a, &b).unwrap());
    let (ra, rb) = (Recording::read(&a).unwrap(), Recording::read(&b).unwrap());
    assert_eq!(diff::first_departure(&ra, &rb).unwrap(), None);
}

#[test]
fn the_first_departure_names_the_field_and_the_time() {
    let (a, b) = (scratch("dep-a.mcap"), scratch("dep-b.mcap"));
    write(&a, f64::from, 40);
    write(&b, |i| if i >= 150 { -1.0 } else { f64::from(i) }, 40);
    assert!(!diff::same_bytes(&a, &b).unwrap());
    let (ra, rb) = (Recording::read(&a).unwrap(), Recording::read(&b).unwrap());
    let d = diff::first_departure(&ra, &rb).unwrap().expect("departs");
    assert_eq!(d.signal, "/plant/ev1/sensors.wheel_rpm");
    assert!((d.time_s - 1.5).abs() < 1e-9, "{d:?}");
    assert_eq!(
        (d.recorded.as_str(), d.replayed.as_str()),
        ("150.0", "-1.0")
    );
    assert!(d.other_fields.is_empty());
    assert_eq!(d.channels_departing, 1);
}

#[test]
fn a_missing_message_departs_where_it_is_missing() {
    let (a, b) = (scratch("miss-a.mcap"), scratch("miss-b.mcap"));
    write(&a, f64::from, 40);
    write(&b, f64::from, 30);
    let (ra, rb) = (Recording::read(&a).unwrap(), Recording::read(&b).unwrap());
    let d = diff::first_departure(&ra, &rb).unwrap().expect("departs");
    assert_eq!(d.signal, "/bus/rs485/frames");
    assert!((d.time_s - 1.5).abs() < 1e-9, "{d:?}");
    assert_eq!(
        (d.recorded.as_str(), d.replayed.as_str()),
        ("message 31", "absent")
    );
    // And the other way round: the replay has one the recording lacks.
    let d = diff::first_departure(&rb, &ra).unwrap().expect("departs");
    assert_eq!(
        (d.recorded.as_str(), d.replayed.as_str()),
        ("absent", "message 31")
    );
}

#[test]
fn export_writes_a_sheet_per_channel() {
    let path = scratch("export.mcap");
    write(&path, f64::from, 3);
    let dir = scratch("csv");
    let (recording, written) = export::to_csv(&path, &dir).unwrap();
    assert_eq!(recording.truncated, None);
    let shape: Vec<(&str, usize, usize)> = written
        .iter()
        .map(|w| (w.topic.as_str(), w.rows, w.columns))
        .collect();
    assert_eq!(
        shape,
        [("/plant/ev1/sensors", 200, 3), ("/bus/rs485/frames", 3, 4)]
    );
    let sensors = std::fs::read_to_string(dir.join("plant_ev1_sensors.csv")).unwrap();
    let mut lines = sensors.lines();
    assert_eq!(lines.next(), Some("time_s,energy.out,wheel_rpm"));
    assert_eq!(lines.nth(1), Some("0.010000000,0.01,1.0"));
    let frames = std::fs::read_to_string(dir.join("bus_rs485_frames.csv")).unwrap();
    assert_eq!(
        frames.lines().nth(1),
        Some("0.000000000,master,0103,\"a, \"\"b\"\"\"")
    );
}
