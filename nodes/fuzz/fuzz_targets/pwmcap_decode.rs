//! Any captured widths, any coding and frame kind: decoding never panics, and a
//! decoded frame re-emits to widths that decode to the same frame.
//!
//! Input layout: data bits, dummy bits, start width (2 bytes LE), kind, then the
//! captured widths as u32 LE.
#![no_main]

use libfuzzer_sys::fuzz_target;
use protocols::pwmcap::{PWM_MAX_SYMBOLS, PwmCoding, PwmFrameKind, PwmRepr};

fuzz_target!(|data: &[u8]| {
    let [data_bits, dummy_bits, s0, s1, kind, widths @ ..] = data else {
        return;
    };
    let Ok(coding) = PwmCoding::new(
        150_000_000,
        *data_bits,
        *dummy_bits,
        u32::from(u16::from_le_bytes([*s0, *s1])),
    ) else {
        return;
    };
    let kind = match kind % 3 {
        0 => PwmFrameKind::Broadcast,
        1 => PwmFrameKind::Designated,
        _ => PwmFrameKind::Experiment,
    };
    let widths: Vec<u32> = widths
        .chunks_exact(4)
        .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
        .collect();
    if let Ok(frame) = PwmRepr::parse(kind, &coding, &widths) {
        let mut out = [0u32; PWM_MAX_SYMBOLS];
        let n = frame
            .emit(&coding, &mut out)
            .expect("a decoded frame emits");
        assert_eq!(n, widths.len());
        assert_eq!(PwmRepr::parse(kind, &coding, &out[..n]), Ok(frame));
    }
});
