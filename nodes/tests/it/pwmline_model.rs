//! The PWM-capture line model against the analytic RC response.

use nodes::link::pwmline::{PwmCalibration, PwmLine, PwmLineError, PwmLineParams, decode_captured};
use protocols::pwmcap::PwmCoding;

const CLOCK_HZ: u32 = 150_000_000;

/// 10 m of cable with 20 Ω and 20 nF added: τ ≈ 138 ticks, slow enough that
/// the RC response dominates the one-tick capture quantisation.
fn slow_line(noise_volts_rms: f64) -> PwmLineParams {
    PwmLineParams {
        added_series_ohm: 20.0,
        added_shunt_farad: 20e-9,
        noise_volts_rms,
        ..PwmLineParams::DEFAULT
    }
}

/// Captured width of one pulse of `width` ticks from a settled line, noise
/// free: rising crossing τ·ln(V/(V−Vth)) after the rising edge, falling
/// crossing τ·ln(v₁/Vth) after the falling edge, v₁ = V(1 − e^{−W/τ}).
fn analytic_width(params: &PwmLineParams, width: f64) -> f64 {
    let tau = params.time_constant_s() * f64::from(CLOCK_HZ);
    let (v, th) = (params.drive_volts, params.threshold_volts);
    let v1 = v * (1.0 - (-width / tau).exp());
    width + tau * (v1 / th).ln() - tau * (v / (v - th)).ln()
}

#[test]
fn time_constant_is_lumped_r_times_c() {
    let p = slow_line(0.0);
    let r = 23.0 + 0.188 * 10.0 + 20.0;
    let c = 50e-12 * 10.0 + 20e-9 + 5e-12;
    assert!((p.time_constant_s() - r * c).abs() < 1e-15);
    let line = PwmLine::new(p, CLOCK_HZ, 0).unwrap();
    assert!((line.tau_ticks() - r * c * 150e6).abs() < 1e-9);
}

#[test]
fn single_pulse_width_matches_the_exact_rc_response() {
    let params = slow_line(0.0);
    let mut line = PwmLine::new(params, CLOCK_HZ, 11).unwrap();
    let mut captured = [0u32; 1];
    for width in [120u32, 150, 200, 300, 600, 1000] {
        let expected = analytic_width(&params, f64::from(width));
        for _ in 0..20 {
            let got = line.transmit(&[width], 4000, &mut captured).unwrap();
            assert_eq!(got, 1, "pulse of {width} ticks lost");
            // Counter quantisation: floor of two edges, so within one tick.
            let error = f64::from(captured[0]) - expected;
            assert!(
                error.abs() < 1.0,
                "width {width}: captured {} vs {expected}",
                captured[0]
            );
        }
    }
    // A 200-tick start really shrinks on this line (≈ 37 ticks), the point of the model.
    assert!(analytic_width(&params, 200.0) < 170.0);
}

#[test]
fn pulse_too_short_to_reach_the_threshold_is_not_captured() {
    let params = slow_line(0.0);
    let tau = params.time_constant_s() * f64::from(CLOCK_HZ);
    // With Vth = V/2 the line needs τ·ln 2 ≈ 96 ticks to rise past it.
    let too_short = (tau * 2f64.ln()).floor() as u32 - 2;
    let mut line = PwmLine::new(params, CLOCK_HZ, 1).unwrap();
    let mut captured = [0u32; 1];
    assert_eq!(line.transmit(&[too_short], 4000, &mut captured).unwrap(), 0);
    assert_eq!(
        line.transmit(&[too_short + 6], 4000, &mut captured)
            .unwrap(),
        1
    );
}

#[test]
fn short_off_gap_merges_pulses() {
    let params = slow_line(0.0);
    let mut line = PwmLine::new(params, CLOCK_HZ, 2).unwrap();
    let mut captured = [0u32; 3];
    // 1000 ticks high, 20 low: the line cannot fall back to V/2 (needs ≈ 96).
    assert_eq!(
        line.transmit(&[1000, 1000, 1000], 1020, &mut captured)
            .unwrap(),
        1
    );
    // 400 ticks low is plenty.
    assert_eq!(
        line.transmit(&[1000, 1000, 1000], 1400, &mut captured)
            .unwrap(),
        3
    );
}

#[test]
fn comparator_noise_jitters_widths_as_noise_over_slope() {
    let sigma = 0.05;
    let params = slow_line(sigma);
    let tau = params.time_constant_s() * f64::from(CLOCK_HZ);
    let mut line = PwmLine::new(params, CLOCK_HZ, 5).unwrap();
    let mut captured = [0u32; 1];
    let n = 4000;
    let (mut sum, mut sum_sq) = (0.0, 0.0);
    for _ in 0..n {
        assert_eq!(line.transmit(&[1500], 8000, &mut captured).unwrap(), 1);
        let w = f64::from(captured[0]);
        sum += w;
        sum_sq += w * w;
    }
    let mean = sum / f64::from(n);
    let std = (sum_sq / f64::from(n) - mean * mean).sqrt();
    // Both crossings at V/2 after settling: slope (V/2)/τ, independent samples.
    let slope = params.threshold_volts / tau;
    let edge = sigma / slope;
    // Plus the difference of two uniform quantisation errors (variance 1/6).
    let expected = (2.0 * edge * edge + 1.0 / 6.0).sqrt();
    assert!(
        (std / expected - 1.0).abs() < 0.1,
        "std {std} vs {expected}"
    );
    assert!((mean - 1500.0).abs() < 0.5, "mean {mean}");
}

