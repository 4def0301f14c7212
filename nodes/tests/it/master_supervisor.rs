//! The supervisor against a scripted fake slave: the test plays the bus (wire
//! times at 115 200 baud) and answers each request with canned frames built
//! with the crate's own MEB and RTU codecs.

use nodes::master::{
    LoopMode, PollCounters, Protocol, SetPointStep, SlaveLoopConfig, SpeedSource, Supervisor,
    SupervisorConfig,
};
use nodes::node::{MAX_FRAME, Node};
use protocols::meb::{MebCmd, MebErrorCode, MebRepr, MebWords};
use protocols::modbus::{Registers, Response, rtu};
use protocols::time::{SimDuration, SimTime};

const BAUD: u32 = 115_200;
const TURNAROUND: SimDuration = SimDuration::from_millis(1);
const INPUTS: [u16; 6] = [3000, 200, 2900, 200, 999, 1000];

/// Wire time of `len` 8N1 bytes.
fn wire(len: usize) -> SimDuration {
    SimDuration::bit_times(10 * len as u64, BAUD)
}

fn ms(ms: u64) -> SimDuration {
    SimDuration::from_millis(ms)
}

/// The MEB check, written out again so the test does not trust the codec's.
fn fcs(text: &str) -> u8 {
    text.bytes().fold(0, |acc, byte| acc ^ byte)
}

fn meb_text(body: &str) -> Vec<u8> {
    format!("{body}{:02X}*\n", fcs(body)).into_bytes()
}

fn meb(id: u8, cmd: MebCmd, cnt: u8, data: &[u16]) -> Vec<u8> {
    let repr = MebRepr {
        id,
        cmd,
        addr: 0,
        cnt,
        data: MebWords::from_slice(data).unwrap(),
    };
    let mut out = [0u8; MAX_FRAME];
    let n = repr.emit(&mut out).unwrap();
    out[..n].to_vec()
}

fn rtu_reply(id: u8, response: Response) -> Vec<u8> {
    let mut out = [0u8; 256];
    let reply: Result<Response, protocols::modbus::ExceptionResponse> = Ok(response);
    let n = rtu::RtuRepr {
        unit: id,
        pdu: &reply,
    }
    .emit(&mut out)
    .unwrap();
    out[..n].to_vec()
}

fn hex(text: &str) -> Vec<u8> {
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).unwrap())
        .collect()
}

#[derive(Debug)]
struct Sent {
    start: SimTime,
    end: SimTime,
    bytes: Vec<u8>,
}

/// A point-to-point line between the supervisor and the test's fake slave,
/// driven the way the engine drives a node.
struct Bus {
    master: Supervisor,
    now: SimTime,
}

impl Bus {
    fn new(config: SupervisorConfig) -> Self {
        Self {
            master: Supervisor::new(config).unwrap(),
            now: SimTime::ZERO,
        }
    }

    /// Wakes the master at the instants it asks for until it sends a frame.
    fn next_request(&mut self) -> Sent {
        let mut buf = [0u8; MAX_FRAME];
        for _ in 0..100 {
            if let Some(n) = self.master.poll_transmit(self.now, &mut buf) {
                let start = self.now;
                let end = start + wire(n);
                self.master.transmit_done(end);
                self.now = end;
                return Sent {
                    start,
                    end,
                    bytes: buf[..n].to_vec(),
                };
            }
            let at = self
                .master
                .poll_timeout()
                .expect("a master always has a next instant");
            assert!(at >= self.now, "the master asked to be woken in the past");
            self.now = at;
            self.master.handle_timeout(at);
        }
        panic!("no request");
    }

    /// The slave answers `bytes` after its turnaround; returns the reply's end.
    fn reply_after(&mut self, turnaround: SimDuration, bytes: &[u8]) -> SimTime {
        self.now = self.now + turnaround + wire(bytes.len());
        self.master.handle_bytes(self.now, bytes);
        self.now
    }

