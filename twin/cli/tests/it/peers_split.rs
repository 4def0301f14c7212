//! Serial frames as real links deliver them to `twin serve`: in pieces with
//! gaps (a USB adapter holds bytes for milliseconds; the Controller_network
//! master writes its 8 bytes as it likes) and back to back (a master that
//! pipelines). On a pseudo-terminal a frame ends after 5 ms of silence, as
//! the protocol pages say; every frame must be answered, in order.

use crate::peers;

use peers::{DirectPty, Serve, readable};
use protocols::crc::crc16_modbus;
use std::fs::File;
use std::io::{Read, Write};
use std::time::{Duration, Instant};

/// Longer than a loaded machine takes to hand a reply over, with room.
const REPLY_WAIT: Duration = Duration::from_secs(3);
/// A piece that reached the pty later than this after the one before may
/// rightly have ended its frame (the silence is 5 ms): the test thread was
/// held up, not the server wrong, and that request is not counted.
const HELD_UP: Duration = Duration::from_millis(4);

/// Exactly `n` bytes, or what came before a wait of `wait` ran out.
fn read_n(link: &mut File, n: usize, wait: Duration) -> Result<Vec<u8>, Vec<u8>> {
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    while got.len() < n {
        if !readable(link, wait) {
            return Err(got);
        }
        let k = link.read(&mut buf[..(n - got.len()).min(4096)]).unwrap();
        got.extend_from_slice(&buf[..k]);
    }
    Ok(got)
}

/// Writes `frame` in `pieces`, `pause` apart; the longest gap seen between
/// two writes.
fn write_in_pieces(port: &mut File, frame: &[u8], pieces: &[usize], pause: Duration) -> Duration {
    let mut longest = Duration::ZERO;
    let mut at = 0;
    let mut last: Option<Instant> = None;
    for &len in pieces {
        if last.is_some() {
            std::thread::sleep(pause);
        }
        let now = Instant::now();
        if let Some(l) = last {
            longest = longest.max(now - l);
        }
        port.write_all(&frame[at..at + len]).unwrap();
        last = Some(now);
        at += len;
    }
    longest
}

/// The Controller_network motor node's "read control state" (CRC high byte
/// first, as its firmware sends it).
fn modbus8_read_state() -> Vec<u8> {
    let mut f = vec![1, 3, 0, 1, 0, 0];
    f.extend_from_slice(&crc16_modbus(&f).to_be_bytes());
    f
}

fn rtu_read_inputs(first: u16, count: u16) -> Vec<u8> {
    let a = first.to_be_bytes();
    let n = count.to_be_bytes();
    let mut f = vec![1, 4, a[0], a[1], n[0], n[1]];
    f.extend_from_slice(&crc16_modbus(&f).to_le_bytes());
    f
}

/// `tries` requests, each written in `pieces` `pause` apart, and their
/// replies: (answered, counted) where requests whose pieces were held up
/// past [`HELD_UP`] are not counted.
fn split_requests(
    port: &mut File,
    tries: usize,
    pieces: &[usize],
    pause: Duration,
) -> (usize, usize) {
    let (mut answered, mut counted) = (0, 0);
    for _ in 0..tries {
        let gap = write_in_pieces(port, &modbus8_read_state(), pieces, pause);
        let reply = read_n(
            port,
            8,
            if gap > HELD_UP {
                Duration::from_millis(200)
            } else {
                REPLY_WAIT
            },
        );
        if gap > HELD_UP {
            continue;
        }
        counted += 1;
        if let Ok(r) = reply {
            assert_eq!(&r[..4], &[1, 3, 0, 1], "a read-state reply: {r:02x?}");
            assert_eq!(crc16_modbus(&r[..6]).to_be_bytes(), [r[6], r[7]]);
            answered += 1;
        }
    }
    (answered, counted)
}

#[test]
fn a_modbus8_frame_in_pieces_is_answered() {
    // A server held up past the 5 ms silence ends a frame between two
    // pieces: beside other tests' servers on two cores that happened.
    let _cores = crate::support::cores_to_myself();
    let mut m8 = DirectPty::new();
    let mut serve = Serve::start(&["--quiet", "--modbus8", m8.path.to_str().unwrap()]);
    let port = &mut m8.master;
    // Half and half, 1 ms apart.
    let (answered, counted) = split_requests(port, 40, &[4, 4], Duration::from_millis(1));
    assert!(
        counted >= 30,
        "the test thread was held up too often: {counted} of 40"
    );
    // The server's own reads can be held up too (its carrier descheduled
    // past the 5 ms silence, the pieces then read with a gap between them
    // that the line never had): one such cut in a run is the machine, more
    // would be the framing.
    assert!(
        answered + 1 >= counted,
        "4 + 4 bytes 1 ms apart: {answered} of {counted} answered"
    );
    // A byte every 0.5 ms.
    let (answered, counted) = split_requests(port, 20, &[1; 8], Duration::from_micros(500));
    assert!(
        counted >= 10,
        "the test thread was held up too often: {counted} of 20"
    );
    assert!(
        answered + 1 >= counted,
        "one byte per 0.5 ms: {answered} of {counted} answered"
    );
    serve.assert_running();
}

#[test]
fn pipelined_rtu_requests_on_a_pty_get_every_reply_in_order() {
    let mut rtu = DirectPty::new();
    let mut serve = Serve::start(&["--quiet", "--modbus-rtu", rtu.path.to_str().unwrap()]);
    let port = &mut rtu.master;
    // 100 requests in one write, for 1 to 4 registers in turn: each reply's
    // length says which request it answers.
    let count = |i: usize| 1 + (i % 4) as u16;
    let burst: Vec<u8> = (0..100)
        .flat_map(|i| rtu_read_inputs(0, count(i)))
        .collect();
    port.write_all(&burst).unwrap();
    let expected: usize = (0..100).map(|i| 5 + 2 * count(i) as usize).sum();
    let replies = read_n(port, expected, REPLY_WAIT)
        .unwrap_or_else(|got| panic!("{} of {expected} bytes", got.len()));
    let mut rest = &replies[..];
    for i in 0..100 {
        let len = 5 + 2 * count(i) as usize;
        let (r, after) = rest.split_at(len);
        assert_eq!(
            &r[..3],
            &[1, 4, 2 * count(i) as u8],
            "reply {i}, in order: {r:02x?}"
        );
        assert_eq!(
            crc16_modbus(&r[..len - 2]).to_le_bytes(),
            [r[len - 2], r[len - 1]],
            "reply {i}"
        );
        rest = after;
    }
    assert!(
        read_n(port, 1, Duration::from_millis(200)).is_err(),
        "no more than 100 replies"
    );
    serve.assert_running();
}
