//! `twin serve` as a master sees it: the real binary on real TCP sockets and
//! pseudo-terminals, spoken to with the `nodes` crate's own codecs. Every
//! server binds port 0 and the test reads the port it prints.

use protocols::meb::{MebCmd, MebErrorCode, MebRepr, MebWords};
use protocols::modbus::{self, Adu, Exception, Request, Response};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::support;
use support::Proc;

/// A running `twin serve` and the links it printed (protocol, address, ids).
struct Server {
    proc: Proc,
    links: Vec<(String, String, String)>,
}

impl Server {
    fn start(args: &[&str]) -> Server {
        Self::spawn(args, Stdio::null())
    }

    /// With a console: the test types commands on the server's stdin.
    fn with_console(args: &[&str]) -> (Server, std::process::ChildStdin) {
        let mut server = Self::spawn(args, Stdio::piped());
        let stdin = server.proc.child.stdin.take().expect("stdin");
        (server, stdin)
    }

    fn spawn(args: &[&str], stdin: Stdio) -> Server {
        let args: Vec<&str> = std::iter::once("serve")
            .chain(args.iter().copied())
            .collect();
        let proc = Proc::spawn(&args, stdin);
        let links = proc
            .links()
            .into_iter()
            .map(|f| (f[0].clone(), f[1].clone(), f[2].clone()))
            .collect();
        Server { proc, links }
    }

    /// The address printed for the `n`th link.
    fn tcp(&self, n: usize) -> String {
        support::host_port(&self.links[n].1).to_string()
    }

    fn output(&self) -> String {
        self.proc.output()
    }

    fn printed(&self, needle: &str) -> bool {
        self.proc.printed(needle)
    }

    fn terminate(self) -> String {
        self.proc.terminate()
    }
}

fn scratch(name: &str) -> PathBuf {
    support::scratch("serve-cli", name)
}

fn connect(addr: &str) -> TcpStream {
    let s = TcpStream::connect(addr).expect("connects");
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s.set_nodelay(true).unwrap();
    s
}

fn meb_frame(id: u8, cmd: MebCmd, addr: u8, cnt: u8, data: &[u16]) -> Vec<u8> {
    let repr = MebRepr {
        id,
        cmd,
        addr,
        cnt,
        data: MebWords::from_slice(data).expect("words fit"),
    };
    let mut out = [0u8; 512];
    let n = repr.emit(&mut out).expect("emits");
    out[..n].to_vec()
}

/// Sends an MEB request and reads one reply line, as bytes.
fn meb_raw(s: &mut TcpStream, request: &[u8]) -> Vec<u8> {
    s.write_all(request).unwrap();
    let mut reply = Vec::new();
    let mut byte = [0u8; 1];
    while reply.last() != Some(&b'\n') {
        let n = s.read(&mut byte).expect("a reply before the timeout");
        assert_eq!(n, 1, "connection closed; got {reply:?}");
        reply.push(byte[0]);
    }
    reply
}

/// Sends an MEB request and reads one reply.
fn meb(s: &mut TcpStream, request: &[u8]) -> MebRepr {
    MebRepr::parse(&meb_raw(s, request)).expect("a well-formed MEB reply")
}

fn read_ea(s: &mut TcpStream) -> Vec<u16> {
    let r = meb(s, &meb_frame(1, MebCmd::EA, 0, 6, &[]));
    assert_eq!((r.id, r.cmd), (1, MebCmd::EA));
    r.data.as_slice().to_vec()
}

/// Sends a Modbus TCP request and reads its reply.
fn modbus_tcp(
    s: &mut TcpStream,
    tid: u16,
    unit: u8,
    request: &Request,
) -> Result<Response, modbus::ExceptionResponse> {
    let mut out = [0u8; 300];
    let n = modbus::tcp::TcpRepr {
        transaction_id: tid,
        unit,
        pdu: request,
    }
    .emit(&mut out)
    .unwrap();
    s.write_all(&out[..n]).unwrap();
    let mut header = [0u8; 6];
    s.read_exact(&mut header).expect("an MBAP header");
    let len = usize::from(u16::from_be_bytes([header[4], header[5]]));
    let mut rest = vec![0u8; len];
    s.read_exact(&mut rest).expect("the rest of the reply");
    let mut adu = header.to_vec();
    adu.extend(rest);
    let frame = modbus::tcp::TcpFrame::new_checked(&adu).expect("a well-formed reply");
    assert_eq!(frame.transaction_id(), tid, "transaction id echoed");
    assert_eq!(frame.unit(), unit, "unit id echoed");
    frame.response().expect("a valid PDU")
}

/// VEL (holding register 0) written over Modbus TCP, the write's echo checked.
fn write_vel(s: &mut TcpStream, tid: u16, vel: u16) {
    let r = modbus_tcp(
        s,
        tid,
        1,
        &Request::WriteSingleRegister {
            address: 0,
            value: vel,
        },
    );
    assert!(
        matches!(r, Ok(Response::WriteSingleRegister { .. })),
        "{r:?}"
    );
}