    fn reply(&mut self, bytes: &[u8]) -> SimTime {
        self.reply_after(TURNAROUND, bytes)
    }

    /// No answer: lets the master's reply timeout fire; returns when it did.
    fn silence(&mut self) -> SimTime {
        let at = self.master.poll_timeout().unwrap();
        self.now = at;
        self.master.handle_timeout(at);
        at
    }

    fn event_kinds(&mut self) -> Vec<&'static str> {
        std::iter::from_fn(|| self.master.poll_event())
            .map(|event| event.kind)
            .collect()
    }

    fn counters(&self, id: u8) -> PollCounters {
        self.master.loop_state(id).unwrap().counters
    }
}

fn one_slave(protocol: Protocol, slave: SlaveLoopConfig) -> SupervisorConfig {
    SupervisorConfig::new(protocol, vec![slave])
}

fn closed_loop(id: u8, set_point: f64) -> SlaveLoopConfig {
    SlaveLoopConfig {
        kp: 0.5,
        ki: 2.0,
        set_points: vec![SetPointStep {
            at: SimTime::ZERO,
            rpm: set_point,
        }],
        ..SlaveLoopConfig::new(id)
    }
}

#[test]
fn meb_start_up_enables_the_module_then_reads_and_writes_vel() {
    let mut config = one_slave(Protocol::Meb, closed_loop(1, 1000.0));
    // Three exchanges at 115 200 baud take 12.9 ms: give them room.
    config.poll_period = ms(20);
    let mut bus = Bus::new(config);

    // SD0 = 0x000E: EN = 0 enabled, BRK = 1 released, PRO = 1 boost off,
    // DES = 1 not discharging, FR = 0 clockwise; SD1 = 0x0001 charger off.
    let start_up = bus.next_request();
    assert_eq!(start_up.start, SimTime::ZERO);
    assert_eq!(start_up.bytes, b"@01SD0002000E000120*\n");
    let ack_end = bus.reply(b"@01SD000254*\n");

    let read = bus.next_request();
    assert_eq!(read.bytes, b"@01EA000643*\n");
    assert_eq!(read.start, ack_end, "no gap configured");
    bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));

    // Hall rpm 200 against 1000: error 800; the first pass integrates over
    // one poll period: 0.5 * 800 + 2.0 * 800 * 0.020 = 432 counts.
    let write = bus.next_request();
    assert_eq!(write.bytes, meb_text("@01SA000101B0"));
    bus.reply(b"@01SA000152*\n");

    let state = bus.master.loop_state(1).unwrap();
    assert_eq!(state.set_point_rpm, 1000.0);
    assert_eq!(state.measured_rpm, 200.0);
    assert_eq!(state.error_rpm, 800.0);
    assert_eq!(state.output, 432);
    assert_eq!(state.vel_written, Some(432));
    assert_eq!(state.inputs, INPUTS);
    assert!(state.started);
    let counters = state.counters;
    assert_eq!((counters.requests, counters.replies), (3, 3));

    // The next cycle starts one period after the first, without a second
    // start-up write.
    let next = bus.next_request();
    assert_eq!(next.start, SimTime::ZERO + ms(20));
    assert_eq!(next.bytes, b"@01EA000643*\n");
    assert!(bus.event_kinds().is_empty());
}

#[test]
fn the_light_sensor_rpm_can_close_the_loop() {
    let slave = SlaveLoopConfig {
        speed_source: SpeedSource::Light,
        ..closed_loop(1, 1000.0)
    };
    let mut config = one_slave(Protocol::Meb, slave);
    config.startup_outputs = None;
    let mut bus = Bus::new(config);
    assert_eq!(bus.next_request().bytes, b"@01EA000643*\n");
    bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));
    let state = bus.master.loop_state(1).unwrap();
    assert_eq!(state.measured_rpm, 999.0);
    assert_eq!(state.error_rpm, 1.0);
}

