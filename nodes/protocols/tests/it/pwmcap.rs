//! PWM-capture coding: the paper's Table 2 figures, the width coding and its
//! noise margin, the checked view over captured widths, and emit -> parse round
//! trips of every frame kind.

use proptest::prelude::*;
use protocols::pwmcap::{
    PWM_MAX_DATA, PWM_MAX_SYMBOLS, PwmCoding, PwmCommandType, PwmData, PwmError, PwmFrame,
    PwmFrameKind, PwmRepr, PwmStatus,
};
use protocols::time::{SimDuration, TICKS_PER_SECOND};

fn nanos(d: SimDuration) -> f64 {
    d.as_secs_f64() * 1e9
}

#[test]
fn table2_frame_times() {
    let c = PwmCoding::TABLE2;
    assert_eq!(c.c_max(), 256);
    // 8 bare symbols of 256 ticks at 150 MHz: 2048 ticks = 13.653 µs, exactly 2048/150 µs.
    let bare = c.ticks_to_duration(c.table2_bare_ticks(8));
    assert_eq!(bare.0 * 150_000_000, 2048 * TICKS_PER_SECOND);
    assert_eq!(nanos(bare).round(), 13_653.0);
    // Plus a start symbol of S = 100 ticks: 14.320 µs.
    let with_start = c.ticks_to_duration(c.table2_with_start_ticks(8));
    assert_eq!(with_start, SimDuration::from_nanos(14_320));
    // The 8-byte Modbus frame at 1 Mbit/s: 64 µs of data bits, 92 µs with start,
    // parity and 1.5 stop bits (11.5 bit times a byte).
    let modbus_data = SimDuration::bit_times(8 * 8, 1_000_000);
    let modbus_framed = SimDuration::bit_times(8 * 23, 2_000_000);
    assert_eq!(modbus_data, SimDuration::from_micros(64));
    assert_eq!(modbus_framed, SimDuration::from_micros(92));
    // The paper's "about 4.7x" and "up to 6x".
    let speedup = modbus_data.as_secs_f64() / bare.as_secs_f64();
    assert!((speedup - 4.6875).abs() < 1e-9, "{speedup}");
    let framed_speedup = modbus_framed.as_secs_f64() / with_start.as_secs_f64();
    assert!((6.0..6.5).contains(&framed_speedup), "{framed_speedup}");
}

#[test]
fn twin_frame_times_with_its_own_coding() {
    // Every symbol, start included, takes S + C_max ticks in the twin.
    let table2 = PwmCoding::TABLE2;
    assert_eq!(table2.symbol_period_ticks(), 356);
    let t = table2.ticks_to_duration(table2.frame_ticks(9));
    assert_eq!(t, SimDuration::from_nanos(21_360));
    let paper = PwmCoding::PAPER;
    assert_eq!((paper.c_max(), paper.symbol_period_ticks()), (1024, 1224));
    let t = paper.ticks_to_duration(paper.frame_ticks(9));
    assert_eq!(t, SimDuration::from_nanos(73_440));
}

#[test]
fn ten_bits_is_the_resolution_that_fits_modbus_time_budget() {
    // 8 symbols must fit the 64 µs an 8-byte Modbus frame takes at 1 Mbit/s.
    let budget = SimDuration::from_micros(64);
    let fits = |bits: u8| {
        let c = PwmCoding::new(150_000_000, bits, 0, 1).unwrap();
        c.ticks_to_duration(c.table2_bare_ticks(8)) <= budget
    };
    let best = (1..=16).filter(|&bits| fits(bits)).max();
    assert_eq!(best, Some(10));
}

#[test]
fn width_coding_and_its_noise_margin() {
    let c = PwmCoding::PAPER;
    assert_eq!(c.encode_width(0), Ok(200));
    assert_eq!(c.encode_width(255), Ok(200 + 1020));
    assert_eq!(
        c.encode_width(256),
        Err(PwmError::ValueOutOfRange {
            value: 256,
            max: 255
        })
    );
    // Two dummy bits: an error of -2..=+1 ticks rounds back to the value.
    for error in -2i64..=1 {
        let width = (1020 + 200 + error) as u32;
        assert_eq!(c.decode_width(width, 200), Ok(255), "error {error}");
        let width = (40 + 200 + error) as u32;
        assert_eq!(c.decode_width(width, 200), Ok(10), "error {error}");
    }
    assert_eq!(c.decode_width(40 + 200 + 2, 200), Ok(11));
    assert_eq!(
        c.decode_width(1222, 200),
        Err(PwmError::WidthAboveRange {
            width: 1222,
            start: 200
        })
    );
    assert_eq!(c.decode_width(198, 200), Ok(0));
    assert_eq!(
        c.decode_width(197, 200),
        Err(PwmError::WidthBelowStart {
            width: 197,
            start: 200
        })
    );
    // A delay added to every edge cancels: the measured start carries it too.
    assert_eq!(c.decode_width(40 + 200 + 37, 200 + 37), Ok(10));
}

