//! Parse and emit throughput of the protocol codecs, one core, reported by
//! criterion as frames per second (`elem/s`) and bytes per second.
//!
//! One function per format registers its group; a new format adds its function
//! and one name to `criterion_group!` at the bottom.
//!
//! Run: `cargo bench -p protocols --bench codecs -- --warm-up-time 1 --measurement-time 3`

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use protocols::meb::{MEB_MAX_FRAME_LEN, MebDecoder, MebRepr, MebWords};
use protocols::pwmcap::{
    PWM_MAX_SYMBOLS, PwmCoding, PwmCommandType, PwmData, PwmFrameKind, PwmRepr, PwmStatus,
};
use protocols::time::SimTime;

fn frames(elements: usize, bytes: usize) -> Throughput {
    Throughput::ElementsAndBytes {
        elements: elements as u64,
        bytes: bytes as u64,
    }
}

fn meb(c: &mut Criterion) {
    let longest = MebRepr {
        id: 5,
        cmd: protocols::meb::MebCmd::FA,
        addr: 0,
        cnt: 99,
        data: MebWords::from_slice(&[0x1234; 99]).expect("99 words"),
    };
    let mut longest_bytes = [0u8; MEB_MAX_FRAME_LEN];
    let longest_len = longest.emit(&mut longest_bytes).expect("emit");
    let cases: [(&str, &[u8]); 3] = [
        ("read_request", b"@01EA000346*\n"),
        ("reply_3_words", b"@01EA00030A3C012307D034*\n"),
        ("reply_99_words", &longest_bytes[..longest_len]),
    ];

    let mut group = c.benchmark_group("meb");
    for (name, bytes) in cases {
        let repr = MebRepr::parse(bytes).expect("valid frame");
        group.throughput(frames(1, bytes.len()));
        group.bench_function(format!("parse/{name}"), |b| {
            b.iter(|| MebRepr::parse(black_box(bytes)))
        });
        let mut out = [0u8; MEB_MAX_FRAME_LEN];
        group.bench_function(format!("emit/{name}"), |b| {
            b.iter(|| black_box(&repr).emit(black_box(&mut out)))
        });
    }

    // A long capture of the bus: request, reply, request, reply…, fed in one call
    // per event as a transport would after one read.
    let pair = [cases[0].1, cases[1].1].concat();
    let stream = pair.repeat(500);
    group.throughput(frames(1000, stream.len()));
    group.bench_function("stream/1000_frames", |b| {
        b.iter(|| {
            let mut decoder = MebDecoder::new();
            let mut rest = black_box(stream.as_slice());
            let mut delivered = 0u32;
            while !rest.is_empty() {
                let (used, event) = decoder.push(SimTime::ZERO, rest);
                delivered += u32::from(matches!(event, Some(Ok(_))));
                rest = &rest[used..];
            }
            assert_eq!(delivered, 1000);
        })
    });
    group.finish();
}

fn pwmcap(c: &mut Criterion) {
    let coding = PwmCoding::PAPER;
    let status = PwmStatus {
        high: 1,
        command: PwmCommandType::Current,
    };
    let cases = [
        (
            "broadcast_3_values",
            PwmRepr::Broadcast {
                status,
                data: PwmData::from_slice(&[10, 128, 255]).expect("3"),
            },
        ),
        (
            "experiment",
            PwmRepr::Experiment {
                function_code: 4,
                status,
                reference_1: 100,
                reference_2: 200,
            },
        ),
    ];

    let mut group = c.benchmark_group("pwmcap");
    for (name, frame) in cases {
        let mut widths = [0u32; PWM_MAX_SYMBOLS];
        let n = frame.emit(&coding, &mut widths).expect("emit");
        group.throughput(frames(1, n * size_of::<u32>()));
        group.bench_function(format!("emit/{name}"), |b| {
            let mut out = [0u32; PWM_MAX_SYMBOLS];
            b.iter(|| black_box(&frame).emit(&coding, black_box(&mut out)))
        });
        let kind: PwmFrameKind = frame.kind();
        group.bench_function(format!("decode/{name}"), |b| {
            b.iter(|| PwmRepr::parse(kind, &coding, black_box(&widths[..n])))
        });
    }
    group.finish();
}

criterion_group!(codecs, meb, pwmcap);
criterion_main!(codecs);
