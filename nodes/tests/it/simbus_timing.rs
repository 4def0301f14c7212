//! The simulated RS-485 bus: wire time, turnaround, collisions, wiring and
//! event order, checked against exact tick arithmetic.

use nodes::link::{BusConfig, BusEvent, PortConfig, PortId, SimBus, Wiring};
use protocols::time::{SimDuration, SimTime, TICKS_PER_SECOND};

/// A port that starts sending the instant it is asked to.
const NO_TURNAROUND: PortConfig = PortConfig {
    turnaround: SimDuration::ZERO,
};

/// One delivered byte: (listener, arrival, byte, corrupted).
type Arrival = (PortId, SimTime, u8, bool);

/// Drains every event, jumping virtual time to each in turn.
fn drain(bus: &mut SimBus) -> Vec<BusEvent> {
    let mut events = Vec::new();
    while let Some(at) = bus.poll_timeout() {
        let event = bus
            .poll_event(at)
            .expect("an event is due at its own timeout");
        assert_eq!(event.at(), at);
        events.push(event);
    }
    events
}

fn bytes_to(events: &[BusEvent], port: PortId) -> Vec<Arrival> {
    events
        .iter()
        .filter_map(|e| match *e {
            BusEvent::Byte {
                to,
                at,
                byte,
                corrupted,
                ..
            } if to == port => Some((to, at, byte, corrupted)),
            _ => None,
        })
        .collect()
}

fn done_of(events: &[BusEvent], port: PortId) -> Vec<SimTime> {
    events
        .iter()
        .filter_map(|e| match *e {
            BusEvent::TransmitDone { port: p, at } if p == port => Some(at),
            _ => None,
        })
        .collect()
}

const REQUEST: [u8; 8] = [0x01, 0x03, 0x00, 0x01, 0x00, 0x00, 0x0a, 0x14];
const REPLY: [u8; 8] = [0x01, 0x03, 0x00, 0x01, 0x00, 0x01, 0xca, 0xd5];

#[test]
fn an_8_byte_frame_occupies_80_bit_times_and_its_last_byte_arrives_then() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let master = bus.add_port(NO_TURNAROUND);
    let slave = bus.add_port(NO_TURNAROUND);
    let t0 = SimTime(123_456_789);
    let info = bus.send(t0, master, &REQUEST).unwrap();

    // 8 × 10 / 115200 s = 694.4 µs: exactly 50 000 000 ticks.
    assert_eq!((info.end - info.start).0 * 115_200, 80 * TICKS_PER_SECOND);
    assert_eq!(info.start, t0);
    assert_eq!(bus.char_time(), SimDuration(6_250_000));
    assert_eq!(bus.busy_until(), info.end);

    let events = drain(&mut bus);
    let got = bytes_to(&events, slave);
    assert_eq!(got.len(), 8);
    for (i, &(_, at, byte, corrupted)) in got.iter().enumerate() {
        // Byte i's stop bit ends (i + 1) character times after the start bit.
        assert_eq!(
            at.0 - t0.0,
            (i as u64 + 1) * 10 * TICKS_PER_SECOND / 115_200
        );
        assert_eq!(byte, REQUEST[i]);
        assert!(!corrupted);
    }
    assert_eq!(got.last().map(|b| b.1), Some(info.end));
    assert_eq!(done_of(&events, master), vec![info.end]);
    // The last byte is handed over before the sender hears it is done.
    assert!(matches!(events.last(), Some(BusEvent::TransmitDone { .. })));
    assert_eq!(bus.stats().bytes_sent, 8);
    assert_eq!(bus.stats().bytes_delivered, 8);
}

#[test]
fn a_reply_starts_exactly_one_turnaround_after_the_requests_last_stop_bit() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let master = bus.add_port(NO_TURNAROUND);
    let slave = bus.add_port(PortConfig::default());
    assert_eq!(
        bus.port_config(slave).unwrap().turnaround,
        SimDuration::from_millis(1)
    );

    let request = bus.send(SimTime::ZERO, master, &REQUEST).unwrap();
    let events = drain(&mut bus);
    let heard_at = bytes_to(&events, slave).last().unwrap().1;
    assert_eq!(heard_at, request.end);

    // The slave answers the instant it has the frame; the bus adds its turnaround.
    let reply = bus.send(heard_at, slave, &REPLY).unwrap();
    assert_eq!(reply.start, request.end + SimDuration::from_millis(1));
    let events = drain(&mut bus);
    let answer = bytes_to(&events, master);
    assert_eq!(answer.iter().map(|b| b.2).collect::<Vec<_>>(), REPLY);
    assert_eq!(answer.last().unwrap().1, reply.end);

    // 8 + 8 bytes at 115200 baud: 1.3889 ms of wire, plus the turnaround.
    let wire = (request.end - request.start) + (reply.end - reply.start);
    assert_eq!(wire.0 * 115_200, 160 * TICKS_PER_SECOND);
    assert_eq!((wire.as_secs_f64() * 1e6).round(), 1389.0);
    let transaction = reply.end - request.start;
    assert_eq!(transaction, wire + SimDuration::from_millis(1));
}

