//! What an abuse probe found in `twin serve`'s links, each against the real
//! process: bytes outside any frame hold no place for ever, a newcomer to a
//! full listener is refused at once instead of queued, a Modbus TCP header
//! of length 0 closes its connection without waiting for a seventh byte, the
//! 8-byte Modbus link answers every request of a write and counts a frame
//! split by its writer as one, and RTU and TCP answer a malformed write alike.

use crate::peers;

use peers::{DirectPty, Serve, readable};
use protocols::crc::crc16_modbus;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

const WAIT: Duration = Duration::from_secs(10);

fn meb_frame(body: &str) -> Vec<u8> {
    let fcs = body.bytes().fold(0u8, |x, b| x ^ b);
    format!("{body}{fcs:02X}*\n").into_bytes()
}

fn connect(addr: &str) -> TcpStream {
    let s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    s
}

/// An MEB request on a new connection; its reply line, or why none came.
fn meb_ask(addr: &str) -> Result<String, String> {
    let s = connect(addr);
    (&s).write_all(&meb_frame("@01EA0001"))
        .map_err(|e| e.to_string())?;
    let mut line = String::new();
    match BufReader::new(&s).read_line(&mut line) {
        Ok(0) => Err("closed without a reply".into()),
        Ok(_) => Ok(line),
        Err(e) => Err(e.to_string()),
    }
}

