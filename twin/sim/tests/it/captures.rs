//! The Controller_network project's five oscilloscope captures, as the
//! embedded scenarios that reproduce them: each recording holds exactly
//! the frames the write-up's captions describe, read back with the
//! recording reader, and the scripted `[[request]]`s that make them are
//! refused with file, line and field when they cannot be sent.

use std::path::PathBuf;

use twin_recording::read::{BusFrame, Event, Recording};
use twin_sim::scenario::{EMBEDDED, Scenario};
use twin_sim::virtual_run::run;

fn out(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twin-sim-captures-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(format!("{name}.mcap"))
}

/// The frames and events of the embedded scenario `name`'s run.
fn recorded(name: &str) -> (Vec<BusFrame>, Vec<Event>) {
    let scenario = Scenario::load(name).unwrap_or_else(|e| panic!("{name}: {e}"));
    let path = out(name);
    run(&scenario, &path, |_| {}).unwrap_or_else(|e| panic!("{name}: {e:#}"));
    let recording = Recording::read(&path).expect("readable");
    let frames = recording.frames().expect("frames");
    let events = recording.events().expect("events");
    let _ = std::fs::remove_file(&path);
    (frames, events)
}

fn bytes(hex: &str) -> Vec<u8> {
    protocols::hex::bytes(hex).expect("hex")
}

/// Who sent what, in order.
fn sent(frames: &[BusFrame]) -> Vec<(String, Vec<u8>)> {
    frames
        .iter()
        .map(|f| (f.from.clone(), f.bytes.clone()))
        .collect()
}

/// The request and the reply of a capture: the reply starts as on the
/// project's scope, 0.72 to 0.81 ms after the request does.
fn request_and_reply(name: &str, request: &str, reply: &str) -> Vec<Event> {
    let (frames, events) = recorded(name);
    assert_eq!(
        sent(&frames),
        [
            ("rpi".to_string(), bytes(request)),
            ("motor".to_string(), bytes(reply))
        ],
        "{name}"
    );
    let after_ms = (frames[1].time_s - frames[0].time_s) * 1e3;
    assert!(
        (0.72..=0.81).contains(&after_ms),
        "{name}: the reply starts {after_ms} ms after the request"
    );
    events
}

fn has(events: &[Event], node: &str, kind: &str, detail: &str) -> bool {
    events
        .iter()
        .any(|e| e.node == node && e.kind == kind && e.detail.contains(detail))
}

#[test]
fn the_pi_s_request_with_a_wrong_crc_is_ignored() {
    let (frames, events) = recorded("controller-network-bad-crc-master");
    // CRC 0xaad9 plus one, and not a byte from either Nano.
    assert_eq!(
        sent(&frames),
        [("rpi".to_string(), bytes("01 06 0001 0080 aada"))]
    );
    assert!(
        (frames[0].time_s - 0.05).abs() < 1e-9,
        "{}",
        frames[0].time_s
    );
    // The `modbus` program reads once, finds nothing, and stops.
    assert!(
        has(&events, "rpi", "timeout", "no reply from 01"),
        "{events:?}"
    );
}

#[test]
fn the_motor_s_reply_with_a_wrong_crc_is_refused_by_the_pi() {
    let events = request_and_reply(
        "controller-network-bad-crc-slave",
        "01 06 0001 0080 aad9",
        "01 06 0001 0080 aada",
    );
    // As the write-up's terminal shows it.
    assert!(
        has(
            &events,
            "rpi",
            "log",
            "CRC Error, will not use message. Received: 0xaada Calculated: 0xaad9"
        ),
        "{events:?}"
    );
}

#[test]
fn the_exception_replies_carry_codes_2_3_and_1() {
    // The frames of the project's captures (nodes/tests/vectors/modbus8.jsonl).
    for (name, request, reply, printed) in [
        (
            "controller-network-illegal-address",
            "01 06 0002 0078 2828",
            "01 86 0002 0002 15a8",
            "Illegal Data Address",
        ),
        (
            "controller-network-illegal-value",
            "01 06 0001 0078 28d8",
            "01 86 0001 0003 d599",
            "Illegal Data Value",
        ),
        (
            "controller-network-illegal-function",
            "01 04 0001 0000 caa1",
            "01 84 0001 0001 d461",
            "Illegal Function",
        ),
    ] {
        let events = request_and_reply(name, request, reply);
        assert!(has(&events, "rpi", "log", printed), "{name}: {events:?}");
        assert!(has(&events, "rpi", "exception", ""), "{name}: {events:?}");
    }
}