fn input_registers(s: &mut TcpStream, tid: u16) -> Vec<u16> {
    let request = Request::ReadInputRegisters {
        address: 0,
        quantity: 10,
    };
    match modbus_tcp(s, tid, 1, &request) {
        Ok(Response::ReadInputRegisters(r)) => r.as_slice().to_vec(),
        other => panic!("unexpected reply {other:?}"),
    }
}

/// SD0 with EN applied and brake, boost and discharge released (active low).
const SD0_RUN: u16 = 0b0_1110;

#[test]
fn meb_and_modbus_tcp_serve_one_module_and_a_write_turns_the_wheel() {
    let out = scratch("turns.mcap");
    let server = Server::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(server.links[0].0, "meb");
    assert_eq!(server.links[1].0, "modbus-tcp");
    assert_eq!(server.links[0].2, "01");
    let mut m = connect(&server.tcp(0));
    let mut t = connect(&server.tcp(1));

    // Both front ends read the same image: V1 agrees (the battery at rest).
    let ea = read_ea(&mut m);
    let ir = input_registers(&mut t, 1);
    assert!(ea[2] > 3000, "V1 counts of a charged pack: {ea:?}");
    assert!(ea[2].abs_diff(ir[2]) <= 2, "MEB {ea:?} vs Modbus {ir:?}");
    assert_eq!(ea[3], 0, "the wheel is still");

    // Units 0 and 255 are this device over TCP.
    for unit in [0u8, 255] {
        let r = modbus_tcp(
            &mut t,
            9,
            unit,
            &Request::ReadHoldingRegisters {
                address: 0,
                quantity: 3,
            },
        );
        assert!(matches!(r, Ok(Response::ReadHoldingRegisters(_))), "{r:?}");
    }

    // Enable over MEB, set VEL over Modbus: the hall rpm rises.
    let ack = meb(&mut m, &meb_frame(1, MebCmd::SD, 0, 1, &[SD0_RUN]));
    assert_eq!(ack.cmd, MebCmd::SD, "{ack:?}");
    write_vel(&mut t, 2, 2048);
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut tid = 10;
    let rpm = loop {
        tid += 1;
        let rpm = input_registers(&mut t, tid)[3];
        if rpm > 1000 || Instant::now() > deadline {
            break rpm;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(rpm > 1000, "the wheel turns at half VEL: RPM_M {rpm}");
    let meb_rpm = read_ea(&mut m)[3];
    assert!(
        meb_rpm.abs_diff(rpm) < 300,
        "MEB RPM_M {meb_rpm} vs Modbus {rpm}"
    );

    let text = server.terminate();
    assert!(text.contains("stopped (SIGTERM)"), "{text}");
    assert!(text.contains("tick lateness over"), "{text}");

    // The recording holds both links' frames, the plant and the lateness.
    let bytes = std::fs::read(&out).expect("recording written");
    let mut topics = std::collections::BTreeMap::<String, usize>::new();
    for m in mcap::MessageStream::new(&bytes).expect("valid MCAP") {
        *topics
            .entry(m.expect("message").channel.topic.clone())
            .or_default() += 1;
    }
    for topic in [
        "/link/meb/frames",
        "/link/modbus-tcp/frames",
        "/plant/ev1/sensors",
        "/plant/ev1/actuators",
        "/realtime/lateness",
    ] {
        assert!(
            topics.get(topic).is_some_and(|&n| n > 0),
            "{topic}: {topics:?}"
        );
    }
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("has one");
    assert!(!summary.metadata_indexes.is_empty());
}

/// A client polling every 15-40 ms reads the plant of its request's
/// arrival, though the engine sleeps through batches of plant ticks between
/// requests: each request that finds the plant behind has it caught up
/// first. Read from the recording (the controller's readings at every tick,
/// `--record-hz 1000`, and each request's arrival on the link): every reply
/// is the readings of the tick of its arrival or of the one before (as when
/// a tick runs a little late), never of a later one, while the wheel speeds
/// up and the words change from tick to tick; and the engine woke far
/// fewer times than the session had ticks.
#[test]
fn a_polled_module_answers_from_the_plant_of_each_request_s_arrival() {
    let dir = scratch("fresh");
    let recording = dir.join("fresh.mcap");
    let server = Server::start(&[
        "--modbus",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--record-hz",
        "1000",
        "--out",
        recording.to_str().unwrap(),
    ]);
    let mut t = connect(&server.tcp(0));
    // EN (coil 0) and FR (coil 4) to 0: SD0_RUN; then VEL at half.
    for (tid, address) in [(1, 0), (2, 4)] {
        let r = modbus_tcp(
            &mut t,
            tid,
            1,
            &Request::WriteSingleCoil {
                address,
                value: false,
            },
        );
        assert!(matches!(r, Ok(Response::WriteSingleCoil { .. })), "{r:?}");
    }
    write_vel(&mut t, 3, 2048);
    let mut read = std::collections::BTreeMap::new();
    for i in 0..80u16 {
        std::thread::sleep(Duration::from_millis(15 + u64::from(i * 7 % 26)));
        let tid = 100 + i;
        let request = Request::ReadInputRegisters {
            address: 0,
            quantity: 6,
        };
        match modbus_tcp(&mut t, tid, 1, &request) {
            Ok(Response::ReadInputRegisters(r)) => read.insert(tid, r.as_slice().to_vec()),
            other => panic!("unexpected reply {other:?}"),
        };
    }
    let said = server.terminate();

    // Each request's arrival (its first bytes on the link), the readings
    // of every tick, and how many times the engine woke for late ticks
    // (once a tick when it ticks every millisecond; in batches, once a
    // batch and once per request that found the plant behind).
    let mut arrived = std::collections::BTreeMap::<u16, f64>::new();
    let mut readings = std::collections::BTreeMap::<u64, Vec<u16>>::new();
    let mut woke_for = 0;
    twin_recording::Recording::scan(&recording, |msg| {
        match msg.topic {
            "/link/modbus-tcp/frames" => {
                let v = msg.value()?;
                if let Some(tid) = v["decoded"]["transaction"].as_u64() {
                    let start = v["start_s"].as_f64().unwrap_or(f64::NAN);
                    arrived.entry(tid as u16).or_insert(start);
                }
            }
            "/controller/ev1/readings" => {
                let v = msg.value()?;
                let words = ["V2", "I", "V1", "RPM_M", "RPM_L", "LDR"]
                    .iter()
                    .map(|w| v["meb"][w].as_u64().unwrap_or(u64::MAX) as u16)
                    .collect();
                readings.insert(msg.log_time_ns / 1_000_000, words);
            }
            "/realtime/lateness" => {
                woke_for = msg.value()?["total"]["ticks"].as_u64().unwrap_or(0);
            }
            _ => {}
        }
        Ok(())
    })
    .expect("the recording reads");
    let last_ms = *readings.keys().last().expect("readings");
    assert!(
        woke_for * 4 < last_ms,
        "the engine woke {woke_for} times in {last_ms} ms: it did not batch ({said})"
    );
    let mut changing = 0;
    for (tid, words) in &read {
        let at = arrived[tid];
        let tick = (at * 1000.0).floor() as u64;
        let near: Vec<_> = (tick.saturating_sub(1)..=tick)
            .filter_map(|ms| Some((ms, readings.get(&ms)?)))
            .collect();
        assert!(
            near.iter().any(|(_, r)| *r == words),
            "request {tid} came at {at:.4} s and read {words:?}; the ticks around it: {near:?}"
        );
        // The words of a few ticks before differ: a stale reply would show.
        if readings
            .get(&tick.saturating_sub(5))
            .is_some_and(|r| r != words)
        {
            changing += 1;
        }
    }
    assert!(
        changing >= read.len() / 2,
        "only {changing} of {} replies read words that changed within 5 ms",
        read.len()
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// RPM_M and RPM_L once the wheel turns at VEL `vel`: as soon as they agree
/// within 5 %, or 3 s after the hall rpm passed 800 (15 s at most).
fn spin_and_read_speeds(server: &Server, vel: u16) -> (u16, u16) {
    let mut m = connect(&server.tcp(0));
    let ack = meb(&mut m, &meb_frame(1, MebCmd::SD, 0, 1, &[SD0_RUN]));
    assert_eq!(ack.cmd, MebCmd::SD, "{ack:?}");
    let ack = meb(&mut m, &meb_frame(1, MebCmd::SA, 0, 1, &[vel]));
    assert_eq!(ack.cmd, MebCmd::SA, "{ack:?}");
    let mut deadline = Instant::now() + Duration::from_secs(15);
    let mut fast = false;
    loop {
        let ea = read_ea(&mut m);
        let (hall, light) = (ea[3], ea[4]);
        if hall > 800 && !fast {
            fast = true;
            deadline = deadline.min(Instant::now() + Duration::from_secs(3));
        }
        let close = hall > 800 && light.abs_diff(hall) < hall / 20;
        if close || Instant::now() > deadline {
            return (hall, light);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn adaptive_light_lets_rpm_l_follow_the_wheel_and_says_its_limit() {
    // The adaptive detector is the default, as in the default scenario.
    let server = Server::start(&["--meb", "tcp://127.0.0.1:0", "--quiet", "--no-record"]);
    assert!(
        server.printed(
            "ev1 light detector: adaptive (swing ≥ 0.244 V); it sees the flag up to 1793 rpm"
        ),
        "{}",
        server.output()
    );
    let (hall, light) = spin_and_read_speeds(&server, 1100);
    assert!(hall > 800, "the wheel turns: RPM_M {hall}");
    assert!(
        light.abs_diff(hall) < hall / 20,
        "RPM_L {light} follows RPM_M {hall}"
    );
    server.terminate();

    // On the fixed threshold the controller says so, and its light sensor
    // loses the flag at that speed.
    let server = Server::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--no-record",
        "--light-detector",
        "fixed",
    ]);
    assert!(
        server.printed(
            "ev1 light detector: fixed 2.36 V; it sees the flag up to 260 rpm (--light-detector adaptive"
        ),
        "{}",
        server.output()
    );
    let (hall, light) = spin_and_read_speeds(&server, 1100);
    assert!(hall > 800, "the wheel turns: RPM_M {hall}");
    assert!(light < hall / 2, "RPM_L {light} cannot follow RPM_M {hall}");
    server.terminate();
}

/// The server stopped (SIGSTOP) for 300 ms every 2 s while the wheel turns
/// and a client polls: each stall slips the session's clock and every tick
/// still runs, so the light sensor sees the flag at every turn and RPM_L
/// keeps following the wheel. In the recording, every light reading once
/// the wheel is up to speed is within 10 % of the hall reading beside it
/// (the ticks a stall skipped once read as drops from 1200 to 300-600 rpm).
#[test]
fn under_stalls_rpm_l_keeps_following_the_wheel() {
    let dir = scratch("light-stall");
    let recording = dir.join("light.mcap");
    let server = Server::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--out",
        recording.to_str().unwrap(),
    ]);
    let (hall, light) = spin_and_read_speeds(&server, 1100);
    assert!(
        hall > 800 && light.abs_diff(hall) < hall / 20,
        "RPM_L {light} follows RPM_M {hall} before any stall"
    );
    let pid = server.proc.child.id().to_string();
    let mut m = connect(&server.tcp(0));
    let mut stalls = 0;
    for _ in 0..3 {
        let until = Instant::now() + Duration::from_secs(2);
        while Instant::now() < until {
            read_ea(&mut m);
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = Command::new("kill").args(["-STOP", &pid]).status();
        std::thread::sleep(Duration::from_millis(300));
        let _ = Command::new("kill").args(["-CONT", &pid]).status();
        stalls += 1;
    }
    read_ea(&mut m);
    let said = server.terminate();
    let mut readings = Vec::new();
    let mut slips = 0;
    twin_recording::Recording::scan(&recording, |msg| {
        if msg.topic == "/controller/ev1/readings" {
            let v = msg.value()?;
            let (hall, light) = (v["hall_rpm"].as_f64(), v["light_rpm"].as_f64());
            if let (Some(hall), Some(light)) = (hall, light) {
                readings.push((msg.time_s(), hall, light));
            }
        } else if msg.topic == "/realtime/lateness" {
            slips = msg.value()?["total"]["slips"].as_u64().unwrap_or(0);
        }
        Ok(())
    })
    .expect("the recording reads");
    // Up to speed: from half a second after the hall reading first came
    // within 3 % of where it ends.
    let end = readings.last().expect("readings").1;
    let reached = readings
        .iter()
        .find(|&&(_, h, _)| (h - end).abs() < end * 0.03)
        .expect("the wheel reaches its speed")
        .0;
    let settled = readings
        .iter()
        .position(|&(t, _, _)| t >= reached + 0.5)
        .expect("readings after it");
    let after = &readings[settled..];
    assert!(after.len() > 300, "{} readings", after.len());
    for &(t, hall, light) in after {
        assert!(
            (light - hall).abs() < hall / 10.0,
            "at {t:.3} s RPM_L read {light} while RPM_M read {hall}: {said}"
        );
    }
    assert!(slips >= stalls, "{slips} slips for {stalls} stalls: {said}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn console_commands_force_inputs_and_switch_faults() {
    let (server, mut console) = Server::with_console(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--no-record",
        "--status-every",
        "0.1",
    ]);
    let mut m = connect(&server.tcp(0));
    let mut t = connect(&server.tcp(1));
    let mut say = |line: &str, echo: &str| {
        writeln!(console, "{line}").unwrap();
        assert!(server.printed(echo), "`{line}`: {}", server.output());
    };

    // A forced V1 is what the controller measures at its next loop tick.
    let sensing = plant::PlantParams::preset("vemodule").unwrap().sensing;
    let forced = sensing.counts(30.5 / sensing.battery_divider);
    say("force v1 30.5", "forced v1 = 30.5");
    // The status line names what is forced in the console's words.
    assert!(
        server.printed("ev1 forced v1 30.50 V;"),
        "{}",
        server.output()
    );
    std::thread::sleep(Duration::from_millis(20));
    assert_eq!(read_ea(&mut m)[2], forced);
    assert_eq!(input_registers(&mut t, 1)[2], forced);
    say("release v1", "released v1");
    std::thread::sleep(Duration::from_millis(20));
    assert!(read_ea(&mut m)[2].abs_diff(forced) > 100, "measured again");

    // An exception on one link only.
    say(
        "fault exception 2 modbus-tcp",
        "fault exception 02 (Modbus ILLEGAL DATA ADDRESS, MEB ER 02 illegal address) on modbus-tcp",
    );
    assert!(
        server.printed(
            "; fault exception 02 (Modbus ILLEGAL DATA ADDRESS, MEB ER 02 illegal address)"
        ),
        "the status line names the exception: {}",
        server.output()
    );
    let r = modbus_tcp(
        &mut t,
        2,
        1,
        &Request::ReadInputRegisters {
            address: 0,
            quantity: 1,
        },
    );
    assert_eq!(
        r.expect_err("exception").exception,
        Exception::IllegalDataAddress
    );
    assert_eq!(read_ea(&mut m).len(), 6, "MEB unaffected");

    // A bad check: the reply is whole but its FCS is off by one.
    say("fault bad-check meb", "fault bad-check on meb");
    let reply = meb_raw(&mut m, &meb_frame(1, MebCmd::EA, 0, 6, &[]));
    assert!(
        MebRepr::parse(&reply).is_err(),
        "{}",
        String::from_utf8_lossy(&reply)
    );

    // A delay.
    say("fault delay 200", "fault delay 200 ms on every link");
    let sent = Instant::now();
    assert!(MebRepr::parse(&meb_raw(&mut m, &meb_frame(1, MebCmd::EA, 0, 6, &[]))).is_ok());
    assert!(
        sent.elapsed() >= Duration::from_millis(200),
        "{:?}",
        sent.elapsed()
    );

    // No reply at all, then everything normal again.
    say("fault no-reply", "fault no-reply on every link");
    m.set_read_timeout(Some(Duration::from_millis(300)))
        .unwrap();
    m.write_all(&meb_frame(1, MebCmd::EA, 0, 6, &[])).unwrap();
    let mut buf = [0u8; 64];
    assert!(m.read(&mut buf).is_err(), "no reply");
    say("fault off", "fault off");
    m.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    assert_eq!(read_ea(&mut m).len(), 6);
    assert!(input_registers(&mut t, 3).len() == 10);
    say("frobnicate", "error: unrecognized subcommand 'frobnicate'");
    // What `help` and `help fault` print is what the book shows.
    for (asked, block) in console_help_in_the_book() {
        let before = server.output().len();
        // Waits for its last line, so the whole text is there.
        say(asked, block.trim_end().lines().last().unwrap_or_default());
        let said = server.output();
        assert!(
            said[before..].contains(block.trim_end()),
            "docs/lab-session.md shows for `{asked}`:\n{block}\nthe console said:\n{}",
            &said[before..]
        );
    }
    let out = server.output();
    for rust in [
        "Forces",
        "Some(",
        "Exception(",
        "BadCheck",
        "NoReply",
        "Delay(",
    ] {
        assert!(!out.contains(rust), "`{rust}` printed: {out}");
    }
}

/// The console's help as docs/lab-session.md shows it: each `text` block
/// that follows a line `> help…` (the command typed), with that command.
fn console_help_in_the_book() -> Vec<(&'static str, String)> {
    let page = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/lab-session.md"),
    )
    .unwrap();
    let shown: Vec<(&'static str, String)> = ["help", "help fault"]
        .into_iter()
        .filter_map(|asked| {
            let typed = format!("```text\n> {asked}\n");
            let start = page.find(&typed)? + typed.len();
            let block = &page[start..start + page[start..].find("```")?];
            Some((asked, block.to_string()))
        })
        .collect();
    assert_eq!(
        shown.len(),
        2,
        "docs/lab-session.md shows `help` and `help fault`"
    );
    shown
}

#[test]
fn garbage_half_frames_and_disconnects_leave_other_clients_served() {
    let server = Server::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--partial-timeout",
        "0.5",
        "--quiet",
        "--no-record",
    ]);
    let mut good = connect(&server.tcp(0));
    let mut good_modbus = connect(&server.tcp(1));
    let errs_before = meb(&mut good, &meb_frame(1, MebCmd::FA, 0, 2, &[]))
        .data
        .as_slice()[1];

    // Garbage and a frame with a bad FCS on one connection: ignored, counted.
    let mut bad = connect(&server.tcp(0));
    bad.write_all(b"\x00\xffnoise@01EA0006FF*\n@@@\n").unwrap();
    let mut bad_modbus = connect(&server.tcp(1));
    bad_modbus
        .write_all(&[0xde, 0xad, 0xbe, 0xef, 0, 0, 0, 0])
        .unwrap();
    // A half frame, then an abrupt close mid-frame.
    let mut half = connect(&server.tcp(0));
    half.write_all(b"@01EA00").unwrap();
    drop(half);
    let half_modbus = connect(&server.tcp(1));
    (&half_modbus).write_all(&[0, 1, 0, 0, 0, 6, 1]).unwrap();
    drop(half_modbus);

    for round in 0..5 {
        assert_eq!(read_ea(&mut good).len(), 6);
        assert_eq!(input_registers(&mut good_modbus, round).len(), 10);
    }
    // A good request after the garbage on the same connection is answered.
    assert_eq!(read_ea(&mut bad).len(), 6);
    let errs = meb(&mut good, &meb_frame(1, MebCmd::FA, 0, 2, &[]))
        .data
        .as_slice()[1];
    assert!(
        errs >= errs_before + 2,
        "ERRS counted the bad frames: {errs_before} -> {errs}"
    );

    // A connection holding a partial frame past the timeout is closed ...
    let mut stuck = connect(&server.tcp(0));
    stuck.write_all(b"@01EA").unwrap();
    let mut buf = [0u8; 16];
    let started = Instant::now();
    let n = stuck.read(&mut buf).unwrap_or(0);
    assert_eq!(n, 0, "closed, not answered");
    assert!(started.elapsed() >= Duration::from_millis(400));
    // ... and a quiet one stays open and is served.
    std::thread::sleep(Duration::from_millis(700));
    assert_eq!(read_ea(&mut good).len(), 6);
    assert!(server.printed("partial frame"), "{}", server.output());
}

#[test]
fn extra_clients_are_refused_and_read_only_refuses_writes() {
    let server = Server::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--max-clients",
        "1",
        "--read-only",
        "--quiet",
        "--no-record",
    ]);
    let mut first = connect(&server.tcp(0));
    assert_eq!(read_ea(&mut first).len(), 6);
    let mut second = connect(&server.tcp(0));
    let _ = second.write_all(&meb_frame(1, MebCmd::EA, 0, 6, &[]));
    let mut buf = [0u8; 64];
    assert_eq!(
        second.read(&mut buf).unwrap_or(0),
        0,
        "the second client is refused"
    );
    assert_eq!(read_ea(&mut first).len(), 6, "the first is still served");
    assert!(
        server.printed("refused, 1 client(s) already connected"),
        "{}",
        server.output()
    );

    let refused = meb(&mut first, &meb_frame(1, MebCmd::SA, 0, 1, &[2048]));
    assert_eq!(refused.cmd, MebCmd::ER);
    assert_eq!(refused.error_code(), Some(MebErrorCode::IllegalCommand));
    let mut t = connect(&server.tcp(1));
    let r = modbus_tcp(
        &mut t,
        1,
        1,
        &Request::WriteSingleRegister {
            address: 0,
            value: 2048,
        },
    );
    let e = r.expect_err("an exception");
    assert_eq!(e.exception, Exception::IllegalFunction);
    assert_eq!(input_registers(&mut t, 2).len(), 10, "reads still work");
}

