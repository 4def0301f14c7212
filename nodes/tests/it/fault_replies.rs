//! The faults a master's check needs, byte for byte on the wire: a refusal
//! of every request, a reply from the wrong id, a reply split over two
//! writes with its gap, junk before or after a reply; on MEB, the 8-byte
//! Modbus and Modbus RTU. The expected bytes were worked out by hand (FCS,
//! CRC-16/MODBUS), not by the code under test.

use nodes::controller_network::{MotorConfig, MotorNode};
use nodes::firmware::{EvController, EvControllerConfig, Refusal, SlaveProtocol};
use nodes::link::{
    BusConfig, BusEvent, CheckKind, Fault, FaultyNode, Junk, JunkBytes, JunkPlace, PortConfig,
    SimBus,
};
use nodes::node::{MAX_FRAME, Node};
use protocols::meb::MebFrame;
use protocols::modbus::rtu;
use protocols::modbus8::{self, CrcOrder};
use protocols::time::{SimDuration, SimTime};

/// A reply from `vectors/meb.jsonl` ("reply with three analog inputs").
const MEB_REPLY: &[u8] = b"@01EA00030A3C012307D034*\n";
/// The motor's echo of a write of 0x80 to its state register.
const MODBUS8_REPLY: [u8; 8] = [0x01, 0x06, 0x00, 0x01, 0x00, 0x80, 0xaa, 0xd9];
/// A read-holding-registers reply of one register, 42, from unit 1.
const RTU_REPLY: [u8; 7] = [0x01, 0x03, 0x02, 0x00, 0x2a, 0x39, 0x9b];

/// A slave that answers any byte with a fixed reply, and counts the ends
/// of its transmissions it hears of.
#[derive(Debug)]
struct Fixed {
    reply: Vec<u8>,
    pending: bool,
    done: Vec<SimTime>,
}

impl Node for Fixed {
    fn handle_bytes(&mut self, _now: SimTime, _bytes: &[u8]) {
        self.pending = true;
    }
    fn handle_timeout(&mut self, _now: SimTime) {}
    fn poll_transmit(&mut self, _now: SimTime, buf: &mut [u8]) -> Option<usize> {
        if !std::mem::take(&mut self.pending) {
            return None;
        }
        buf.get_mut(..self.reply.len())?
            .copy_from_slice(&self.reply);
        Some(self.reply.len())
    }
    fn poll_timeout(&self) -> Option<SimTime> {
        None
    }
    fn transmit_done(&mut self, now: SimTime) {
        self.done.push(now);
    }
}

fn faulty(reply: &[u8], check: CheckKind, fault: Fault) -> FaultyNode<Fixed> {
    let fixed = Fixed {
        reply: reply.to_vec(),
        pending: false,
        done: Vec::new(),
    };
    let mut node = FaultyNode::new(fixed, check);
    node.set_fault(Some(fault));
    node
}

fn transmit<N: Node>(node: &mut N, now: SimTime) -> Option<Vec<u8>> {
    let mut buf = [0u8; MAX_FRAME];
    node.poll_transmit(now, &mut buf)
        .map(|len| buf[..len].to_vec())
}

/// What `node` sends for `request`: the request's bytes, then its timers
/// (the RTU silence that ends a frame) until it answers.
fn answer<N: Node>(node: &mut N, request: &[u8]) -> Vec<u8> {
    let mut now = SimTime::ZERO;
    node.handle_bytes(now, request);
    for _ in 0..4 {
        if let Some(reply) = transmit(node, now) {
            return reply;
        }
        let Some(at) = node.poll_timeout() else { break };
        now = at;
        node.handle_timeout(now);
    }
    panic!("no reply to {request:02x?}");
}

#[test]
fn a_wrong_id_reply_is_well_formed_and_only_its_id_and_check_differ() {
    let cases: [(CheckKind, &[u8], &[u8]); 3] = [
        (CheckKind::Meb, MEB_REPLY, b"@02EA00030A3C012307D037*\n"),
        (
            CheckKind::Modbus8,
            &MODBUS8_REPLY,
            &[0x02, 0x06, 0x00, 0x01, 0x00, 0x80, 0x99, 0xd9],
        ),
        (
            CheckKind::ModbusRtu,
            &RTU_REPLY,
            &[0x02, 0x03, 0x02, 0x00, 0x2a, 0x39, 0x9b],
        ),
    ];
    for (check, reply, as_two) in cases {
        // Unchosen, the id next to its own (2): byte for byte, the check good.
        let mut node = faulty(reply, check, Fault::WrongId(None));
        node.handle_bytes(SimTime::ZERO, &[0]);
        let sent = transmit(&mut node, SimTime::ZERO).unwrap();
        if check == CheckKind::ModbusRtu {
            // The CRC covers the id: worked out separately below.
            assert_eq!(sent[..5], as_two[..5], "{check:?}");
            assert!(
                rtu::RtuFrame::new_checked(&sent).is_ok(),
                "{check:?}: {sent:02x?}"
            );
        } else {
            assert_eq!(sent, as_two, "{check:?}");
        }
        assert_eq!(node.stats().frames_wrong_id, 1);
        assert_eq!(node.poll_event().map(|e| e.kind), Some("fault"));
    }
    // A chosen id: unit 7, CRC B1 9B (low byte first).
    let mut node = faulty(&RTU_REPLY, CheckKind::ModbusRtu, Fault::WrongId(Some(7)));
    node.handle_bytes(SimTime::ZERO, &[0]);
    assert_eq!(
        transmit(&mut node, SimTime::ZERO).unwrap(),
        [0x07, 0x03, 0x02, 0x00, 0x2a, 0xb1, 0x9b]
    );
    let meb = MebFrame::new_checked(&b"@02EA00030A3C012307D037*\n"[..]).unwrap();
    assert_eq!(meb.id(), 2);
    let m8 = modbus8::Modbus8Repr::parse(
        &[0x02, 0x06, 0x00, 0x01, 0x00, 0x80, 0x99, 0xd9],
        CrcOrder::HighFirst,
    )
    .unwrap();
    assert_eq!(m8.id, 2);
}

