//! The PWM-capture medium: what each listener's capture unit gets, when, and
//! who may drive the line (half duplex with enable, full duplex).

use nodes::link::{BusError, BusEvent, PortConfig, PortId, PwmBus, PwmBusConfig, PwmDuplex};
use nodes::parallel::{PwmReceiver, RxOutcome};
use protocols::pwmcap::PwmCoding;
use protocols::time::{SimDuration, SimTime};

fn quiet_config(duplex: PwmDuplex) -> PwmBusConfig {
    let mut config = PwmBusConfig {
        duplex,
        seed: 7,
        ..PwmBusConfig::default()
    };
    config.line.cable_length_m = 1.0;
    config.line.noise_volts_rms = 0.0;
    config
}

fn frame(widths: &[u32]) -> Vec<u8> {
    widths.iter().flat_map(|w| w.to_le_bytes()).collect()
}

fn port() -> PortConfig {
    PortConfig {
        turnaround: SimDuration::ZERO,
    }
}

/// Every event, in delivery order.
fn drain(bus: &mut PwmBus) -> Vec<BusEvent> {
    let mut events = Vec::new();
    while let Some(t) = bus.poll_timeout() {
        while let Some(e) = bus.poll_event(t) {
            events.push(e);
        }
    }
    events
}

/// Per listener: the widths of its capture records and when each landed.
fn records(events: &[BusEvent], listener: PortId) -> Vec<(u32, SimTime)> {
    let bytes: Vec<(u8, SimTime)> = events
        .iter()
        .filter_map(|e| match *e {
            BusEvent::Byte { to, byte, at, .. } if to == listener => Some((byte, at)),
            _ => None,
        })
        .collect();
    bytes
        .chunks(4)
        .map(|c| {
            let width = u32::from_le_bytes([c[0].0, c[1].0, c[2].0, c[3].0]);
            (width, c[3].1)
        })
        .collect()
}

#[test]
fn each_listener_gets_every_width_at_its_falling_edge() {
    let mut bus = PwmBus::new(quiet_config(PwmDuplex::Half)).expect("link");
    let master = bus.add_port(port());
    let listeners = [bus.add_port(port()), bus.add_port(port())];
    let widths = [200, 300, 500, 1100];
    let start = SimTime::ZERO + SimDuration::from_micros(10);
    let info = bus.send(start, master, &frame(&widths)).expect("sent");
    let period = f64::from(bus.period_ticks());
    assert_eq!(info.start, start);
    let tick = 1.0 / 150e6;
    assert!((info.end.as_secs_f64() - start.as_secs_f64() - 4.0 * period * tick).abs() < 1e-11);
    let events = drain(&mut bus);
    // τ·ln 2 after each sender edge, the comparator flips (τ is under a tick here).
    let tau = quiet_config(PwmDuplex::Half).line.time_constant_s();
    for listener in listeners {
        let got = records(&events, listener);
        assert_eq!(
            got.iter().map(|r| r.0).collect::<Vec<_>>(),
            widths,
            "{listener:?}"
        );
        for (i, (width, at)) in got.iter().enumerate() {
            let fall = start.as_secs_f64() + (i as f64 * period + f64::from(*width)) * tick;
            let expected = fall + tau * std::f64::consts::LN_2;
            assert!(
                (at.as_secs_f64() - expected).abs() < 1e-9,
                "symbol {i}: {at:?}"
            );
        }
    }
    assert!(records(&events, master).is_empty(), "nobody hears itself");
    assert_eq!(
        events.last(),
        Some(&BusEvent::TransmitDone {
            port: master,
            at: info.end
        })
    );
    let stats = bus.pwm_stats();
    assert_eq!(
        (
            stats.receptions,
            stats.receptions_clean,
            stats.symbols_wrong
        ),
        (2, 2, 0)
    );
}