#[test]
fn open_loop_writes_vel_only_when_it_changes() {
    let slave = SlaveLoopConfig {
        mode: LoopMode::Open { vel: 2000 },
        ..SlaveLoopConfig::new(7)
    };
    let mut config = one_slave(Protocol::Meb, slave);
    config.startup_outputs = None;
    let mut bus = Bus::new(config);

    assert_eq!(bus.next_request().bytes, meb_text("@07EA0006"));
    bus.reply(&meb(7, MebCmd::EA, 6, &INPUTS));
    assert_eq!(bus.next_request().bytes, meb_text("@07SA000107D0"));
    bus.reply(&meb(7, MebCmd::SA, 1, &[]));

    let read = bus.next_request();
    assert_eq!(
        (read.start, read.bytes),
        (SimTime::ZERO + ms(10), meb_text("@07EA0006"))
    );
    bus.reply(&meb(7, MebCmd::EA, 6, &INPUTS));
    // Unchanged output: the next frame is the third cycle's read.
    let read = bus.next_request();
    assert_eq!(
        (read.start, read.bytes),
        (SimTime::ZERO + ms(20), meb_text("@07EA0006"))
    );

    assert!(bus.master.set_mode(7, LoopMode::Open { vel: 100 }));
    bus.reply(&meb(7, MebCmd::EA, 6, &INPUTS));
    assert_eq!(bus.next_request().bytes, meb_text("@07SA00010064"));
}

#[test]
fn rtu_start_up_writes_the_coils_then_reads_and_writes_vel() {
    let mut bus = Bus::new(one_slave(Protocol::ModbusRtu, closed_loop(1, 1000.0)));

    // FC 15, coils 0-5 = EN 0, BRK 1, PRO 1, DES 1, FR 0, CHG 1 -> 0x2E.
    let start_up = bus.next_request();
    assert_eq!(start_up.bytes, hex("010f00000006012e1f4a"));
    bus.reply(&rtu_reply(
        1,
        Response::WriteMultipleCoils {
            address: 0,
            quantity: 6,
        },
    ));

    assert_eq!(bus.next_request().bytes, hex("0104000000067008"));
    let registers = Registers::from_slice(&INPUTS).unwrap();
    bus.reply(&rtu_reply(1, Response::ReadInputRegisters(registers)));

    // FC 06, holding register 0 = 0.5 * 800 + 2.0 * 800 * 0.010 = 416 (0x01A0).
    assert_eq!(bus.next_request().bytes, hex("0106000001a08822"));
    bus.reply(&rtu_reply(
        1,
        Response::WriteSingleRegister {
            address: 0,
            value: 416,
        },
    ));
    let state = bus.master.loop_state(1).unwrap();
    assert_eq!(state.vel_written, Some(416));
    assert_eq!((state.counters.requests, state.counters.replies), (3, 3));
    assert_eq!(bus.next_request().start, SimTime::ZERO + ms(10));
}

#[test]
fn a_timeout_is_retried_then_counted_as_lost() {
    let mut config = one_slave(Protocol::Meb, closed_loop(1, 1000.0));
    config.startup_outputs = None;
    config.inter_frame_gap = ms(2);
    let mut bus = Bus::new(config);

    let mut attempts = Vec::new();
    for _ in 0..3 {
        let sent = bus.next_request();
        assert_eq!(sent.bytes, b"@01EA000643*\n");
        let timed_out = bus.silence();
        // The reply timeout runs from the request's last stop bit.
        assert_eq!(timed_out, sent.end + ms(100));
        attempts.push((sent, timed_out));
    }
    // Each retry follows the timeout after the inter-frame gap.
    for pair in attempts.windows(2) {
        assert_eq!(pair[1].0.start, pair[0].1 + ms(2));
    }
    assert_eq!(
        bus.event_kinds(),
        ["timeout", "retry", "timeout", "retry", "timeout", "dropped"]
    );
    let counters = bus.counters(1);
    assert_eq!(
        counters,
        PollCounters {
            requests: 3,
            timeouts: 3,
            retries: 2,
            lost: 1,
            ..PollCounters::default()
        }
    );
    let state = bus.master.loop_state(1).unwrap();
    assert_eq!(state.measured_at, None, "nothing measured, no PI pass");
    assert_eq!(state.output, 0);

    // The overrun cycle is followed at once (after the gap) by the next one,
    // which starts with a fresh set of attempts.
    let last_timeout = attempts[2].1;
    let next = bus.next_request();
    assert_eq!(next.start, last_timeout + ms(2));
    assert_eq!(next.bytes, b"@01EA000643*\n");
    bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));
    assert_eq!(bus.counters(1).replies, 1);
    assert_eq!(bus.master.cycles(), 1);
}

