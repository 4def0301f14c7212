//! `twin scope` as a user runs it, its files read back by sigrok (Debian's
//! `sigrok-cli`, the decoders PulseView runs): the bytes the `uart` decoder
//! finds on the exported line are the recording's frames, in order, each
//! within one bit of its recorded time; Modbus RTU decodes with `modbus` on
//! top; a collision and noise show where the engine put them; a frame that
//! opens the window decodes; a real-time session's recording decodes as
//! the bytes went, reconstructed at the link's baud.

use crate::support;
use std::path::{Path, PathBuf};
use std::process::Command;
use support::{text, twin};
use twin_recording::read::{BusFrame, Recording};
use twin_recording::topics::{LINE_COLLISION, LINE_NOISE, LineSample, Topic};

fn scratch(name: &str) -> PathBuf {
    support::scratch("scope", name)
}

pub(crate) fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// Runs `scenario` for `seconds` into a recording; its frames.
pub(crate) fn run(scenario: &str, seconds: &str, name: &str) -> (PathBuf, Vec<BusFrame>) {
    let out = scratch(name);
    let o = twin(&["run", scenario, "--duration", seconds, "--out", s(&out)]);
    assert!(o.status.success(), "{}", text(&o));
    let frames = Recording::read(&out).unwrap().frames().unwrap();
    (out, frames)
}

/// Where the recording says the line differed from what was sent.
fn line_marks(path: &Path) -> Vec<LineSample> {
    let mut marks = Vec::new();
    Recording::scan(path, |m| {
        if let Topic::BusLine(_) = Topic::parse(m.topic) {
            marks.push(m.json()?);
        }
        Ok(())
    })
    .unwrap();
    marks
}

/// Whether `m` marks frame `f` (its sender and first start bit; the
/// frame's time as read back is within a nanosecond of the mark's).
fn same_frame(m: &LineSample, f: &BusFrame) -> bool {
    m.from == f.from && (m.frame_start_s - f.time_s).abs() < 1e-9
}

/// `frames`' bytes as `marks` say the line carried them: each character a
/// collision garbled as garbled, then the bits noise flipped at any listener.
fn as_received(frames: &[BusFrame], marks: &[LineSample]) -> Vec<BusFrame> {
    let mut frames = frames.to_vec();
    for f in &mut frames {
        let ours: Vec<&LineSample> = marks.iter().filter(|m| same_frame(m, f)).collect();
        for m in ours.iter().filter(|m| m.kind == LINE_COLLISION) {
            f.bytes[m.index] = m.byte;
        }
        for m in ours.iter().filter(|m| m.kind == LINE_NOISE) {
            f.bytes[m.index] ^= m.mask;
        }
    }
    frames
}

/// A window from the idle line before frame `first` to the idle line after
/// frame `last` (s), and the frames inside it.
fn window(frames: &[BusFrame], first: usize, last: usize) -> (f64, f64, Vec<BusFrame>) {
    let from = (frames[first - 1].end_s + frames[first].time_s) / 2.0;
    let to = (frames[last].end_s + frames[last + 1].time_s) / 2.0;
    let inside = frames[first..=last].to_vec();
    (from, to, inside)
}

/// One decoded annotation: its first and last sample and its text.
#[derive(Debug)]
struct Annotation {
    start: u64,
    text: String,
}

/// `sigrok-cli -i FILE` with `decoders`, the annotations `show` asks for.
fn decode(file: &Path, input: &str, decoders: &str, show: &str) -> Vec<Annotation> {
    let o = Command::new("sigrok-cli")
        .args(["-i", s(file), "-I", input, "-P", decoders, "-A", show])
        .arg("--protocol-decoder-samplenum")
        .output()
        .expect("sigrok-cli runs (.ci/install installs it)");
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    out.lines()
        .filter_map(|line| {
            let (samples, rest) = line.split_once(' ')?;
            let (start, _) = samples.split_once('-')?;
            let (_, text) = rest.split_once(": ")?;
            Some(Annotation {
                start: start.parse().ok()?,
                text: text.to_string(),
            })
        })
        .collect()
}

/// Every byte the uart decoder found with its start bit's time (s).
fn bytes_at(annotations: &[Annotation], t0: f64, sample_s: f64, bit_s: f64) -> Vec<(u8, f64)> {
    annotations
        .iter()
        .filter_map(|a| {
            let byte = u8::from_str_radix(&a.text, 16).ok()?;
            // The data annotation starts after the start bit.
            Some((byte, t0 + a.start as f64 * sample_s - bit_s))
        })
        .collect()
}

