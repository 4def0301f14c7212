//! The 8-byte Modbus codec against the frames of tests/vectors/modbus8.jsonl
//! (copied from the Controller_network project's terminal output and scope captures), and
//! the stream decoder's silence rule with explicit simulated time.

use protocols::crc::crc16_modbus;
use protocols::modbus::Exception;
use protocols::modbus8::{CrcOrder, Modbus8Decoder, Modbus8Error, Modbus8Frame, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};
use serde::Deserialize;

const VECTORS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/vectors/modbus8.jsonl");

#[derive(Debug, Deserialize)]
struct Vector {
    frame_hex: String,
    valid: bool,
    valid_standard_order: bool,
    note: String,
    id: Option<u8>,
    fc: Option<u8>,
    addr: Option<u16>,
    value: Option<u16>,
}

impl Vector {
    fn bytes(&self) -> Vec<u8> {
        (0..self.frame_hex.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&self.frame_hex[i..i + 2], 16).unwrap())
            .collect()
    }

    fn expected(&self) -> Modbus8Repr {
        Modbus8Repr {
            id: self.id.expect("valid vector has id"),
            function: self.fc.expect("valid vector has fc"),
            addr: self.addr.expect("valid vector has addr"),
            value: self.value.expect("valid vector has value"),
        }
    }
}

fn vectors() -> Vec<Vector> {
    let text = std::fs::read_to_string(VECTORS).expect("read modbus8.jsonl");
    let vectors: Vec<Vector> = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l}: {e}")))
        .collect();
    assert!(
        vectors.len() >= 15,
        "vectors file shrank: {}",
        vectors.len()
    );
    vectors
}

/// Checks one vector under one CRC order: valid frames parse to the stated
/// fields and re-emit to the same bytes; invalid ones are a bad CRC carrying
/// the received and calculated values.
fn check(v: &Vector, order: CrcOrder, valid: bool) {
    let bytes = v.bytes();
    let result = Modbus8Repr::parse(&bytes, order);
    if valid {
        let frame = result.unwrap_or_else(|e| panic!("{} ({order:?}): {e}", v.note));
        assert_eq!(frame, v.expected(), "{}", v.note);
        assert_eq!(frame.to_bytes(order).as_slice(), bytes, "{}", v.note);
        let mut out = [0u8; 8];
        assert_eq!(frame.emit(&mut out, order), Ok(8));
        assert_eq!(out.as_slice(), bytes);
    } else {
        let received = match order {
            CrcOrder::HighFirst => u16::from_be_bytes([bytes[6], bytes[7]]),
            CrcOrder::LowFirst => u16::from_le_bytes([bytes[6], bytes[7]]),
        };
        assert_eq!(
            result,
            Err(Modbus8Error::BadCrc {
                received,
                calculated: crc16_modbus(&bytes[..6])
            }),
            "{} ({order:?})",
            v.note
        );
    }
}

#[test]
fn every_vector_under_the_default_order() {
    for v in vectors() {
        check(&v, CrcOrder::default(), v.valid);
    }
}

#[test]
fn every_vector_under_the_standard_order() {
    for v in vectors() {
        check(&v, CrcOrder::LowFirst, v.valid_standard_order);
    }
}

#[test]
fn the_projects_crc_error_message() {
    let v = vectors()
        .into_iter()
        .find(|v| v.frame_hex == "010600010080aada")
        .expect("the project's bad-CRC vector");
    let err = Modbus8Repr::parse(&v.bytes(), CrcOrder::HighFirst).unwrap_err();
    assert_eq!(
        err.to_string(),
        "CRC error: received 0xaada, calculated 0xaad9"
    );
}

#[test]
fn exception_vectors_are_replies_not_errors() {
    let codes: Vec<_> = vectors()
        .iter()
        .filter(|v| v.valid && v.fc.is_some_and(|fc| fc & 0x80 != 0))
        .map(|v| {
            Modbus8Repr::parse(&v.bytes(), CrcOrder::HighFirst)
                .unwrap()
                .reply()
        })
        .collect();
    assert_eq!(
        codes,
        [
            Err(Exception::IllegalDataValue),
            Err(Exception::IllegalDataAddress),
            Err(Exception::IllegalFunction)
        ]
    );
}

const BAUD: u32 = 115_200;

fn char_time() -> SimDuration {
    SimDuration::bit_times(10, BAUD)
}

/// The value of a frame the decoder yields.
fn value(item: Result<Modbus8Frame<&[u8]>, Modbus8Error>) -> Result<Modbus8Repr, Modbus8Error> {
    item.map(|frame| Modbus8Repr::from_frame(&frame))
}

/// Feeds `bytes` one per character time starting at `start`, as a serial line
/// delivers them, collecting what the decoder yields; returns the time after
/// the last byte.
fn feed_bytewise(
    decoder: &mut Modbus8Decoder,
    start: SimTime,
    bytes: &[u8],
    out: &mut Vec<Result<Modbus8Repr, Modbus8Error>>,
) -> SimTime {
    let mut now = start;
    for byte in bytes {
        now += char_time();
        let mut input = std::slice::from_ref(byte);
        while let Some(item) = decoder.decode(now, &mut input) {
            out.push(value(item));
        }
    }
    now
}

fn valid_frames() -> Vec<(Vec<u8>, Modbus8Repr)> {
    vectors()
        .iter()
        .filter(|v| v.valid)
        .map(|v| (v.bytes(), v.expected()))
        .collect()
}

