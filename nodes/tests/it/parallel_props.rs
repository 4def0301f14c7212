//! The parallel-module nodes and the PWM link under arbitrary input: nothing
//! panics, time never runs backwards, every frame handed over either goes on
//! the line or is refused.

use nodes::firmware::EvControllerConfig;
use nodes::link::{PortConfig, PwmBus, PwmBusConfig};
use nodes::node::Node;
use nodes::parallel::{
    ParallelLink, ParallelMaster, ParallelMasterConfig, PwmAddressing, PwmReceiver, PwmSlave,
    PwmSlaveConfig,
};
use proptest::prelude::*;
use protocols::pwmcap::PwmCoding;
use protocols::time::{SimDuration, SimTime};

fn master(link: ParallelLink) -> ParallelMaster {
    let coding = PwmCoding::PAPER;
    ParallelMaster::new(ParallelMasterConfig {
        link,
        slaves: vec![2, 3],
        coding,
        period_ticks: coding.symbol_period_ticks(),
        update_period: SimDuration::from_millis(1),
        reply_timeout: SimDuration::from_micros(500),
        retries: 2,
        kp: 0.45,
        ki: 2.5,
        set_points: Vec::new(),
        controller: EvControllerConfig::default(),
        rtu_silence: SimDuration::from_micros(1750),
    })
    .expect("valid master")
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    /// Garbage and half records at any times: the receiver and both nodes
    /// keep going, and any timeout they ask for is not in the past.
    #[test]
    fn nodes_survive_arbitrary_bytes(
        chunks in prop::collection::vec((0u64..2_000_000, prop::collection::vec(any::<u8>(), 0..9)), 1..40),
    ) {
        let coding = PwmCoding::PAPER;
        let mut rx = PwmReceiver::new(&coding, coding.symbol_period_ticks());
        let mut slave = PwmSlave::new(PwmSlaveConfig {
            id: 2,
            addressing: PwmAddressing::Designated,
            coding,
            period_ticks: coding.symbol_period_ticks(),
            controller: EvControllerConfig::default(),
        })
        .expect("slave");
        let mut masters = [
            master(ParallelLink::PwmDesignated),
            master(ParallelLink::ModbusRtu),
            master(ParallelLink::PwmBroadcast),
        ];
        let mut now = SimTime::ZERO;
        let mut buf = [0u8; 520];
        for (gap, bytes) in chunks {
            now += SimDuration(gap);
            for &b in &bytes {
                let _ = rx.push(now, b);
            }
            let _ = rx.handle_timeout(now);
            slave.handle_bytes(now, &bytes);
            slave.handle_timeout(now);
            let _ = slave.poll_transmit(now, &mut buf);
            while slave.poll_event().is_some() {}
            for m in &mut masters {
                m.handle_bytes(now, &bytes);
                let _ = m.poll_transmit(now, &mut buf);
                m.transmit_done(now);
                m.handle_timeout(now);
                while m.poll_event().is_some() {}
                if let Some(due) = m.poll_timeout() {
                    prop_assert!(due >= now || m.poll_transmit(now, &mut buf).is_some());
                }
            }
            if let Some(due) = rx.poll_timeout() {
                prop_assert!(due > now);
            }
        }
    }

    /// Any bytes handed to the link: refused as malformed, or sent with an
    /// end after the start and every delivery inside [start, end].
    #[test]
    fn the_link_refuses_or_sends(frames in prop::collection::vec(prop::collection::vec(any::<u8>(), 0..24), 1..10), seed: u64) {
        let mut bus = PwmBus::new(PwmBusConfig { seed, ..PwmBusConfig::default() }).expect("link");
        let ports = [bus.add_port(PortConfig::default()), bus.add_port(PortConfig::default())];
        for (i, bytes) in frames.iter().enumerate() {
            let now = SimTime::ZERO + SimDuration::from_micros(100 * i as u64);
            if let Ok(info) = bus.send(now, ports[i % 2], bytes) {
                prop_assert!(info.end > info.start && info.start >= now);
            }
        }
        let mut last = SimTime::ZERO;
        while let Some(t) = bus.poll_timeout() {
            prop_assert!(t >= last);
            last = t;
            while bus.poll_event(t).is_some() {}
        }
    }
}