#[test]
fn a_client_over_the_rate_limit_is_closed() {
    let server = Server::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--rate-limit",
        "2000",
        "--quiet",
        "--no-record",
    ]);
    let mut good = connect(&server.tcp(0));
    let mut flood = connect(&server.tcp(0));
    let request = meb_frame(1, MebCmd::EA, 0, 6, &[]);
    let burst: Vec<u8> = request
        .iter()
        .copied()
        .cycle()
        .take(request.len() * 400)
        .collect();
    let _ = flood.write_all(&burst);
    flood
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut sink = Vec::new();
    let _ = flood.read_to_end(&mut sink);
    assert!(
        sink.len() < burst.len() * 3,
        "served only until the limit: {} bytes back",
        sink.len()
    );
    assert_eq!(read_ea(&mut good).len(), 6, "others are served");
    assert!(server.printed("rate limit"), "{}", server.output());
}

/// A pseudo-terminal pair: the twin opens the slave side by path, the test
/// speaks on the master side.
fn pty() -> (serialport::TTYPort, serialport::TTYPort, String) {
    use serialport::SerialPort;
    let (mut master, slave) = serialport::TTYPort::pair().expect("a pty pair");
    master.set_timeout(Duration::from_secs(3)).unwrap();
    let name = slave.name().expect("slave path");
    (master, slave, name)
}