#[test]
fn a_reply_just_inside_the_timeout_is_used() {
    let mut config = one_slave(Protocol::Meb, closed_loop(1, 1000.0));
    config.startup_outputs = None;
    let mut bus = Bus::new(config);
    bus.next_request();
    let reply = meb(1, MebCmd::EA, 6, &INPUTS);
    let late = SimDuration(ms(100).0 - wire(reply.len()).0 - 1);
    bus.reply_after(late, &reply);
    assert_eq!(bus.counters(1).replies, 1);
    assert_eq!(bus.counters(1).timeouts, 0);
}

/// A request the engine writes late (a busy machine, a stopped process: the
/// real-time links report the write when it happens) waits its whole reply
/// timeout from then, however long it sat before: no retry goes out while
/// its first copy is still unwritten, and a reply inside the timeout counted
/// from the write is used. Before, the timeout ran from `poll_transmit`, so a
/// first copy held back 300 ms was retried the moment it left.
#[test]
fn a_request_written_late_waits_its_whole_timeout_from_the_write() {
    let mut config = one_slave(Protocol::Meb, closed_loop(1, 1000.0));
    config.startup_outputs = None;
    config.reply_timeout = ms(30);
    let mut master = Supervisor::new(config).unwrap();
    let mut buf = [0u8; MAX_FRAME];
    let decided = SimTime::ZERO;
    let n = master
        .poll_transmit(decided, &mut buf)
        .expect("the first poll");
    assert_eq!(&buf[..n], b"@01EA000643*\n");
    // Not written yet: nothing to time out, nothing more to send, and a
    // reply (an earlier copy's, late) heard meanwhile is not its reply.
    assert_eq!(master.poll_timeout(), None);
    master.handle_timeout(decided + ms(31));
    assert_eq!(master.poll_transmit(decided + ms(31), &mut buf), None);
    master.handle_bytes(decided + ms(40), &meb(1, MebCmd::EA, 6, &INPUTS));
    let counters = master.loop_state(1).unwrap().counters;
    assert_eq!((counters.replies, counters.timeouts), (0, 0));

    let written = decided + ms(300);
    master.transmit_done(written);
    assert_eq!(master.poll_timeout(), Some(written + ms(30)));
    // A second report of the same request does not move its timeout.
    master.transmit_done(written + ms(5));
    assert_eq!(master.poll_timeout(), Some(written + ms(30)));
    master.handle_timeout(written + ms(29));
    master.handle_bytes(written + ms(29), &meb(1, MebCmd::EA, 6, &INPUTS));
    let counters = master.loop_state(1).unwrap().counters;
    assert_eq!((counters.replies, counters.timeouts), (1, 0));

    // The next request, written at once, times out 30 ms after its write.
    let next = written + ms(31);
    while master.poll_transmit(next, &mut buf).is_none() {
        let at = master.poll_timeout().expect("the next poll's instant");
        assert!(
            at <= next,
            "the next poll is due by {next:?}, asked for {at:?}"
        );
        master.handle_timeout(at);
    }
    master.transmit_done(next);
    master.handle_timeout(next + ms(29));
    assert!(std::iter::from_fn(|| master.poll_event()).all(|e| e.kind != "timeout"));
    master.handle_timeout(next + ms(30));
    let kinds: Vec<_> = std::iter::from_fn(|| master.poll_event())
        .map(|e| e.kind)
        .collect();
    assert_eq!(kinds, ["timeout", "retry"]);
}

