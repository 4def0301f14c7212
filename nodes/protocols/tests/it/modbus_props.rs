//! Property tests for the Modbus codecs: emit→parse round trips for every frame
//! type and framing, stream decoders that give the same frames whatever the
//! chunking and timing of their input, and decoders that account for every
//! byte of arbitrary input without panicking.

use proptest::prelude::*;
use protocols::modbus::ascii::{self, AsciiDecoder};
use protocols::modbus::pdu::{
    MAX_READ_BITS, MAX_READ_REGISTERS, MAX_WRITE_COILS, MAX_WRITE_REGISTERS,
};
use protocols::modbus::rtu::{self, Direction, RtuDecoder};
use protocols::modbus::serial::{PTY_SILENCE, Timing, silence_3_5_chars};
use protocols::modbus::tcp::{self, TcpDecoder};
use protocols::modbus::{
    Adu, Bits, EncodePdu, Exception, ExceptionResponse, Registers, Request, Response,
};
use protocols::modbus8::{CrcOrder, Modbus8Decoder, Modbus8Repr};
use protocols::time::{SimDuration, SimTime};

// ---------------------------------------------------------------- strategies

fn bits(max: u16) -> impl Strategy<Value = Bits> {
    prop::collection::vec(any::<bool>(), 1..=usize::from(max))
        .prop_map(|v| Bits::from_bools(&v).unwrap())
}

/// Read replies carry whole bytes of bits.
fn packed_bits() -> impl Strategy<Value = Bits> {
    prop::collection::vec(any::<u8>(), 1..=250)
        .prop_map(|v| Bits::from_packed(&v, v.len() as u16 * 8).unwrap())
}

fn registers(max: u16) -> impl Strategy<Value = Registers> {
    prop::collection::vec(any::<u16>(), 1..=usize::from(max))
        .prop_map(|v| Registers::from_slice(&v).unwrap())
}

fn request() -> impl Strategy<Value = Request> {
    let a = any::<u16>();
    prop_oneof![
        (a, 1..=MAX_READ_BITS)
            .prop_map(|(address, quantity)| Request::ReadCoils { address, quantity }),
        (a, 1..=MAX_READ_BITS)
            .prop_map(|(address, quantity)| Request::ReadDiscreteInputs { address, quantity }),
        (a, 1..=MAX_READ_REGISTERS)
            .prop_map(|(address, quantity)| Request::ReadHoldingRegisters { address, quantity }),
        (a, 1..=MAX_READ_REGISTERS)
            .prop_map(|(address, quantity)| Request::ReadInputRegisters { address, quantity }),
        (a, any::<bool>()).prop_map(|(address, value)| Request::WriteSingleCoil { address, value }),
        (a, any::<u16>())
            .prop_map(|(address, value)| Request::WriteSingleRegister { address, value }),
        (a, bits(MAX_WRITE_COILS))
            .prop_map(|(address, coils)| Request::WriteMultipleCoils { address, coils }),
        (a, registers(MAX_WRITE_REGISTERS)).prop_map(|(address, registers)| {
            Request::WriteMultipleRegisters { address, registers }
        }),
    ]
}

fn exception_response() -> impl Strategy<Value = ExceptionResponse> {
    (0u8..0x80, any::<u8>()).prop_map(|(function, code)| ExceptionResponse {
        function,
        exception: Exception::from_code(code),
    })
}

fn reply() -> impl Strategy<Value = Result<Response, ExceptionResponse>> {
    let a = any::<u16>();
    prop_oneof![
        packed_bits().prop_map(|b| Ok(Response::ReadCoils(b))),
        packed_bits().prop_map(|b| Ok(Response::ReadDiscreteInputs(b))),
        registers(MAX_READ_REGISTERS).prop_map(|r| Ok(Response::ReadHoldingRegisters(r))),
        registers(MAX_READ_REGISTERS).prop_map(|r| Ok(Response::ReadInputRegisters(r))),
        (a, any::<bool>())
            .prop_map(|(address, value)| Ok(Response::WriteSingleCoil { address, value })),
        (a, any::<u16>())
            .prop_map(|(address, value)| Ok(Response::WriteSingleRegister { address, value })),
        (a, 1..=MAX_WRITE_COILS)
            .prop_map(|(address, quantity)| Ok(Response::WriteMultipleCoils { address, quantity })),
        (a, 1..=MAX_WRITE_REGISTERS).prop_map(|(address, quantity)| Ok(
            Response::WriteMultipleRegisters { address, quantity }
        )),
        exception_response().prop_map(Err),
    ]
}