/// Reads exactly `n` bytes from the pty's master side.
fn read_n(port: &mut serialport::TTYPort, n: usize) -> Vec<u8> {
    let mut out = vec![0u8; n];
    port.read_exact(&mut out).expect("a reply on the pty");
    out
}

#[test]
fn modbus_rtu_and_meb_on_ptys_answer_after_the_turnaround() {
    let (mut rtu, _rtu_slave, rtu_path) = pty();
    let (mut meb_port, _meb_slave, meb_path) = pty();
    let server = Server::start(&[
        "--modbus-rtu",
        &rtu_path,
        "--meb",
        &format!("{meb_path}?turnaround_ms=5"),
        "--quiet",
        "--no-record",
    ]);
    let listed = |p: &str| server.links.iter().find(|l| l.0 == p).cloned();
    assert_eq!(
        listed("modbus-rtu"),
        Some(("modbus-rtu".into(), rtu_path.clone(), "01".into()))
    );
    assert_eq!(listed("meb").map(|l| l.1), Some(meb_path.clone()));

    let mut frame = [0u8; 300];
    let request = Request::ReadInputRegisters {
        address: 0,
        quantity: 10,
    };
    let n = modbus::rtu::RtuRepr {
        unit: 1,
        pdu: &request,
    }
    .emit(&mut frame)
    .unwrap();
    rtu.write_all(&frame[..n]).unwrap();
    // unit, function, byte count, 20 data bytes, CRC
    let reply = read_n(&mut rtu, 25);
    let parsed = modbus::rtu::RtuFrame::new_checked(&reply).expect("CRC checks");
    assert_eq!(parsed.unit(), 1);
    match parsed.response() {
        Ok(Ok(Response::ReadInputRegisters(r))) => assert!(r.as_slice()[2] > 3000),
        other => panic!("{other:?}"),
    }
    // Another unit's request gets silence; the next one for us is served.
    let n = modbus::rtu::RtuRepr {
        unit: 7,
        pdu: &request,
    }
    .emit(&mut frame)
    .unwrap();
    rtu.write_all(&frame[..n]).unwrap();
    std::thread::sleep(Duration::from_millis(50));
    let n = modbus::rtu::RtuRepr {
        unit: 1,
        pdu: &request,
    }
    .emit(&mut frame)
    .unwrap();
    rtu.write_all(&frame[..n]).unwrap();
    assert!(modbus::rtu::RtuFrame::new_checked(&read_n(&mut rtu, 25)).is_ok());

    let request = meb_frame(1, MebCmd::EA, 0, 6, &[]);
    let sent = Instant::now();
    meb_port.write_all(&request).unwrap();
    let mut reply = Vec::new();
    let mut byte = [0u8; 1];
    while reply.last() != Some(&b'\n') {
        meb_port.read_exact(&mut byte).expect("an MEB reply");
        reply.push(byte[0]);
    }
    let waited = sent.elapsed();
    assert!(MebRepr::parse(&reply).is_ok(), "{reply:?}");
    assert!(
        waited >= Duration::from_millis(5),
        "turnaround held: {waited:?}"
    );
}