#[test]
fn a_reply_with_a_bad_fcs_is_not_used_and_the_request_is_retried() {
    let mut config = one_slave(Protocol::Meb, closed_loop(1, 1000.0));
    config.startup_outputs = None;
    let mut bus = Bus::new(config);

    let first = bus.next_request();
    let mut corrupted = meb(1, MebCmd::EA, 6, &INPUTS);
    // RPM_M 0x00C8 -> 0x10C8: the XOR FCS no longer matches.
    let rpm_m_digit = 9 + 3 * 4;
    assert_eq!(corrupted[rpm_m_digit], b'0');
    corrupted[rpm_m_digit] = b'1';
    let bad_end = bus.reply(&corrupted);

    let state = bus.master.loop_state(1).unwrap();
    assert_eq!(state.measured_at, None);
    assert_eq!(state.counters.bad_checks, 1);
    assert_eq!(bus.event_kinds(), ["bad_check", "retry"]);

    // Retried once the line has been quiet for the silence interval (the bad
    // frame might have been cut short by noise), not after the reply timeout.
    let quiet = SimDuration::from_micros(1_750);
    let retry = bus.next_request();
    assert_eq!((retry.start, &retry.bytes), (bad_end + quiet, &first.bytes));
    bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));
    let state = bus.master.loop_state(1).unwrap();
    assert_eq!(state.measured_rpm, 200.0);
    let counters = state.counters;
    assert_eq!(
        (
            counters.requests,
            counters.replies,
            counters.bad_checks,
            counters.retries
        ),
        (2, 1, 1, 1)
    );
}

#[test]
fn a_reply_with_a_bad_crc_is_not_used_and_the_request_is_retried() {
    let mut config = one_slave(Protocol::ModbusRtu, closed_loop(1, 1000.0));
    config.startup_outputs = None;
    let mut bus = Bus::new(config);

    let first = bus.next_request();
    let registers = Registers::from_slice(&INPUTS).unwrap();
    let good = rtu_reply(1, Response::ReadInputRegisters(registers));
    let mut corrupted = good.clone();
    // The low byte of RPM_M (register 3): unit, fc, count, then 2 bytes each.
    corrupted[3 + 2 * 3 + 1] ^= 0x40;
    let bad_end = bus.reply(&corrupted);
    assert_eq!(bus.master.loop_state(1).unwrap().measured_at, None);
    assert_eq!(bus.event_kinds(), ["bad_check", "retry"]);

    let quiet = SimDuration::from_micros(1_750);
    let retry = bus.next_request();
    assert_eq!((retry.start, &retry.bytes), (bad_end + quiet, &first.bytes));
    bus.reply(&good);
    let state = bus.master.loop_state(1).unwrap();
    assert_eq!(state.measured_rpm, 200.0);
    assert_eq!((state.counters.bad_checks, state.counters.replies), (1, 1));
}

#[test]
fn an_error_reply_is_counted_and_retried() {
    let mut config = one_slave(Protocol::Meb, closed_loop(1, 1000.0));
    config.startup_outputs = None;
    config.retries = 1;
    let mut bus = Bus::new(config);

    let refusal = {
        let mut out = [0u8; 32];
        let n = MebRepr::error_reply(1, 0, MebErrorCode::DeviceFailure)
            .emit(&mut out)
            .unwrap();
        out[..n].to_vec()
    };
    assert_eq!(refusal, b"@01ER0001000453*\n");
    for _ in 0..2 {
        bus.next_request();
        bus.reply(&refusal);
    }
    assert_eq!(
        bus.event_kinds(),
        ["exception", "retry", "exception", "dropped"]
    );
    let counters = bus.counters(1);
    assert_eq!(
        (
            counters.requests,
            counters.exceptions,
            counters.retries,
            counters.lost
        ),
        (2, 2, 1, 1)
    );
    assert_eq!(counters.replies, 0);
}

