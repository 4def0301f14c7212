//! The supervisor's MEB-over-TCP server (`docs/protocols/meb.md`, "The supervisor's
//! image") against the crate's real EV controller on a point-to-point line:
//! requests are written out as the spec spells them (the FCS computed here
//! again), and every reply is compared byte for byte.

use nodes::firmware::{EvController, EvControllerConfig};
use nodes::master::image_server::{ClientId, CloseReason, ImageServer, ImageServerConfig};
use nodes::master::{Protocol, SlaveLoopConfig, Supervisor, SupervisorConfig};
use nodes::node::{Firmware, MAX_FRAME, Node};
use plant::Sensors;
use protocols::meb::MebError;
use protocols::time::{SimDuration, SimTime};

const BAUD: u32 = 115_200;
const TURNAROUND: SimDuration = SimDuration::from_millis(1);

/// `@…` with its FCS and `*\n` appended; the XOR written out again here.
fn frame(body: &str) -> Vec<u8> {
    let fcs = body.bytes().fold(0u8, |acc, b| acc ^ b);
    format!("{body}{fcs:02X}*\n").into_bytes()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn wire(len: usize) -> SimDuration {
    SimDuration::bit_times(10 * len as u64, BAUD)
}

/// A supervisor, the EV controller it polls and the TCP server's logic, on a
/// line with real wire times. Each client is a queue of bytes it received.
struct Rig {
    now: SimTime,
    supervisor: Supervisor,
    slave: EvController,
    server: ImageServer,
    /// Frames on the line: arrival time, to the slave (true) or master, bytes.
    line: Vec<(SimTime, bool, Vec<u8>)>,
    /// The slave is unplugged: it hears nothing.
    unplugged: bool,
    sensors: Sensors,
    next_tick: SimTime,
}

impl Rig {
    fn new(config: ImageServerConfig) -> Self {
        Self::reading_status(config, 0)
    }

    /// A supervisor that reads the status words every `status_every` cycles.
    fn reading_status(config: ImageServerConfig, status_every: u32) -> Self {
        let mut loop_config = SlaveLoopConfig::new(1);
        loop_config.kp = 0.45;
        loop_config.ki = 2.5;
        let mut supervisor_config = SupervisorConfig::new(Protocol::Meb, vec![loop_config]);
        supervisor_config.status_every = status_every;
        let supervisor = Supervisor::new(supervisor_config).unwrap();
        let sensors = Sensors {
            bus_counts: 3000,
            current_counts: 200,
            battery_counts: 2900,
            ldr_counts: 1000,
            ..Sensors::default()
        };
        Self {
            now: SimTime::ZERO,
            supervisor,
            slave: EvController::new(EvControllerConfig::default()),
            server: ImageServer::new(config),
            line: Vec::new(),
            unplugged: false,
            sensors,
            next_tick: SimTime::ZERO,
        }
    }

    /// Runs everything up to `until`, event by event.
    fn run_for(&mut self, duration: SimDuration) {
        let until = self.now + duration;
        let mut buf = [0u8; MAX_FRAME];
        loop {
            self.server.collect(&mut self.supervisor);
            if let Some(n) = self.supervisor.poll_transmit(self.now, &mut buf) {
                let end = self.now + wire(n);
                self.supervisor.transmit_done(end);
                if !self.unplugged {
                    self.line.push((end, true, buf[..n].to_vec()));
                }
                continue;
            }
            let next_line = self.line.iter().map(|(at, _, _)| *at).min();
            let next = [
                next_line,
                self.supervisor.poll_timeout(),
                Some(self.next_tick),
                self.server.poll_timeout(),
            ]
            .into_iter()
            .flatten()
            .min()
            .unwrap();
            if next > until {
                self.now = until;
                return;
            }
            self.now = self.now.max(next);
            if self.next_tick <= self.now {
                self.slave.loop_tick(self.now, &self.sensors);
                self.next_tick = self.now + self.slave.loop_period();
            }
            self.server.handle_timeout(self.now);
            if let Some(i) = self.line.iter().position(|(at, _, _)| *at <= self.now) {
                let (_, to_slave, bytes) = self.line.remove(i);
                if to_slave {
                    self.slave.handle_bytes(self.now, &bytes);
                    if let Some(n) = self.slave.poll_transmit(self.now, &mut buf) {
                        let arrives = self.now + TURNAROUND + wire(n);
                        self.line.push((arrives, false, buf[..n].to_vec()));
                    }
                } else {
                    self.supervisor.handle_bytes(self.now, &bytes);
                }
            }
            self.supervisor.handle_timeout(self.now);
        }
    }

    fn connect(&mut self) -> ClientId {
        self.server.accept(self.now).unwrap()
    }

    fn send(&mut self, client: ClientId, bytes: &[u8]) {
        self.server
            .handle_bytes(self.now, client, bytes, &mut self.supervisor);
    }

    /// Every reply `client` is owed and can have now, as text.
    fn replies(&mut self, client: ClientId) -> Vec<String> {
        self.server.collect(&mut self.supervisor);
        let mut buf = [0u8; MAX_FRAME];
        let mut out = Vec::new();
        while let Some(n) = self.server.poll_transmit(client, &mut buf) {
            out.push(text(&buf[..n]));
        }
        out
    }

    /// Sends `request` and returns the replies after `wait`.
    fn ask(&mut self, client: ClientId, request: &[u8], wait: SimDuration) -> Vec<String> {
        self.send(client, request);
        self.run_for(wait);
        self.replies(client)
    }
}

fn ms(n: u64) -> SimDuration {
    SimDuration::from_millis(n)
}

fn s(text: &str) -> String {
    String::from_utf8(frame(text)).unwrap()
}

#[test]
fn reads_are_answered_from_the_last_poll_and_never_reach_the_bus() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    // Before the first poll there is nothing to answer with.
    assert_eq!(
        rig.ask(client, &frame("@01EA0003"), SimDuration::ZERO),
        [s("@01ER00010004")]
    );
    rig.run_for(ms(50));
    let requests_before = rig.supervisor.loop_state(1).unwrap().counters.requests;
    // Read at once, from the image: the inputs the controller sampled.
    rig.send(client, &frame("@01EA0006"));
    assert_eq!(
        rig.replies(client),
        [s("@01EA00060BB800C80B540000000003E8")]
    );
    assert_eq!(
        rig.ask(client, &frame("@01EA0202"), SimDuration::ZERO),
        [s("@01EA02020B540000")]
    );
    let requests_after = rig.supervisor.loop_state(1).unwrap().counters.requests;
    assert!(
        requests_after - requests_before <= 2,
        "the reads added bus traffic: {requests_before} -> {requests_after}"
    );
}