/// Clients that send nothing but bytes outside any frame (no `@`) are as
/// quiet as clients that send nothing: they make room after
/// `--make-room-after` and are closed after `--idle-timeout`. Before, their
/// bytes counted as activity, and eight of them locked every newcomer out.
#[test]
fn stray_bytes_hold_no_place_for_ever() {
    let serve = Serve::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--max-clients",
        "2",
        "--make-room-after",
        "1",
    ]);
    let addr = serve.tcp("meb");
    let stray: Vec<TcpStream> = (0..2).map(|_| connect(&addr)).collect();
    let started = Instant::now();
    while started.elapsed() < Duration::from_millis(1500) {
        for s in &stray {
            (&*s).write_all(b"0").unwrap();
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let line = meb_ask(&addr).expect("a newcomer takes the place of a stray-byte client");
    assert!(line.starts_with("@01EA0001"), "{line:?}");
    let made = serve.expect_line("made room for a new client", WAIT);
    assert!(made.contains("idle for"), "{made}");
    drop(serve);

    let serve = Serve::start(&["--meb", "tcp://127.0.0.1:0", "--idle-timeout", "1"]);
    let s = connect(&serve.tcp("meb"));
    let writer = s.try_clone().unwrap();
    let sender = std::thread::spawn(move || {
        // Junk every 100 ms until the server closes the connection.
        for _ in 0..100 {
            if (&writer).write_all(b"0").is_err() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    });
    let mut got = Vec::new();
    let _ = (&s).read_to_end(&mut got);
    assert!(got.is_empty(), "noise is not answered: {got:02x?}");
    let line = serve.expect_line("longer than --idle-timeout", WAIT);
    assert!(line.contains("closed by the twin: idle for"), "{line}");
    sender.join().unwrap();
}

/// At the client limit, with no place to make, every newcomer is closed at
/// once: twenty of them are all closed within seconds, where each used to
/// wait a second for a place behind the one before it. The clients in place
/// keep being served, and the console says so once, not twenty times.
#[test]
fn newcomers_to_a_full_listener_are_refused_at_once() {
    let serve = Serve::start(&["--meb", "tcp://127.0.0.1:0", "--max-clients", "2"]);
    let addr = serve.tcp("meb");
    let ask = |s: &TcpStream| {
        (&*s).write_all(&meb_frame("@01EA0001")).unwrap();
        let mut line = String::new();
        BufReader::new(s).read_line(&mut line).unwrap();
        assert!(line.starts_with("@01EA0001"), "{line:?}");
    };
    let kept: Vec<TcpStream> = (0..2).map(|_| connect(&addr)).collect();
    for s in &kept {
        ask(s);
    }
    let newcomers: Vec<TcpStream> = (0..20).map(|_| connect(&addr)).collect();
    let started = Instant::now();
    for (i, s) in newcomers.iter().enumerate() {
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut got = Vec::new();
        (&*s)
            .read_to_end(&mut got)
            .unwrap_or_else(|e| panic!("newcomer {i} is closed, not kept waiting: {e}"));
        assert!(got.is_empty(), "newcomer {i}: {got:02x?}");
    }
    let took = started.elapsed();
    assert!(
        took < Duration::from_secs(5),
        "20 newcomers closed in {took:?}: one at a time, a second each, would take 20 s"
    );
    for s in &kept {
        ask(s);
    }
    let first = serve.expect_line("refused, 2 client(s) already connected", WAIT);
    assert!(first.contains("--max-clients"), "{first}");
    let said = serve
        .stdout()
        .lines()
        .filter(|l| l.contains("already connected"))
        .count();
    assert!(
        said < 20,
        "a line per second at most, not per newcomer: {said}"
    );
}

/// A Modbus TCP header whose length is 0 cannot be valid: the connection is
/// closed on its sixth byte, not held until a seventh arrives.
#[test]
fn a_modbus_tcp_header_of_length_0_closes_without_a_seventh_byte() {
    let serve = Serve::start(&["--modbus", "tcp://127.0.0.1:0"]);
    let s = connect(&serve.tcp("modbus-tcp"));
    (&s).write_all(&[0x00, 0x01, 0x00, 0x00, 0x00, 0x00])
        .unwrap();
    let mut got = Vec::new();
    (&s).read_to_end(&mut got)
        .expect("closed within the read timeout");
    assert!(got.is_empty(), "{got:02x?}");
    let line = serve.expect_line("cannot be valid", WAIT);
    assert!(line.contains("closed by the twin"), "{line}");
}

/// A Controller_network request (CRC high byte first).
fn modbus8(id: u8, function: u8, addr: u16, value: u16) -> [u8; 8] {
    let [a0, a1] = addr.to_be_bytes();
    let [v0, v1] = value.to_be_bytes();
    let body = [id, function, a0, a1, v0, v1];
    let [c0, c1] = crc16_modbus(&body).to_be_bytes();
    [id, function, a0, a1, v0, v1, c0, c1]
}

/// Reads from `pty` until `n` bytes came or the line stays quiet for 1 s.
fn read_bytes(pty: &std::fs::File, n: usize) -> Vec<u8> {
    let mut got = Vec::new();
    let mut buf = [0u8; 256];
    while got.len() < n && readable(pty, Duration::from_secs(1)) {
        match (&*pty).read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(k) => got.extend_from_slice(&buf[..k]),
        }
    }
    got
}

/// Reads from `pty` what comes within a second, until it stays quiet for 200 ms.
fn read_reply(pty: &std::fs::File) -> Vec<u8> {
    let mut got = Vec::new();
    let mut buf = [0u8; 256];
    let mut wait = Duration::from_secs(1);
    while readable(pty, wait) {
        match (&*pty).read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(k) => got.extend_from_slice(&buf[..k]),
        }
        wait = Duration::from_millis(200);
    }
    got
}