#[test]
fn the_captures_are_embedded_and_short() {
    let captures: Vec<_> = EMBEDDED
        .iter()
        .filter(|(name, _, _)| name.starts_with("controller-network-"))
        .collect();
    assert_eq!(captures.len(), 5);
    for (name, _, _) in captures {
        let s = Scenario::load(name).expect("parses");
        assert!(s.duration_s <= 1.0, "{name}");
        assert_eq!(s.requests.len(), 1, "{name}");
    }
}

/// A capture scenario's text with `from` replaced by `to`.
fn capture_with(from: &str, to: &str) -> String {
    let (_, _, text) = EMBEDDED
        .iter()
        .find(|(name, _, _)| *name == "controller-network-illegal-value")
        .expect("embedded");
    assert!(text.contains(from), "{from}");
    text.replacen(from, to, 1)
}

fn line_of(text: &str, needle: &str) -> usize {
    text.lines().position(|l| l.contains(needle)).expect(needle) + 1
}

#[test]
fn a_request_that_cannot_be_sent_names_its_file_line_and_field() {
    let text = capture_with("send = \"01 06 0001 0078\"", "send = \"01 06 0001\"");
    let e = Scenario::parse(&text, "c.toml").unwrap_err().to_string();
    let line = line_of(&text, "send = \"01 06 0001\"");
    assert_eq!(
        e,
        format!(
            "c.toml:{line}: `send` of the request from `rpi`: `01 06 0001` is 4 bytes: an \
             8-byte Modbus frame is six bytes (id, function, address, value) before its CRC, \
             which the master adds"
        )
    );
    let text = capture_with("send = \"01 06 0001 0078\"", "send = \"01 06 0001 00x8\"");
    let e = Scenario::parse(&text, "c.toml").unwrap_err().to_string();
    assert!(e.contains("`x8` in `00x8` is not a hex byte"), "{e}");

    let text = capture_with("at_s = 0.05", "at_s = 5.0");
    let e = Scenario::parse(&text, "c.toml").unwrap_err().to_string();
    let line = line_of(&text, "at_s = 5.0");
    assert!(e.starts_with(&format!("c.toml:{line}: `at_s` ")), "{e}");
    assert!(e.contains("duration_s (0.2)"), "{e}");

    let text = capture_with("node = \"rpi\"\nat_s", "node = \"motor\"\nat_s");
    let e = Scenario::parse(&text, "c.toml").unwrap_err().to_string();
    let line = line_of(&text, "node = \"motor\"");
    assert!(e.starts_with(&format!("c.toml:{line}: `node` ")), "{e}");
    assert!(e.contains("not a controller-network-master"), "{e}");
}

#[test]
fn a_master_told_to_send_only_requests_needs_some() {
    let text = capture_with("[[request]]", "[[nothing]]");
    let text = text.replace(
        "[[nothing]]\nnode = \"rpi\"\nat_s = 0.05\nsend = \"01 06 0001 0078\"\n",
        "",
    );
    let e = Scenario::parse(&text, "c.toml").unwrap_err().to_string();
    let line = line_of(&text, "program = \"requests\"");
    assert!(e.starts_with(&format!("c.toml:{line}: `program` ")), "{e}");
    assert!(e.contains("no [[request]] names it"), "{e}");
}

#[test]
fn scripted_requests_go_between_the_loop_s_polls() {
    // The bench's own loop, with one scripted request 2 s in.
    let (_, _, text) = EMBEDDED
        .iter()
        .find(|(name, _, _)| *name == "controller-network")
        .expect("embedded");
    let text = format!(
        "{}\n[[request]]\nnode = \"rpi\"\nat_s = 2.0\nsend = \"01 04 0001 0000\"\n",
        text.replace("duration_s = 30.0", "duration_s = 4.0")
    );
    let scenario = Scenario::parse(&text, "loop.toml").expect("parses");
    let path = out("loop");
    run(&scenario, &path, |_| {}).expect("runs");
    let recording = Recording::read(&path).expect("readable");
    let frames = recording.frames().expect("frames");
    let _ = std::fs::remove_file(&path);
    let scripted = frames
        .iter()
        .position(|f| f.bytes.get(1) == Some(&0x04))
        .expect("the scripted request went out");
    assert!(
        frames[scripted].time_s >= 2.0,
        "{}",
        frames[scripted].time_s
    );
    assert_eq!(frames[scripted + 1].bytes, bytes("01 84 0001 0001 d461"));
    // The loop polls before and after it.
    let polls = |range: &[BusFrame]| range.iter().filter(|f| f.from == "rpi").count();
    assert!(polls(&frames[..scripted]) > 2, "{frames:?}");
    assert!(polls(&frames[scripted + 2..]) > 2, "{frames:?}");
}