#[test]
fn what_the_image_does_not_hold_is_refused_with_the_spec_codes() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    rig.run_for(ms(50));
    let cases = [
        ("@01EA0403", "@01ER04010002"), // EA 4..6: past the six inputs
        ("@01ED0001", "@01ER00010002"), // not polled, not held
        ("@01FA0001", "@01ER00010002"), // the slave's flags are not held
        ("@01FA0F02", "@01ER0F010002"), // runs into the mirrors from below
        ("@01FA1004", "@01ER10010002"), // past FA 12
        ("@07EA0001", "@07ER00010002"), // a slave this supervisor does not poll
        ("@01ea0001", "@01ER00010001"), // lower-case command
        ("@01XY0001", "@01ER00010001"), // no such command
        ("@01EA0000", "@01ER00010003"), // CNT 0
    ];
    for (request, reply) in cases {
        assert_eq!(
            rig.ask(client, &frame(request), SimDuration::ZERO),
            [s(reply)],
            "request {request}"
        );
    }
    let stats = rig.server.client_stats(client).unwrap();
    assert_eq!(stats.requests, cases.len() as u64);
    assert_eq!(stats.errors, cases.len() as u64);
}

#[test]
fn writes_are_acknowledged_only_once_the_slave_acknowledged_them() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    rig.run_for(ms(50));
    // Disable the module and apply the brake: SD0 = 0x001D.
    rig.send(client, &frame("@01SD0001001D"));
    assert!(
        rig.replies(client).is_empty(),
        "acknowledged before the bus answered"
    );
    rig.run_for(ms(20));
    assert_eq!(rig.replies(client), [s("@01SD0001")]);
    assert_eq!(rig.slave.image().stored.sd0, 0x001D);
    // The slave's own variables are forwarded too: RPM_WIN = 50 ms.
    assert_eq!(
        rig.ask(client, &frame("@01VA01010032"), ms(20)),
        [s("@01VA0101")]
    );
    assert_eq!(rig.slave.image().stored.rpm_window_ms, 50);
}

