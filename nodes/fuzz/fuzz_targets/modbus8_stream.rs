//! Any bytes as an 8-byte Modbus line: the decoder never panics, gives the same
//! frames and drop counts whether a burst comes at once or in chunks (sizes
//! drawn from the input), and with arrival gaps drawn from the input it
//! accounts for every byte: framed + dropped + pending = fed.
#![no_main]

#[path = "../common/chunking.rs"]
mod chunking;

use chunking::chunks;
use libfuzzer_sys::fuzz_target;
use protocols::modbus::Drops;
use protocols::modbus8::{CrcOrder, FRAME_LEN, Modbus8Decoder, Modbus8Error, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};

type Events = Vec<Result<Modbus8Repr, Modbus8Error>>;

fn run<'a>(
    order: CrcOrder,
    chunks: impl Iterator<Item = (SimTime, &'a [u8])>,
) -> (Events, Drops, usize) {
    let mut decoder = Modbus8Decoder::for_pty(order);
    let mut events = Vec::new();
    for (now, chunk) in chunks {
        let mut input = chunk;
        while let Some(item) = decoder.decode(now, &mut input) {
            events.push(item.map(|frame| Modbus8Repr::from_frame(&frame)));
        }
        assert!(input.is_empty());
        assert!(decoder.pending() < FRAME_LEN);
    }
    (events, *decoder.drops(), decoder.pending())
}

/// Splits `bytes` into chunks whose sizes (1..=23) come from the data itself.
fuzz_target!(|data: &[u8]| {
    let Some((&control, bytes)) = data.split_first() else {
        return;
    };
    let order = if control & 1 == 0 {
        CrcOrder::HighFirst
    } else {
        CrcOrder::LowFirst
    };

    let whole = run(order, std::iter::once((SimTime::ZERO, bytes)));
    let split = run(order, chunks(bytes).into_iter().map(|c| (SimTime::ZERO, c)));
    assert_eq!(whole, split);

    // Gaps of 0..8 ms between chunks: some end partial frames and discards.
    let mut now = SimTime::ZERO;
    let timed = chunks(bytes).into_iter().map(|c| {
        now += SimDuration::from_micros(u64::from(c[0]) * 32);
        (now, c)
    });
    let (events, drops, pending) = run(order, timed);
    let framed = events.iter().filter(|e| e.is_ok()).count() * FRAME_LEN;
    assert_eq!(
        framed as u64 + drops.total_bytes() + pending as u64,
        bytes.len() as u64
    );
    for frame in events.iter().flatten() {
        assert_eq!(
            Modbus8Repr::parse(&frame.to_bytes(order), order),
            Ok(*frame)
        );
    }
});