#[test]
fn codings_out_of_range_are_refused() {
    assert_eq!(PwmCoding::new(0, 8, 2, 200), Err(PwmError::InvalidCoding));
    assert_eq!(
        PwmCoding::new(150_000_000, 0, 2, 200),
        Err(PwmError::InvalidCoding)
    );
    assert_eq!(
        PwmCoding::new(150_000_000, 17, 0, 200),
        Err(PwmError::InvalidCoding)
    );
    assert_eq!(
        PwmCoding::new(150_000_000, 16, 9, 200),
        Err(PwmError::InvalidCoding)
    );
    assert_eq!(
        PwmCoding::new(150_000_000, 8, 2, 0),
        Err(PwmError::InvalidCoding)
    );
    assert_eq!(PwmCoding::new(150_000_000, 8, 2, 200), Ok(PwmCoding::PAPER));
    assert_eq!(
        PwmCoding::new(150_000_000, 8, 0, 100),
        Ok(PwmCoding::TABLE2)
    );
}

#[test]
fn experiment_frame_symbols() {
    let frame = PwmRepr::Experiment {
        function_code: 0x04,
        status: PwmStatus {
            high: 0x1,
            command: PwmCommandType::Power,
        },
        reference_1: 100,
        reference_2: 255,
    };
    let mut widths = [0u32; PWM_MAX_SYMBOLS];
    let n = frame.emit(&PwmCoding::PAPER, &mut widths).unwrap();
    assert_eq!(
        &widths[..n],
        &[200, 200 + 4 * 4, 200 + 4 * 0x12, 200 + 400, 200 + 1020]
    );
    assert_eq!(
        PwmRepr::parse(PwmFrameKind::Experiment, &PwmCoding::PAPER, &widths[..n]),
        Ok(frame)
    );
    // The view reads the same values, against the start width it measured.
    let delayed = widths.map(|w| w + 37);
    let view =
        PwmFrame::new_checked(&delayed[..n], PwmFrameKind::Experiment, &PwmCoding::PAPER).unwrap();
    assert_eq!(view.start_width(), 237);
    assert_eq!(view.function_code(), Some(0x04));
    assert_eq!(view.status().command, PwmCommandType::Power);
    assert_eq!(view.references(), Some((100, 255)));
    assert!(view.data().is_empty());
    assert_eq!(PwmRepr::from_frame(&view), frame);
    // The kind decides the layout: five symbols are not an experiment frame with a missing one.
    assert_eq!(
        PwmRepr::parse(PwmFrameKind::Experiment, &PwmCoding::PAPER, &widths[..4]),
        Err(PwmError::SymbolCount {
            kind: PwmFrameKind::Experiment,
            got: 4
        })
    );
    let mut short = [0u32; 4];
    assert_eq!(
        frame.emit(&PwmCoding::PAPER, &mut short),
        Err(PwmError::BufferTooSmall { needed: 5 })
    );
    // Status nibble 4..15 names no command type.
    let mut bad = widths;
    bad[2] = 200 + 4 * 0x17;
    assert_eq!(
        PwmRepr::parse(PwmFrameKind::Experiment, &PwmCoding::PAPER, &bad[..n]),
        Err(PwmError::UnknownCommandType(7))
    );
}