#[test]
fn other_framings_and_bauds_are_exact_too() {
    for (baud, bits) in [(9600u32, 11u32), (19_200, 10), (57_600, 12), (921_600, 11)] {
        let config = BusConfig {
            baud,
            bits_per_char: bits,
            ..BusConfig::default()
        };
        let mut bus = SimBus::new(config).unwrap();
        let a = bus.add_port(NO_TURNAROUND);
        bus.add_port(NO_TURNAROUND);
        let info = bus.send(SimTime::ZERO, a, &[0x55; 13]).unwrap();
        assert_eq!(
            u128::from(info.end.0) * u128::from(baud),
            13 * u128::from(bits) * u128::from(TICKS_PER_SECOND),
            "{baud} baud, {bits} bits"
        );
    }
}

#[test]
fn a_ports_second_frame_queues_behind_its_first_without_a_collision() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let a = bus.add_port(NO_TURNAROUND);
    let b = bus.add_port(NO_TURNAROUND);
    let first = bus.send(SimTime::ZERO, a, &REQUEST).unwrap();
    let second = bus.send(SimTime::ZERO, a, &REPLY).unwrap();
    assert_eq!(second.start, first.end);
    let events = drain(&mut bus);
    let got: Vec<u8> = bytes_to(&events, b).iter().map(|x| x.2).collect();
    assert_eq!(got, [REQUEST, REPLY].concat());
    assert_eq!(bus.stats().collisions, 0);
    assert_eq!(done_of(&events, a), vec![first.end, second.end]);
}

#[test]
fn overlapping_frames_garble_both_the_same_for_every_listener_and_count_a_collision() {
    let mut bus = SimBus::new(BusConfig {
        seed: 9,
        ..BusConfig::default()
    })
    .unwrap();
    let a = bus.add_port(NO_TURNAROUND);
    let b = bus.add_port(NO_TURNAROUND);
    let c = bus.add_port(NO_TURNAROUND);
    let char_time = bus.char_time();
    let from_a = [0xA0, 0xA1, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7];
    let from_b = [0xB0, 0xB1, 0xB2, 0xB3, 0xB4, 0xB5, 0xB6, 0xB7];
    bus.send(SimTime::ZERO, a, &from_a).unwrap();
    // B starts talking half-way through A's fifth byte: A's bytes 4..8 and
    // B's bytes 0..4 share the wire (B's byte 3 ends half a character after A).
    let b_start = SimTime(char_time.0 * 9 / 2);
    bus.send(b_start, b, &from_b).unwrap();
    assert_eq!(bus.stats().collisions, 1);
    assert_eq!(bus.stats().bytes_garbled_by_collision, 8);

    let events = drain(&mut bus);
    let c_bytes = bytes_to(&events, c);
    assert_eq!(c_bytes.len(), 16);
    // C hears both frames interleaved by arrival time; split them back by time.
    let (a_at_c, b_at_c): (Vec<Arrival>, Vec<Arrival>) =
        c_bytes.iter().partition(|x| (x.1.0 % char_time.0) == 0);
    for (i, &(_, _, byte, corrupted)) in a_at_c.iter().enumerate() {
        let collided = i >= 4;
        assert_eq!(corrupted, collided, "A byte {i}");
        assert_eq!(byte != from_a[i], collided, "A byte {i}");
    }
    for (i, &(_, _, byte, corrupted)) in b_at_c.iter().enumerate() {
        let collided = i < 4;
        assert_eq!(corrupted, collided, "B byte {i}");
        assert_eq!(byte != from_b[i], collided, "B byte {i}");
    }
    // The garbled line reads the same at every receiver.
    let a_at_b: Vec<u8> = bytes_to(&events, b).iter().map(|x| x.2).collect();
    let b_at_a: Vec<u8> = bytes_to(&events, a).iter().map(|x| x.2).collect();
    assert_eq!(a_at_b, a_at_c.iter().map(|x| x.2).collect::<Vec<_>>());
    assert_eq!(b_at_a, b_at_c.iter().map(|x| x.2).collect::<Vec<_>>());
}

