//! Parse and emit throughput of the Modbus codecs, in frames per second on one
//! core: 8-byte Modbus, RTU / TCP / ASCII with an FC03 request and reply, and
//! the RTU and 8-byte stream decoders over a long buffer.
//!
//! Run briefly: `cargo bench -p protocols --bench modbus -- --warm-up-time 1 --measurement-time 3`.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use protocols::modbus::rtu::{Direction, RtuDecoder};
use protocols::modbus::serial::{PTY_SILENCE, Timing};
use protocols::modbus::{EncodePdu, Registers, Request, Response, ascii, rtu, tcp};
use protocols::modbus8::{CrcOrder, Modbus8Decoder, Modbus8Repr};
use protocols::time::SimTime;

/// FC03: read 10 holding registers from 0, and its reply.
fn fc03() -> (Request, Response) {
    let request = Request::ReadHoldingRegisters {
        address: 0,
        quantity: 10,
    };
    let values: Vec<u16> = (0..10).map(|i| 1000 + i).collect();
    let response = Response::ReadHoldingRegisters(Registers::from_slice(&values).unwrap());
    (request, response)
}

fn modbus8(c: &mut Criterion) {
    let mut g = c.benchmark_group("modbus8");
    g.throughput(Throughput::Elements(1));
    let frame = Modbus8Repr {
        id: 1,
        function: 3,
        addr: 5,
        value: 9857,
    };
    let bytes = frame.to_bytes(CrcOrder::HighFirst);
    g.bench_function("parse", |b| {
        b.iter(|| Modbus8Repr::parse(black_box(&bytes), CrcOrder::HighFirst))
    });
    let mut out = [0u8; 8];
    g.bench_function("emit", |b| {
        b.iter(|| black_box(&frame).emit(&mut out, CrcOrder::HighFirst))
    });
    g.finish();
}

/// Parse (framing check + PDU) and emit of one request and one reply with
/// `emit_adu` / `parse_pdu` for a framing.
fn framing<E, P>(c: &mut Criterion, name: &str, emit_adu: E, parse_pdu: P)
where
    E: Fn(&dyn EncodeDyn, &mut [u8]) -> usize,
    P: Fn(&[u8], bool) -> bool,
{
    let (request, response) = fc03();
    let mut g = c.benchmark_group(name);
    g.throughput(Throughput::Elements(1));
    let mut out = [0u8; 600];
    for (label, pdu, is_request) in [
        ("fc03_request", &request as &dyn EncodeDyn, true),
        ("fc03_response", &response as &dyn EncodeDyn, false),
    ] {
        let n = emit_adu(pdu, &mut out);
        let adu = out[..n].to_vec();
        assert!(parse_pdu(&adu, is_request), "{name} {label} must parse");
        g.bench_function(format!("{label}/parse"), |b| {
            b.iter(|| parse_pdu(black_box(&adu), is_request))
        });
        let mut buf = [0u8; 600];
        g.bench_function(format!("{label}/emit"), |b| {
            b.iter(|| emit_adu(black_box(pdu), &mut buf))
        });
    }
    g.finish();
}

/// Object-safe stand-in so that one closure serves both PDU types.
trait EncodeDyn {
    fn rtu(&self, out: &mut [u8]) -> usize;
    fn ascii(&self, out: &mut [u8]) -> usize;
    fn tcp(&self, out: &mut [u8]) -> usize;
}

impl<T: EncodePdu> EncodeDyn for T {
    fn rtu(&self, out: &mut [u8]) -> usize {
        rtu::RtuRepr { unit: 1, pdu: self }.emit(out).unwrap_or(0)
    }
    fn ascii(&self, out: &mut [u8]) -> usize {
        ascii::AsciiRepr { unit: 1, pdu: self }
            .emit(out)
            .unwrap_or(0)
    }
    fn tcp(&self, out: &mut [u8]) -> usize {
        tcp::TcpRepr {
            transaction_id: 7,
            unit: 1,
            pdu: self,
        }
        .emit(out)
        .unwrap_or(0)
    }
}

fn pdu_ok(pdu: &[u8], is_request: bool) -> bool {
    if is_request {
        Request::parse(pdu).is_ok()
    } else {
        matches!(Response::parse(pdu), Ok(Ok(_)))
    }
}

fn framings(c: &mut Criterion) {
    framing(
        c,
        "rtu",
        |p, out| p.rtu(out),
        |adu, req| rtu::RtuFrame::new_checked(adu).is_ok_and(|f| pdu_ok(f.pdu(), req)),
    );
    framing(
        c,
        "tcp",
        |p, out| p.tcp(out),
        |adu, req| tcp::TcpFrame::new_checked(adu).is_ok_and(|f| pdu_ok(f.pdu(), req)),
    );
    framing(
        c,
        "ascii",
        |p, out| p.ascii(out),
        |adu, req| {
            let mut scratch = [0u8; ascii::MAX_BINARY_LEN];
            ascii::AsciiFrame::decode_line(adu, &mut scratch).is_ok_and(|f| pdu_ok(f.pdu(), req))
        },
    );
}

fn streams(c: &mut Criterion) {
    const FRAMES: usize = 1000;
    let (request, _) = fc03();
    let mut stream = Vec::new();
    let mut out = [0u8; 300];
    for unit in (0..FRAMES).map(|i| (i % 247 + 1) as u8) {
        let n = rtu::RtuRepr {
            unit,
            pdu: &request,
        }
        .emit(&mut out)
        .unwrap();
        stream.extend_from_slice(&out[..n]);
    }
    let mut g = c.benchmark_group("stream");
    g.throughput(Throughput::Elements(FRAMES as u64));
    for chunk in [1usize, 64, 4096] {
        g.bench_function(format!("rtu_decode_1000_frames/chunk{chunk}"), |b| {
            b.iter(|| {
                let mut decoder = RtuDecoder::new(Direction::Request, Timing::Silence(PTY_SILENCE));
                let mut frames = 0;
                for piece in stream.chunks(chunk) {
                    let mut input = piece;
                    while let Some(item) = decoder.decode(SimTime::ZERO, &mut input) {
                        frames += usize::from(item.is_ok());
                    }
                }
                assert_eq!(frames, FRAMES);
                frames
            })
        });
    }
    let m8: Vec<u8> = (0..FRAMES)
        .flat_map(|i| {
            Modbus8Repr {
                id: 1,
                function: 3,
                addr: 5,
                value: i as u16,
            }
            .to_bytes(CrcOrder::HighFirst)
        })
        .collect();
    g.bench_function("modbus8_decode_1000_frames/chunk64", |b| {
        b.iter(|| {
            let mut decoder = Modbus8Decoder::for_pty(CrcOrder::HighFirst);
            let mut frames = 0;
            for piece in m8.chunks(64) {
                let mut input = piece;
                while let Some(item) = decoder.decode(SimTime::ZERO, &mut input) {
                    frames += usize::from(item.is_ok());
                }
            }
            assert_eq!(frames, FRAMES);
            frames
        })
    });
    g.finish();
}

criterion_group!(benches, modbus8, framings, streams);
criterion_main!(benches);