#[test]
fn same_seed_same_captures_other_seed_differs() {
    let run = |seed| {
        let mut line = PwmLine::new(slow_line(0.05), CLOCK_HZ, seed).unwrap();
        let mut out = [[0u32; 3]; 50];
        for row in &mut out {
            line.transmit(&[300, 700, 500], 2000, row).unwrap();
        }
        out
    };
    assert_eq!(run(9), run(9));
    assert_ne!(run(9), run(10));
}

#[test]
fn start_compensation_cancels_a_line_delay_on_a_fast_line() {
    // The bare 10 m line: τ ≈ 2 ticks, every width settles, values come back exact.
    let mut line = PwmLine::new(PwmLineParams::DEFAULT, CLOCK_HZ, 3).unwrap();
    let coding = PwmCoding::PAPER;
    let values = [0u16, 1, 127, 128, 200, 254];
    let mut decoded = [None; 6];
    for _ in 0..50 {
        line.send_values(&coding, 0, &values, &mut decoded).unwrap();
        assert_eq!(decoded, values.map(Some));
    }
}

#[test]
fn lost_symbols_decode_as_none() {
    let coding = PwmCoding::PAPER;
    let mut decoded = [Some(1); 4];
    // Start 200, one value of 3 (width 212), then nothing.
    decode_captured(&coding, &[199, 211], &mut decoded);
    assert_eq!(decoded, [Some(3), None, None, None]);
    decode_captured(&coding, &[], &mut decoded);
    assert_eq!(decoded, [None; 4]);
    // Merged pulse: far above the range.
    decode_captured(&coding, &[200, 5000], &mut decoded);
    assert_eq!(decoded[0], None);
}

#[test]
fn calibration_lengthens_the_start_only_on_a_slow_line() {
    let coding = PwmCoding::PAPER;
    let mut fast = PwmLine::new(PwmLineParams::DEFAULT, CLOCK_HZ, 4).unwrap();
    let found = PwmCalibration::find(&mut fast, &coding).unwrap().unwrap();
    assert_eq!(found.guard_ticks, 0);
    assert_eq!(found.coding, coding);

    let mut slow = PwmLine::new(slow_line(0.5e-3), CLOCK_HZ, 4).unwrap();
    let found = PwmCalibration::find(&mut slow, &coding).unwrap().unwrap();
    // The start must at least rise past the threshold and settle: several τ.
    assert!(found.coding.start_ticks() > 200 + 2 * 138, "{found:?}");
    let mut decoded = [None; 4];
    let values = [0u16, 255, 255, 0];
    slow.send_values(&found.coding, found.guard_ticks, &values, &mut decoded)
        .unwrap();
    assert_eq!(decoded, values.map(Some));
}

#[test]
fn bad_parameters_and_widths_are_errors_not_panics() {
    let bad = PwmLineParams {
        threshold_volts: 5.0,
        ..PwmLineParams::DEFAULT
    };
    assert_eq!(
        PwmLine::new(bad, CLOCK_HZ, 0).unwrap_err(),
        PwmLineError::InvalidParameter("threshold_volts")
    );
    let nan = PwmLineParams {
        cable_length_m: f64::NAN,
        ..PwmLineParams::DEFAULT
    };
    assert!(PwmLine::new(nan, CLOCK_HZ, 0).is_err());
    assert!(PwmLine::new(PwmLineParams::DEFAULT, 0, 0).is_err());
    let mut line = PwmLine::new(PwmLineParams::DEFAULT, CLOCK_HZ, 0).unwrap();
    let mut captured = [0u32; 2];
    assert_eq!(
        line.transmit(&[100, 500], 500, &mut captured).unwrap_err(),
        PwmLineError::WidthNotBelowPeriod {
            width: 500,
            period: 500
        }
    );
    // More values than a frame holds: an error, not an index panic.
    let mut decoded = [None; 40];
    assert!(
        line.send_values(&PwmCoding::PAPER, 0, &[0; 40], &mut decoded)
            .is_err()
    );
}

#[test]
fn the_elmore_cable_charges_only_what_lies_downstream() {
    use nodes::link::CableModel;
    let lumped = PwmLineParams {
        cable_length_m: 100.0,
        added_series_ohm: 20.0,
        added_shunt_farad: 20e-9,
        ..PwmLineParams::DEFAULT
    };
    let elmore = PwmLineParams {
        cable_model: CableModel::Elmore,
        ..lumped
    };
    let (cable_r, cable_c) = (0.188 * 100.0, 50e-12 * 100.0);
    let load_c = 20e-9 + 5e-12;
    let expected = 23.0 * (cable_c + load_c) + cable_r * (cable_c / 2.0 + load_c) + 20.0 * load_c;
    assert!((elmore.time_constant_s() - expected).abs() < 1e-15);
    // Lumped minus Elmore: the cable's own r·c/2 and the added R times the cable's C.
    let difference = cable_r * cable_c / 2.0 + 20.0 * cable_c;
    assert!((lumped.time_constant_s() - elmore.time_constant_s() - difference).abs() < 1e-15);
    // No cable, no difference.
    let short = |model| PwmLineParams {
        cable_length_m: 0.0,
        cable_model: model,
        ..lumped
    };
    let (a, b) = (
        short(CableModel::Lumped).time_constant_s(),
        short(CableModel::Elmore).time_constant_s(),
    );
    assert!((a - b).abs() < 1e-18, "{a} vs {b}");
}
