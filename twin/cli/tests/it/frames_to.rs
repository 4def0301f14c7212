//! `twin replay --frames-to`: the recorded master requests go out on a real
//! TCP socket (port 0, chosen by the system) and a real pseudo-terminal pair
//! (socat) to a slave that answers from a script: the recorded replies, one
//! with a changed value (correctly checked), one withheld, one with a broken
//! check. The replay must count and show exactly those.

use crate::support;
use protocols::meb::{MebRepr, MebWords};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use support::{text, twin};
use twin_recording::Recording;
use twin_sim::engine::FrameKind;

fn scratch(name: &str) -> PathBuf {
    support::scratch("frames-to", name)
}

const REQUESTS: usize = 12;
const CHANGED: usize = 3;
const WITHHELD: usize = 5;
const BROKEN: usize = 8;

/// The slave's script: per request, the reply to send (None: stay silent).
fn script(recording: &Path) -> Vec<(Vec<u8>, Option<Vec<u8>>)> {
    let frames = Recording::read(recording)
        .expect("recording")
        .frames()
        .expect("frames");
    let mut out = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        if f.from != "supervisor" {
            continue;
        }
        let reply = frames
            .get(i + 1)
            .filter(|r| r.from != "supervisor")
            .map(|r| r.bytes.clone());
        out.push((f.bytes.clone(), reply));
    }
    out.truncate(REQUESTS);
    // Request CHANGED gets a reply with its first data word moved by one,
    // re-emitted with a good FCS; BROKEN gets one byte flipped.
    let reply = out[CHANGED].1.as_mut().expect("recorded reply");
    let mut repr = MebRepr::parse(reply).expect("MEB reply");
    let mut words: Vec<u16> = repr.data.as_slice().to_vec();
    assert!(!words.is_empty(), "a reply with data: {repr:?}");
    words[0] ^= 1;
    repr.data = MebWords::from_slice(&words).unwrap();
    let mut buf = [0u8; 512];
    let n = repr.emit(&mut buf).unwrap();
    *reply = buf[..n].to_vec();
    out[WITHHELD].1 = None;
    let broken = out[BROKEN].1.as_mut().expect("recorded reply");
    broken[3] = if broken[3] == b'1' { b'2' } else { b'1' };
    out
}

/// Answer requests on `io` from the script until it runs out.
fn serve(mut io: impl Read + Write, script: Vec<(Vec<u8>, Option<Vec<u8>>)>) {
    let mut buf = Vec::new();
    let mut byte = [0u8; 1];
    for (request, reply) in script {
        buf.clear();
        while !FrameKind::of(&request).passes_check(&buf) {
            if io.read(&mut byte).unwrap_or(0) == 0 {
                return;
            }
            buf.push(byte[0]);
        }
        assert_eq!(buf, request, "the requests arrive as recorded");
        if let Some(r) = reply {
            io.write_all(&r).unwrap();
            io.flush().unwrap();
        }
    }
}

