//! Any bytes as a Modbus RTU line, either direction, with and without timing:
//! the decoder never panics, gives the same frames and drop counts whether a
//! burst comes at once or in chunks, and with arrival gaps drawn from the input
//! accounts for every byte: framed + dropped + pending = fed. Every frame it
//! yields re-parses, and its PDU parses or fails with a typed error.
#![no_main]

#[path = "../common/chunking.rs"]
mod chunking;

use chunking::chunks;
use libfuzzer_sys::fuzz_target;
use protocols::modbus::rtu::{self, Direction, MAX_ADU_LEN, RtuDecoder};
use protocols::modbus::serial::{PTY_SILENCE, Timing};
use protocols::modbus::{Adu, Drops, FrameError, Request, Response};
use protocols::time::{SimDuration, SimTime};

type Events = Vec<Result<(u8, Vec<u8>), FrameError>>;

fn run<'a>(
    direction: Direction,
    timing: Timing,
    chunks: impl Iterator<Item = (SimTime, &'a [u8])>,
) -> (Events, Drops, usize) {
    let mut decoder = RtuDecoder::new(direction, timing);
    let mut events = Vec::new();
    let mut last = SimTime::ZERO;
    for (now, chunk) in chunks {
        last = now;
        let mut input = chunk;
        while let Some(item) = decoder.decode(now, &mut input) {
            events.push(item.map(|f| (f.unit(), f.pdu().to_vec())));
        }
        assert!(input.is_empty());
        assert!(decoder.pending() <= MAX_ADU_LEN);
    }
    if let Some(due) = decoder.poll_timeout() {
        assert!(due > last);
        if let Some(item) = decoder.handle_timeout(due) {
            events.push(item.map(|f| (f.unit(), f.pdu().to_vec())));
        }
        assert_eq!(decoder.pending(), 0);
        assert_eq!(decoder.poll_timeout(), None);
    }
    (events, *decoder.drops(), decoder.pending())
}

fuzz_target!(|data: &[u8]| {
    let Some((&control, bytes)) = data.split_first() else {
        return;
    };
    let direction = if control & 1 == 0 {
        Direction::Request
    } else {
        Direction::Response
    };
    let timing = if control & 2 == 0 {
        Timing::Silence(PTY_SILENCE)
    } else {
        Timing::None
    };

    let whole = run(direction, timing, std::iter::once((SimTime::ZERO, bytes)));
    let split = run(
        direction,
        timing,
        chunks(bytes).into_iter().map(|c| (SimTime::ZERO, c)),
    );
    assert_eq!(whole, split);

    let mut now = SimTime::ZERO;
    let timed = chunks(bytes).into_iter().map(|c| {
        now += SimDuration::from_micros(u64::from(c[0]) * 32);
        (now, c)
    });
    let (events, drops, pending) = run(direction, timing, timed);
    let mut framed = 0;
    let mut out = [0u8; MAX_ADU_LEN];
    for (unit, pdu) in events.iter().flatten() {
        framed += pdu.len() + 3;
        let n = rtu::RtuRepr {
            unit: *unit,
            pdu: &pdu[..],
        }
        .emit(&mut out)
        .expect("a decoded frame fits");
        let again = rtu::RtuFrame::new_checked(&out[..n]).expect("a decoded frame re-parses");
        assert_eq!((again.unit(), again.pdu()), (*unit, &pdu[..]));
        match direction {
            Direction::Request => drop(Request::parse(pdu)),
            Direction::Response => drop(Response::parse(pdu)),
        }
    }
    assert_eq!(
        framed as u64 + drops.total_bytes() + pending as u64,
        bytes.len() as u64
    );
});
