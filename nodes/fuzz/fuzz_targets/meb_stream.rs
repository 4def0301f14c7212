//! Any bytes as a MEB byte stream: the decoder never panics, never holds more than
//! one frame, gives the same events whether the bytes come at once or in chunks
//! (sizes drawn from the input), and never more than one frame per `\n`.
#![no_main]

use libfuzzer_sys::fuzz_target;
use protocols::meb::{MEB_MAX_FRAME_LEN, MebDecodeError, MebDecoder, MebError, MebRepr};
use protocols::time::{SimDuration, SimTime};

type Events = Vec<Result<MebRepr, MebDecodeError>>;

fn decode<'a>(chunks: impl Iterator<Item = &'a [u8]>) -> (Events, MebDecoder) {
    let mut decoder = MebDecoder::with_partial_timeout(SimDuration::from_secs(5));
    let mut events = Vec::new();
    for (i, chunk) in chunks.enumerate() {
        let now = SimTime::ZERO + SimDuration::from_micros(i as u64);
        events.extend(decoder.frames(now, chunk));
        assert!(decoder.buffered() <= MEB_MAX_FRAME_LEN);
    }
    (events, decoder)
}

fuzz_target!(|data: &[u8]| {
    let (whole, whole_decoder) = decode(std::iter::once(data));

    let mut chunks = Vec::new();
    let mut rest = data;
    let mut i = 0;
    while !rest.is_empty() {
        let size = 1 + usize::from(data[i % data.len()]) % 23;
        let (chunk, tail) = rest.split_at(size.min(rest.len()));
        chunks.push(chunk);
        rest = tail;
        i += 1;
    }
    let (split, split_decoder) = decode(chunks.into_iter());

    assert_eq!(whole, split);
    assert_eq!(whole_decoder.stats(), split_decoder.stats());
    assert_eq!(whole_decoder.buffered(), split_decoder.buffered());

    let terminators = data.iter().filter(|&&b| b == b'\n').count();
    let ended = whole
        .iter()
        .filter(|e| {
            !matches!(
                e,
                Err(MebDecodeError::Interrupted | MebDecodeError::Malformed(MebError::TooLong))
            )
        })
        .count();
    assert!(ended <= terminators);
    let stats = whole_decoder.stats();
    let bytes_accounted = stats.noise_bytes as usize + whole_decoder.buffered();
    assert!(bytes_accounted <= data.len());
});