/// One half-second ev-meb run shared by the tests (made once: tests run in
/// parallel and must not read it half-written).
fn recorded_run() -> PathBuf {
    static RUN: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    RUN.get_or_init(|| {
        let out = scratch("ev-meb.mcap");
        let o = twin(&[
            "run",
            "ev-meb",
            "--duration",
            "0.5",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", text(&o));
        out
    })
    .clone()
}

/// socat, stopped however the test ends.
struct Socat(std::process::Child);

impl Drop for Socat {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn check_report(o: &Output) {
    let t = text(o);
    assert!(!o.status.success(), "a missing reply fails: {t}");
    assert!(
        t.contains(&format!("{REQUESTS} requests of supervisor on bus rs485")),
        "{t}"
    );
    assert!(
        t.contains(&format!("  {} replies as recorded", REQUESTS - 3)),
        "{t}"
    );
    assert!(t.contains("  1 replies differ in their values only"), "{t}");
    assert!(
        t.contains("1 missing (no reply within 300 ms), 0 unexpected, 1 different"),
        "{t}"
    );
    let order: Vec<&str> = t
        .lines()
        .filter_map(|l| l.trim().split_once("] ").map(|(_, v)| v))
        .collect();
    assert_eq!(order, ["values differ", "missing", "different"], "{t}");
}

#[test]
fn frames_to_a_tcp_slave_counts_changed_missing_and_broken_replies() {
    let run = recorded_run();
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let port = listener.local_addr().unwrap().port();
    let script = script(&run);
    let slave = std::thread::spawn(move || {
        let (mut stream, _) = listener.accept().expect("accept");
        serve(&mut stream, script);
        // Like a real slave, stay on the line until the master hangs up.
        let mut rest = Vec::new();
        let _ = stream.read_to_end(&mut rest);
    });
    let o = twin(&[
        "replay",
        run.to_str().unwrap(),
        "--frames-to",
        &format!("tcp://127.0.0.1:{port}"),
        "--limit",
        &REQUESTS.to_string(),
        "--timeout-ms",
        "300",
    ]);
    check_report(&o);
    slave.join().expect("slave ran");
}

#[test]
fn frames_to_a_pseudo_terminal_slave() {
    let run = recorded_run();
    let (a, b) = (scratch("ttyA"), scratch("ttyB"));
    let _socat = Socat(
        Command::new("socat")
            .args([
                format!("pty,raw,echo=0,link={}", a.display()),
                format!("pty,raw,echo=0,link={}", b.display()),
            ])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("socat is installed (apt-get install socat)"),
    );
    let started = std::time::Instant::now();
    while !(a.exists() && b.exists()) {
        assert!(started.elapsed().as_secs() < 10, "socat made no ptys");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let script = script(&run);
    let b2 = b.clone();
    let slave = std::thread::spawn(move || {
        let io = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&b2)
            .expect("open pty");
        serve(io, script);
    });
    let o = twin(&[
        "replay",
        run.to_str().unwrap(),
        "--frames-to",
        a.to_str().unwrap(),
        "--limit",
        &REQUESTS.to_string(),
        "--timeout-ms",
        "300",
    ]);
    check_report(&o);
    slave.join().expect("slave ran");
}

#[test]
fn frames_to_a_closed_port_says_so() {
    let run = recorded_run();
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let o = twin(&[
        "replay",
        run.to_str().unwrap(),
        "--frames-to",
        &format!("tcp://127.0.0.1:{port}"),
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("cannot connect to 127.0.0.1"),
        "{}",
        text(&o)
    );
    let o = twin(&["replay", run.to_str().unwrap(), "--frames-to", "udp://x"]);
    assert!(text(&o).contains("unknown link `udp://x`"), "{}", text(&o));
    // The grammar of `twin serve`'s links, whose options a link used as it
    // is does not take; its mistakes are said as `twin serve` says them.
    let o = twin(&[
        "replay",
        run.to_str().unwrap(),
        "--frames-to",
        "/dev/ttyUSB0?baud=9600",
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("option `baud` is not taken here"),
        "{}",
        text(&o)
    );
    let o = twin(&[
        "replay",
        run.to_str().unwrap(),
        "--frames-to",
        "tcp://127.0.0.1",
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("is not HOST:PORT (no port)"),
        "{}",
        text(&o)
    );
}

/// A child process (socat, the Python slave), stopped however the test ends.
struct Child(std::process::Child);

impl Drop for Child {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn frames_to_a_pymodbus_rtu_slave_on_a_pseudo_terminal() {
    // A peer we did not write: pymodbus' RTU server (unit 1, every register
    // zero) on one end of a socat pty pair. The supervisor's writes (FC15
    // start-up coils, FC06 VEL) come back as recorded, byte for byte; its
    // FC04 reads come back as well-formed replies of the same length with
    // the server's zeros instead of the plant's readings.
    let scenario = scratch("ev-rtu.toml");
    std::fs::write(
        &scenario,
        r#"name = "ev-rtu"
duration_s = 0.3
[[module]]
name = "ev1"
[[bus]]
name = "rs485"
[[node]]
kind = "ev-controller"
name = "ev1"
bus = "rs485"
module = "ev1"
protocol = "modbus-rtu"
[[node]]
kind = "supervisor"
name = "supervisor"
bus = "rs485"
slaves = [1]
protocol = "modbus-rtu"
kp = 0.45
ki = 2.5
set_points = [[0.0, 0.0], [0.1, 1500.0]]
"#,
    )
    .unwrap();
    let run = scratch("ev-rtu.mcap");
    let o = twin(&[
        "run",
        scenario.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let (a, b) = (scratch("rtuA"), scratch("rtuB"));
    let _socat = Child(
        Command::new("socat")
            .args([
                format!("pty,raw,echo=0,link={}", a.display()),
                format!("pty,raw,echo=0,link={}", b.display()),
            ])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("socat is installed (apt-get install socat)"),
    );
    let started = std::time::Instant::now();
    while !(a.exists() && b.exists()) {
        assert!(started.elapsed().as_secs() < 10, "socat made no ptys");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/peers/pymodbus_rtu_slave.py"
    );
    let mut slave = Child(
        Command::new("python3")
            .args([script, b.to_str().unwrap()])
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("python3 runs"),
    );
    // The slave says when it serves.
    let mut line = [0u8; 8];
    slave
        .0
        .stdout
        .take()
        .unwrap()
        .read_exact(&mut line)
        .expect("pymodbus (and pyserial) installed: the slave starts");
    assert_eq!(&line, b"serving\n");

    let requests: Vec<u8> = Recording::read(&run)
        .unwrap()
        .frames()
        .unwrap()
        .iter()
        .filter(|f| f.from == "supervisor")
        .map(|f| f.bytes[1])
        .collect();
    // The last request of the run has no recorded reply: it is not sent.
    let sent = &requests[..requests.len() - 1];
    let reads = sent.iter().filter(|&&f| f == 4).count();
    assert!(
        reads > 10 && sent.contains(&15) && sent.contains(&6),
        "{sent:?}"
    );

    let o = twin(&[
        "replay",
        run.to_str().unwrap(),
        "--frames-to",
        a.to_str().unwrap(),
        "--timeout-ms",
        "1000",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains(&format!("{} requests of supervisor", sent.len())),
        "{t}"
    );
    assert!(
        t.contains(&format!("  {} replies as recorded", sent.len() - reads)),
        "{t}"
    );
    assert!(
        t.contains(&format!("  {reads} replies differ in their values only")),
        "{t}"
    );
    assert!(
        t.contains("0 missing (no reply within 1000 ms), 0 unexpected, 0 different"),
        "{t}"
    );
    assert!(t.contains("live      01 04 0c 00 00 00 00"), "{t}");
}
