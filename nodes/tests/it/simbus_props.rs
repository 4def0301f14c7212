//! Properties of the simulated bus under arbitrary traffic, against an oracle
//! built from the frames' wire intervals.

use nodes::link::{BusConfig, BusEvent, FrameInfo, PortConfig, PortId, SimBus};
use proptest::prelude::*;
use protocols::time::{SimDuration, SimTime};

const PORTS: u16 = 3;

/// One send: which port, how long after the previous send, what bytes.
fn sends() -> impl Strategy<Value = Vec<(u16, u64, Vec<u8>)>> {
    prop::collection::vec(
        (
            0..PORTS,
            // Up to ~2.3 character times between hand-overs: plenty of overlap.
            0u64..15_000_000,
            prop::collection::vec(any::<u8>(), 0..12),
        ),
        1..12,
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    /// Every byte reaches every other port once, in time order; it is flagged
    /// corrupted exactly when it differs from what was sent, and that happens
    /// exactly when its wire time overlaps another port's frame.
    #[test]
    fn delivery_matches_the_wire_intervals(sends in sends(), turnaround_us in 0u64..200, seed: u64) {
        let mut bus = SimBus::new(BusConfig { seed, ..BusConfig::default() }).unwrap();
        for _ in 0..PORTS {
            bus.add_port(PortConfig { turnaround: SimDuration::from_micros(turnaround_us) });
        }
        let char_time = bus.char_time();
        let mut frames: Vec<(FrameInfo, Vec<u8>)> = Vec::new();
        let mut events = Vec::new();
        let mut now = SimTime::ZERO;
        for (port, gap, bytes) in &sends {
            now += SimDuration(*gap);
            // An engine drains what is due before it acts at `now`.
            while let Some(event) = bus.poll_event(now) {
                events.push(event);
            }
            let info = bus.send(now, PortId(*port), bytes).unwrap();
            prop_assert!(info.start >= now + SimDuration::from_micros(turnaround_us));
            frames.push((info, bytes.clone()));
        }
        while let Some(at) = bus.poll_timeout() {
            let event = bus.poll_event(at).unwrap();
            events.push(event);
        }

        // Time order.
        prop_assert!(events.windows(2).all(|w| w[0].at() <= w[1].at()));

        // Collisions: pairs of frames from different ports whose wire time overlaps.
        let overlaps = |a: &FrameInfo, b: &FrameInfo| a.from != b.from && a.start.max(b.start) < a.end.min(b.end);
        let mut pairs = 0;
        for (i, (a, _)) in frames.iter().enumerate() {
            for (b, _) in &frames[i + 1..] {
                pairs += u64::from(overlaps(a, b));
            }
        }
        prop_assert_eq!(bus.stats().collisions, pairs);

        for listener in 0..PORTS {
            let listener = PortId(listener);
            // What the listener should get: (arrival, send order, sent byte, collided).
            let mut expected = Vec::new();
            for (seq, (info, bytes)) in frames.iter().enumerate() {
                if info.from == listener {
                    continue;
                }
                for (i, &byte) in bytes.iter().enumerate() {
                    let begin = info.start + SimDuration(char_time.0 * i as u64);
                    let end = begin + char_time;
                    let collided = frames.iter().any(|(other, b)| {
                        other.from != info.from && !b.is_empty() && begin.max(other.start) < end.min(other.end)
                    });
                    expected.push((end, seq, byte, collided));
                }
            }
            expected.sort_by_key(|&(at, seq, _, _)| (at, seq));
            let got: Vec<(SimTime, u8, bool)> = events
                .iter()
                .filter_map(|e| match *e {
                    BusEvent::Byte { to, at, byte, corrupted, .. } if to == listener => Some((at, byte, corrupted)),
                    _ => None,
                })
                .collect();
            prop_assert_eq!(got.len(), expected.len());
            for (&(at, byte, corrupted), &(want_at, _, sent, collided)) in got.iter().zip(&expected) {
                prop_assert_eq!(at, want_at);
                prop_assert_eq!(corrupted, collided);
                prop_assert_eq!(byte != sent, collided);
            }
        }

        // Each frame's end is reported to its sender once.
        let dones = events.iter().filter(|e| matches!(e, BusEvent::TransmitDone { .. })).count();
        prop_assert_eq!(dones, frames.len());
        prop_assert_eq!(bus.poll_timeout(), None);
    }
}