/// On a pty, where bytes carry no line timing: a request written as 4 + 4
/// bytes is one request, answered and shown as one frame (it was shown and
/// counted as two CRC errors); three or ten requests in one write get as
/// many replies, in order (they got one).
#[test]
fn the_8_byte_modbus_link_answers_every_request_of_a_write() {
    let pty = DirectPty::new();
    let serve = Serve::start(&["--modbus8", pty.path.to_str().unwrap()]);
    let link = &pty.master;
    let read_state = modbus8(1, 3, 1, 0);
    for _ in 0..5 {
        (&*link).write_all(&read_state[..4]).unwrap();
        std::thread::sleep(Duration::from_millis(1));
        (&*link).write_all(&read_state[4..]).unwrap();
        let reply = read_bytes(link, 8);
        assert_eq!(reply.len(), 8, "split request answered: {reply:02x?}");
        assert_eq!(reply[..4], read_state[..4]);
    }
    for count in [3usize, 10] {
        // Motor state, set speed and the light sensor's value in turn.
        let requests: Vec<[u8; 8]> = (0..count)
            .map(|i| match i % 3 {
                0 => modbus8(1, 3, 1, 0),
                1 => modbus8(1, 3, 5, 0),
                _ => modbus8(2, 3, 6, 0),
            })
            .collect();
        (&*link).write_all(&requests.concat()).unwrap();
        let replies = read_bytes(link, 8 * count);
        assert_eq!(replies.len(), 8 * count, "{count} requests: {replies:02x?}");
        for (request, reply) in requests.iter().zip(replies.chunks(8)) {
            assert_eq!(reply[..4], request[..4], "in order: {replies:02x?}");
            let crc = u16::from_be_bytes([reply[6], reply[7]]);
            assert_eq!(crc, crc16_modbus(&reply[..6]), "{reply:02x?}");
        }
    }
    std::thread::sleep(Duration::from_millis(300));
    let monitor = serve.stdout();
    assert!(
        !monitor.contains("CRC error"),
        "no request was a CRC error:\n{monitor}"
    );
    let requests_shown = monitor
        .lines()
        .filter(|l| l.contains(" <- 01 03 00 01"))
        .count();
    // 5 split + 1 + 4 whole reads of motor state.
    assert_eq!(requests_shown, 5 + 1 + 4, "{monitor}");
}

/// Function 16 whose byte count does not match its quantity, in a whole
/// CRC-valid RTU frame: exception 03, as over Modbus TCP. A frame whose
/// count promises more data than came cannot be told from a partial one on
/// RTU and stays silent (as libmodbus); over TCP the MBAP length ends it.
#[test]
fn rtu_and_tcp_answer_a_malformed_write_alike() {
    let pty = DirectPty::new();
    let serve = Serve::start(&[
        "--modbus-rtu",
        pty.path.to_str().unwrap(),
        "--modbus",
        "tcp://127.0.0.1:0",
    ]);
    let tcp = connect(&serve.tcp("modbus-tcp"));
    let link = &pty.master;
    let mut tid = 0u16;
    let mut over_tcp = |pdu: &[u8]| -> Vec<u8> {
        tid += 1;
        let [t0, t1] = tid.to_be_bytes();
        let mut adu = vec![t0, t1, 0, 0, 0, 1 + pdu.len() as u8, 1];
        adu.extend_from_slice(pdu);
        (&tcp).write_all(&adu).unwrap();
        let mut header = [0u8; 7];
        (&tcp).read_exact(&mut header).unwrap();
        let mut rest = vec![0u8; usize::from(header[5]) - 1];
        (&tcp).read_exact(&mut rest).unwrap();
        rest
    };
    let over_rtu = |pdu: &[u8]| -> Vec<u8> {
        let mut adu = vec![1u8];
        adu.extend_from_slice(pdu);
        let crc = crc16_modbus(&adu);
        adu.extend_from_slice(&crc.to_le_bytes());
        (&*link).write_all(&adu).unwrap();
        let reply = read_reply(link);
        reply
            .get(1..reply.len().saturating_sub(2))
            .unwrap_or_default()
            .to_vec()
    };
    let whole: [&[u8]; 3] = [
        // Quantity 2 with a byte count of 2; quantity 1 with 4; 9 coils with 1.
        &[0x10, 0x00, 0x00, 0x00, 0x02, 0x02, 0x12, 0x34],
        &[0x10, 0x00, 0x00, 0x00, 0x01, 0x04, 0x12, 0x34, 0x56, 0x78],
        &[0x0F, 0x00, 0x00, 0x00, 0x09, 0x01, 0xFF],
    ];
    for pdu in whole {
        let expected = [pdu[0] | 0x80, 0x03];
        assert_eq!(over_rtu(pdu), expected, "RTU {pdu:02x?}");
        assert_eq!(over_tcp(pdu), expected, "TCP {pdu:02x?}");
    }
    // A count of 4 with two bytes of data.
    let short = [0x10, 0x00, 0x00, 0x00, 0x02, 0x04, 0x12, 0x34];
    assert_eq!(over_rtu(&short), Vec::<u8>::new(), "silent on RTU");
    assert_eq!(over_tcp(&short), [0x90, 0x03], "exception 03 over TCP");
    // And the line is in step again for the next request.
    let read = [0x04, 0x00, 0x00, 0x00, 0x01];
    let reply = over_rtu(&read);
    assert_eq!(reply.get(..2), Some(&[0x04, 0x02][..]), "{reply:02x?}");
}

