//! Any bytes as a Modbus TCP stream: the decoder never panics, gives the same
//! frames whether the bytes come at once or in chunks, accounts for every byte
//! (framed + dropped + pending = fed), and every frame re-emits to the same
//! bytes; its PDU parses either way or fails with a typed error.
#![no_main]

#[path = "../common/chunking.rs"]
mod chunking;

use chunking::chunks;
use libfuzzer_sys::fuzz_target;
use protocols::modbus::tcp::{self, MAX_ADU_LEN, TcpDecoder};
use protocols::modbus::{Adu, Drops, FrameError, Request, Response};

type Events = Vec<Result<(u16, u8, Vec<u8>), FrameError>>;

fn run<'a>(chunks: impl Iterator<Item = &'a [u8]>) -> (Events, Drops, usize) {
    let mut decoder = TcpDecoder::new();
    let mut events = Vec::new();
    for chunk in chunks {
        let mut input = chunk;
        while let Some(item) = decoder.decode(&mut input) {
            events.push(item.map(|f| (f.transaction_id(), f.unit(), f.pdu().to_vec())));
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
    let mut framed = 0;
    let mut out = [0u8; MAX_ADU_LEN];
    for (tid, unit, pdu) in events.iter().flatten() {
        framed += pdu.len() + tcp::MBAP_LEN;
        let n = tcp::TcpRepr {
            transaction_id: *tid,
            unit: *unit,
            pdu: &pdu[..],
        }
        .emit(&mut out)
        .expect("a decoded frame fits");
        let again = tcp::TcpFrame::new_checked(&out[..n]).expect("a decoded frame re-parses");
        assert_eq!(
            (again.transaction_id(), again.unit(), again.pdu()),
            (*tid, *unit, &pdu[..])
        );
        drop(Request::parse(pdu));
        drop(Response::parse(pdu));
    }
    assert_eq!(
        framed as u64 + drops.total_bytes() + pending as u64,
        data.len() as u64
    );
});