#[test]
fn paced_replies_take_their_wire_time_at_the_links_baud() {
    let (mut port, _slave, path) = pty();
    let link = format!("{path}?baud=9600&pace=1&turnaround_ms=0");
    let _server = Server::start(&["--meb", &link, "--quiet", "--no-record"]);
    let mut reply = Vec::new();
    let mut byte = [0u8; 1];
    let sent = Instant::now();
    port.write_all(&meb_frame(1, MebCmd::EA, 0, 6, &[]))
        .unwrap();
    while reply.last() != Some(&b'\n') {
        port.read_exact(&mut byte).expect("an MEB reply");
        reply.push(byte[0]);
    }
    let waited = sent.elapsed();
    // 37 bytes of 10 bits at 9600 baud: 38.5 ms on the wire.
    assert_eq!(reply.len(), 37);
    let wire = Duration::from_secs_f64(37.0 * 10.0 / 9600.0);
    assert!(waited >= wire, "paced: {waited:?} < {wire:?}");
    assert!(waited < wire * 4, "but not much later: {waited:?}");
}

#[test]
fn the_controller_network_network_answers_both_ids_on_one_pty() {
    use protocols::modbus8::{CrcOrder, Modbus8Repr};
    let (mut port, _slave, path) = pty();
    let server = Server::start(&["--modbus8", &path, "--quiet", "--no-record"]);
    assert_eq!(server.links[0].0, "modbus8");
    assert_eq!(server.links[0].2, "01,02");
    for (id, addr) in [(1u8, 0x0001u16), (2, 0x0006)] {
        let request = Modbus8Repr {
            id,
            function: 3,
            addr,
            value: 1,
        }
        .to_bytes(CrcOrder::HighFirst);
        port.write_all(&request).unwrap();
        let reply = read_n(&mut port, 8);
        let frame = Modbus8Repr::parse(&reply, CrcOrder::HighFirst).expect("CRC checks");
        assert_eq!((frame.id, frame.addr), (id, addr), "{reply:02x?}");
    }
}

