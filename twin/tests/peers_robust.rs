//! Garbage, half frames, absurd lengths, abrupt disconnects and a serial port
//! vanishing, on every kind of link `twin serve` has (Modbus TCP, MEB over
//! TCP, Modbus RTU, Modbus ASCII and the 8-byte Modbus on pseudo-terminals),
//! while well-behaved clients keep polling over TCP: none of them may miss a
//! reply, each abused serial link answers its next valid request after a
//! silence, and the server is still running at the end.

mod peers;

use nodes::proto::crc::{crc16_modbus, lrc};
use peers::{PtyPair, Serve, scratch};
use rustix::event::{PollFd, PollFlags, Timespec, poll};
use rustix::fs::OFlags;
use rustix::termios::{OptionalActions, tcgetattr, tcsetattr};
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

const REPLY_TIMEOUT: Duration = Duration::from_secs(2);
/// A frame gap for the slaves (3.5 characters, 5 ms on a pty), with room for
/// the socat relay, which on a loaded machine sometimes holds bytes for over
/// 10 ms: abuse and the valid request after it must not arrive as one burst.
const SILENCE: Duration = Duration::from_millis(200);

fn open_raw(path: &Path) -> File {
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(OFlags::NOCTTY.bits() as i32)
        .open(path)
        .expect("open pty");
    let mut t = tcgetattr(&file).unwrap();
    t.make_raw();
    tcsetattr(&file, OptionalActions::Now, &t).unwrap();
    file
}

/// Waits up to `wait` for `link` to have bytes to read.
fn readable(link: &File, wait: Duration) -> bool {
    let t = Timespec {
        tv_sec: wait.as_secs() as i64,
        tv_nsec: i64::from(wait.subsec_nanos()),
    };
    let mut fds = [PollFd::new(link, PollFlags::IN)];
    poll(&mut fds, Some(&t)).unwrap() > 0
}

/// Reads until `done(bytes)` holds, each wait bounded by [`REPLY_TIMEOUT`].
fn read_until(link: &mut File, done: impl Fn(&[u8]) -> bool) -> Vec<u8> {
    let mut got = Vec::new();
    let mut buf = [0u8; 512];
    while !done(&got) {
        assert!(
            readable(link, REPLY_TIMEOUT),
            "no (complete) reply within {REPLY_TIMEOUT:?}; got {got:02x?}"
        );
        let n = link.read(&mut buf).unwrap();
        got.extend_from_slice(&buf[..n]);
    }
    got
}

/// Whatever arrives within `wait` (nothing expected).
fn drain(link: &mut File, wait: Duration) -> Vec<u8> {
    let mut got = Vec::new();
    let mut buf = [0u8; 512];
    let end = Instant::now() + wait;
    loop {
        let left = end.saturating_duration_since(Instant::now());
        if left.is_zero() || !readable(link, left) {
            return got;
        }
        let n = link.read(&mut buf).unwrap();
        got.extend_from_slice(&buf[..n]);
    }
}

fn rtu_read_inputs() -> Vec<u8> {
    let mut f = vec![1, 4, 0, 0, 0, 10];
    let crc = crc16_modbus(&f).to_le_bytes();
    f.extend_from_slice(&crc);
    f
}

fn modbus8_read_state() -> Vec<u8> {
    let mut f = vec![1, 3, 0, 1, 0, 0];
    let crc = crc16_modbus(&f).to_be_bytes(); // seed 002: high byte first
    f.extend_from_slice(&crc);
    f
}

fn ascii_read_inputs() -> Vec<u8> {
    let bin = [1u8, 4, 0, 0, 0, 10];
    let mut text = String::from(":");
    for b in bin.iter().chain([lrc(&bin)].iter()) {
        text.push_str(&format!("{b:02X}"));
    }
    text.push_str("\r\n");
    text.into_bytes()
}

fn meb_frame(body: &str) -> Vec<u8> {
    let fcs = body.bytes().fold(0u8, |x, b| x ^ b);
    format!("{body}{fcs:02X}*\n").into_bytes()
}