/// Connections that never finish a frame displace nobody: a newcomer that
/// could take the place of a stale partial frame is let in on probation and
/// takes it only with a whole request. Slowloris clients reconnecting as
/// fast as they are closed (they used to displace one another, keeping every
/// place fresh and refusing everyone else) leave real clients served.
#[test]
fn only_a_whole_request_earns_a_place_on_a_full_listener() {
    let serve = Serve::start(&["--meb", "tcp://127.0.0.1:0", "--max-clients", "2"]);
    let addr = serve.tcp("meb");
    let members: Vec<TcpStream> = (0..2)
        .map(|_| {
            let s = connect(&addr);
            (&s).write_all(b"@01EA").unwrap();
            s
        })
        .collect();
    std::thread::sleep(Duration::from_millis(1200));
    // On probation with half a frame: closed after a second, nobody displaced.
    let slow = connect(&addr);
    (&slow).write_all(b"@01").unwrap();
    let mut got = Vec::new();
    (&slow).read_to_end(&mut got).expect("closed on probation");
    let line = serve.expect_line("sent no whole request in time", WAIT);
    assert!(line.contains("over --max-clients"), "{line}");
    assert!(
        !serve.stdout().contains("made room"),
        "no member made room for it:\n{}",
        serve.stdout()
    );
    drop(members);

    // Forty slowloris clients, each holding its half frame until the server
    // closes it, and back 10 ms later.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let attackers: Vec<_> = (0..40)
        .map(|_| {
            let (addr, stop) = (addr.clone(), stop.clone());
            std::thread::spawn(move || {
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    if let Ok(s) = TcpStream::connect(&addr) {
                        let _ = (&s).write_all(b"@01EA");
                        s.set_read_timeout(Some(Duration::from_millis(200)))
                            .unwrap();
                        let mut sink = [0u8; 16];
                        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                            match (&s).read(&mut sink) {
                                Ok(0) => break,
                                Err(e) if e.kind() != std::io::ErrorKind::WouldBlock => break,
                                _ => {}
                            }
                        }
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(1500));
    let served = (0..10)
        .filter(|_| {
            std::thread::sleep(Duration::from_millis(200));
            meb_ask(&addr).is_ok_and(|l| l.starts_with("@01EA0001"))
        })
        .count();
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    for a in attackers {
        a.join().unwrap();
    }
    // What the server said, for a failure's message.
    let out = serve.stdout();
    let said: Vec<String> = ["made room", "none quiet", "in time", "newer clients"]
        .iter()
        .map(|what| {
            format!(
                "{what}: {}",
                out.lines().filter(|l| l.contains(what)).count()
            )
        })
        .collect();
    assert!(
        served >= 8,
        "real clients served among slowloris: {served} of 10 ({said:?})"
    );
}
