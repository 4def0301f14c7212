//! Properties of the MEB codec: emit -> parse round trip, and a stream decoder
//! whose output does not depend on how the bytes are chunked.

use proptest::prelude::*;
use protocols::meb::{
    MEB_MAX_FRAME_LEN, MEB_MAX_WORDS, MebCmd, MebDecodeError, MebDecoder, MebError, MebFrame,
    MebRepr, MebWords,
};
use protocols::time::{SimDuration, SimTime};

fn arb_cmd() -> impl Strategy<Value = MebCmd> {
    let table = prop::sample::select(vec![
        MebCmd::EA,
        MebCmd::ED,
        MebCmd::SA,
        MebCmd::SD,
        MebCmd::VA,
        MebCmd::VD,
        MebCmd::FA,
        MebCmd::FD,
        MebCmd::ER,
    ]);
    let letter = prop::sample::select((b'A'..=b'Z').chain(b'a'..=b'z').collect::<Vec<u8>>());
    let any_letters =
        (letter.clone(), letter).prop_map(|(a, b)| MebCmd::new([a, b]).expect("letters"));
    prop_oneof![3 => table, 1 => any_letters]
}

fn arb_repr() -> impl Strategy<Value = MebRepr> {
    (
        0u8..=99,
        arb_cmd(),
        any::<u8>(),
        0usize..=MEB_MAX_WORDS,
        any::<bool>(),
    )
        .prop_flat_map(|(id, cmd, addr, cnt, with_data)| {
            let words = prop::collection::vec(any::<u16>(), if with_data { cnt } else { 0 });
            words.prop_map(move |words| MebRepr {
                id,
                cmd,
                addr,
                cnt: cnt as u8,
                data: MebWords::from_slice(&words).expect("at most 99 words"),
            })
        })
}

fn emit(repr: &MebRepr) -> Vec<u8> {
    let mut buf = [0u8; MEB_MAX_FRAME_LEN];
    let len = repr.emit(&mut buf).expect("a valid repr emits");
    buf[..len].to_vec()
}

/// What arrives between frames: bytes that may hold `\n` but never `@`.
fn arb_noise() -> impl Strategy<Value = Vec<u8>> {
    prop::collection::vec(any::<u8>().prop_filter("no BOF", |&b| b != b'@'), 0..20)
}

/// Splits `bytes` at the given cut points (taken modulo the length).
fn chunked<'a>(bytes: &'a [u8], cuts: &[usize]) -> Vec<&'a [u8]> {
    let mut cuts: Vec<usize> = cuts.iter().map(|c| c % (bytes.len() + 1)).collect();
    cuts.push(0);
    cuts.push(bytes.len());
    cuts.sort_unstable();
    cuts.windows(2).map(|w| &bytes[w[0]..w[1]]).collect()
}

type Events = Vec<Result<MebRepr, MebDecodeError>>;

fn decode_chunks(chunks: &[&[u8]]) -> (Events, MebDecoder) {
    let mut decoder = MebDecoder::new();
    let mut events = Vec::new();
    for (i, chunk) in chunks.iter().enumerate() {
        let now = SimTime::ZERO + SimDuration::from_micros(87 * i as u64);
        events.extend(decoder.frames(now, chunk));
        assert!(decoder.buffered() <= MEB_MAX_FRAME_LEN);
    }
    (events, decoder)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn emit_then_parse_gives_the_same_frame(repr in arb_repr()) {
        let bytes = emit(&repr);
        prop_assert_eq!(bytes.len(), repr.emitted_len());
        prop_assert_eq!(MebRepr::parse(&bytes), Ok(repr));
        let view = MebFrame::new_checked(bytes.as_slice()).expect("checked");
        prop_assert_eq!(view.shape(), repr.shape());
        prop_assert_eq!(view.words().collect::<Vec<_>>(), repr.data.to_vec());
    }

    #[test]
    fn lower_case_and_crlf_parse_to_the_same_frame(repr in arb_repr()) {
        let canonical = emit(&repr);
        let n = canonical.len();
        // Lower-case the hex fields (ADDR, DATA) but not the command, then fix the FCS
        // over the bytes as sent and end with `*\r\n`.
        let mut sent = canonical[..n - 4].to_vec();
        sent[5..].make_ascii_lowercase();
        let fcs = sent.iter().fold(0u8, |a, b| a ^ b);
        sent.extend(format!("{fcs:02x}*\r\n").bytes());
        prop_assert_eq!(MebRepr::parse(&sent), Ok(repr));
    }

    #[test]
    fn frames_between_noise_all_arrive_whatever_the_chunking(
        frames in prop::collection::vec((arb_noise(), arb_repr()), 1..8),
        tail in arb_noise(),
        cuts in prop::collection::vec(any::<usize>(), 0..40),
    ) {
        let mut stream = Vec::new();
        for (noise, repr) in &frames {
            stream.extend(noise);
            stream.extend(emit(repr));
        }
        stream.extend(&tail);
        let (events, decoder) = decode_chunks(&chunked(&stream, &cuts));
        let expected: Events = frames.iter().map(|(_, repr)| Ok(*repr)).collect();
        prop_assert_eq!(events, expected);
        let noise: usize = frames.iter().map(|(n, _)| n.len()).sum::<usize>() + tail.len();
        prop_assert_eq!(decoder.stats().noise_bytes, noise as u64);
        prop_assert_eq!(decoder.stats().dropped_frames(), 0);
    }

    #[test]
    fn any_bytes_decode_the_same_whatever_the_chunking(
        pieces in prop::collection::vec(
            prop_oneof![
                arb_repr().prop_map(|r| emit(&r)),
                // A frame cut short, or with a byte changed.
                (arb_repr(), any::<usize>()).prop_map(|(r, cut)| {
                    let bytes = emit(&r);
                    bytes[..cut % bytes.len()].to_vec()
                }),
                (arb_repr(), any::<usize>(), any::<u8>()).prop_map(|(r, at, b)| {
                    let mut bytes = emit(&r);
                    let at = at % bytes.len();
                    bytes[at] = b;
                    bytes
                }),
                prop::collection::vec(any::<u8>(), 0..500),
                prop::collection::vec(prop::sample::select(b"@*\r\n0A".to_vec()), 0..30),
            ],
            0..10,
        ),
        cuts in prop::collection::vec(any::<usize>(), 0..60),
    ) {
        let stream: Vec<u8> = pieces.concat();
        let (whole, whole_decoder) = decode_chunks(&[&stream]);
        let (split, split_decoder) = decode_chunks(&chunked(&stream, &cuts));
        prop_assert_eq!(&whole, &split);
        prop_assert_eq!(whole_decoder.stats(), split_decoder.stats());
        // Never more than one frame, good or malformed, per terminator.
        let terminators = stream.iter().filter(|&&b| b == b'\n').count();
        let ended = whole
            .iter()
            .filter(|e| !matches!(e, Err(MebDecodeError::Interrupted | MebDecodeError::Malformed(MebError::TooLong))))
            .count();
        prop_assert!(ended <= terminators, "{} frames for {} terminators", ended, terminators);
        // Every frame delivered is well formed and re-emits to a frame that parses.
        for frame in whole.iter().flatten() {
            prop_assert_eq!(MebRepr::parse(&emit(frame)), Ok(*frame));
        }
    }

    #[test]
    fn parse_never_panics_and_accepts_only_what_re_emits(bytes in prop::collection::vec(any::<u8>(), 0..450)) {
        if let Ok(repr) = MebRepr::parse(&bytes) {
            prop_assert_eq!(MebRepr::parse(&emit(&repr)), Ok(repr));
        }
    }
}