#[test]
fn a_reply_from_another_slave_is_ignored() {
    let mut config = one_slave(Protocol::Meb, closed_loop(1, 1000.0));
    config.startup_outputs = None;
    let mut bus = Bus::new(config);
    bus.next_request();
    bus.reply(&meb(2, MebCmd::EA, 6, &INPUTS));
    let state = bus.master.loop_state(1).unwrap();
    assert_eq!(state.measured_at, None);
    assert_eq!(state.counters.unexpected, 1);
    // Still waiting: the right reply is used.
    bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));
    assert_eq!(bus.counters(1).replies, 1);
}

fn two_open_slaves(gap: SimDuration, period: SimDuration) -> SupervisorConfig {
    let slave = |id| SlaveLoopConfig {
        mode: LoopMode::Open { vel: 100 },
        ..SlaveLoopConfig::new(id)
    };
    let mut config = SupervisorConfig::new(Protocol::Meb, vec![slave(1), slave(2)]);
    config.startup_outputs = None;
    config.inter_frame_gap = gap;
    config.poll_period = period;
    config.first_poll_at = SimTime::ZERO + ms(3);
    config
}

/// Answers the next request of slave `id`'s read-and-write exchange; returns the
/// start of the read and the end of the write's acknowledgement.
fn read_and_write(bus: &mut Bus, id: u8, turnaround: SimDuration) -> (SimTime, SimTime) {
    let read = bus.next_request();
    assert_eq!(read.bytes, meb_text(&format!("@{id:02}EA0006")));
    bus.reply_after(turnaround, &meb(id, MebCmd::EA, 6, &INPUTS));
    let write = bus.next_request();
    assert_eq!(write.bytes, meb_text(&format!("@{id:02}SA00010064")));
    (
        read.start,
        bus.reply_after(turnaround, &meb(id, MebCmd::SA, 1, &[])),
    )
}

#[test]
fn cycles_keep_the_poll_period_and_requests_keep_the_gap() {
    let gap = SimDuration::from_micros(500);
    let mut bus = Bus::new(two_open_slaves(gap, ms(50)));
    let cycle_start = SimTime::ZERO + ms(3);

    let (read_1, end_1) = read_and_write(&mut bus, 1, TURNAROUND);
    assert_eq!(read_1, cycle_start);
    let (read_2, end_2) = read_and_write(&mut bus, 2, TURNAROUND);
    assert_eq!(read_2, end_1 + gap);
    assert!(end_2 < cycle_start + ms(50), "the cycle fits in its period");

    // Second cycle: reads only (outputs unchanged), at cycle start + period.
    let read = bus.next_request();
    assert_eq!(read.start, cycle_start + ms(50));
    let reply_end = bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));
    let read = bus.next_request();
    assert_eq!(
        (read.start, read.bytes),
        (reply_end + gap, meb_text("@02EA0006"))
    );
    bus.reply(&meb(2, MebCmd::EA, 6, &INPUTS));
    assert_eq!(bus.next_request().start, cycle_start + ms(100));
    assert_eq!(bus.master.cycles(), 2);
}

#[test]
fn an_overrun_cycle_is_followed_at_once_after_the_gap() {
    let gap = SimDuration::from_micros(500);
    let mut bus = Bus::new(two_open_slaves(gap, ms(20)));
    let cycle_start = SimTime::ZERO + ms(3);
    // Slow slaves: four exchanges with 5 ms turnarounds take about 34 ms.
    let slow = ms(5);
    let (read_1, _) = read_and_write(&mut bus, 1, slow);
    assert_eq!(read_1, cycle_start);
    let (_, end) = read_and_write(&mut bus, 2, slow);
    assert!(end > cycle_start + ms(20));
    let next = bus.next_request();
    assert_eq!(next.start, end + gap);
    // The period counts from there: a fast cycle now waits for it.
    bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));
    bus.next_request();
    bus.reply(&meb(2, MebCmd::EA, 6, &INPUTS));
    assert!(bus.now < end + gap + ms(20), "the fast cycle fits");
    assert_eq!(bus.next_request().start, end + gap + ms(20));
}

