//! A recording cut by SIGKILL, read by a reader we did not write: Python's
//! `mcap` package (`make_reader`, on the file and on a stream), against what
//! `twin recover` finds in it and copies; a recording closed as usual, which
//! keeps its summary; and a file another writer made (Python's), cut and
//! recovered with all it holds.

use crate::peers::script;
use crate::support::{Proc, scratch, text, twin};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn s(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 path")
}

/// What `tests/peers/mcap_read.py` found in `path`.
fn python_reads(path: &Path) -> serde_json::Value {
    let o = Command::new("python3")
        .arg(script("mcap_read.py"))
        .arg(path)
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "the Python `mcap` package must be installed (pip install mcap): {}",
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).expect("one JSON object")
}

/// The messages both Python readers iterated, the same count from each and
/// no error from either.
fn python_messages(path: &Path) -> (u64, serde_json::Value) {
    let v = python_reads(path);
    for reader in ["seeking", "streaming"] {
        assert_eq!(v[reader]["error"], serde_json::Value::Null, "{reader}: {v}");
    }
    let n = v["seeking"]["messages"].as_u64().expect("a count");
    assert_eq!(v["streaming"]["messages"].as_u64(), Some(n), "{v}");
    (n, v)
}

/// The messages `twin recover` copies out of `path`: as many as it says,
/// and as many as Python reads in the copy, which has its summary.
fn recovered(path: &Path) -> u64 {
    let out = path.with_extension("recovered.mcap");
    let o = twin(&["recover", s(path), "--out", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    let said = text(&o);
    assert!(
        said.contains("the data stops there: the file ends without its summary"),
        "{said}"
    );
    let n = message_count(&said);
    let (in_python, v) = python_messages(&out);
    assert_eq!(in_python, n, "{v}");
    assert_eq!(v["summary"], true, "{v}");
    assert_eq!(v["summary_messages"].as_u64(), Some(n), "{v}");
    n
}

/// The messages `twin recover` copies out of the complete file `path`.
fn messages_of_complete(path: &Path) -> u64 {
    let out = path.with_extension("copy.mcap");
    let o = twin(&["recover", s(path), "--out", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("complete already"), "{}", text(&o));
    message_count(&text(&o))
}

/// The `N messages` `twin recover` printed.
fn message_count(said: &str) -> u64 {
    let words: Vec<&str> = said.split_whitespace().collect();
    let count = words
        .windows(2)
        .find(|w| w[1] == "messages")
        .and_then(|w| w[0].parse().ok());
    count.unwrap_or_else(|| panic!("no message count in {said}"))
}

/// Waits (30 s at most) until `path` holds `bytes`.
fn wait_for_size(path: &Path, bytes: u64) {
    let started = Instant::now();
    while std::fs::metadata(path).map_or(0, |m| m.len()) < bytes {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "{} never reached {bytes} bytes",
            path.display()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_served_session_killed_reads_in_python_as_far_as_it_got() {
    let path = scratch("cut-recording", "killed-serve.mcap");
    let _ = std::fs::remove_file(&path);
    let mut serve = Proc::start(&["serve", "--modbus", "tcp://127.0.0.1:0", "--out", s(&path)]);
    // A session closes a chunk about every second: a few of them.
    wait_for_size(&path, 24 * 1024);
    serve.child.kill().expect("SIGKILL");
    serve.child.wait().expect("reaped");

    let (n, v) = python_messages(&path);
    assert!(n > 0, "{v}");
    assert_eq!(v["summary"], false, "a cut file has no summary: {v}");
    assert_eq!(v["metadata"], serde_json::json!(["twin.run"]), "{v}");
    assert_eq!(recovered(&path), n, "{v}");
    // The twin still sees that the session never finished.
    let o = twin(&["compare", s(&path), s(&path)]);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("twin recover"), "{}", text(&o));
}

#[test]
fn a_virtual_run_killed_while_it_writes_reads_in_python_as_far_as_it_got() {
    // A run on the virtual clock writes a chunk every few milliseconds, so
    // a kill lands anywhere: in the compression, in a write, between two.
    for (i, after) in [0u64, 120, 350].into_iter().enumerate() {
        let path = scratch("cut-recording", &format!("killed-run-{i}.mcap"));
        let _ = std::fs::remove_file(&path);
        let mut child = Command::new(env!("CARGO_BIN_EXE_twin"))
            .args(["run", "ev-meb", "--duration", "600", "--out", s(&path)])
            .stdout(Stdio::null())
            .spawn()
            .expect("twin starts");
        // The header and metadata are about 2 kB; a simulated second's
        // chunk about 60 kB.
        wait_for_size(&path, 8 * 1024);
        std::thread::sleep(Duration::from_millis(after));
        child.kill().expect("SIGKILL");
        child.wait().expect("reaped");

        let (n, v) = python_messages(&path);
        assert!(n > 0, "kill {i}: {v}");
        assert_eq!(v["summary"], false, "kill {i}: {v}");
        assert_eq!(recovered(&path), n, "kill {i}: {v}");
    }
}

#[test]
fn a_recording_closed_as_usual_keeps_its_summary() {
    let run = scratch("cut-recording", "whole-run.mcap");
    let o = twin(&["run", "ev-meb", "--duration", "3", "--out", s(&run)]);
    assert!(o.status.success(), "{}", text(&o));
    let served = scratch("cut-recording", "whole-serve.mcap");
    let _ = std::fs::remove_file(&served);
    let serve = Proc::start(&[
        "serve",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--out",
        s(&served),
    ]);
    wait_for_size(&served, 24 * 1024);
    serve.terminate();
    for path in [&run, &served] {
        let (n, v) = python_messages(path);
        assert_eq!(v["summary"], true, "{v}");
        assert_eq!(v["summary_messages"].as_u64(), Some(n), "{v}");
        assert!(n > 0, "{v}");
        // The summary's statistics count what the twin reads, and the twin
        // reads the file as complete.
        assert_eq!(messages_of_complete(path), n, "{v}");
    }
}

/// What `tests/peers/mcap_dump.py` (the Python `mcap` package) reads in
/// `path`: header, schemas, channels, messages, metadata, attachments and
/// the summary's statistics.
fn python_dump(path: &Path) -> serde_json::Value {
    let o = Command::new("python3")
        .arg(script("mcap_dump.py"))
        .arg(path)
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "the Python `mcap` package must read {} (pip install mcap): {}",
        path.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).expect("one JSON object")
}

#[test]
fn a_file_another_writer_made_is_recovered_with_all_it_holds() {
    // Written by the Python `mcap` package's writer: its own ids, profile,
    // channel metadata, sequence numbers and publish times.
    let original = scratch("cut-recording", "python-written.mcap");
    let o = Command::new("python3")
        .arg(script("mcap_write.py"))
        .arg(&original)
        .output()
        .expect("python3 runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let whole = python_dump(&original);
    let all = whole["messages"].as_array().expect("messages");
    assert_eq!(all.len(), 3000, "{}", whole["statistics"]);

    // Cut in a chunk, past the attachment and the first metadata record.
    let bytes = std::fs::read(&original).expect("the file");
    let cut = scratch("cut-recording", "python-written-cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 8 / 10]).expect("cut");
    let out = scratch("cut-recording", "python-written.recovered.mcap");
    let o = twin(&["recover", s(&cut), "--out", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    let copy = python_dump(&out);
    let got = copy["messages"].as_array().expect("messages");
    let n = got.len();
    assert!(n > 1200 && n < all.len(), "{n} messages recovered");
    assert_eq!(message_count(&text(&o)), n as u64);
    // Every message as it was (channel id, sequence, log and publish time,
    // data), in order, up to the cut; and what the file declared, with its
    // ids and metadata.
    assert_eq!(got[..], all[..n]);
    for field in ["header", "schemas", "channels"] {
        assert_eq!(copy[field], whole[field], "{field}");
    }
    assert_eq!(copy["attachments"], whole["attachments"]);
    // The file's metadata up to the cut, then the copy's own record saying
    // where the run stops.
    let mut metadata = copy["metadata"].as_array().expect("metadata").clone();
    let said = metadata.pop().expect("the copy's own record");
    assert_eq!(said[0], "twin.recovered", "{said}");
    assert!(!metadata.is_empty());
    assert_eq!(
        metadata[..],
        whole["metadata"].as_array().unwrap()[..metadata.len()]
    );
    // The summary the copy gained counts what it holds.
    assert_eq!(copy["statistics"]["messages"], n);
    assert_eq!(copy["statistics"]["channels"], 3);
    assert_eq!(copy["statistics"]["attachments"], 1);

    // The complete file is copied whole, and the twin reads the copy.
    let out = scratch("cut-recording", "python-written.copy.mcap");
    let o = twin(&["recover", s(&original), "--out", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("complete already"), "{}", text(&o));
    assert_eq!(python_dump(&out), whole);
    let csv = scratch("cut-recording", "python-written-csv");
    let o = twin(&["export", s(&out), "--csv", s(&csv)]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("/point"), "{}", text(&o));
}

/// A file holding another tool's binary channel beside a JSON one: `twin
/// export` writes the JSON channel's CSV and says it left the other out;
/// a file of binary channels alone is refused in words, nothing written.
/// (The whole export was refused for the one channel it could not read.)
#[test]
fn export_leaves_out_a_channel_it_does_not_read_and_writes_the_rest() {
    let mixed = scratch("cut-recording", "with-binary.mcap");
    let binary = scratch("cut-recording", "binary-only.mcap");
    let o = Command::new("python3")
        .arg("-c")
        .arg(
            "import json, sys\n\
             from mcap.writer import Writer\n\
             for path, with_json in ((sys.argv[1], True), (sys.argv[2], False)):\n\
             \x20   with open(path, 'wb') as f:\n\
             \x20       w = Writer(f)\n\
             \x20       w.start()\n\
             \x20       camera = w.register_channel('/camera', 'application/octet-stream', 0)\n\
             \x20       point = with_json and w.register_channel('/point', 'json', 0)\n\
             \x20       for i in range(10):\n\
             \x20           t = i * 1_000_000\n\
             \x20           w.add_message(camera, log_time=t, data=bytes([i]) * 64, publish_time=t)\n\
             \x20           if with_json:\n\
             \x20               w.add_message(point, log_time=t, data=json.dumps({'x': i}).encode(), publish_time=t)\n\
             \x20       w.finish()\n",
        )
        .arg(&mixed)
        .arg(&binary)
        .output()
        .expect("python3 runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let csv = scratch("cut-recording", "with-binary-csv");
    let o = twin(&["export", s(&mixed), "--csv", s(&csv)]);
    let said = text(&o);
    assert!(o.status.success(), "{said}");
    assert!(
        said.contains("/camera")
            && said.contains("left out: the messages on /camera are `application/octet-stream`"),
        "{said}"
    );
    let point = std::fs::read_to_string(csv.join("point.csv")).expect("point.csv");
    assert_eq!(point.lines().count(), 1 + 10, "{point}");
    assert_eq!(point.lines().nth(3), Some("0.002000000,2"));
    assert!(!csv.join("camera.csv").exists());

    let csv = scratch("cut-recording", "binary-only-csv");
    let o = twin(&["export", s(&binary), "--csv", s(&csv)]);
    let said = text(&o);
    assert!(!o.status.success(), "{said}");
    assert!(
        said.contains(
            "the messages on /camera are `application/octet-stream`, which the twin does not read"
        ) && said.contains("no CSV file was written"),
        "{said}"
    );
    assert!(!csv.exists());
}
