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
    let export::Exported {
        recording,
        written,
        skipped,
    } = export::to_csv(&path, &dir).unwrap();
    assert_eq!(recording.truncated, None);
    assert_eq!(skipped, []);
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

/// A protobuf frame holds its bytes once (`text` for MEB, `hex` for
/// Modbus); the reader gives back both fields, as the JSON recordings and
/// the protobuf ones that kept both hold them, and `frames()` the bytes.
#[test]
fn frames_kept_once_read_back_with_text_and_hex() {
    let path = scratch("frames-once.mcap");
    let mut rec = Recorder::create(&path).unwrap();
    let bus = topics::bus_frames("rs485");
    let id = rec
        .add_channel(
            &bus,
            &json!({"from": "", "start_s": 0.0, "end_s": 0.0, "len": 0, "text": "", "hex": ""}),
        )
        .unwrap();
    assert!(rec.is_protobuf(id), "frames are protobuf");
    let meb = b"@01SD0002000E000120*\n";
    let rtu = [1u8, 3, 0, 0, 0, 3, 0x05, 0xcb];
    let frame = |text: Option<&str>, hex: Option<&str>, len: usize| {
        let mut f = json!({"from": "supervisor", "start_s": 0.5, "end_s": 0.501, "len": len});
        if let Some(text) = text {
            f["text"] = json!(text);
        }
        if let Some(hex) = hex {
            f["hex"] = json!(hex);
        }
        f
    };
    let meb_text = std::str::from_utf8(meb).unwrap();
    let meb_hex: String = meb.iter().map(|b| format!("{b:02x}")).collect();
    // Kept once, as the twin writes them now; then both, as before.
    rec.write(&bus, 0.5, &frame(Some(meb_text), None, meb.len()))
        .unwrap();
    rec.write(&bus, 0.6, &frame(None, Some("01030000000305cb"), rtu.len()))
        .unwrap();
    rec.write(&bus, 0.7, &frame(Some(meb_text), Some(&meb_hex), meb.len()))
        .unwrap();
    rec.write(
        &bus,
        0.8,
        &frame(Some(""), Some("01030000000305cb"), rtu.len()),
    )
    .unwrap();
    rec.finish().unwrap();
    let recording = Recording::read(&path).unwrap();
    let frames = recording.frames().unwrap();
    let bytes: Vec<&[u8]> = frames.iter().map(|f| f.bytes.as_slice()).collect();
    assert_eq!(bytes, [&meb[..], &rtu, meb, &rtu]);
    let mut values = Vec::new();
    Recording::scan(&path, |m| {
        values.push(m.value()?);
        Ok(())
    })
    .unwrap();
    for v in &values[..2] {
        assert!(v["text"].is_string() && v["hex"].is_string(), "{v}");
    }
    assert_eq!(values[0]["text"], values[2]["text"]);
    assert_eq!(values[0]["hex"], values[2]["hex"]);
    assert_eq!(values[1]["text"], "");
    assert_eq!(values[1]["hex"], values[3]["hex"]);
    // Typed, as `twin view` reads a frame.
    let typed: Vec<topics::FrameSample> = values
        .iter()
        .map(|v| serde_json::from_value(v.clone()).unwrap())
        .collect();
    assert_eq!(typed[0].hex, meb_hex);
}