#[test]
fn a_refusal_by_the_slave_is_passed_on_and_silence_is_error_04() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    rig.run_for(ms(50));
    // VEL above the 12-bit DAC: the controller answers ER 03, passed on as is.
    assert_eq!(
        rig.ask(client, &frame("@01SA00011000"), ms(20)),
        [s("@01ER00010003")]
    );
    // SD 02: the controller has two digital output words.
    assert_eq!(
        rig.ask(client, &frame("@01SD02010000"), ms(20)),
        [s("@01ER02010002")]
    );
    rig.unplugged = true;
    rig.send(client, &frame("@01SA00010800"));
    // Three attempts of 100 ms each before the supervisor gives up.
    rig.run_for(ms(250));
    assert!(rig.replies(client).is_empty(), "gave up before its retries");
    rig.run_for(ms(100));
    assert_eq!(rig.replies(client), [s("@01ER00010004")]);
}

#[test]
fn a_read_only_client_reads_but_every_write_is_error_01() {
    let mut rig = Rig::new(ImageServerConfig {
        read_only: true,
        ..ImageServerConfig::default()
    });
    let client = rig.connect();
    rig.run_for(ms(50));
    assert_eq!(
        rig.ask(client, &frame("@01SA00010800"), ms(20)),
        [s("@01ER00010001")]
    );
    assert_eq!(
        rig.ask(client, &frame("@01VA10010200"), ms(20)),
        [s("@01ER10010001")]
    );
    assert_eq!(
        rig.ask(client, &frame("@01EA0301"), ms(0)),
        [s("@01EA03010000")]
    );
    assert_eq!(
        rig.slave.image().stored.vel,
        0,
        "a read-only write reached the slave"
    );
    // The server's default is per client: another may be made writable.
    let writer = rig.connect();
    rig.server.set_read_only(writer, false);
    assert_eq!(
        rig.ask(writer, &frame("@01SA00010800"), ms(20)),
        [s("@01SA0001")]
    );
}

