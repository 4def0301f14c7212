//! The fault injector: each fault checked against the real codecs, and a
//! faulty slave on the simulated bus.

use nodes::link::{
    BusConfig, BusEvent, CheckKind, Fault, FaultWindow, FaultyNode, PortConfig, SimBus,
};
use nodes::node::{MAX_FRAME, Node};
use protocols::meb::{MebError, MebFrame};
use protocols::modbus::{FrameError, rtu};
use protocols::modbus8::{self, CrcOrder, Modbus8Error};
use protocols::time::{SimDuration, SimTime};

/// A slave that answers every `expect` bytes it hears with a fixed reply and
/// remembers what happened to it.
#[derive(Debug, Default)]
struct Scripted {
    reply: Vec<u8>,
    expect: usize,
    heard: usize,
    pending: bool,
    received: Vec<u8>,
    transmit_done: Vec<SimTime>,
    wake: Option<SimTime>,
    woken: Vec<SimTime>,
}

impl Scripted {
    fn new(reply: &[u8], expect: usize) -> Self {
        Scripted {
            reply: reply.to_vec(),
            expect,
            ..Scripted::default()
        }
    }
}

impl Node for Scripted {
    fn handle_bytes(&mut self, _now: SimTime, bytes: &[u8]) {
        self.received.extend_from_slice(bytes);
        self.heard += bytes.len();
        if self.heard >= self.expect {
            self.heard = 0;
            self.pending = true;
        }
    }
    fn handle_timeout(&mut self, now: SimTime) {
        self.woken.push(now);
        self.wake = None;
    }
    fn poll_transmit(&mut self, _now: SimTime, buf: &mut [u8]) -> Option<usize> {
        if !std::mem::take(&mut self.pending) {
            return None;
        }
        let out = buf.get_mut(..self.reply.len())?;
        out.copy_from_slice(&self.reply);
        Some(self.reply.len())
    }
    fn poll_timeout(&self) -> Option<SimTime> {
        self.wake
    }
    fn transmit_done(&mut self, now: SimTime) {
        self.transmit_done.push(now);
    }
}

/// A reply from `vectors/meb.jsonl` ("reply with three analog inputs").
const MEB_REPLY: &[u8] = b"@01EA00030A3C012307D034*\n";
/// From `vectors/modbus8.jsonl`: motor, write control state 0x80 (the
/// Controller_network project's CRC is high byte first; its own bad-CRC test
/// printed 0xaada against 0xaad9).
const MODBUS8_FRAME: [u8; 8] = [0x01, 0x06, 0x00, 0x01, 0x00, 0x80, 0xaa, 0xd9];

fn transmit<N: Node>(node: &mut N, now: SimTime) -> Option<Vec<u8>> {
    let mut buf = [0u8; MAX_FRAME];
    node.poll_transmit(now, &mut buf)
        .map(|len| buf[..len].to_vec())
}

fn triggered(reply: &[u8], check: CheckKind) -> FaultyNode<Scripted> {
    let mut node = FaultyNode::new(Scripted::new(reply, 1), check);
    node.handle_bytes(SimTime::ZERO, &[0]);
    node
}

fn vector_frames_are_valid() {
    assert!(MebFrame::new_checked(MEB_REPLY).is_ok());
    assert!(modbus8::Modbus8Repr::parse(&MODBUS8_FRAME, CrcOrder::HighFirst).is_ok());
}

#[test]
fn bad_check_fails_the_meb_codec_and_changes_only_the_fcs() {
    vector_frames_are_valid();
    for frame in [MEB_REPLY.to_vec(), b"@01EA00030A3C012307D034*\r\n".to_vec()] {
        let mut clean = triggered(&frame, CheckKind::Meb);
        let sent = transmit(&mut clean, SimTime::ZERO).unwrap();
        assert!(MebFrame::new_checked(&sent[..]).is_ok());

        let mut node = triggered(&frame, CheckKind::Meb);
        node.set_fault(Some(Fault::BadCheck));
        let spoiled = transmit(&mut node, SimTime::ZERO).unwrap();
        assert_eq!(
            MebFrame::new_checked(&spoiled[..]).err(),
            Some(MebError::BadFcs)
        );
        let fcs_at = frame.iter().position(|&b| b == b'*').unwrap() - 2;
        assert_eq!(&spoiled[fcs_at..fcs_at + 2], b"35");
        assert_eq!(spoiled[..fcs_at], frame[..fcs_at]);
        assert_eq!(spoiled[fcs_at + 2..], frame[fcs_at + 2..]);
        assert_eq!(node.stats().frames_bad_check, 1);
        let event = node.poll_event().unwrap();
        assert_eq!(event.kind, "fault");
    }
}