/// A Modbus TCP client polling FC04 back to back until told to stop.
fn modbus_poller(
    addr: String,
    stop: Arc<AtomicBool>,
    ok: Arc<AtomicU64>,
) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let mut s = TcpStream::connect(&addr).unwrap();
        s.set_nodelay(true).unwrap();
        s.set_read_timeout(Some(REPLY_TIMEOUT)).unwrap();
        let mut tid: u16 = 0;
        while !stop.load(Ordering::Relaxed) {
            tid = tid.wrapping_add(1);
            let t = tid.to_be_bytes();
            s.write_all(&[t[0], t[1], 0, 0, 0, 6, 1, 4, 0, 0, 0, 10])
                .unwrap();
            let mut reply = [0u8; 29];
            s.read_exact(&mut reply)
                .expect("the good Modbus TCP client got its reply");
            assert_eq!(&reply[..2], &t, "reply to this request");
            assert_eq!(reply[7], 4, "an FC04 reply, no exception: {reply:02x?}");
            ok.fetch_add(1, Ordering::Relaxed);
        }
    })
}

/// An MEB-over-TCP client reading EA 0 1 back to back until told to stop.
fn meb_poller(
    addr: String,
    stop: Arc<AtomicBool>,
    ok: Arc<AtomicU64>,
) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let s = TcpStream::connect(&addr).unwrap();
        s.set_nodelay(true).unwrap();
        s.set_read_timeout(Some(REPLY_TIMEOUT)).unwrap();
        let mut w = s.try_clone().unwrap();
        let mut r = BufReader::new(s);
        let req = meb_frame("@01EA0001");
        while !stop.load(Ordering::Relaxed) {
            w.write_all(&req).unwrap();
            let mut line = String::new();
            r.read_line(&mut line)
                .expect("the good MEB client got its reply");
            assert!(
                line.starts_with("@01EA0001") && line.ends_with("*\n"),
                "{line:?}"
            );
            ok.fetch_add(1, Ordering::Relaxed);
        }
    })
}

fn abuse_tcp(addr: &str, bursts: &[&[u8]]) {
    for burst in bursts {
        let mut s = TcpStream::connect(addr).unwrap();
        let _ = s.write_all(burst);
        // Dropped mid-frame: the server sees the connection end abruptly.
    }
    // Connect and vanish without a byte.
    drop(TcpStream::connect(addr).unwrap());
}