#[test]
fn the_loop_variables_are_written_at_once_and_mirrored_in_the_flags() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    rig.run_for(ms(50));
    // FA 10-12 at start: set point 0, Kp 0.45, Ki 2.5 (x1000); FD 10: closed.
    assert_eq!(
        rig.ask(client, &frame("@01FA1003"), ms(0)),
        [s("@01FA1003000001C209C4")]
    );
    assert_eq!(
        rig.ask(client, &frame("@01FD1001"), ms(0)),
        [s("@01FD10010001")]
    );
    // Set point 1500 rpm, Kp 0.5, Ki 3.0 in one write.
    assert_eq!(
        rig.ask(client, &frame("@01VA100305DC01F40BB8"), ms(0)),
        [s("@01VA1003")]
    );
    assert_eq!(rig.supervisor.set_point(1, rig.now), Some(1500.0));
    assert_eq!(rig.supervisor.gains(1), Some((0.5, 3.0)));
    assert_eq!(
        rig.ask(client, &frame("@01FA1003"), ms(0)),
        [s("@01FA100305DC01F40BB8")]
    );
    // Only Ki: VA 12.
    assert_eq!(
        rig.ask(client, &frame("@01VA12010FA0"), ms(0)),
        [s("@01VA1201")]
    );
    assert_eq!(rig.supervisor.gains(1), Some((0.5, 4.0)));
    // Out of range: 20001 rpm, VD bits other than bit 0; past VA 12; from the
    // slave's variables into the loop's. Nothing is applied.
    let refused = [
        ("@01VA10014E21", "@01ER10010003"),
        ("@01VD10010002", "@01ER10010003"),
        ("@01VA12020000 0000", "@01ER12010002"),
        ("@01VA0F0200000000", "@01ER0F010002"),
        ("@01VD11010001", "@01ER11010002"),
    ];
    for (request, reply) in refused {
        let request = request.replace(' ', "");
        assert_eq!(
            rig.ask(client, &frame(&request), ms(0)),
            [s(reply)],
            "{request}"
        );
    }
    assert_eq!(rig.supervisor.set_point(1, rig.now), Some(1500.0));
    assert_eq!(rig.supervisor.gains(1), Some((0.5, 4.0)));
    // Open the loop: the supervisor holds the VEL the slave has and the flag follows.
    assert_eq!(
        rig.ask(client, &frame("@01VD10010000"), ms(0)),
        [s("@01VD1001")]
    );
    assert_eq!(
        rig.ask(client, &frame("@01FD1001"), ms(0)),
        [s("@01FD10010000")]
    );
    // With the loop open, a client's VEL write is what the supervisor holds.
    assert_eq!(
        rig.ask(client, &frame("@01SA00010123"), ms(20)),
        [s("@01SA0001")]
    );
    rig.run_for(ms(100));
    assert_eq!(rig.slave.image().stored.vel, 0x0123);
    assert_eq!(rig.supervisor.loop_state(1).unwrap().output, 0x0123);
}

#[test]
fn pipelined_requests_are_answered_in_order() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    rig.run_for(ms(50));
    let mut burst = frame("@01EA0301");
    burst.extend(frame("@01SD0001001D"));
    burst.extend(frame("@01FD1001"));
    burst.extend(frame("@01EA0001"));
    rig.send(client, &burst);
    // The first read is ready; the rest wait behind the forwarded write.
    assert_eq!(rig.replies(client), [s("@01EA03010000")]);
    rig.run_for(ms(20));
    assert_eq!(
        rig.replies(client),
        [s("@01SD0001"), s("@01FD10010001"), s("@01EA00010BB8")]
    );
}

#[test]
fn garbage_and_half_frames_from_one_client_do_not_touch_another() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let noisy = rig.connect();
    let quiet = rig.connect();
    rig.run_for(ms(50));
    // Noise, a bad FCS, a frame cut by a new `@`, and half a frame left open.
    let mut garbage = b"\x00\xffhello*\n".to_vec();
    let mut bad_fcs = frame("@01EA0001");
    bad_fcs[9] ^= 0x01;
    garbage.extend(bad_fcs);
    garbage.extend(b"@01EA00");
    garbage.extend(frame("@01EA0001"));
    garbage.extend(b"@01SA0001");
    rig.send(noisy, &garbage);
    // The one good frame in it is answered; the rest is counted.
    assert_eq!(rig.replies(noisy), [s("@01EA00010BB8")]);
    let stats = rig.server.decoder_stats(noisy).unwrap();
    assert_eq!(stats.malformed(MebError::BadFcs), 1);
    assert_eq!(stats.interrupted, 1);
    assert_eq!(stats.noise_bytes, 9);
    // The other client is served meanwhile, as if nothing happened.
    assert_eq!(
        rig.ask(quiet, &frame("@01EA0201"), ms(0)),
        [s("@01EA02010B54")]
    );
    assert_eq!(rig.server.close_reason(noisy), None);
    // The half frame is held for 5 s, then that connection is closed.
    rig.run_for(ms(4_900));
    assert_eq!(rig.server.close_reason(noisy), None);
    rig.run_for(ms(200));
    assert_eq!(
        rig.server.close_reason(noisy),
        Some(CloseReason::PartialTimeout)
    );
    assert_eq!(rig.server.close_reason(quiet), None);
    rig.server.disconnect(noisy);
    assert_eq!(
        rig.ask(quiet, &frame("@01EA0201"), ms(0)),
        [s("@01EA02010B54")]
    );
}