#[test]
fn frames_that_touch_without_overlap_do_not_collide() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let a = bus.add_port(NO_TURNAROUND);
    let b = bus.add_port(NO_TURNAROUND);
    let first = bus.send(SimTime::ZERO, a, &REQUEST).unwrap();
    bus.send(first.end, b, &REPLY).unwrap();
    let events = drain(&mut bus);
    assert_eq!(bus.stats().collisions, 0);
    assert!(events.iter().all(|e| !matches!(
        e,
        BusEvent::Byte {
            corrupted: true,
            ..
        }
    )));
}

#[test]
fn nobody_hears_itself_and_slaves_never_hear_each_other() {
    // Multi-drop: everyone but the sender.
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let ports: Vec<PortId> = (0..4).map(|_| bus.add_port(NO_TURNAROUND)).collect();
    let mut t = SimTime::ZERO;
    for &from in &ports {
        let info = bus.send(t, from, &REQUEST).unwrap();
        t = info.end;
        let events = drain(&mut bus);
        for &to in &ports {
            let heard = bytes_to(&events, to).len();
            assert_eq!(heard, if to == from { 0 } else { 8 }, "{from:?} -> {to:?}");
        }
    }

    // Master and slaves (as in the Controller_network project): master on port 0.
    let mut bus = SimBus::new(BusConfig {
        wiring: Wiring::MasterSlaves { master: PortId(0) },
        ..BusConfig::default()
    })
    .unwrap();
    let master = bus.add_port(NO_TURNAROUND);
    let motor = bus.add_port(NO_TURNAROUND);
    let light = bus.add_port(NO_TURNAROUND);
    let info = bus.send(SimTime::ZERO, master, &REQUEST).unwrap();
    let events = drain(&mut bus);
    assert_eq!(bytes_to(&events, master).len(), 0);
    assert_eq!(bytes_to(&events, motor).len(), 8);
    assert_eq!(bytes_to(&events, light).len(), 8);
    for slave in [motor, light] {
        bus.send(info.end, slave, &REPLY).unwrap();
        let events = drain(&mut bus);
        assert_eq!(bytes_to(&events, master).len(), 8);
        assert_eq!(
            bytes_to(&events, motor).len() + bytes_to(&events, light).len(),
            0
        );
    }
}

#[test]
fn events_come_in_time_order_with_ties_in_send_order_then_port_order() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let a = bus.add_port(NO_TURNAROUND);
    let b = bus.add_port(NO_TURNAROUND);
    let c = bus.add_port(NO_TURNAROUND);
    // Nothing due before the first arrival.
    let info = bus.send(SimTime::ZERO, b, &[0x11, 0x22]).unwrap();
    assert_eq!(bus.poll_timeout(), Some(SimTime::ZERO + bus.char_time()));
    assert_eq!(bus.poll_event(SimTime(bus.char_time().0 - 1)), None);
    let events = drain(&mut bus);
    let order: Vec<(PortId, u8)> = events
        .iter()
        .map(|e| match *e {
            BusEvent::Byte { to, byte, .. } => (to, byte),
            BusEvent::TransmitDone { port, .. } => (port, 0xDD),
        })
        .collect();
    assert_eq!(
        order,
        vec![(a, 0x11), (c, 0x11), (a, 0x22), (c, 0x22), (b, 0xDD)]
    );
    assert_eq!(events.last().map(BusEvent::at), Some(info.end));
    assert_eq!(bus.poll_timeout(), None);
}

#[test]
fn an_empty_frame_only_reports_its_end() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let a = bus.add_port(NO_TURNAROUND);
    bus.add_port(NO_TURNAROUND);
    let info = bus.send(SimTime(5), a, &[]).unwrap();
    assert_eq!(info.start, info.end);
    assert_eq!(
        drain(&mut bus),
        vec![BusEvent::TransmitDone {
            port: a,
            at: SimTime(5)
        }]
    );
}

#[test]
fn a_frame_handed_over_late_never_starts_before_what_was_already_delivered() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let a = bus.add_port(NO_TURNAROUND);
    let b = bus.add_port(NO_TURNAROUND);
    let first = bus.send(SimTime::ZERO, a, &REQUEST).unwrap();
    // Deliver the first three bytes, then let B "send" at t = 0: it cannot
    // garble bytes A's listeners already have, so it starts at the third arrival.
    let third = SimTime::ZERO + bus.wire_time(3);
    while bus.poll_event(third).is_some() {}
    let late = bus.send(SimTime::ZERO, b, &REPLY).unwrap();
    assert_eq!(late.start, third);
    assert_eq!(bus.stats().collisions, 1);
    let events = drain(&mut bus);
    // A's remaining five bytes all overlap B's frame.
    let at_b = bytes_to(&events, b);
    assert_eq!(at_b.len(), 5);
    assert!(at_b.iter().all(|x| x.3));
    assert_eq!(at_b.last().unwrap().1, first.end);
}