#[test]
fn an_io_map_file_moves_the_meb_signals() {
    let map = scratch("map.toml");
    std::fs::write(
        &map,
        "# V1 first, as on our bench\n[EA]\nV1 = 0\nV2 = 1\nRPM_M = 2\n",
    )
    .unwrap();
    let server = Server::start(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--map",
        map.to_str().unwrap(),
        "--quiet",
        "--no-record",
        "--status-every",
        "0.1",
    ]);
    let mut m = connect(&server.tcp(0));
    let mut t = connect(&server.tcp(1));
    let r = meb(&mut m, &meb_frame(1, MebCmd::EA, 0, 3, &[]));
    let ir = input_registers(&mut t, 1);
    assert!(
        r.data.as_slice()[0].abs_diff(ir[2]) <= 2,
        "EA 0 is V1: {r:?} vs {ir:?}"
    );
    assert!(r.data.as_slice()[1].abs_diff(ir[0]) <= 2, "EA 1 is V2");
    let past = meb(&mut m, &meb_frame(1, MebCmd::EA, 0, 4, &[]));
    assert_eq!(past.cmd, MebCmd::ER, "EA holds three words now");

    std::fs::write(&map, "[EA]\nV1 = 0\nV1x = 1\n").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args([
            "serve",
            "--meb",
            "tcp://127.0.0.1:0",
            "--no-record",
            "--map",
        ])
        .arg(&map)
        .output()
        .expect("twin runs");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("map.toml:3:") && err.contains("unknown signal"),
        "{err}"
    );
}

