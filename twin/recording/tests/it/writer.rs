//! The recorder's two writers (on the caller's thread, on one of its own)
//! and its deferred messages give the same bytes, and a write that fails is
//! reported, not lost.

use serde::Serialize;
use serde_json::json;
use std::path::{Path, PathBuf};
use twin_recording::Recording;
use twin_recording::record::{Recorder, WriteError};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twin-recording-writer-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// A plant-sample-like message, big enough that batches fill.
#[derive(Debug, Clone, Copy, Serialize)]
struct Sample {
    time_s: f64,
    wheel_rpm: f64,
    counts: u16,
    on: bool,
}

/// Encoded by the writer through serde (it has no protobuf of its own).
impl twin_recording::record::Deferred for Sample {}

fn sample(i: u32) -> Sample {
    let t = f64::from(i) * 0.001;
    Sample {
        time_s: t,
        wheel_rpm: (t * 7.0).sin() * 1234.567,
        counts: (i % 4096) as u16,
        on: i.is_multiple_of(3),
    }
}

/// Five simulated seconds: a sample each millisecond (as JSON or deferred),
/// a frame every 10 ms (through serde and written by hand, in turn),
/// metadata, a flush at 2.5 s: several batches of either writer and a chunk
/// per simulated second.
fn write(path: &Path, threaded: bool, deferred: bool) {
    let mut rec: Recorder<Sample> = if threaded {
        Recorder::create_threaded(path).unwrap()
    } else {
        Recorder::create_inline(path).unwrap()
    };
    rec.write_metadata(
        "twin.run",
        [("kind".to_string(), "test".to_string())].into(),
    )
    .unwrap();
    let sensors = rec.add_channel("/plant/ev1/sensors", &sample(0)).unwrap();
    let mut frames = None;
    for i in 0..5000u32 {
        let t = f64::from(i) * 0.001;
        if i.is_multiple_of(10) {
            let frame = json!({"from": "master", "hex": format!("{i:04x}")});
            let channel = match frames {
                Some(c) => c,
                None => *frames.insert(rec.add_channel("/bus/rs485/frames", &frame).unwrap()),
            };
            if i.is_multiple_of(20) {
                // Written by hand, as the twin writes its frames; each
                // second's first message is one of them, so a chunk closes
                // before one.
                let frame = twin_recording::protobuf::twin::Frame {
                    from: Some("master".into()),
                    hex: Some(format!("{i:08x}")),
                    ..Default::default()
                };
                let typed = rec
                    .write_protobuf(channel, t, "twin.Frame", |out| {
                        twin_recording::protobuf::append(&frame, out);
                    })
                    .unwrap();
                assert!(typed, "the frames' channel is twin.Frame");
            } else {
                rec.write_to(channel, t, &frame).unwrap();
            }
        }
        if deferred {
            rec.write_deferred(sensors, t, sample(i)).unwrap();
        } else {
            rec.write_to(sensors, t, &sample(i)).unwrap();
        }
        if i == 2500 {
            rec.flush().unwrap();
        }
    }
    rec.finish().unwrap();
}

#[test]
fn both_writers_and_deferred_messages_give_the_same_bytes() {
    let reference = scratch("inline-json.mcap");
    write(&reference, false, false);
    let expected = std::fs::read(&reference).unwrap();
    for (name, threaded, deferred) in [
        ("inline-deferred.mcap", false, true),
        ("threaded-json.mcap", true, false),
        ("threaded-deferred.mcap", true, true),
    ] {
        let path = scratch(name);
        write(&path, threaded, deferred);
        assert!(
            std::fs::read(&path).unwrap() == expected,
            "{name} differs from the inline JSON recording"
        );
    }
    let r = Recording::read(&reference).unwrap();
    assert_eq!(r.truncated, None);
    let counts: Vec<(&str, u64)> = r
        .channels
        .iter()
        .map(|c| (c.topic.as_str(), c.message_count))
        .collect();
    assert_eq!(
        counts,
        [("/plant/ev1/sensors", 5000), ("/bus/rs485/frames", 500)]
    );
    // A chunk per simulated second, and one more closed by the flush.
    assert_eq!(r.chunks, 6, "{r:?}");
}

#[test]
fn a_recorder_dropped_unfinished_leaves_a_complete_file() {
    for threaded in [false, true] {
        let path = scratch(&format!("dropped-{threaded}.mcap"));
        {
            let mut rec: Recorder<Sample> = if threaded {
                Recorder::create_threaded(&path).unwrap()
            } else {
                Recorder::create_inline(&path).unwrap()
            };
            let c = rec.add_channel("/plant/ev1/sensors", &sample(0)).unwrap();
            for i in 0..3000 {
                rec.write_deferred(c, f64::from(i) * 0.001, sample(i))
                    .unwrap();
            }
        }
        let r = Recording::read(&path).unwrap();
        assert_eq!(r.truncated, None, "threaded {threaded}");
        assert_eq!(r.message_count(), 3000, "threaded {threaded}");
    }
}

#[test]
fn a_write_that_fails_is_reported_by_either_writer() {
    // Linux's /dev/full accepts the open and refuses every write (ENOSPC).
    let full = Path::new("/dev/full");
    if !full.exists() {
        return;
    }
    for threaded in [false, true] {
        let attempt = || -> Result<(), WriteError> {
            let mut rec: Recorder<Sample> = if threaded {
                Recorder::create_threaded(full)?
            } else {
                Recorder::create_inline(full)?
            };
            let c = rec.add_channel("/plant/ev1/sensors", &sample(0))?;
            for i in 0..200_000 {
                rec.write_deferred(c, f64::from(i) * 0.001, sample(i))?;
            }
            rec.finish()?;
            Ok(())
        };
        let error = attempt().expect_err("a full device cannot hold the file");
        // Refused by the disk, not taken for a bad message.
        assert!(
            matches!(
                error,
                WriteError::Write { .. } | WriteError::Start { .. } | WriteError::Finish { .. }
            ),
            "threaded {threaded}: {error:?}"
        );
        let text = error.to_string();
        assert!(text.contains("/dev/full"), "threaded {threaded}: {text}");
    }
}