/// The recorded bytes with their start bits' times.
fn recorded(frames: &[BusFrame], char_s: f64) -> Vec<(u8, f64)> {
    frames
        .iter()
        .flat_map(|f| {
            f.bytes
                .iter()
                .enumerate()
                .map(move |(i, &b)| (b, f.time_s + i as f64 * char_s))
        })
        .collect()
}

fn same_within_a_bit(what: &str, got: &[(u8, f64)], want: &[(u8, f64)], bit_s: f64) {
    let bytes = |v: &[(u8, f64)]| v.iter().map(|b| b.0).collect::<Vec<_>>();
    assert_eq!(bytes(got), bytes(want), "{what}: the bytes");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g.1 - w.1).abs() < bit_s,
            "{what}: byte {i} decoded at {} s, recorded at {} s",
            g.1,
            w.1
        );
    }
}

#[test]
fn vcd_and_sigrok_session_of_ev_meb_decode_to_the_recorded_frames() {
    let (run, frames) = run("ev-meb", "0.7", "ev-meb.mcap");
    let first = frames.iter().position(|f| f.time_s > 0.5).unwrap();
    let (from, to, inside) = window(&frames, first, first + 5);
    let (vcd, sr) = (scratch("ev-meb.vcd"), scratch("ev-meb.sr"));
    let o = twin(&[
        "scope",
        s(&run),
        "--from",
        &from.to_string(),
        "--to",
        &to.to_string(),
        "--vcd",
        s(&vcd),
        "--sr",
        s(&sr),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("decode: sigrok-cli -i FILE -P uart:rx=bus.rs485.line:baudrate=115200"),
        "{}",
        text(&o)
    );
    let bit_s = 1.0 / 115_200.0;
    let want = recorded(&inside, 10.0 * bit_s);
    assert!(want.len() > 40, "{want:?}");
    let uart = "uart:rx=bus.rs485.line:baudrate=115200";

    // VCD: sigrok samples it at 1 GHz (the 1 ns timescale) from its first
    // timestamp, the window's start.
    let vcd_from = (from * 1e9).round() * 1e-9;
    let got = decode(&vcd, "vcd", uart, "uart=rx-data");
    same_within_a_bit("VCD", &bytes_at(&got, vcd_from, 1e-9, bit_s), &want, bit_s);

    // The sigrok session at its default 16 samples per bit.
    let got = decode(&sr, "srzip", uart, "uart=rx-data");
    let rate = 16.0 * 115_200.0;
    same_within_a_bit("sr", &bytes_at(&got, from, 1.0 / rate, bit_s), &want, bit_s);

    // Each node's TX line carries its own frames only.
    let supervisor: Vec<BusFrame> = inside
        .iter()
        .filter(|f| f.from == "supervisor")
        .cloned()
        .collect();
    let got = decode(
        &sr,
        "srzip",
        "uart:rx=bus.rs485.supervisor.tx:baudrate=115200",
        "uart=rx-data",
    );
    same_within_a_bit(
        "the supervisor's TX",
        &bytes_at(&got, from, 1.0 / rate, bit_s),
        &recorded(&supervisor, 10.0 * bit_s),
        bit_s,
    );
}

#[test]
fn modbus_rtu_decodes_with_sigroks_modbus_decoder_on_top() {
    let (run, frames) = run("parallel-rtu-115200", "0.1", "rtu.mcap");
    let first = frames.iter().position(|f| f.time_s > 0.05).unwrap();
    let (from, to, inside) = window(&frames, first, first + 5);
    let sr = scratch("rtu.sr");
    let o = twin(&[
        "scope",
        s(&run),
        "--from",
        &from.to_string(),
        "--to",
        &to.to_string(),
        "--sr",
        s(&sr),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    // The slaves answer 0.1 ms after a request, under Modbus RTU's
    // 3.5-character silence: the decoder's frame gap is set below it.
    let got = decode(
        &sr,
        "srzip",
        "uart:rx=bus.rs485.line:baudrate=115200,modbus:framegap=10",
        "modbus",
    );
    let texts: Vec<&str> = got.iter().map(|a| a.text.as_str()).collect();
    let crcs = texts.iter().filter(|t| **t == "CRC correct").count();
    assert_eq!(crcs, inside.len(), "{texts:#?}");
    assert!(
        !texts
            .iter()
            .any(|t| t.contains("error") || t.contains("invalid")),
        "{texts:#?}"
    );
    let ids = texts.iter().filter(|t| t.starts_with("Slave ID: ")).count();
    assert_eq!(ids, inside.len(), "{texts:#?}");
}

#[test]
fn a_collision_garbles_the_line_where_the_two_frames_overlap() {
    let scenario = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../docs/examples/two-supervisors.toml"
    );
    let (run, frames) = run(scenario, "0.3", "two.mcap");
    // Both supervisors answer the controller's reply at once, with requests
    // that differ: the engine counts a collision and garbles both.
    let i = (1..frames.len() - 2)
        .find(|&i| {
            let (a, b) = (&frames[i], &frames[i + 1]);
            a.from != b.from && a.time_s == b.time_s && a.bytes != b.bytes
        })
        .expect("two different requests at once");
    let (a, b) = (&frames[i], &frames[i + 1]);
    assert_eq!(a.bytes.len(), b.bytes.len());
    let bit_s = 1.0 / 115_200.0;
    // From before the reply they answer (which ends as they start).
    let reply = &frames[i - 1];
    let from = reply.time_s - 20.0 * bit_s;
    let to = a.end_s.max(b.end_s) + 20.0 * bit_s;
    assert!(frames[i + 2].time_s > to, "{:?}", frames[i + 2]);
    let sr = scratch("two.sr");
    let o = twin(&[
        "scope",
        s(&run),
        "--from",
        &from.to_string(),
        "--to",
        &to.to_string(),
        "--sr",
        s(&sr),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let rate = 16.0 * 115_200.0;
    let uart = |line: &str| format!("uart:rx=bus.rs485.{line}:baudrate=115200");
    // The engine garbled every character of both requests (they overlap
    // from the first start bit to the last stop bit), and the recording
    // says how: on the pair each driver puts its characters as garbled,
    // low wherever either is low, each at the time both went.
    let marks = line_marks(&run);
    let garbled = |f: &BusFrame| {
        marks
            .iter()
            .filter(|m| m.kind == LINE_COLLISION && same_frame(m, f))
            .count()
    };
    assert_eq!((garbled(a), garbled(b)), (a.bytes.len(), b.bytes.len()));
    assert_eq!(garbled(reply), 0);
    let received = as_received(&[a.clone(), b.clone()], &marks);
    let both: Vec<(u8, f64)> = recorded(&received[..1], 10.0 * bit_s)
        .into_iter()
        .zip(&received[1].bytes)
        .map(|((x, at), y)| (x & y, at))
        .collect();
    let mut want = recorded(std::slice::from_ref(reply), 10.0 * bit_s);
    want.extend(&both);
    let got = decode(&sr, "srzip", &uart("line"), "uart=rx-data");
    same_within_a_bit(
        "the pair",
        &bytes_at(&got, from, 1.0 / rate, bit_s),
        &want,
        bit_s,
    );
    // The controller, which hears both, receives the same.
    let got = decode(&sr, "srzip", &uart("ev1.rx"), "uart=rx-data");
    same_within_a_bit(
        "ev1's RX",
        &bytes_at(&got, from, 1.0 / rate, bit_s),
        &both,
        bit_s,
    );
    // Each talker's TX still carries its own frame, whole.
    for f in [a, b] {
        let got = decode(
            &sr,
            "srzip",
            &uart(&format!("{}.tx", f.from)),
            "uart=rx-data",
        );
        assert_ne!(f.from, reply.from);
        same_within_a_bit(
            &f.from,
            &bytes_at(&got, from, 1.0 / rate, bit_s),
            &recorded(std::slice::from_ref(f), 10.0 * bit_s),
            bit_s,
        );
    }
}

/// `ev-meb` with noise on its bus (the book's example): `bit_error_rate`
/// flips bits at the receivers.
const NOISY_BUS: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../docs/examples/noisy-pair.toml"
);

#[test]
fn noise_shows_on_the_pair_and_the_receiver_where_the_engine_flipped_bits() {
    let (run, frames) = run(NOISY_BUS, "0.3", "noisy.mcap");
    let marks = line_marks(&run);
    assert!(marks.iter().all(|m| m.kind == LINE_NOISE), "no collisions");
    // A window of a few frames around the first the noise hit.
    let hit = marks.first().expect("noise flipped some bits");
    let i = frames
        .iter()
        .position(|f| same_frame(hit, f))
        .expect("the flipped frame is recorded");
    let (first, last) = (i.max(2) - 1, (i + 2).min(frames.len() - 2));
    let (from, to, inside) = window(&frames, first, last);
    let vcd = scratch("noisy.vcd");
    let o = twin(&[
        "scope",
        s(&run),
        "--from",
        &from.to_string(),
        "--to",
        &to.to_string(),
        "--vcd",
        s(&vcd),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("with bits flipped by noise"),
        "{}",
        text(&o)
    );
    let bit_s = 1.0 / 115_200.0;
    let vcd_from = (from * 1e9).round() * 1e-9;
    let received = as_received(&inside, &marks);
    let want = recorded(&received, 10.0 * bit_s);
    let sent = recorded(&inside, 10.0 * bit_s);
    let wrong: Vec<usize> = (0..sent.len())
        .filter(|&k| sent[k].0 != want[k].0)
        .collect();
    assert!(!wrong.is_empty(), "the flipped byte is in the window");
    // The pair: a wrong byte exactly where the engine flipped bits, the
    // bytes as sent everywhere else.
    let uart = |line: &str| format!("uart:rx=bus.rs485.{line}:baudrate=115200");
    let got = decode(&vcd, "vcd", &uart("line"), "uart=rx-data");
    same_within_a_bit(
        "the pair",
        &bytes_at(&got, vcd_from, 1e-9, bit_s),
        &want,
        bit_s,
    );
    // Each listener's RX shows what it got: ev-meb has two nodes, so each
    // frame has one listener and its RX reads as the pair does.
    for (node, other) in [("ev1", "supervisor"), ("supervisor", "ev1")] {
        let heard: Vec<BusFrame> = received
            .iter()
            .filter(|f| f.from == other)
            .cloned()
            .collect();
        let got = decode(&vcd, "vcd", &uart(&format!("{node}.rx")), "uart=rx-data");
        same_within_a_bit(
            &format!("{node}'s RX"),
            &bytes_at(&got, vcd_from, 1e-9, bit_s),
            &recorded(&heard, 10.0 * bit_s),
            bit_s,
        );
    }
    // The talkers' TX lines carry what was sent.
    let sup: Vec<BusFrame> = inside
        .iter()
        .filter(|f| f.from == "supervisor")
        .cloned()
        .collect();
    let got = decode(&vcd, "vcd", &uart("supervisor.tx"), "uart=rx-data");
    same_within_a_bit(
        "the supervisor's TX",
        &bytes_at(&got, vcd_from, 1e-9, bit_s),
        &recorded(&sup, 10.0 * bit_s),
        bit_s,
    );
}

#[test]
fn a_window_that_opens_on_a_start_bit_begins_with_idle_line() {
    let (run, frames) = run("ev-meb", "0.2", "lead-in.mcap");
    let f = frames.iter().position(|f| f.time_s > 0.1).unwrap();
    let (_, to, inside) = window(&frames, f, f + 1);
    // From the first start bit itself: without idle line before it, a
    // decoder would see no falling edge and misread the first byte.
    let from = inside[0].time_s;
    let (vcd, sr) = (scratch("lead-in.vcd"), scratch("lead-in.sr"));
    let o = twin(&[
        "scope",
        s(&run),
        "--from",
        &from.to_string(),
        "--to",
        &to.to_string(),
        "--vcd",
        s(&vcd),
        "--sr",
        s(&sr),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("after a character of idle line"),
        "{}",
        text(&o)
    );
    let bit_s = 1.0 / 115_200.0;
    let char_s = 10.0 * bit_s;
    let want = recorded(&inside, char_s);
    let uart = "uart:rx=bus.rs485.line:baudrate=115200";
    let vcd_from = (from * 1e9).round() * 1e-9 - (char_s * 1e9).floor() * 1e-9;
    let got = decode(&vcd, "vcd", uart, "uart=rx-data");
    same_within_a_bit("VCD", &bytes_at(&got, vcd_from, 1e-9, bit_s), &want, bit_s);
    let got = decode(&sr, "srzip", uart, "uart=rx-data");
    let rate = 16.0 * 115_200.0;
    same_within_a_bit(
        "sr",
        &bytes_at(&got, from - char_s, 1.0 / rate, bit_s),
        &want,
        bit_s,
    );
}

#[test]
fn errors_say_what_to_choose() {
    let (run, _) = run("ev-meb", "0.2", "short.mcap");
    let o = twin(&[
        "scope",
        s(&run),
        "--bus",
        "can",
        "--vcd",
        s(&scratch("x.vcd")),
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("has no bus or link `can` with frames (it has bus rs485)"),
        "{}",
        text(&o)
    );
    let o = twin(&[
        "scope",
        s(&run),
        "--frame",
        "99999",
        "--vcd",
        s(&scratch("x.vcd")),
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("--frame 99999: "), "{}", text(&o));
}