fn modbus8_frame() -> impl Strategy<Value = Modbus8Repr> {
    (any::<u8>(), any::<u8>(), any::<u16>(), any::<u16>()).prop_map(
        |(id, function, addr, value)| Modbus8Repr {
            id,
            function,
            addr,
            value,
        },
    )
}

fn crc_order() -> impl Strategy<Value = CrcOrder> {
    prop_oneof![Just(CrcOrder::HighFirst), Just(CrcOrder::LowFirst)]
}

/// Cut sizes for splitting a stream into chunks.
fn cuts() -> impl Strategy<Value = Vec<usize>> {
    prop::collection::vec(1usize..40, 1..60)
}

/// Splits `bytes` into chunks of the sizes in `cuts` (cycled).
fn chunks<'a>(bytes: &'a [u8], cuts: &[usize]) -> Vec<&'a [u8]> {
    let mut out = Vec::new();
    let mut rest = bytes;
    for &cut in cuts.iter().cycle() {
        if rest.is_empty() {
            break;
        }
        let (head, tail) = rest.split_at(cut.min(rest.len()));
        out.push(head);
        rest = tail;
    }
    out
}

fn pdu_bytes(pdu: &(impl EncodePdu + ?Sized)) -> Vec<u8> {
    let mut out = vec![0u8; 300];
    let n = pdu.encode_pdu(&mut out).unwrap();
    out.truncate(n);
    out
}

fn rtu_bytes(unit: u8, pdu: &(impl EncodePdu + ?Sized)) -> Vec<u8> {
    let mut out = vec![0u8; rtu::MAX_ADU_LEN];
    let n = rtu::RtuRepr { unit, pdu }.emit(&mut out).unwrap();
    out.truncate(n);
    out
}

fn ascii_bytes(unit: u8, pdu: &(impl EncodePdu + ?Sized)) -> Vec<u8> {
    let mut out = vec![0u8; ascii::MAX_ADU_LEN];
    let n = ascii::AsciiRepr { unit, pdu }.emit(&mut out).unwrap();
    out.truncate(n);
    out
}

fn tcp_bytes(tid: u16, unit: u8, pdu: &(impl EncodePdu + ?Sized)) -> Vec<u8> {
    let mut out = vec![0u8; tcp::MAX_ADU_LEN];
    let n = tcp::TcpRepr {
        transaction_id: tid,
        unit,
        pdu,
    }
    .emit(&mut out)
    .unwrap();
    out.truncate(n);
    out
}

// ---------------------------------------------------------------- round trips

