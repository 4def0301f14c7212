//! Any bytes as a Modbus ASCII stream: the decoder never panics, gives the same
//! frames and drop counts whether the bytes come at once or in chunks, accounts
//! for every byte (framed + dropped + pending = fed), never yields more frames
//! than there are line feeds, and every frame re-emits and re-parses.
#![no_main]

#[path = "../common/chunking.rs"]
mod chunking;

use chunking::chunks;
use libfuzzer_sys::fuzz_target;
use protocols::modbus::ascii::{self, AsciiDecoder, MAX_ADU_LEN, MAX_BINARY_LEN};
use protocols::modbus::{Adu, Drops, FrameError, Request, Response};

type Events = Vec<Result<(u8, Vec<u8>), FrameError>>;

fn run<'a>(chunks: impl Iterator<Item = &'a [u8]>) -> (Events, Drops, usize) {
    let mut decoder = AsciiDecoder::new();
    let mut events = Vec::new();
    for chunk in chunks {
        let mut input = chunk;
        while let Some(item) = decoder.decode(&mut input) {
            events.push(item.map(|f| (f.unit(), f.pdu().to_vec())));
        }
        assert!(input.is_empty());
        assert!(decoder.pending() <= MAX_ADU_LEN);
    }
    (events, *decoder.drops(), decoder.pending())
}

fuzz_target!(|data: &[u8]| {
    let whole = run(std::iter::once(data));
    let split = run(chunks(data).into_iter());
    assert_eq!(whole, split);

    let (events, drops, pending) = whole;
    let line_feeds = data.iter().filter(|&&b| b == b'\n').count();
    assert!(events.len() <= line_feeds);
    let mut framed = 0;
    let mut out = [0u8; MAX_ADU_LEN];
    let mut scratch = [0u8; MAX_BINARY_LEN];
    for (unit, pdu) in events.iter().flatten() {
        framed += 1 + 2 * (pdu.len() + 2) + 2;
        let n = ascii::AsciiRepr {
            unit: *unit,
            pdu: &pdu[..],
        }
        .emit(&mut out)
        .expect("a decoded frame fits");
        let again = ascii::AsciiFrame::decode_line(&out[..n], &mut scratch)
            .expect("a decoded frame re-parses");
        assert_eq!((again.unit(), again.pdu()), (*unit, &pdu[..]));
        drop(Request::parse(pdu));
        drop(Response::parse(pdu));
    }
    assert_eq!(
        framed as u64 + drops.total_bytes() + pending as u64,
        data.len() as u64
    );
});