#[test]
fn all_valid_vectors_through_the_decoder_byte_by_byte() {
    let mut decoder = Modbus8Decoder::for_baud(CrcOrder::HighFirst, BAUD);
    let mut out = Vec::new();
    let mut now = SimTime::ZERO;
    let frames = valid_frames();
    for (bytes, _) in &frames {
        now = feed_bytewise(&mut decoder, now, bytes, &mut out);
        // 3.5 character times between frames, as a master must leave.
        now += SimDuration::bit_times(35, BAUD);
    }
    let expected: Vec<_> = frames.into_iter().map(|(_, f)| Ok(f)).collect();
    assert_eq!(out, expected);
    assert_eq!(decoder.drops().total_bytes(), 0);
}

#[test]
fn a_partial_frame_followed_by_silence_is_dropped() {
    let frames = valid_frames();
    let (first, _) = &frames[0];
    let (second, second_frame) = &frames[1];
    let mut decoder = Modbus8Decoder::for_baud(CrcOrder::HighFirst, BAUD);
    let mut out = Vec::new();
    // Five bytes of a frame, then the line goes quiet.
    let now = feed_bytewise(&mut decoder, SimTime::ZERO, &first[..5], &mut out);
    let due = decoder
        .poll_timeout()
        .expect("a partial frame waits for silence");
    assert_eq!(due, now + SimDuration::bit_times(35, BAUD));
    // Just before the silence is complete nothing is dropped...
    decoder.handle_timeout(SimTime(due.0 - 1));
    assert_eq!(decoder.pending(), 5);
    // ...at the silence the partial frame goes.
    decoder.handle_timeout(due);
    assert_eq!(decoder.pending(), 0);
    assert_eq!(decoder.drops().timed_out.events, 1);
    assert_eq!(decoder.drops().timed_out.bytes, 5);
    assert_eq!(decoder.poll_timeout(), None);
    // The next whole frame is read correctly.
    feed_bytewise(&mut decoder, due, second, &mut out);
    assert_eq!(out, [Ok(*second_frame)]);
}

#[test]
fn silence_is_also_seen_when_the_next_chunk_arrives() {
    // An engine that never calls handle_timeout still gets the rule applied
    // from the next chunk's arrival time.
    let frames = valid_frames();
    let mut decoder = Modbus8Decoder::for_pty(CrcOrder::HighFirst);
    let mut input = &frames[0].0[..3];
    assert!(decoder.decode(SimTime::ZERO, &mut input).is_none());
    let later = SimTime::ZERO + SimDuration::from_millis(5);
    let mut input = &frames[1].0[..];
    assert_eq!(
        decoder.decode(later, &mut input).map(value),
        Some(Ok(frames[1].1))
    );
    assert_eq!(decoder.drops().timed_out.bytes, 3);
}

#[test]
fn a_stray_byte_does_not_misalign_later_frames() {
    let frames = valid_frames();
    let mut decoder = Modbus8Decoder::for_baud(CrcOrder::HighFirst, BAUD);
    let mut out = Vec::new();
    // A noise byte right before a frame: the first eight bytes fail the CRC,
    // the ninth is thrown away up to the silence.
    let mut line = vec![0x55];
    line.extend(&frames[0].0);
    let mut now = feed_bytewise(&mut decoder, SimTime::ZERO, &line, &mut out);
    assert_eq!(out.len(), 1);
    assert!(
        matches!(out[0], Err(Modbus8Error::BadCrc { .. })),
        "{out:?}"
    );
    out.clear();
    for (bytes, _) in &frames[1..4] {
        now += SimDuration::bit_times(35, BAUD);
        now = feed_bytewise(&mut decoder, now, bytes, &mut out);
    }
    let expected: Vec<_> = frames[1..4].iter().map(|(_, f)| Ok(*f)).collect();
    assert_eq!(out, expected);
    let drops = decoder.drops();
    assert_eq!((drops.bad_check.events, drops.bad_check.bytes), (1, 8));
    assert_eq!(
        (drops.after_bad_frame.events, drops.after_bad_frame.bytes),
        (1, 1)
    );
}

#[test]
fn a_stray_byte_before_a_silence_is_a_timed_out_partial() {
    let frames = valid_frames();
    let mut decoder = Modbus8Decoder::for_baud(CrcOrder::HighFirst, BAUD);
    let mut out = Vec::new();
    let mut now = feed_bytewise(&mut decoder, SimTime::ZERO, &[0xFF], &mut out);
    now += SimDuration::bit_times(35, BAUD);
    feed_bytewise(&mut decoder, now, &frames[2].0, &mut out);
    assert_eq!(out, [Ok(frames[2].1)]);
    assert_eq!(decoder.drops().timed_out.bytes, 1);
}

#[test]
fn back_to_back_frames_on_a_pty_need_no_gap() {
    // A pty delivers a burst at once: frames are cut every eight bytes.
    let frames = valid_frames();
    let burst: Vec<u8> = frames.iter().flat_map(|(b, _)| b.clone()).collect();
    let mut decoder = Modbus8Decoder::for_pty(CrcOrder::HighFirst);
    let mut input = &burst[..];
    let mut out = Vec::new();
    while let Some(item) = decoder.decode(SimTime::ZERO, &mut input) {
        out.push(value(item).unwrap());
    }
    let expected: Vec<_> = frames.iter().map(|(_, f)| *f).collect();
    assert_eq!(out, expected);
}

#[test]
fn the_standard_order_decoder_reads_the_low_first_vector() {
    let v = vectors()
        .into_iter()
        .find(|v| v.valid_standard_order)
        .expect("a standard-order vector");
    let mut decoder = Modbus8Decoder::for_pty(CrcOrder::LowFirst);
    assert_eq!(decoder.crc_order(), CrcOrder::LowFirst);
    let bytes = v.bytes();
    let mut input = &bytes[..];
    assert_eq!(
        decoder.decode(SimTime::ZERO, &mut input).map(value),
        Some(Ok(v.expected()))
    );
}