#[test]
fn designated_view_reads_id_and_data() {
    let frame = PwmRepr::Designated {
        status: PwmStatus {
            high: 3,
            command: PwmCommandType::Voltage,
        },
        data: PwmData::from_slice(&[0x0F, 0xA0]).unwrap(),
    };
    let mut widths = [0u32; PWM_MAX_SYMBOLS];
    let n = frame.emit(&PwmCoding::PAPER, &mut widths).unwrap();
    let view =
        PwmFrame::new_checked(&widths[..n], PwmFrameKind::Designated, &PwmCoding::PAPER).unwrap();
    assert_eq!(
        (view.kind(), view.status().high),
        (PwmFrameKind::Designated, 3)
    );
    assert_eq!(view.data().as_slice(), &[0x0F, 0xA0]);
    assert_eq!((view.function_code(), view.references()), (None, None));
    assert_eq!(view.as_widths(), &widths[..n]);
    // A width above the coding's range fails the check, not an accessor.
    let mut wide = widths;
    wide[3] = 200 + 1024 + 2;
    assert_eq!(
        PwmFrame::new_checked(&wide[..n], PwmFrameKind::Designated, &PwmCoding::PAPER),
        Err(PwmError::WidthAboveRange {
            width: 1226,
            start: 200
        })
    );
}

fn arb_coding() -> impl Strategy<Value = PwmCoding> {
    (8u8..=16, 0u8..=6, 1u32..=2000).prop_filter_map("valid coding", |(bits, dummy, start)| {
        PwmCoding::new(150_000_000, bits, dummy, start).ok()
    })
}

fn arb_command() -> impl Strategy<Value = PwmCommandType> + Clone {
    prop::sample::select(vec![
        PwmCommandType::Current,
        PwmCommandType::Resistance,
        PwmCommandType::Power,
        PwmCommandType::Voltage,
    ])
}

fn arb_frame(max_value: u16) -> impl Strategy<Value = PwmRepr> {
    let status = (0u8..16, arb_command()).prop_map(|(high, command)| PwmStatus { high, command });
    let data = prop::collection::vec(0..=max_value, 0..=PWM_MAX_DATA)
        .prop_map(|v| PwmData::from_slice(&v).unwrap());
    prop_oneof![
        (status.clone(), data.clone())
            .prop_map(|(status, data)| PwmRepr::Broadcast { status, data }),
        (status.clone(), data).prop_map(|(status, data)| PwmRepr::Designated { status, data }),
        (any::<u8>(), status, 0..=max_value, 0..=max_value).prop_map(|(f, status, r1, r2)| {
            PwmRepr::Experiment {
                function_code: f,
                status,
                reference_1: r1,
                reference_2: r2,
            }
        }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// Emit, then add a line delay to every pulse and noise under half a dummy
    /// step to every data pulse: the receiver decodes the frame sent.
    #[test]
    fn emit_then_decode_through_a_delaying_noisy_line(
        (coding, frame) in arb_coding().prop_flat_map(|c| (Just(c), arb_frame(c.max_value()))),
        delay in 0u32..500,
        noise in prop::collection::vec(any::<i64>(), PWM_MAX_SYMBOLS),
    ) {
        let mut widths = [0u32; PWM_MAX_SYMBOLS];
        let n = frame.emit(&coding, &mut widths).unwrap();
        prop_assert_eq!(n, frame.symbol_count());
        prop_assert!(widths[1..n].iter().all(|&w| w < coding.symbol_period_ticks()));
        let half_step = (1i64 << coding.dummy_bits()) / 2;
        let mut captured = widths;
        for (i, w) in captured[..n].iter_mut().enumerate() {
            let jitter = if i == 0 || half_step == 0 { 0 } else { noise[i].rem_euclid(2 * half_step) - half_step };
            *w = (i64::from(*w) + i64::from(delay) + jitter) as u32;
        }
        prop_assert_eq!(PwmRepr::parse(frame.kind(), &coding, &captured[..n]), Ok(frame));
    }

    #[test]
    fn decode_never_panics(
        widths in prop::collection::vec(any::<u32>(), 0..24),
        coding in arb_coding(),
        kind in prop::sample::select(vec![PwmFrameKind::Broadcast, PwmFrameKind::Designated, PwmFrameKind::Experiment]),
    ) {
        let parsed = PwmRepr::parse(kind, &coding, &widths);
        if let Ok(frame) = parsed {
            prop_assert_eq!(frame.kind(), kind);
            prop_assert_eq!(frame.symbol_count(), widths.len());
        }
        // The view and the value agree on what is a frame.
        let view = PwmFrame::new_checked(&widths[..], kind, &coding);
        prop_assert_eq!(view.map(|v| PwmRepr::from_frame(&v)), parsed);
    }
}