proptest! {
    #[test]
    fn request_round_trips_through_every_framing(req in request(), unit: u8, tid: u16) {
        let pdu = pdu_bytes(&req);
        prop_assert_eq!(pdu.len(), req.pdu_len());
        prop_assert_eq!(&Request::parse(&pdu).unwrap(), &req);

        let adu = rtu_bytes(unit, &req);
        let frame = rtu::RtuFrame::new_checked(&adu).unwrap();
        prop_assert_eq!(frame.unit(), unit);
        prop_assert_eq!(&frame.request().unwrap(), &req);

        let adu = ascii_bytes(unit, &req);
        let mut scratch = [0u8; ascii::MAX_BINARY_LEN];
        let frame = ascii::AsciiFrame::decode_line(&adu, &mut scratch).unwrap();
        prop_assert_eq!(frame.unit(), unit);
        prop_assert_eq!(&frame.request().unwrap(), &req);

        let adu = tcp_bytes(tid, unit, &req);
        let frame = tcp::TcpFrame::new_checked(&adu).unwrap();
        prop_assert_eq!((frame.transaction_id(), frame.unit()), (tid, unit));
        prop_assert_eq!(&frame.request().unwrap(), &req);
    }

    #[test]
    fn reply_round_trips_through_every_framing(rep in reply(), unit: u8, tid: u16) {
        let pdu = pdu_bytes(&rep);
        prop_assert_eq!(&Response::parse(&pdu).unwrap(), &rep);

        let adu = rtu_bytes(unit, &rep);
        prop_assert_eq!(&rtu::RtuFrame::new_checked(&adu).unwrap().response().unwrap(), &rep);

        let adu = ascii_bytes(unit, &rep);
        let mut scratch = [0u8; ascii::MAX_BINARY_LEN];
        prop_assert_eq!(&ascii::AsciiFrame::decode_line(&adu, &mut scratch).unwrap().response().unwrap(), &rep);

        let adu = tcp_bytes(tid, unit, &rep);
        prop_assert_eq!(&tcp::TcpFrame::new_checked(&adu).unwrap().response().unwrap(), &rep);
    }

    #[test]
    fn modbus8_round_trips_in_both_orders(frame in modbus8_frame(), order in crc_order()) {
        let bytes = frame.to_bytes(order);
        prop_assert_eq!(Modbus8Repr::parse(&bytes, order), Ok(frame));
        // The other order rejects it unless both CRC bytes happen to be equal.
        let other = match order {
            CrcOrder::HighFirst => CrcOrder::LowFirst,
            CrcOrder::LowFirst => CrcOrder::HighFirst,
        };
        prop_assert_eq!(Modbus8Repr::parse(&bytes, other).is_ok(), bytes[6] == bytes[7]);
    }

    #[test]
    fn every_single_bit_flip_is_caught(req in request(), unit: u8, bit in 0usize..2048) {
        let mut adu = rtu_bytes(unit, &req);
        let bit = bit % (adu.len() * 8);
        adu[bit / 8] ^= 1 << (bit % 8);
        prop_assert!(rtu::RtuFrame::new_checked(&adu).is_err());
    }
}

// ---------------------------------------------------------------- streams

/// Feeds `chunks` to an RTU decoder, the i-th at `times[i]`, then lets the
/// line fall silent; returns each frame's (unit, PDU).
fn run_rtu(decoder: &mut RtuDecoder, chunks: &[&[u8]], times: &[SimTime]) -> Vec<(u8, Vec<u8>)> {
    let mut out = Vec::new();
    for (chunk, &now) in chunks.iter().zip(times) {
        let mut input = *chunk;
        while let Some(item) = decoder.decode(now, &mut input) {
            if let Ok(frame) = item {
                out.push((frame.unit(), frame.pdu().to_vec()));
            }
        }
    }
    if let Some(due) = decoder.poll_timeout()
        && let Some(Ok(frame)) = decoder.handle_timeout(due)
    {
        out.push((frame.unit(), frame.pdu().to_vec()));
    }
    out
}

/// Arrival times for `n` chunks, each within `max_gap` of the previous one.
fn times(n: usize, gaps: &[u64], max_gap: u64) -> Vec<SimTime> {
    let mut now = SimTime::ZERO;
    (0..n)
        .map(|i| {
            now += SimDuration(gaps.get(i % gaps.len().max(1)).copied().unwrap_or(0) % max_gap);
            now
        })
        .collect()
}