#[test]
fn a_split_reply_goes_in_two_writes_the_rest_a_gap_after_the_first_ends() {
    let gap = SimDuration::from_millis(2);
    let turnaround = SimDuration::from_micros(100);
    for (check, reply) in [
        (CheckKind::Meb, MEB_REPLY),
        (CheckKind::Modbus8, &MODBUS8_REPLY[..]),
        (CheckKind::ModbusRtu, &RTU_REPLY[..]),
    ] {
        let fault = Fault::SplitReply { first: None, gap };
        let mut node = faulty(reply, check, fault).with_turnaround(turnaround);
        let t0 = SimTime(1_000);
        node.handle_bytes(t0, &[0]);
        let half = reply.len() / 2;
        assert_eq!(transmit(&mut node, t0).unwrap(), reply[..half], "{check:?}");
        // Nothing more until the first write has ended and the gap passed.
        assert_eq!(transmit(&mut node, t0), None);
        assert_eq!(node.poll_timeout(), None);
        let end = SimTime(5_000);
        node.transmit_done(end);
        assert!(node.inner().done.is_empty(), "the node's frame is not over");
        // The link waits its turnaround before the write: asked for that early.
        let release = SimTime(end.0 + gap.0 - turnaround.0);
        assert_eq!(node.poll_timeout(), Some(release));
        assert_eq!(transmit(&mut node, SimTime(release.0 - 1)), None);
        assert_eq!(transmit(&mut node, release).unwrap(), reply[half..]);
        node.transmit_done(SimTime(9_000));
        assert_eq!(node.inner().done, vec![SimTime(9_000)]);
        assert_eq!(node.stats().frames_split, 1);
    }
    // Split after a chosen byte: the MEB reply's `@01` alone first.
    let fault = Fault::SplitReply {
        first: Some(3),
        gap,
    };
    let mut node = faulty(MEB_REPLY, CheckKind::Meb, fault);
    node.handle_bytes(SimTime::ZERO, &[0]);
    assert_eq!(transmit(&mut node, SimTime::ZERO).unwrap(), b"@01");
}

/// On the simulated bus the gap is bus time: the line is quiet for exactly
/// the gap between the first write's last stop bit and the rest's first
/// start bit, and the master hears the whole reply, in two pieces.
#[test]
fn on_the_bus_the_split_replys_gap_is_quiet_line_of_exactly_the_gap() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let master = bus.add_port(PortConfig {
        turnaround: SimDuration::ZERO,
    });
    let turnaround = SimDuration::from_micros(100);
    let slave_port = bus.add_port(PortConfig { turnaround });
    let gap = SimDuration::from_millis(3);
    let fault = Fault::SplitReply { first: None, gap };
    let mut slave = faulty(&MODBUS8_REPLY, CheckKind::Modbus8, fault).with_turnaround(turnaround);
    bus.send(SimTime::ZERO, master, &[0x55]).unwrap();
    let mut heard = Vec::new();
    let mut writes = Vec::new();
    let mut buf = [0u8; MAX_FRAME];
    let mut wake = None;
    loop {
        let next = match (bus.poll_timeout(), wake) {
            (Some(a), Some(b)) => a.min(b),
            (a, b) => match a.or(b) {
                Some(t) => t,
                None => break,
            },
        };
        if wake.is_some_and(|w| w <= next) {
            slave.handle_timeout(next);
        }
        while let Some(event) = bus.poll_event(next) {
            match event {
                BusEvent::Byte { to, byte, at, .. } if to == master => heard.push((at, byte)),
                BusEvent::Byte { to, byte, at, .. } if to == slave_port => {
                    slave.handle_bytes(at, &[byte])
                }
                BusEvent::TransmitDone { port, at } if port == slave_port => {
                    slave.transmit_done(at)
                }
                _ => {}
            }
        }
        while let Some(len) = slave.poll_transmit(next, &mut buf) {
            writes.push(bus.send(next, slave_port, &buf[..len]).unwrap());
        }
        wake = slave.poll_timeout();
    }
    assert_eq!(writes.len(), 2);
    assert_eq!(writes[1].start.saturating_since(writes[0].end), gap);
    let bytes: Vec<u8> = heard.iter().map(|&(_, b)| b).collect();
    assert_eq!(bytes, MODBUS8_REPLY);
    assert!(modbus8::Modbus8Repr::parse(&bytes, CrcOrder::HighFirst).is_ok());
    assert_eq!(slave.inner().done.len(), 1);
}