#[test]
fn a_missing_serial_port_is_a_clear_error() {
    let o = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["serve", "--meb", "/tmp/no-such-tty-for-twin", "--no-record"])
        .stdin(Stdio::null())
        .output()
        .expect("twin runs");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("does not exist"), "{err}");
    assert!(err.contains("pseudo-terminal"), "{err}");
    let o = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["serve", "--modbus", "/tmp/ttyV1", "--no-record"])
        .output()
        .expect("twin runs");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("Modbus TCP needs tcp://"), "{err}");
}

/// An interactive shell on a pseudo-terminal of its own (`script`), so
/// that `&` and `fg` are the shell's job control, as at a lab PC.
struct Shell {
    child: std::process::Child,
    stdin: std::process::ChildStdin,
}

impl Shell {
    fn start() -> Shell {
        let mut child = Command::new("script")
            .args(["-qfec", "bash --norc --noprofile -i", "/dev/null"])
            .env("TERM", "dumb")
            .env("PS1", "$ ")
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("script (util-linux) runs an interactive bash");
        let stdin = child.stdin.take().expect("stdin");
        Shell { child, stdin }
    }

    fn type_line(&mut self, line: &str) {
        writeln!(self.stdin, "{line}").expect("the shell reads its terminal");
        self.stdin.flush().expect("flush");
    }
}