proptest! {
    #[test]
    fn rtu_requests_survive_any_chunking(
        frames in prop::collection::vec((any::<u8>(), request()), 1..8),
        cuts in cuts(),
        gaps in prop::collection::vec(any::<u64>(), 1..16),
    ) {
        let stream: Vec<u8> = frames.iter().flat_map(|(u, r)| rtu_bytes(*u, r)).collect();
        let chunks = chunks(&stream, &cuts);
        // Gaps shorter than the silence never split a frame.
        let silence = silence_3_5_chars(115_200, 10);
        let times = times(chunks.len(), &gaps, silence.0);
        let mut decoder = RtuDecoder::new(Direction::Request, Timing::Silence(silence));
        let got = run_rtu(&mut decoder, &chunks, &times);
        let want: Vec<_> = frames.iter().map(|(u, r)| (*u, pdu_bytes(r))).collect();
        prop_assert_eq!(got, want);
        prop_assert_eq!(decoder.drops().total_bytes(), 0);
    }

    #[test]
    fn rtu_replies_survive_any_chunking_without_timing(
        frames in prop::collection::vec((any::<u8>(), reply()), 1..8),
        cuts in cuts(),
    ) {
        let stream: Vec<u8> = frames.iter().flat_map(|(u, r)| rtu_bytes(*u, r)).collect();
        let chunks = chunks(&stream, &cuts);
        let times = vec![SimTime::ZERO; chunks.len()];
        let mut decoder = RtuDecoder::new(Direction::Response, Timing::None);
        let got = run_rtu(&mut decoder, &chunks, &times);
        let want: Vec<_> = frames.iter().map(|(u, r)| (*u, pdu_bytes(r))).collect();
        prop_assert_eq!(got, want);
    }

    #[test]
    fn rtu_garbage_between_silences_loses_no_frame(
        segments in prop::collection::vec(
            prop_oneof![
                (any::<u8>(), request()).prop_map(|(u, r)| (true, rtu_bytes(u, &r))),
                prop::collection::vec(any::<u8>(), 1..4).prop_map(|g| (false, g)),
            ],
            1..10,
        ),
        cuts in cuts(),
    ) {
        // Each segment is followed by a silence; garbage is too short to be a
        // frame, so it must be dropped without taking a real frame with it.
        let mut chunk_list: Vec<&[u8]> = Vec::new();
        let mut times = Vec::new();
        let mut now = SimTime::ZERO;
        for (_, bytes) in &segments {
            for chunk in chunks(bytes, &cuts) {
                now += SimDuration::bit_times(10, 115_200);
                chunk_list.push(chunk);
                times.push(now);
            }
            now += PTY_SILENCE;
        }
        let mut decoder = RtuDecoder::new(Direction::Request, Timing::Silence(PTY_SILENCE));
        let got: Vec<Vec<u8>> = run_rtu(&mut decoder, &chunk_list, &times)
            .into_iter()
            .map(|(u, pdu)| rtu_bytes(u, &pdu[..]))
            .collect();
        let want: Vec<Vec<u8>> =
            segments.iter().filter(|(f, _)| *f).map(|(_, b)| b.clone()).collect();
        let garbage: usize = segments.iter().filter(|(f, _)| !*f).map(|(_, b)| b.len()).sum();
        prop_assert_eq!(got, want);
        prop_assert_eq!(decoder.drops().total_bytes(), garbage as u64);
    }

    #[test]
    fn modbus8_frames_survive_any_chunking(
        frames in prop::collection::vec(modbus8_frame(), 1..20),
        order in crc_order(),
        cuts in cuts(),
        gaps in prop::collection::vec(any::<u64>(), 1..16),
    ) {
        let stream: Vec<u8> = frames.iter().flat_map(|f| f.to_bytes(order)).collect();
        let chunks = chunks(&stream, &cuts);
        let times = times(chunks.len(), &gaps, PTY_SILENCE.0);
        let mut decoder = Modbus8Decoder::for_pty(order);
        let mut got = Vec::new();
        for (chunk, &now) in chunks.iter().zip(&times) {
            let mut input = *chunk;
            while let Some(item) = decoder.decode(now, &mut input) {
                got.push(Modbus8Repr::from_frame(&item.unwrap()));
            }
        }
        prop_assert_eq!(got, frames);
    }

    #[test]
    fn tcp_frames_survive_any_chunking(
        frames in prop::collection::vec((any::<u16>(), any::<u8>(), reply()), 1..8),
        cuts in cuts(),
    ) {
        let stream: Vec<u8> =
            frames.iter().flat_map(|(t, u, r)| tcp_bytes(*t, *u, r)).collect();
        let mut decoder = TcpDecoder::new();
        let mut got = Vec::new();
        for chunk in chunks(&stream, &cuts) {
            let mut input = chunk;
            while let Some(item) = decoder.decode(&mut input) {
                let frame = item.unwrap();
                got.push((frame.transaction_id(), frame.unit(), frame.response().unwrap()));
            }
        }
        prop_assert_eq!(got, frames);
        prop_assert_eq!(decoder.pending(), 0);
    }

    #[test]
    fn ascii_frames_survive_any_chunking_and_noise(
        frames in prop::collection::vec(
            (any::<u8>(), request(), prop::collection::vec(any::<u8>(), 0..8)),
            1..8,
        ),
        cuts in cuts(),
    ) {
        // Noise between frames, never containing the start character.
        let mut stream = Vec::new();
        let mut noise_len = 0;
        for (unit, req, noise) in &frames {
            let noise: Vec<u8> = noise.iter().map(|&b| if b == b':' { b'!' } else { b }).collect();
            noise_len += noise.len();
            stream.extend(noise);
            stream.extend(ascii_bytes(*unit, req));
        }
        let mut decoder = AsciiDecoder::new();
        let mut got = Vec::new();
        for chunk in chunks(&stream, &cuts) {
            let mut input = chunk;
            while let Some(item) = decoder.decode(&mut input) {
                let frame = item.unwrap();
                got.push((frame.unit(), frame.request().unwrap()));
            }
        }
        let want: Vec<_> = frames.iter().map(|(u, r, _)| (*u, r.clone())).collect();
        prop_assert_eq!(got, want);
        prop_assert_eq!(decoder.drops().noise.bytes, noise_len as u64);
    }
}