#[test]
fn a_client_over_the_rate_limit_is_closed_and_the_client_limit_refuses_newcomers() {
    let mut rig = Rig::new(ImageServerConfig {
        max_clients: 2,
        rate_per_second: 10.0,
        rate_burst: 5.0,
        ..ImageServerConfig::default()
    });
    let flood = rig.connect();
    let calm = rig.connect();
    assert!(
        rig.server.accept(rig.now).is_err(),
        "a third client was let in"
    );
    rig.run_for(ms(50));
    let one = frame("@01EA0001");
    for _ in 0..5 {
        rig.send(flood, &one);
    }
    assert_eq!(rig.server.close_reason(flood), None);
    rig.send(flood, &one);
    assert_eq!(rig.server.close_reason(flood), Some(CloseReason::RateLimit));
    // The calm client sends within the rate: never closed.
    for _ in 0..20 {
        rig.send(calm, &one);
        rig.run_for(ms(100));
    }
    assert_eq!(rig.server.close_reason(calm), None);
    assert_eq!(rig.replies(calm).len(), 20);
    // A place freed is taken again.
    rig.server.disconnect(flood);
    assert!(rig.server.accept(rig.now).is_ok());
}

#[test]
fn reply_shaped_frames_and_broadcasts_get_no_reply() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    rig.run_for(ms(50));
    for ignored in [
        "@01EA00010BB8",
        "@01SA0001",
        "@01ER00010002",
        "@00SA00010800",
        "@00EA0001",
    ] {
        assert!(
            rig.ask(client, &frame(ignored), ms(20)).is_empty(),
            "{ignored}"
        );
    }
    assert_eq!(rig.server.client_stats(client).unwrap().ignored, 5);
    assert_eq!(rig.slave.image().stored.vel, 0);
}

#[test]
fn servers_sharing_one_supervisor_each_get_their_own_outcomes() {
    // The real-time engine gives every TCP connection its own server state;
    // all of them forward through the one supervisor.
    let mut rig = Rig::new(ImageServerConfig::default());
    let mut other = ImageServer::new(ImageServerConfig::default());
    let first = rig.connect();
    let second = other.accept(rig.now).unwrap();
    rig.run_for(ms(50));
    rig.send(first, &frame("@01SD0001001D"));
    other.handle_bytes(
        rig.now,
        second,
        &frame("@01SA00011000"),
        &mut rig.supervisor,
    );
    // The first server collects before the second: it must leave the
    // second's outcome alone.
    rig.run_for(ms(30));
    assert_eq!(rig.replies(first), [s("@01SD0001")]);
    other.collect(&mut rig.supervisor);
    let mut buf = [0u8; MAX_FRAME];
    let n = other.poll_transmit(second, &mut buf).expect("its reply");
    assert_eq!(text(&buf[..n]), s("@01ER00010003"));
    assert_eq!(rig.supervisor.forwards_in_flight(), 0);
}

