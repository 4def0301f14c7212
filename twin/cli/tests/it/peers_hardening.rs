//! What a careless or hostile client must not break in `twin serve`: a
//! client pipelining requests gets every reply, in order; a Modbus TCP
//! header that cannot be valid closes its connection at once, saying why; a
//! quiet connection is closed after `--idle-timeout`, and a newcomer to a
//! full listener takes the place of a client quiet longer than
//! `--make-room-after`.

use crate::peers;

use peers::Serve;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(10);

fn meb_frame(body: &str) -> Vec<u8> {
    let fcs = body.bytes().fold(0u8, |x, b| x ^ b);
    format!("{body}{fcs:02X}*\n").into_bytes()
}

fn modbus_read_inputs(tid: u16) -> [u8; 12] {
    let t = tid.to_be_bytes();
    [t[0], t[1], 0, 0, 0, 6, 1, 4, 0, 0, 0, 10]
}

fn connect(addr: &str) -> TcpStream {
    let s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    s
}

/// `requests` MEB requests in one write, for addresses in turn, get as many
/// replies, in their order.
fn meb_pipelined(addr: &str, requests: usize) {
    let s = connect(addr);
    let mut burst = Vec::new();
    for i in 0..requests {
        burst.extend(meb_frame(&format!("@01EA0{}01", i % 6)));
    }
    (&s).write_all(&burst).unwrap();
    let mut lines = BufReader::new(&s);
    for i in 0..requests {
        let mut line = String::new();
        lines
            .read_line(&mut line)
            .unwrap_or_else(|e| panic!("reply {i} of {requests} on {addr}: {e}"));
        assert!(
            line.starts_with(&format!("@01EA0{}01", i % 6)),
            "reply {i} of {requests}, in order: {line:?}"
        );
    }
}

#[test]
fn pipelined_requests_get_every_reply_in_order() {
    let serve = Serve::start(&[
        "--quiet",
        "--meb",
        "tcp://127.0.0.1:0",
        "--meb",
        "tcp://127.0.0.1:0?pace&turnaround_ms=1",
        "--modbus",
        "tcp://127.0.0.1:0",
    ]);
    let meb: Vec<String> = serve
        .links
        .iter()
        .filter(|l| l.protocol == "meb")
        .map(|l| crate::support::host_port(&l.address).to_string())
        .collect();
    meb_pipelined(&meb[0], 100);
    // Paced replies wait for their wire time: the connection is not read
    // while 64 are owed, and none is lost.
    meb_pipelined(&meb[1], 300);

    let mut s = connect(&serve.tcp("modbus-tcp"));
    let burst: Vec<u8> = (1..=100).flat_map(modbus_read_inputs).collect();
    s.write_all(&burst).unwrap();
    for tid in 1..=100u16 {
        let mut reply = [0u8; 29];
        s.read_exact(&mut reply)
            .unwrap_or_else(|e| panic!("Modbus TCP reply {tid} of 100: {e}"));
        assert_eq!(reply[..2], tid.to_be_bytes(), "replies in order");
        assert_eq!(reply[7], 4, "an FC04 reply: {reply:02x?}");
    }
}

#[test]
fn a_modbus_tcp_header_that_cannot_be_valid_closes_the_connection() {
    let serve = Serve::start(&["--modbus", "tcp://127.0.0.1:0"]);
    let addr = serve.tcp("modbus-tcp");
    let good = modbus_read_inputs(7);
    // Lengths 0, 1, 255 and 260; protocol ids 1, 2, 0x8000 and 0xFFFF.
    let bad: [(usize, [u8; 2]); 8] = [
        (4, [0, 0]),
        (4, [0, 1]),
        (4, [0, 255]),
        (4, [1, 4]),
        (2, [0, 1]),
        (2, [0, 2]),
        (2, [0x80, 0]),
        (2, [0xFF, 0xFF]),
    ];
    for (at, field) in bad {
        let mut header = good;
        header[at..at + 2].copy_from_slice(&field);
        let mut s = connect(&addr);
        let mut burst = header.to_vec();
        burst.extend(good);
        s.write_all(&burst).unwrap();
        let mut got = Vec::new();
        let started = std::time::Instant::now();
        s.read_to_end(&mut got)
            .expect("the server closes the connection");
        assert!(got.is_empty(), "no reply after a bad header: {got:02x?}");
        assert!(
            started.elapsed() < Duration::from_secs(3),
            "closed at once, not after the partial-frame timeout: {:?}",
            started.elapsed()
        );
    }
    let line = serve.expect_line("cannot be valid", WAIT);
    assert!(line.contains("closed by the twin"), "{line}");
    // A good client is served as before.
    let mut s = connect(&addr);
    s.write_all(&good).unwrap();
    let mut reply = [0u8; 29];
    s.read_exact(&mut reply).unwrap();
    assert_eq!(reply[7], 4);
}