impl Drop for Shell {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Waits up to 30 s for `file` to contain `needle`, then returns it whole.
fn file_shows(file: &std::path::Path, needle: &str, what: &str) -> String {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let text = std::fs::read_to_string(file).unwrap_or_default();
        if text.contains(needle) {
            return text;
        }
        assert!(
            Instant::now() < deadline,
            "{what}: no `{needle}` in {text:?}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn started_with_an_ampersand_it_serves_and_fg_gives_it_the_console() {
    let _cores = support::RealTime::share_the_cores();
    let out = scratch("background.out");
    let _ = std::fs::remove_file(&out);
    let mut shell = Shell::start();
    shell.type_line(&format!(
        "'{}' serve --meb tcp://127.0.0.1:0 --quiet --no-record --status-every 0 --duration 60 > '{}' 2>&1 &",
        env!("CARGO_BIN_EXE_twin"),
        out.display()
    ));
    // Before, the console's first read of the terminal stopped the whole
    // process (SIGTTIN) and the master below got nothing but timeouts.
    let started = file_shows(&out, "ready", "twin serve started with &");
    assert!(
        started.contains("in the background: `fg` for its commands"),
        "{started}"
    );
    let addr = started
        .lines()
        .find_map(|l| l.trim().strip_prefix("meb tcp://"))
        .and_then(|l| l.split_whitespace().next())
        .unwrap_or_else(|| panic!("no meb link in {started:?}"))
        .to_string();
    let slave = format!("tcp://{addr}");
    let supervised = support::twin(&[
        "supervise",
        "--meb",
        &slave,
        "--no-server",
        "--duration",
        "1.5",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let printed = support::text(&supervised);
    assert!(supervised.status.success(), "{printed}");
    let slave_line = printed
        .lines()
        .find(|l| l.trim_start().starts_with("slave 01:"))
        .unwrap_or_else(|| panic!("no slave line in {printed}"));
    // A stopped server answers nothing: every poll times out. (A busy
    // machine may cost a timeout or two; that is not what is checked.)
    let count = |what: &str| -> u64 {
        slave_line
            .split([';', ','])
            .find_map(|part| part.trim().strip_suffix(what)?.trim().parse().ok())
            .unwrap_or_else(|| panic!("no `{what}` in {slave_line}"))
    };
    assert!(
        count(" replies") > count(" timeouts"),
        "the server started with & did not serve: {slave_line}"
    );
    // Brought to the foreground, it reads the terminal: commands work.
    shell.type_line("fg");
    std::thread::sleep(Duration::from_millis(300));
    shell.type_line("status");
    file_shows(&out, "ev1: wheel", "the `status` typed after fg");
    shell.type_line("stop");
    let ended = file_shows(
        &out,
        "twin serve: stopped (console)",
        "the `stop` typed after fg",
    );
    assert!(ended.contains("stopping"), "{ended}");
    shell.type_line("exit");
}

/// What a run prints after `light detector: ` (to the end of the line).
fn light_detector_of(printed: &str) -> String {
    printed
        .lines()
        .find_map(|l| l.split_once("light detector: ").map(|(_, d)| d.to_string()))
        .unwrap_or_else(|| panic!("no light detector named in {printed}"))
}

#[test]
fn serve_starts_on_the_light_detector_of_the_default_scenario() {
    let dir = support::folder("serve", "light-default");
    let run = support::twin(&[
        "run",
        "--duration",
        "0.2",
        "--out",
        dir.join("run.mcap").to_str().expect("a UTF-8 path"),
    ]);
    let virtual_clock = support::text(&run);
    assert!(run.status.success(), "{virtual_clock}");
    let _cores = support::RealTime::share_the_cores();
    let serve = support::twin(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--duration",
        "0.3",
        "--quiet",
        "--status-every",
        "0",
        "--no-record",
    ]);
    let real_time = support::text(&serve);
    assert!(serve.status.success(), "{real_time}");
    // Before, `twin serve` started on the fixed threshold: RPM_L 0 at
    // 2500 rpm where `twin run` read the wheel.
    assert_eq!(
        light_detector_of(&real_time),
        light_detector_of(&virtual_clock),
        "twin serve and twin run start the EV controller on different light detectors"
    );
}
