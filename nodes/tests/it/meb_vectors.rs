//! Every frame of `vectors/meb.jsonl` parses to its stated fields or fails with
//! its stated error kind, and every valid one re-emits canonically.

use protocols::meb::{
    MEB_MAX_FRAME_LEN, MebCmd, MebDecodeError, MebDecoder, MebError, MebErrorCode, MebFrame,
    MebRepr, MebShape,
};
use protocols::time::{SimDuration, SimTime};
use serde::Deserialize;

const VECTORS: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/vectors/meb.jsonl"
));

#[derive(Debug, Deserialize)]
struct Vector {
    frame: String,
    valid: bool,
    id: Option<u8>,
    cmd: Option<String>,
    addr: Option<u8>,
    cnt: Option<u8>,
    data: Option<Vec<u16>>,
    error: Option<String>,
}

fn vectors() -> Vec<Vector> {
    VECTORS
        .lines()
        .filter(|line| !line.trim().is_empty())
        .map(|line| serde_json::from_str(line).expect("vector line is JSON"))
        .collect()
}

/// The canonical form of a frame: upper-case hex, `*\n`, FCS recomputed.
fn canonical(frame: &str) -> Vec<u8> {
    let text = frame.trim_end_matches('\n').trim_end_matches('\r');
    let text = text.strip_suffix('*').expect("frame ends with *");
    with_fcs(&text[..text.len() - 2].to_ascii_uppercase())
}

/// `body` (from `@` to the last byte before FCS) completed with its FCS and `*\n`.
fn with_fcs(body: &str) -> Vec<u8> {
    let fcs = body.bytes().fold(0u8, |acc, b| acc ^ b);
    format!("{body}{fcs:02X}*\n").into_bytes()
}

#[test]
fn every_vector_parses_or_fails_as_stated() {
    let vectors = vectors();
    assert!(vectors.len() >= 23, "only {} vectors", vectors.len());
    let mut buf = [0u8; MEB_MAX_FRAME_LEN];
    for v in &vectors {
        let bytes = v.frame.as_bytes();
        let parsed = MebRepr::parse(bytes);
        if v.valid {
            let repr = parsed.unwrap_or_else(|e| panic!("{:?}: {e}", v.frame));
            assert_eq!(Some(repr.id), v.id, "{:?}", v.frame);
            assert_eq!(Some(repr.cmd.to_string()), v.cmd, "{:?}", v.frame);
            assert_eq!(Some(repr.addr), v.addr, "{:?}", v.frame);
            assert_eq!(Some(repr.cnt), v.cnt, "{:?}", v.frame);
            assert_eq!(Some(repr.data.to_vec()), v.data, "{:?}", v.frame);
            let len = repr.emit(&mut buf).expect("emit");
            assert_eq!(&buf[..len], canonical(&v.frame).as_slice(), "{:?}", v.frame);
            // The view agrees with the value.
            let view = MebFrame::new_checked(bytes).expect("view");
            assert_eq!(MebRepr::from_frame(&view), repr);
            assert_eq!(view.words().count(), repr.data.len());
        } else {
            let error = parsed.expect_err(&v.frame);
            assert_eq!(Some(error.name()), v.error.as_deref(), "{:?}", v.frame);
        }
    }
}

#[test]
fn canonical_frames_re_emit_byte_for_byte() {
    let mut buf = [0u8; MEB_MAX_FRAME_LEN];
    let mut canonical_count = 0;
    for v in vectors().iter().filter(|v| v.valid) {
        if canonical(&v.frame) == v.frame.as_bytes() {
            canonical_count += 1;
            let len = MebRepr::parse(v.frame.as_bytes())
                .unwrap()
                .emit(&mut buf)
                .unwrap();
            assert_eq!(&buf[..len], v.frame.as_bytes());
        }
    }
    // Two valid vectors are deliberately non-canonical (lower case, CR LF).
    assert_eq!(canonical_count, 11);
}

#[test]
fn every_error_kind_has_its_own_name() {
    let names: std::collections::HashSet<_> = MebError::ALL.iter().map(|e| e.name()).collect();
    assert_eq!(names.len(), MebError::ALL.len());
    // The kinds the vectors do not exercise, each in a frame whose FCS is right.
    assert_eq!(
        MebRepr::parse(&with_fcs("@01E10003")),
        Err(MebError::BadCmd)
    );
    assert_eq!(
        MebRepr::parse(&with_fcs("@01SA00010G00")),
        Err(MebError::BadData)
    );
    assert_eq!(MebRepr::parse(b"@01EA0003Z6*\n"), Err(MebError::BadFcs));
    assert_eq!(MebRepr::parse(b""), Err(MebError::NoBof));
}