#[test]
fn abuse_on_every_link_leaves_the_others_served() {
    let dir = scratch("robust");
    let rtu = PtyPair::new(&dir.join("rtu").tap_mkdir());
    let ascii = PtyPair::new(&dir.join("ascii").tap_mkdir());
    let m8 = PtyPair::new(&dir.join("m8").tap_mkdir());
    let recording = dir.join("robust.mcap");
    let mut serve = Serve::start(&[
        "--quiet",
        "--out",
        recording.to_str().unwrap(),
        "--modbus",
        "tcp://127.0.0.1:0",
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus-rtu",
        rtu.a.to_str().unwrap(),
        "--modbus-ascii",
        ascii.a.to_str().unwrap(),
        "--modbus8",
        m8.a.to_str().unwrap(),
    ]);
    let modbus = serve.tcp("modbus-tcp");
    let meb = serve.tcp("meb");

    let stop = Arc::new(AtomicBool::new(false));
    let (mb_ok, meb_ok) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let pollers = [
        modbus_poller(modbus.clone(), stop.clone(), mb_ok.clone()),
        meb_poller(meb.clone(), stop.clone(), meb_ok.clone()),
    ];

    // Modbus TCP: garbage, half an MBAP header, a header announcing 65535
    // bytes, a whole header with half its PDU, a frame for another unit.
    let garbage: Vec<u8> = (0..2000u32).map(|i| (i * 73 % 251) as u8).collect();
    abuse_tcp(
        &modbus,
        &[
            &garbage,
            &[0, 1, 0, 0, 0],
            &[0, 1, 0, 0, 0xff, 0xff, 1, 4],
            &[0, 1, 0, 0, 0, 6, 1, 4, 0],
            &[0, 1, 0, 0, 0, 6, 77, 4, 0, 0, 0, 1],
        ],
    );
    // MEB over TCP: garbage without a line end, half a frame, 5000 bytes with
    // no terminator (past the longest frame), a bad FCS.
    let long = vec![b'A'; 5000];
    abuse_tcp(
        &meb,
        &[b"hello\x00\xff", b"@01EA00", &long, b"@01EA000100*\n"],
    );

    // Serial links: garbage or half a frame, a silence, then a valid request
    // must be answered (once, and whole).
    let mut port = open_raw(&rtu.b);
    port.write_all(&garbage[..300]).unwrap();
    std::thread::sleep(SILENCE);
    port.write_all(&rtu_read_inputs()[..5]).unwrap();
    std::thread::sleep(SILENCE);
    let _ = drain(&mut port, SILENCE);
    port.write_all(&rtu_read_inputs()).unwrap();
    let reply = read_until(&mut port, |b| b.len() >= 25);
    assert_eq!(
        &reply[..3],
        &[1, 4, 20],
        "RTU FC04 reply after the abuse: {reply:02x?}"
    );
    assert_eq!(
        crc16_modbus(&reply[..23]).to_le_bytes(),
        [reply[23], reply[24]]
    );

    let mut port = open_raw(&ascii.b);
    port.write_all(b":01zz\r\n:0104000").unwrap();
    std::thread::sleep(SILENCE);
    port.write_all(b"\r\n").unwrap();
    let _ = drain(&mut port, SILENCE);
    port.write_all(&ascii_read_inputs()).unwrap();
    let reply = read_until(&mut port, |b| b.ends_with(b"\r\n"));
    assert!(
        reply.starts_with(b":010414"),
        "ASCII FC04 reply: {:?}",
        String::from_utf8_lossy(&reply)
    );

    let mut port = open_raw(&m8.b);
    port.write_all(&[1, 3, 0]).unwrap();
    std::thread::sleep(SILENCE);
    let mut bad = modbus8_read_state();
    bad[7] ^= 0xff;
    port.write_all(&bad).unwrap();
    assert!(
        drain(&mut port, Duration::from_millis(100)).is_empty(),
        "silent on a bad CRC"
    );
    port.write_all(&modbus8_read_state()).unwrap();
    let reply = read_until(&mut port, |b| b.len() >= 8);
    assert_eq!(reply.len(), 8, "one whole 8-byte reply: {reply:02x?}");
    assert_eq!(&reply[..4], &[1, 3, 0, 1], "{reply:02x?}");
    assert_eq!(
        crc16_modbus(&reply[..6]).to_be_bytes(),
        [reply[6], reply[7]]
    );

    // A serial port vanishes under the server: socat ends, the pty is gone.
    drop(rtu);
    std::thread::sleep(Duration::from_millis(300));

    // The abused TCP servers still take new clients.
    let mut s = TcpStream::connect(&modbus).unwrap();
    s.set_read_timeout(Some(REPLY_TIMEOUT)).unwrap();
    s.write_all(&[0, 9, 0, 0, 0, 6, 1, 3, 0, 0, 0, 1]).unwrap();
    let mut reply = [0u8; 11];
    s.read_exact(&mut reply)
        .expect("a new Modbus TCP client is served");
    assert_eq!(&reply[..2], &[0, 9]);

    let before = (
        mb_ok.load(Ordering::Relaxed),
        meb_ok.load(Ordering::Relaxed),
    );
    std::thread::sleep(Duration::from_millis(300));
    stop.store(true, Ordering::Relaxed);
    for p in pollers {
        p.join().expect("a good client missed a reply");
    }
    let after = (
        mb_ok.load(Ordering::Relaxed),
        meb_ok.load(Ordering::Relaxed),
    );
    assert!(
        after.0 > before.0 && after.1 > before.1,
        "still served at the end: {before:?} {after:?}"
    );
    assert!(
        after.0 > 100 && after.1 > 100,
        "served throughout: {after:?}"
    );
    serve.assert_running();

    // SIGTERM finishes the recording: a whole MCAP file holding the good
    // clients' frames and the garbage alike.
    drop(serve);
    let bytes = std::fs::read(&recording).expect("the recording exists");
    let mut frames = std::collections::BTreeMap::<String, u64>::new();
    for message in mcap::MessageStream::new(&bytes).expect("a valid MCAP file") {
        let message = message.expect("a valid message");
        if message.channel.topic.ends_with("/frames") {
            *frames.entry(message.channel.topic.clone()).or_default() += 1;
        }
    }
    let total: u64 = frames.values().sum();
    assert!(
        frames.len() >= 4 && total > 2 * (after.0 + after.1),
        "frames of every abused link and both directions of the good clients: {frames:?}"
    );
}

trait TapMkdir {
    fn tap_mkdir(self) -> Self;
}

impl TapMkdir for std::path::PathBuf {
    fn tap_mkdir(self) -> Self {
        std::fs::create_dir_all(&self).unwrap();
        self
    }
}