/// A first-order plant behind the fake slave: `VEL` counts drive the wheel
/// towards `GAIN` rpm per count with time constant `TAU`, integrated exactly
/// between bus events.
#[test]
fn the_loop_over_the_bus_settles_on_its_set_point() {
    const GAIN: f64 = 2.5;
    const TAU: f64 = 0.3;
    let slave = SlaveLoopConfig {
        kp: 0.2,
        ki: 1.0,
        set_points: vec![
            SetPointStep {
                at: SimTime::ZERO + ms(100),
                rpm: 3000.0,
            },
            SetPointStep {
                at: SimTime::ZERO + ms(3000),
                rpm: 1500.0,
            },
        ],
        ..SlaveLoopConfig::new(1)
    };
    let mut bus = Bus::new(one_slave(Protocol::Meb, slave));
    let mut rpm = 0.0f64;
    let mut vel = 0u16;
    let mut plant_time = SimTime::ZERO;
    let mut worst_after_settling = [0.0f64; 2];
    while bus.now < SimTime::ZERO + ms(6000) {
        let request = bus.next_request();
        let advance = |rpm: &mut f64, to: SimTime, from: &mut SimTime, vel: u16| {
            let target = GAIN * f64::from(vel);
            *rpm = target + (*rpm - target) * (-(to - *from).as_secs_f64() / TAU).exp();
            *from = to;
        };
        advance(&mut rpm, request.end, &mut plant_time, vel);
        let frame = MebRepr::parse(&request.bytes).unwrap();
        let reply = match frame.cmd {
            cmd if cmd == MebCmd::EA => {
                let mut inputs = INPUTS;
                inputs[3] = rpm.round() as u16;
                meb(1, MebCmd::EA, 6, &inputs)
            }
            cmd if cmd == MebCmd::SA => {
                vel = frame.data[0];
                meb(1, MebCmd::SA, 1, &[])
            }
            _ => meb(1, frame.cmd, frame.cnt, &[]),
        };
        bus.reply(&reply);
        let state = bus.master.loop_state(1).unwrap();
        let t = bus.now.as_secs_f64();
        for (window, (from, to, set_point)) in [(2.0, 3.0, 3000.0), (5.0, 6.0, 1500.0)]
            .into_iter()
            .enumerate()
        {
            if t > from && t < to {
                let error = (rpm - set_point).abs() / set_point;
                worst_after_settling[window] = worst_after_settling[window].max(error);
                assert_eq!(state.set_point_rpm, set_point);
            }
        }
    }
    assert!(worst_after_settling[0] < 0.02, "{worst_after_settling:?}");
    assert!(worst_after_settling[1] < 0.02, "{worst_after_settling:?}");
    assert!(worst_after_settling[0] > 0.0, "the window was visited");
    let counters = bus.counters(1);
    assert_eq!(counters.lost, 0);
    assert_eq!(counters.requests, counters.replies);
}

#[test]
fn configurations_that_cannot_run_are_refused() {
    use nodes::master::SupervisorConfigError as E;
    let config = |slaves| SupervisorConfig::new(Protocol::Meb, slaves);
    assert_eq!(Supervisor::new(config(vec![])).unwrap_err(), E::NoSlaves);
    assert!(matches!(
        Supervisor::new(config(vec![SlaveLoopConfig::new(0)])),
        Err(E::IdOutOfRange { id: 0, .. })
    ));
    assert!(matches!(
        Supervisor::new(config(vec![SlaveLoopConfig::new(100)])),
        Err(E::IdOutOfRange { id: 100, .. })
    ));
    assert_eq!(
        Supervisor::new(config(vec![
            SlaveLoopConfig::new(3),
            SlaveLoopConfig::new(3)
        ]))
        .unwrap_err(),
        E::DuplicateId(3)
    );
    let bad_gain = SlaveLoopConfig {
        kp: f64::NAN,
        ..SlaveLoopConfig::new(1)
    };
    assert!(matches!(
        Supervisor::new(config(vec![bad_gain])),
        Err(E::NotFinite { field: "kp", .. })
    ));
    let rtu = SupervisorConfig::new(Protocol::ModbusRtu, vec![SlaveLoopConfig::new(200)]);
    assert!(Supervisor::new(rtu).is_ok());
}