#[test]
fn reply_shaped_frames_are_classified() {
    let shape = |frame: &[u8]| MebRepr::parse(frame).unwrap().shape();
    assert_eq!(shape(b"@01EA000346*\n"), MebShape::Request);
    assert_eq!(shape(b"@01EA00030A3C012307D034*\n"), MebShape::ReadReply);
    assert_eq!(shape(b"@01SA000108005A*\n"), MebShape::Request);
    assert_eq!(shape(b"@01SA000152*\n"), MebShape::WriteAck);
    assert_eq!(shape(b"@01ER1001000254*\n"), MebShape::ErrorReply);
    // A write with CNT = 00 is a request (answered with error 03), and so is an
    // unknown or lower-case command (answered with error 01).
    let cnt0 = MebRepr {
        cnt: 0,
        ..MebRepr::parse(b"@01SA000152*\n").unwrap()
    };
    assert_eq!(cnt0.shape(), MebShape::Request);
    let lower = MebRepr {
        cmd: MebCmd::new(*b"er").unwrap(),
        ..cnt0
    };
    assert_eq!(lower.shape(), MebShape::Request);
    assert!(lower.cmd.block().is_none());
    assert!(MebShape::WriteAck.is_reply() && !MebShape::Request.is_reply());
}

#[test]
fn error_reply_matches_the_vector() {
    let reply = MebRepr::error_reply(1, 0x10, MebErrorCode::IllegalAddress);
    let mut buf = [0u8; 32];
    let len = reply.emit(&mut buf).unwrap();
    assert_eq!(&buf[..len], b"@01ER1001000254*\n");
    assert_eq!(reply.error_code(), Some(MebErrorCode::IllegalAddress));
    for code in 1..=4 {
        assert_eq!(
            MebErrorCode::from_word(code).map(MebErrorCode::word),
            Some(code)
        );
    }
    assert_eq!(MebErrorCode::from_word(5), None);
    let write = MebRepr::parse(b"@01SA000108005A*\n").unwrap();
    let len = write.acknowledgement().emit(&mut buf).unwrap();
    assert_eq!(&buf[..len], b"@01SA000152*\n");
}

#[test]
fn emit_rejects_what_it_cannot_write() {
    let read = MebRepr::parse(b"@01EA000346*\n").unwrap();
    let mut small = [0u8; 12];
    assert_eq!(
        read.emit(&mut small),
        Err(protocols::meb::MebEmitError::BufferTooSmall { needed: 13 })
    );
    let mut buf = [0u8; 64];
    assert!(MebRepr { id: 100, ..read }.emit(&mut buf).is_err());
    assert!(MebRepr { cnt: 100, ..read }.emit(&mut buf).is_err());
    let reply = MebRepr::parse(b"@01EA00030A3C012307D034*\n").unwrap();
    assert!(MebRepr { cnt: 2, ..reply }.emit(&mut buf).is_err());
}

/// The spec's resync example is answered once, for the second frame.
#[test]
fn a_new_bof_resynchronises() {
    let mut decoder = MebDecoder::new();
    let events: Vec<_> = decoder
        .frames(SimTime::ZERO, b"@01EA@01EA000346*\n")
        .collect();
    assert_eq!(events.len(), 2);
    assert_eq!(events[0], Err(MebDecodeError::Interrupted));
    let frame = events[1].expect("second frame");
    assert_eq!((frame.id, frame.cmd, frame.cnt), (1, MebCmd::EA, 3));
    assert_eq!(decoder.stats().frames, 1);
    assert_eq!(decoder.stats().interrupted, 1);
}