#[test]
fn half_duplex_waits_for_the_enable_full_duplex_does_not() {
    let widths = frame(&[200, 276, 200, 400]);
    let now = SimTime::ZERO;

    let mut half = PwmBus::new(quiet_config(PwmDuplex::Half)).expect("link");
    let (m, s1, s2) = (
        half.add_port(port()),
        half.add_port(port()),
        half.add_port(port()),
    );
    let first = half.send(now, m, &widths).expect("master");
    let second = half.send(now, s1, &widths).expect("slave");
    assert_eq!(
        second.start, first.end,
        "the slave waits until the master drops its enable"
    );
    assert_eq!(half.pwm_stats().frames_deferred, 1);
    let events = drain(&mut half);
    assert_eq!(
        records(&events, s2).len(),
        8,
        "a third port hears both on one pair"
    );

    let mut full = PwmBus::new(quiet_config(PwmDuplex::Full { master: PortId(0) })).expect("link");
    let (m, s1, s2) = (
        full.add_port(port()),
        full.add_port(port()),
        full.add_port(port()),
    );
    let down = full.send(now, m, &widths).expect("master");
    let up = full.send(now, s1, &widths).expect("slave");
    assert_eq!(
        (down.start, up.start),
        (now, now),
        "two pairs: both talk at once"
    );
    let events = drain(&mut full);
    assert_eq!(records(&events, m).len(), 4, "the master hears the slave");
    assert_eq!(
        records(&events, s2).len(),
        4,
        "a slave hears only the master"
    );
    assert_eq!(records(&events, s1).len(), 4);
}

#[test]
fn malformed_frames_are_refused_and_nothing_is_sent() {
    let mut bus = PwmBus::new(quiet_config(PwmDuplex::Half)).expect("link");
    let p = bus.add_port(port());
    bus.add_port(port());
    let period = bus.period_ticks();
    for bytes in [
        vec![1, 2, 3],
        vec![],
        frame(&[200, period]),
        frame(&[0, 200]),
    ] {
        assert!(matches!(
            bus.send(SimTime::ZERO, p, &bytes),
            Err(BusError::Malformed(_))
        ));
    }
    assert_eq!(
        bus.send(SimTime::ZERO, PortId(9), &frame(&[200])),
        Err(BusError::UnknownPort(PortId(9)))
    );
    assert_eq!(bus.poll_timeout(), None);
    assert_eq!(bus.pwm_stats().frames_sent, 0);
}

#[test]
fn the_receiver_frames_by_rising_edges_and_times_out_a_short_frame() {
    let coding = PwmCoding::PAPER;
    let period = coding.symbol_period_ticks();
    let mut rx = PwmReceiver::new(&coding, period);
    let tick = |t: u64| SimTime::ZERO + coding.ticks_to_duration(t);
    let push = |rx: &mut PwmReceiver, fall: u64, width: u32| {
        width
            .to_le_bytes()
            .into_iter()
            .filter_map(|b| rx.push(tick(fall), b))
            .last()
    };
    let p = u64::from(period);
    // Falling edges far apart (short then long pulse) but rising edges one period apart.
    assert_eq!(push(&mut rx, 200, 200), None);
    assert_eq!(push(&mut rx, p + 1200, 1200), None);
    assert_eq!(push(&mut rx, 2 * p + 200, 200), None);
    assert_eq!(
        push(&mut rx, 3 * p + 300, 300),
        Some(RxOutcome::Frame([200, 1200, 200, 300]))
    );
    // A frame that loses its third pulse: the fourth comes two periods late.
    let base = 10 * p;
    push(&mut rx, base + 200, 200);
    push(&mut rx, base + p + 250, 250);
    assert_eq!(
        push(&mut rx, base + 3 * p + 260, 260),
        Some(RxOutcome::Incomplete { got: 2 })
    );
    // The stray pulse left over times out on its own.
    let due = rx.poll_timeout().expect("a partial frame waits");
    assert_eq!(
        rx.handle_timeout(due),
        Some(RxOutcome::Incomplete { got: 1 })
    );
    assert_eq!(rx.poll_timeout(), None);
}