#[test]
fn an_rtu_exception_is_counted_and_retried() {
    use protocols::modbus::{Exception, ExceptionResponse};
    let mut config = one_slave(Protocol::ModbusRtu, closed_loop(1, 1000.0));
    config.startup_outputs = None;
    let mut bus = Bus::new(config);
    let first = bus.next_request();
    let refusal: Result<Response, ExceptionResponse> = Err(ExceptionResponse {
        function: 0x04,
        exception: Exception::IllegalDataAddress,
    });
    let mut out = [0u8; 16];
    let n = rtu::RtuRepr {
        unit: 1,
        pdu: &refusal,
    }
    .emit(&mut out)
    .unwrap();
    bus.reply(&out[..n]);
    assert_eq!(bus.event_kinds(), ["exception", "retry"]);
    assert_eq!(bus.next_request().bytes, first.bytes);
    let counters = bus.counters(1);
    assert_eq!(
        (counters.exceptions, counters.retries, counters.replies),
        (1, 1, 0)
    );
}

#[test]
fn the_schedule_steps_in_time_order_and_an_override_wins() {
    let slave = SlaveLoopConfig {
        // Given out of order: the supervisor sorts them.
        set_points: vec![
            SetPointStep {
                at: SimTime::ZERO + ms(200),
                rpm: 2000.0,
            },
            SetPointStep {
                at: SimTime::ZERO + ms(100),
                rpm: 1000.0,
            },
        ],
        ..SlaveLoopConfig::new(1)
    };
    let mut master = Supervisor::new(one_slave(Protocol::Meb, slave)).unwrap();
    let at = |t| SimTime::ZERO + ms(t);
    let schedule: Vec<_> = [0, 99, 100, 199, 200, 5000]
        .into_iter()
        .map(|t| master.set_point(1, at(t)).unwrap())
        .collect();
    assert_eq!(schedule, [0.0, 0.0, 1000.0, 1000.0, 2000.0, 2000.0]);
    assert!(master.set_set_point(1, Some(1234.0)));
    assert_eq!(master.set_point(1, at(150)), Some(1234.0));
    assert!(!master.set_set_point(1, Some(f64::INFINITY)));
    assert!(!master.set_set_point(9, Some(1.0)));
    assert!(master.set_set_point(1, None));
    assert_eq!(master.set_point(1, at(150)), Some(1000.0));
    assert_eq!(master.set_point(2, at(150)), None);
}

#[test]
fn closing_the_loop_starts_from_the_manual_output() {
    let slave = SlaveLoopConfig {
        mode: LoopMode::Open { vel: 2000 },
        ..closed_loop(1, 200.0)
    };
    let mut config = one_slave(Protocol::Meb, slave);
    config.startup_outputs = None;
    let mut bus = Bus::new(config);
    bus.next_request();
    bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));
    bus.next_request();
    bus.reply(&meb(1, MebCmd::SA, 1, &[]));
    assert!(bus.master.set_mode(1, LoopMode::Closed));
    bus.next_request();
    // Measured 200 = set point: no error, so the output is the integral alone,
    // which starts at the manual 2000 and needs no new write.
    bus.reply(&meb(1, MebCmd::EA, 6, &INPUTS));
    let state = bus.master.loop_state(1).unwrap();
    assert_eq!((state.error_rpm, state.output), (0.0, 2000));
    assert_eq!(bus.next_request().bytes, b"@01EA000643*\n");
}