#[test]
fn bad_check_fails_the_modbus8_codec_as_the_controller_network_saw_it() {
    let mut node = triggered(&MODBUS8_FRAME, CheckKind::Modbus8);
    node.set_fault(Some(Fault::BadCheck));
    let spoiled = transmit(&mut node, SimTime::ZERO).unwrap();
    assert_eq!(
        modbus8::Modbus8Repr::parse(&spoiled, CrcOrder::HighFirst),
        Err(Modbus8Error::BadCrc {
            received: 0xaada,
            calculated: 0xaad9
        })
    );
    assert_eq!(spoiled[..6], MODBUS8_FRAME[..6]);
}

#[test]
fn bad_check_fails_the_rtu_codec() {
    // Read holding register 0, count 1, unit 1: CRC 84 0A (low byte first).
    let request = [0x01, 0x03, 0x00, 0x00, 0x00, 0x01, 0x84, 0x0a];
    assert!(rtu::RtuFrame::new_checked(&request).is_ok());
    let mut node = triggered(&request, CheckKind::ModbusRtu);
    node.set_fault(Some(Fault::BadCheck));
    let spoiled = transmit(&mut node, SimTime::ZERO).unwrap();
    assert_eq!(
        rtu::RtuFrame::new_checked(&spoiled).err(),
        Some(FrameError::BadCrc {
            received: 0x0a85,
            calculated: 0x0a84
        })
    );
}

#[test]
fn dropped_replies_never_leave_but_the_node_believes_it_sent() {
    let mut node = triggered(&MODBUS8_FRAME, CheckKind::Modbus8);
    node.set_fault(Some(Fault::DropReply));
    let now = SimTime(77);
    assert_eq!(transmit(&mut node, now), None);
    assert_eq!(node.inner().transmit_done, vec![now]);
    assert_eq!(node.stats().frames_dropped, 1);
    assert_eq!(node.poll_event().map(|e| e.kind), Some("dropped"));

    // Cleared, it answers again.
    node.set_fault(None);
    node.handle_bytes(now, &[0]);
    assert_eq!(transmit(&mut node, now), Some(MODBUS8_FRAME.to_vec()));
    assert_eq!(node.stats().frames_passed, 1);
}

#[test]
fn delayed_replies_go_out_exactly_the_delay_later_and_in_order() {
    let delay = SimDuration::from_millis(3);
    let mut node = FaultyNode::new(Scripted::new(&MODBUS8_FRAME, 1), CheckKind::Modbus8);
    node.inner_mut().wake = Some(SimTime(1_000));
    node.set_fault(Some(Fault::DelayReply(delay)));
    let t0 = SimTime(500);
    node.handle_bytes(t0, &[0]);
    assert_eq!(transmit(&mut node, t0), None);
    // The inner node's own timer still comes first and still reaches it.
    assert_eq!(node.poll_timeout(), Some(SimTime(1_000)));
    node.handle_timeout(SimTime(1_000));
    assert_eq!(node.inner().woken, vec![SimTime(1_000)]);
    assert_eq!(node.poll_timeout(), Some(t0 + delay));

    // A second frame, produced later with the fault cleared, must not overtake.
    node.set_fault(None);
    let t1 = SimTime(2_000);
    node.handle_bytes(t1, &[0]);
    assert_eq!(transmit(&mut node, t1), None);
    // Waking the wrapper for its held frame does not wake the inner node.
    node.handle_timeout(t0 + delay);
    assert_eq!(node.inner().woken.len(), 1);
    assert_eq!(transmit(&mut node, SimTime((t0 + delay).0 - 1)), None);
    assert_eq!(
        transmit(&mut node, t0 + delay),
        Some(MODBUS8_FRAME.to_vec())
    );
    assert_eq!(
        transmit(&mut node, t0 + delay),
        Some(MODBUS8_FRAME.to_vec())
    );
    assert_eq!(transmit(&mut node, t0 + delay), None);
    assert_eq!(node.poll_timeout(), None);
    assert_eq!(node.stats().frames_delayed, 1);
}