#[test]
fn a_write_that_never_reaches_the_line_is_answered_error_04_and_withdrawn() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    rig.run_for(ms(50));
    // The bus is gone: nothing drives the supervisor, the write waits.
    rig.send(client, &frame("@01SA00010800"));
    let later = rig.now + ms(700);
    rig.server.expire(later, &mut rig.supervisor);
    assert!(rig.replies(client).is_empty(), "expired too early");
    rig.server.expire(later + ms(100), &mut rig.supervisor);
    assert_eq!(rig.replies(client), [s("@01ER00010004")]);
    // Withdrawn: when the bus is back, the stale write is not applied.
    assert_eq!(rig.supervisor.forwards_in_flight(), 0);
    rig.run_for(ms(50));
    assert_eq!(
        rig.slave.image().stored.vel,
        rig.supervisor.loop_state(1).unwrap().vel_written.unwrap()
    );
    assert_ne!(rig.slave.image().stored.vel, 0x0800);
}

#[test]
fn a_write_already_on_the_line_when_its_wait_runs_out_gets_its_own_answer() {
    let mut rig = Rig::new(ImageServerConfig::default());
    let client = rig.connect();
    rig.run_for(ms(50));
    let asked = rig.now;
    rig.send(client, &frame("@01SA00010800"));
    // Until the supervisor has put the write on the line.
    while !rig
        .line
        .iter()
        .any(|(_, to_slave, bytes)| *to_slave && bytes.starts_with(b"@01SA00010800"))
    {
        rig.run_for(SimDuration::from_micros(100));
        assert!(rig.now < asked + ms(100), "the write never went out");
    }
    // The wait runs out mid-exchange (a machine that stalled): too late to
    // withdraw it, so no ER 04 that the slave's own answer would contradict.
    rig.server.expire(asked + ms(900), &mut rig.supervisor);
    assert!(
        rig.replies(client).is_empty(),
        "answered before the slave did"
    );
    rig.run_for(ms(20));
    // The slave's acknowledgement, passed on (the loop writes its own VEL
    // again at its next poll, so the stored value is not the test).
    assert_eq!(rig.replies(client), [s("@01SA0001")]);
}

#[test]
fn the_status_words_are_served_when_the_supervisor_reads_them() {
    let mut rig = Rig::reading_status(ImageServerConfig::default(), 5);
    let client = rig.connect();
    assert_eq!(
        rig.ask(client, &frame("@01FD0001"), ms(0)),
        [s("@01ER00010004")]
    );
    rig.run_for(ms(100));
    let image = rig.slave.image();
    let (hall, soc, errs, status) = (image.hall, image.soc, image.errs, image.status);
    // Disabled and braked by a write, so STATUS changes and the next round shows it.
    assert_eq!(
        rig.ask(client, &frame("@01SD0001001B"), ms(20)),
        [s("@01SD0001")]
    );
    assert_eq!(
        rig.ask(client, &frame("@01ED0001"), ms(0)),
        [s(&format!("@01ED0001{hall:04X}"))]
    );
    assert_eq!(
        rig.ask(client, &frame("@01FA0002"), ms(0)),
        [s(&format!("@01FA0002{soc:04X}{errs:04X}"))]
    );
    assert_eq!(
        rig.ask(client, &frame("@01FD0001"), ms(0)),
        [s(&format!("@01FD0001{status:04X}"))]
    );
    rig.run_for(ms(100));
    let reversed = rig.slave.image().status;
    assert_eq!(
        reversed,
        status | 0b10_0000,
        "the direction did not show in STATUS"
    );
    assert_eq!(
        rig.ask(client, &frame("@01FD0001"), ms(0)),
        [s(&format!("@01FD0001{reversed:04X}"))]
    );
    // Still not held: past the blocks, and the slave's ED beyond word 0.
    assert_eq!(
        rig.ask(client, &frame("@01FA0102"), ms(0)),
        [s("@01ER01010002")]
    );
    assert_eq!(
        rig.ask(client, &frame("@01ED0101"), ms(0)),
        [s("@01ER01010002")]
    );
    // One status round (3 reads) every 5 cycles on top of each cycle's read.
    let c = rig.supervisor.loop_state(1).unwrap().counters;
    assert_eq!(c.requests, c.replies);
}