// ---------------------------------------------------------------- arbitrary input

/// Arbitrary bytes, cut arbitrarily, arriving at arbitrary (increasing) times.
fn noise_input() -> impl Strategy<Value = (Vec<u8>, Vec<usize>, Vec<u64>)> {
    (
        prop::collection::vec(any::<u8>(), 0..600),
        cuts(),
        prop::collection::vec(0u64..2 * PTY_SILENCE.0, 1..16),
    )
}

proptest! {
    #[test]
    fn serial_decoders_account_for_every_byte((bytes, cuts, gaps) in noise_input(), timed: bool) {
        let chunks = chunks(&bytes, &cuts);
        let times = times(chunks.len(), &gaps, 2 * PTY_SILENCE.0);
        let timing = if timed { Timing::Silence(PTY_SILENCE) } else { Timing::None };
        for direction in [Direction::Request, Direction::Response] {
            let mut decoder = RtuDecoder::new(direction, timing);
            let mut framed = 0;
            for (chunk, &now) in chunks.iter().zip(&times) {
                let mut input = *chunk;
                while let Some(item) = decoder.decode(now, &mut input) {
                    if let Ok(frame) = item {
                        framed += frame.pdu().len() + 3;
                    }
                }
            }
            let total = framed as u64 + decoder.drops().total_bytes() + decoder.pending() as u64;
            prop_assert_eq!(total, bytes.len() as u64);
        }

        let mut decoder = Modbus8Decoder::for_pty(CrcOrder::HighFirst);
        let mut framed = 0;
        for (chunk, &now) in chunks.iter().zip(&times) {
            let mut input = *chunk;
            while let Some(item) = decoder.decode(now, &mut input) {
                framed += if item.is_ok() { 8 } else { 0 };
            }
        }
        let total = framed + decoder.drops().total_bytes() + decoder.pending() as u64;
        prop_assert_eq!(total, bytes.len() as u64);
    }

    #[test]
    fn stream_decoders_account_for_every_byte((bytes, cuts, _) in noise_input()) {
        let mut tcp = TcpDecoder::new();
        let mut ascii = AsciiDecoder::new();
        let (mut tcp_framed, mut ascii_framed) = (0u64, 0u64);
        for chunk in chunks(&bytes, &cuts) {
            let mut input = chunk;
            while let Some(item) = tcp.decode(&mut input) {
                tcp_framed += item.map_or(0, |f| (f.pdu().len() + tcp::MBAP_LEN) as u64);
            }
            let mut input = chunk;
            while let Some(item) = ascii.decode(&mut input) {
                ascii_framed += item.map_or(0, |f| (1 + 2 * (f.pdu().len() + 2) + 2) as u64);
            }
        }
        let n = bytes.len() as u64;
        prop_assert_eq!(tcp_framed + tcp.drops().total_bytes() + tcp.pending() as u64, n);
        prop_assert_eq!(ascii_framed + ascii.drops().total_bytes() + ascii.pending() as u64, n);
    }

    #[test]
    fn parsers_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
        let _ = Request::parse(&bytes);
        let _ = Response::parse(&bytes);
        let _ = rtu::RtuFrame::new_checked(&bytes);
        let _ = tcp::TcpFrame::new_checked(&bytes);
        let mut scratch = [0u8; ascii::MAX_BINARY_LEN];
        let _ = ascii::AsciiFrame::decode_line(&bytes, &mut scratch);
        let _ = Modbus8Repr::parse(&bytes, CrcOrder::HighFirst);
    }
}