#[test]
fn a_silent_window_loses_both_directions_only_inside_it() {
    let window = FaultWindow {
        from: SimTime::ZERO + SimDuration::from_secs(1),
        until: SimTime::ZERO + SimDuration::from_secs(2),
        fault: Fault::Silent,
    };
    let mut node = FaultyNode::with_schedule(
        Scripted::new(&MODBUS8_FRAME, 8),
        CheckKind::Modbus8,
        vec![window],
    );
    let before = SimTime::ZERO + SimDuration::from_millis(999);
    let inside = SimTime::ZERO + SimDuration::from_millis(1500);
    let after = window.until;
    assert_eq!(node.active_fault(before), None);
    assert_eq!(node.active_fault(inside), Some(Fault::Silent));
    assert_eq!(node.active_fault(after), None);

    node.handle_bytes(before, &MODBUS8_FRAME);
    assert_eq!(transmit(&mut node, before), Some(MODBUS8_FRAME.to_vec()));
    node.handle_bytes(inside, &MODBUS8_FRAME);
    assert_eq!(transmit(&mut node, inside), None);
    assert_eq!(node.inner().received.len(), 8);
    assert_eq!(node.stats().bytes_ignored, 8);
    node.handle_bytes(after, &MODBUS8_FRAME);
    assert_eq!(transmit(&mut node, after), Some(MODBUS8_FRAME.to_vec()));
    // A fault set by hand overrides the schedule.
    node.set_fault(Some(Fault::DropReply));
    assert_eq!(node.active_fault(inside), Some(Fault::DropReply));
}

/// A master that sends one request at t = 0, on a bus with a faulty slave:
/// the reply reaches the master a turnaround after the request, with the
/// check spoiled, and the real codec rejects it.
#[test]
fn a_faulty_slave_on_the_bus_sends_a_reply_the_master_rejects() {
    let mut bus = SimBus::new(BusConfig::default()).unwrap();
    let master = bus.add_port(PortConfig {
        turnaround: SimDuration::ZERO,
    });
    let slave_port = bus.add_port(PortConfig::default());
    let reply = modbus8::Modbus8Repr {
        id: 1,
        function: modbus8::READ,
        addr: 1,
        value: 1,
    }
    .to_bytes(CrcOrder::HighFirst);
    let mut slave = FaultyNode::new(Scripted::new(&reply, 8), CheckKind::Modbus8);
    slave.set_fault(Some(Fault::BadCheck));

    let request = modbus8::Modbus8Repr {
        id: 1,
        function: modbus8::READ,
        addr: 1,
        value: 0,
    }
    .to_bytes(CrcOrder::HighFirst);
    let sent = bus.send(SimTime::ZERO, master, &request).unwrap();

    let mut at_master = Vec::new();
    let mut reply_start = None;
    let mut buf = [0u8; MAX_FRAME];
    while let Some(now) = bus.poll_timeout() {
        while let Some(event) = bus.poll_event(now) {
            match event {
                BusEvent::Byte { to, byte, .. } if to == slave_port => {
                    slave.handle_bytes(now, &[byte]);
                    if let Some(len) = slave.poll_transmit(now, &mut buf) {
                        reply_start = Some(bus.send(now, slave_port, &buf[..len]).unwrap().start);
                    }
                }
                BusEvent::Byte { to, byte, .. } if to == master => at_master.push(byte),
                BusEvent::TransmitDone { port, at } if port == slave_port => {
                    slave.transmit_done(at)
                }
                _ => {}
            }
        }
    }
    assert_eq!(reply_start, Some(sent.end + SimDuration::from_millis(1)));
    assert!(matches!(
        modbus8::Modbus8Repr::parse(&at_master, CrcOrder::HighFirst),
        Err(Modbus8Error::BadCrc { received, calculated }) if received == calculated.wrapping_add(1)
    ));
    assert_eq!(slave.inner().transmit_done.len(), 1);
}