#[test]
fn quiet_connections_time_out_and_make_room_for_newcomers() {
    let serve = Serve::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--idle-timeout",
        "0.5",
    ]);
    // --idle-timeout: a client that sends nothing is closed.
    let mut quiet = connect(&serve.tcp("meb"));
    let mut got = Vec::new();
    quiet.read_to_end(&mut got).expect("closed for being idle");
    let line = serve.expect_line("longer than --idle-timeout", WAIT);
    assert!(line.contains("idle for"), "{line}");
    drop(serve);

    let serve = Serve::start(&[
        "--modbus",
        "tcp://127.0.0.1:0",
        "--max-clients",
        "2",
        "--make-room-after",
        "1",
    ]);
    let addr = serve.tcp("modbus-tcp");
    let ask = |s: &mut TcpStream, tid: u16| -> std::io::Result<()> {
        s.write_all(&modbus_read_inputs(tid))?;
        let mut reply = [0u8; 29];
        s.read_exact(&mut reply)?;
        assert_eq!(reply[..2], tid.to_be_bytes());
        Ok(())
    };
    // A burst of connect-and-close leaves no place taken.
    for _ in 0..200 {
        drop(TcpStream::connect(&addr).unwrap());
    }
    let mut first = connect(&addr);
    ask(&mut first, 1).expect("served right after the burst");
    let mut second = connect(&addr);
    ask(&mut second, 2).expect("the second place");
    std::thread::sleep(Duration::from_millis(1500));
    // Both have been quiet for 1.5 s; `second` asks again, so `first` is
    // the quietest and makes room.
    ask(&mut second, 3).unwrap();
    let mut third = connect(&addr);
    ask(&mut third, 4).expect("the newcomer is served");
    let mut got = Vec::new();
    first.read_to_end(&mut got).expect("the quietest is closed");
    let line = serve.expect_line("made room for a new client", WAIT);
    assert!(line.contains("--max-clients"), "{line}");
    ask(&mut second, 5).expect("the other client keeps its place");
}

/// Slowloris: every place on the listener held by a frame that never ends.
/// A newcomer takes the place of the one held longest (past a second), so
/// the attack locks nobody out; the clients it displaces were never served.
#[test]
fn partial_frames_that_never_end_do_not_lock_newcomers_out() {
    let serve = Serve::start(&["--meb", "tcp://127.0.0.1:0", "--max-clients", "4"]);
    let addr = serve.tcp("meb");
    let holders: Vec<TcpStream> = (0..4)
        .map(|_| {
            let s = connect(&addr);
            (&s).write_all(b"@01EA").unwrap();
            s
        })
        .collect();
    std::thread::sleep(Duration::from_millis(1200));
    for i in 0..6 {
        let s = connect(&addr);
        (&s).write_all(&meb_frame("@01EA0001")).unwrap();
        let mut line = String::new();
        BufReader::new(&s)
            .read_line(&mut line)
            .unwrap_or_else(|e| panic!("newcomer {i}: {e}"));
        assert!(line.starts_with("@01EA0001"), "newcomer {i}: {line:?}");
        // Its place is kept: it is no partial frame.
        std::thread::sleep(Duration::from_millis(50));
    }
    let line = serve.expect_line("held a partial frame for", WAIT);
    assert!(line.contains("made room for a new client"), "{line}");
    drop(holders);
}
