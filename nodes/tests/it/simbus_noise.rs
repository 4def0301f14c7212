//! Line noise on the simulated bus: statistics against the binomial law, and
//! bit-for-bit determinism under a seed.

use nodes::link::{BusConfig, BusEvent, PortConfig, SimBus};
use protocols::time::{SimDuration, SimTime};

const FRAME: usize = 500;

/// Sends `frames` frames of 500 bytes (a counting pattern) from port 0 to port 1
/// and returns every event.
fn run(config: BusConfig, frames: usize) -> (Vec<BusEvent>, Vec<u8>, SimBus) {
    let mut bus = SimBus::new(config).unwrap();
    let from = bus.add_port(PortConfig {
        turnaround: SimDuration::ZERO,
    });
    bus.add_port(PortConfig::default());
    let mut sent = Vec::with_capacity(frames * FRAME);
    let mut events = Vec::with_capacity(frames * (FRAME + 1));
    let mut frame = [0u8; FRAME];
    let mut now = SimTime::ZERO;
    for k in 0..frames {
        for (i, b) in frame.iter_mut().enumerate() {
            *b = (k * 7 + i) as u8;
        }
        sent.extend_from_slice(&frame);
        now = bus.send(now, from, &frame).unwrap().end;
        while let Some(event) = bus.poll_event(now) {
            events.push(event);
        }
    }
    (events, sent, bus)
}

#[test]
fn corrupted_byte_fraction_at_1e_3_matches_the_binomial_law_within_5_sigma() {
    let p = 1e-3;
    let config = BusConfig {
        bit_error_rate: p,
        seed: 0x5EED,
        ..BusConfig::default()
    };
    let (events, sent, bus) = run(config, 2_000);
    let received: Vec<(u8, bool)> = events
        .iter()
        .filter_map(|e| match *e {
            BusEvent::Byte {
                byte, corrupted, ..
            } => Some((byte, corrupted)),
            BusEvent::TransmitDone { .. } => None,
        })
        .collect();
    let n = received.len();
    assert_eq!(n, 1_000_000);
    assert_eq!(sent.len(), n);

    // `corrupted` says exactly whether the byte differs from what was sent.
    let mut corrupted = 0u64;
    let mut flipped = 0u64;
    for (&(byte, flag), &original) in received.iter().zip(&sent) {
        assert_eq!(flag, byte != original);
        corrupted += u64::from(flag);
        flipped += u64::from((byte ^ original).count_ones());
    }
    assert_eq!(corrupted, bus.stats().bytes_corrupted_by_noise);
    assert_eq!(flipped, bus.stats().bits_flipped);

    let q = 1.0 - (1.0 - p).powi(8);
    let mean = n as f64 * q;
    let sigma = (n as f64 * q * (1.0 - q)).sqrt();
    println!(
        "{corrupted} of {n} bytes corrupted (expected {mean:.0} ± {sigma:.0}), {flipped} bits flipped"
    );
    assert!(
        (corrupted as f64 - mean).abs() < 5.0 * sigma,
        "{corrupted} corrupted bytes, expected {mean:.0} ± {sigma:.0}"
    );
    let bits = 8.0 * n as f64;
    let bit_sigma = (bits * p * (1.0 - p)).sqrt();
    assert!(
        (flipped as f64 - bits * p).abs() < 5.0 * bit_sigma,
        "{flipped} flipped bits, expected {} ± {bit_sigma:.0}",
        bits * p
    );
    assert_eq!(bus.stats().collisions, 0);
}

#[test]
fn no_noise_means_no_corruption() {
    let (events, sent, bus) = run(BusConfig::default(), 50);
    let received: Vec<u8> = events
        .iter()
        .filter_map(|e| match *e {
            BusEvent::Byte {
                byte,
                corrupted: false,
                ..
            } => Some(byte),
            _ => None,
        })
        .collect();
    assert_eq!(received, sent);
    assert_eq!(bus.stats().bytes_corrupted_by_noise, 0);
}

/// A noisy run with collisions: three ports talking over each other.
fn noisy_collisions(seed: u64) -> Vec<BusEvent> {
    let mut bus = SimBus::new(BusConfig {
        bit_error_rate: 1e-2,
        seed,
        ..BusConfig::default()
    })
    .unwrap();
    let ports: Vec<_> = (0..3)
        .map(|_| {
            bus.add_port(PortConfig {
                turnaround: SimDuration::from_micros(10),
            })
        })
        .collect();
    let mut events = Vec::new();
    let mut now = SimTime::ZERO;
    for round in 0..200u64 {
        for (k, &port) in ports.iter().enumerate() {
            let frame = [round as u8; 25];
            bus.send(now + SimDuration::from_micros(97 * k as u64), port, &frame)
                .unwrap();
        }
        now = bus.busy_until();
        while let Some(event) = bus.poll_event(now) {
            events.push(event);
        }
    }
    assert!(bus.stats().collisions >= 200);
    events
}

#[test]
fn the_same_seed_gives_identical_runs_and_another_seed_does_not() {
    let first = noisy_collisions(1);
    let second = noisy_collisions(1);
    assert_eq!(first, second);
    assert!(first.len() > 10_000);
    assert_ne!(first, noisy_collisions(2));
}