#[test]
fn junk_goes_before_or_after_a_reply_in_the_same_write() {
    let given = JunkBytes::given(&[0x00, 0xff, 0x7e]).unwrap();
    for (check, reply) in [
        (CheckKind::Meb, MEB_REPLY),
        (CheckKind::Modbus8, &MODBUS8_REPLY[..]),
        (CheckKind::ModbusRtu, &RTU_REPLY[..]),
    ] {
        for place in [JunkPlace::Before, JunkPlace::After] {
            let junk = Junk {
                bytes: given,
                place,
            };
            let mut node = faulty(reply, check, Fault::Junk(junk));
            node.handle_bytes(SimTime::ZERO, &[0]);
            let sent = transmit(&mut node, SimTime::ZERO).unwrap();
            let expected = match place {
                JunkPlace::Before => [&[0x00, 0xff, 0x7e], reply].concat(),
                JunkPlace::After => [reply, &[0x00, 0xff, 0x7e]].concat(),
            };
            assert_eq!(sent, expected, "{check:?} {place:?}");
            assert_eq!(node.stats().frames_junk, 1);
        }
    }
}

#[test]
fn random_junk_follows_the_seed() {
    let junk = Junk {
        bytes: JunkBytes::random(8).unwrap(),
        place: JunkPlace::Before,
    };
    let run = |seed: u64| {
        let mut node =
            faulty(&MODBUS8_REPLY, CheckKind::Modbus8, Fault::Junk(junk)).with_seed(seed);
        (0..3)
            .map(|_| {
                node.handle_bytes(SimTime::ZERO, &[0]);
                transmit(&mut node, SimTime::ZERO).unwrap()
            })
            .collect::<Vec<_>>()
    };
    let a = run(7);
    assert_eq!(a, run(7), "same seed, same junk");
    assert_ne!(a, run(8), "another seed, other junk");
    for sent in &a {
        assert_eq!(sent.len(), 16);
        assert_eq!(sent[8..], MODBUS8_REPLY);
    }
    // Fresh junk for every reply.
    assert_ne!(a[0][..8], a[1][..8]);
    assert_eq!(JunkBytes::random(0), None);
    assert_eq!(JunkBytes::random(33), None);
}

#[test]
fn an_exception_fault_refuses_every_request_in_each_protocols_own_frame() {
    let refuse = Fault::Exception(Refusal::IllegalAddress);
    // MEB: read EA 0..3 from slave 1, refused with `ER` 02.
    let mut meb = FaultyNode::new(
        EvController::new(EvControllerConfig::default()),
        CheckKind::Meb,
    );
    meb.set_fault(Some(refuse));
    assert_eq!(answer(&mut meb, b"@01EA000346*\n"), b"@01ER0001000255*\n");
    assert_eq!(meb.stats().frames_refused, 1);

    // Modbus RTU: read input register 0 from unit 1, exception 84 02.
    let config = EvControllerConfig {
        protocol: SlaveProtocol::ModbusRtu,
        ..EvControllerConfig::default()
    };
    let mut rtu_slave = FaultyNode::new(EvController::new(config), CheckKind::ModbusRtu);
    rtu_slave.set_fault(Some(refuse));
    let request = [0x01, 0x04, 0x00, 0x00, 0x00, 0x01, 0x31, 0xca];
    assert_eq!(
        answer(&mut rtu_slave, &request),
        [0x01, 0x84, 0x02, 0xc2, 0xc1]
    );

    // The Controller_network motor node: read its state, the project's own
    // exception frame (top bit of the function set, the code in the value).
    let mut motor = FaultyNode::new(MotorNode::new(MotorConfig::default()), CheckKind::Modbus8);
    motor.set_fault(Some(refuse));
    let request = [0x01, 0x03, 0x00, 0x01, 0x00, 0x00, 0x0a, 0x14];
    let reply = answer(&mut motor, &request);
    assert_eq!(reply, [0x01, 0x83, 0x00, 0x01, 0x00, 0x02, 0x15, 0x94]);

    // A refused write stores nothing: state 0x01 refused, still 0x80.
    let write = modbus8::Modbus8Repr {
        id: 1,
        function: modbus8::WRITE,
        addr: 1,
        value: 0x01,
    }
    .to_bytes(CrcOrder::HighFirst);
    assert!(answer(&mut motor, &write)[1] == 0x86);
    motor.set_fault(None);
    let state = answer(&mut motor, &request);
    assert_eq!(state[..6], [0x01, 0x03, 0x00, 0x01, 0x00, 0x80]);
}