#[test]
fn decoder_reports_every_vector_like_parse() {
    let mut decoder = MebDecoder::new();
    for v in vectors() {
        let events: Vec<_> = decoder.frames(SimTime::ZERO, v.frame.as_bytes()).collect();
        if v.valid {
            assert_eq!(
                events,
                vec![MebRepr::parse(v.frame.as_bytes()).map_err(Into::into)]
            );
        } else if v.error.as_deref() == Some("no_bof") {
            // Without its `@` the decoder sees noise, not a frame.
            assert!(events.is_empty());
        } else {
            let kind = events
                .last()
                .copied()
                .expect("an event")
                .expect_err(&v.frame);
            assert_eq!(
                kind,
                MebDecodeError::Malformed(MebRepr::parse(v.frame.as_bytes()).unwrap_err())
            );
        }
        assert_eq!(decoder.buffered(), 0, "{:?}", v.frame);
    }
    let stats = decoder.stats();
    assert_eq!(stats.frames, 13);
    assert_eq!(stats.malformed(MebError::BadDataLength), 2);
    assert_eq!(stats.malformed(MebError::TooLong), 1);
    assert_eq!(
        stats.noise_bytes,
        12 + 6,
        "the no_bof line and the too-long tail"
    );
}

#[test]
fn too_long_is_decided_at_byte_411() {
    let mut decoder = MebDecoder::new();
    let mut long = vec![b'@'];
    long.extend(std::iter::repeat_n(b'0', MEB_MAX_FRAME_LEN - 1));
    let (used, event) = decoder.push(SimTime::ZERO, &long);
    assert_eq!((used, event.is_none()), (MEB_MAX_FRAME_LEN, true));
    let (used, event) = decoder.push(SimTime::ZERO, b"0@01EA000346*\n");
    assert_eq!(used, 1);
    assert_eq!(
        event.map(|e| e.err()),
        Some(Some(MebDecodeError::Malformed(MebError::TooLong)))
    );
    let frames: Vec<_> = decoder.frames(SimTime::ZERO, b"@01EA000346*\n").collect();
    assert!(matches!(frames.as_slice(), [Ok(_)]));
}

/// The longest legal frame (99 words, `*\r\n`) is 410 bytes; one more byte
/// before the terminator makes the 411th byte a `\n` and the frame too long.
#[test]
fn the_410_byte_boundary() {
    let longest = vectors()
        .into_iter()
        .find(|v| v.cnt == Some(99))
        .expect("the 99-word vector")
        .frame
        .replace("*\n", "*\r\n");
    assert_eq!(longest.len(), MEB_MAX_FRAME_LEN);
    let one_more = longest.replace("*\r\n", "*\r\r\n");
    assert_eq!(MebRepr::parse(one_more.as_bytes()), Err(MebError::TooLong));
    for chunk in [1, 7, MEB_MAX_FRAME_LEN, MEB_MAX_FRAME_LEN + 1] {
        let mut decoder = MebDecoder::new();
        let mut events = Vec::new();
        for piece in [longest.as_bytes(), one_more.as_bytes()]
            .concat()
            .chunks(chunk)
        {
            events.extend(decoder.frames(SimTime::ZERO, piece));
        }
        assert_eq!(events.len(), 2, "chunks of {chunk}");
        assert_eq!(events[0].map(|f| f.cnt), Ok(99), "chunks of {chunk}");
        assert_eq!(
            events[1],
            Err(MebDecodeError::Malformed(MebError::TooLong)),
            "chunks of {chunk}"
        );
        assert_eq!((decoder.stats().noise_bytes, decoder.buffered()), (0, 0));
    }
}

#[test]
fn partial_frames_expire() {
    let timeout = SimDuration::from_secs(5);
    let mut decoder = MebDecoder::with_partial_timeout(timeout);
    assert_eq!(decoder.poll_timeout(), None);
    let t0 = SimTime::ZERO + SimDuration::from_millis(3);
    assert_eq!(decoder.frames(t0, b"xx@01EA00").count(), 0);
    assert_eq!(decoder.poll_timeout(), Some(t0 + timeout));
    assert!(!decoder.handle_timeout(t0 + SimDuration(timeout.0 - 1)));
    assert!(decoder.handle_timeout(t0 + timeout));
    assert_eq!((decoder.buffered(), decoder.poll_timeout()), (0, None));
    assert_eq!(decoder.stats().timed_out, 1);
    assert_eq!(decoder.stats().dropped_frames(), 1);
    // The rest of the expired frame is noise; the next frame decodes.
    let frames: Vec<_> = decoder
        .frames(t0 + timeout, b"0346*\n@01EA000346*\n")
        .collect();
    assert!(matches!(frames.as_slice(), [Ok(_)]));
    assert_eq!(decoder.stats().noise_bytes, 2 + 6);
}
