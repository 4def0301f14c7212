//! `twin vsp`, `twin supervise` and `twin client` as a user runs them: the real
//! binary on real pseudo-terminals and TCP sockets. Servers bind port 0 and
//! the test reads the port they print.

use protocols::meb::{MebDecoder, MebRepr};
use protocols::time::SimTime;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::support;
use support::Proc;

/// The first `tcp://` address `proc` printed before `ready`, as HOST:PORT
/// (for `twin supervise`, its server's, not the bus's `master` line).
pub(crate) fn server_tcp(proc: &Proc) -> String {
    let link = proc
        .links()
        .into_iter()
        .find(|f| f.iter().any(|w| w.starts_with("tcp://")) && !f.iter().any(|w| w == "master"))
        .unwrap_or_else(|| panic!("no tcp link printed: {}", proc.output()));
    let field = link.iter().find(|w| w.starts_with("tcp://")).unwrap();
    support::host_port(field).to_string()
}

/// Paths for a vsp pair unique to this test run.
pub(crate) fn pair_paths(name: &str) -> (PathBuf, PathBuf) {
    let base = std::env::temp_dir().join(format!("twin-{}-{name}", std::process::id()));
    (base.with_extension("V0"), base.with_extension("V1"))
}

pub(crate) fn s(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Waits until the supervisor at `url` has polled its slave once.
fn wait_polled(url: &str) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while !client(&[url, "read", "EA", "0", "1"]).status.success() {
        assert!(Instant::now() < deadline, "the supervisor never polled");
        std::thread::sleep(Duration::from_millis(50));
    }
}

pub(crate) fn client(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twin"))
        .arg("client")
        .args(args)
        .stdin(Stdio::null())
        .output()
        .expect("twin client runs")
}

/// A raw MEB connection: frames written as the spec spells them.
pub(crate) struct Raw {
    stream: TcpStream,
    decoder: MebDecoder,
}

impl Raw {
    pub(crate) fn connect(addr: &str) -> Raw {
        let stream = TcpStream::connect(addr).expect("connects");
        stream
            .set_read_timeout(Some(Duration::from_secs(3)))
            .unwrap();
        Raw {
            stream,
            decoder: MebDecoder::new(),
        }
    }

    pub(crate) fn send(&mut self, bytes: &[u8]) {
        self.stream.write_all(bytes).expect("write");
    }

    /// The next `n` frames, as text.
    pub(crate) fn frames(&mut self, n: usize) -> Vec<String> {
        let mut out = Vec::new();
        let mut buf = [0u8; 512];
        while out.len() < n {
            let got = self.stream.read(&mut buf).expect("a reply in time");
            assert!(got > 0, "the server closed the connection");
            let mut rest = &buf[..got];
            while !rest.is_empty() {
                let (used, event) = self.decoder.push(SimTime::ZERO, rest);
                if let Some(Ok(frame)) = event {
                    out.push(String::from_utf8_lossy(frame.as_bytes()).into_owned());
                }
                rest = &rest[used..];
            }
        }
        out
    }
}

/// `@…FCS*\n`, the XOR computed here again.
pub(crate) fn frame(body: &str) -> Vec<u8> {
    let fcs = body.bytes().fold(0u8, |acc, b| acc ^ b);
    format!("{body}{fcs:02X}*\n").into_bytes()
}

pub(crate) fn reply_words(reply: &str) -> Vec<u16> {
    MebRepr::parse(reply.as_bytes())
        .expect("a well-formed reply")
        .data
        .as_slice()
        .to_vec()
}

/// Reads RPM_M through the supervisor until it stays within 3 % of `target`
/// for five readings in a row (a second); returns the readings.
fn wait_for_speed(raw: &mut Raw, target: f64, within: Duration) -> Vec<u16> {
    let deadline = Instant::now() + within;
    let mut seen = Vec::new();
    let mut settled = 0;
    while Instant::now() < deadline {
        raw.send(&frame("@01EA0301"));
        let rpm = reply_words(&raw.frames(1)[0])[0];
        seen.push(rpm);
        if (f64::from(rpm) - target).abs() <= 0.03 * target {
            settled += 1;
            if settled == 5 {
                return seen;
            }
        } else {
            settled = 0;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    panic!("the wheel did not settle at {target} rpm: readings {seen:?}");
}

#[test]
fn vsp_carries_bytes_both_ways_and_survives_either_end_reopening() {
    let (a, b) = pair_paths("reopen");
    let vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let out = vsp.output();
    assert!(
        out.contains(&format!("  {} -> /dev/pts/", a.display())),
        "{out}"
    );
    let open = |p: &Path| {
        std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(p)
            .unwrap()
    };
    let read_exact = |f: &mut std::fs::File, n: usize| {
        let mut got = vec![0u8; n];
        f.read_exact(&mut got).unwrap();
        got
    };
    let (mut fa, mut fb) = (open(&a), open(&b));
    fa.write_all(b"@01EA000346*\n").unwrap();
    assert_eq!(read_exact(&mut fb, 13), b"@01EA000346*\n");
    // Raw mode: binary bytes, CR and LF cross unchanged, nothing echoes back.
    fb.write_all(&[0x00, 0x0D, 0x0A, 0xFF, 0x03]).unwrap();
    assert_eq!(read_exact(&mut fa, 5), [0x00, 0x0D, 0x0A, 0xFF, 0x03]);
    // The Controller_network master opens and closes the port for every transaction.
    for round in 0..5u8 {
        drop(fa);
        fa = open(&a);
        fa.write_all(&[round; 8]).unwrap();
        assert_eq!(read_exact(&mut fb, 8), [round; 8]);
        fb.write_all(&[round ^ 0xFF; 8]).unwrap();
        assert_eq!(read_exact(&mut fa, 8), [round ^ 0xFF; 8]);
    }
    drop(fb);
    let mut fb = open(&b);
    fa.write_all(b"after").unwrap();
    assert_eq!(read_exact(&mut fb, 5), b"after");
    drop((fa, fb));
    let out = vsp.terminate();
    assert!(!a.exists() && !b.exists(), "the links were left behind");
    assert!(
        out.contains(&format!("{} -> {}: 58 bytes", a.display(), b.display())),
        "{out}"
    );
    assert!(
        out.contains(&format!("{} -> {}: 45 bytes", b.display(), a.display())),
        "{out}"
    );
}

#[test]
fn vsp_refuses_to_replace_a_file_that_is_not_a_link() {
    let (a, b) = pair_paths("refuse");
    std::fs::write(&a, b"precious").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["vsp", s(&a), s(&b)])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("exists and is not a symlink"), "{err}");
    assert_eq!(std::fs::read(&a).unwrap(), b"precious");
    std::fs::remove_file(&a).unwrap();
}

#[test]
fn vsp_replaces_a_link_a_killed_run_left_and_says_so() {
    let (a, b) = pair_paths("stale");
    let _ = std::fs::remove_file(&a);
    std::os::unix::fs::symlink("/dev/pts/9999", &a).unwrap();
    let vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    assert!(
        vsp.output()
            .contains(&format!("{} -> /dev/pts/", a.display()))
            && vsp.output().contains(
                "(replaced the link to /dev/pts/9999 that was there, left by an earlier run)"
            ),
        "{}",
        vsp.output()
    );
    assert_ne!(std::fs::read_link(&a).unwrap(), Path::new("/dev/pts/9999"));
}

#[test]
fn supervise_closes_the_speed_loop_against_serve_over_a_vsp_pair() {
    let (a, b) = pair_paths("loop");
    let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let _serve = Proc::start(&[
        "serve",
        "--meb",
        s(&b),
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let out = std::env::temp_dir().join(format!("twin-{}-supervise.mcap", std::process::id()));
    let supervise = Proc::start(&[
        "supervise",
        "--meb",
        s(&a),
        "--listen",
        "tcp://127.0.0.1:0",
        "--set-point",
        "1500",
        "--quiet",
        "--status-every",
        "0",
        "--out",
        s(&out),
    ]);
    let printed = supervise.output();
    assert!(
        printed.contains(&format!("  meb {} master 01", a.display())),
        "{printed}"
    );
    let addr = server_tcp(&supervise);
    let mut raw = Raw::connect(&addr);
    wait_for_speed(&mut raw, 1500.0, Duration::from_secs(20));

    // A new set point through the image (VA 10), read back in FA 10.
    let url = format!("tcp://{addr}");
    let set = client(&[&url, "write", "VA", "10", "2500"]);
    assert!(
        set.status.success(),
        "{}",
        String::from_utf8_lossy(&set.stderr)
    );
    let mirror = client(&[&url, "read", "FA", "10", "1"]);
    assert!(String::from_utf8_lossy(&mirror.stdout).contains("FA 10 =  2500"));
    wait_for_speed(&mut raw, 2500.0, Duration::from_secs(20));

    // A write the slave refuses comes back as its ER, and the client fails.
    let refused = client(&[&url, "write", "SA", "0", "5000"]);
    assert_eq!(refused.status.code(), Some(1));
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("ER 03"), "{err}");
    // A forwarded write the slave takes: the brake (BRK = 0) stops the wheel.
    let brake = client(&[&url, "write", "SD", "0", "0x000C"]);
    assert!(
        brake.status.success(),
        "{}",
        String::from_utf8_lossy(&brake.stderr)
    );
    wait_for_speed_below(&mut raw, 100, Duration::from_secs(20));

    let printed = supervise.terminate();
    assert!(printed.contains("recording: "), "{printed}");
    let topics = topic_counts(&out);
    assert!(
        topics.get("/master/supervisor/loop").copied().unwrap_or(0) > 100,
        "{topics:?}"
    );
    assert!(
        topics.get("/link/bus/frames").copied().unwrap_or(0) > 100,
        "{topics:?}"
    );
    assert!(
        topics.get("/link/tcp/frames").copied().unwrap_or(0) > 10,
        "{topics:?}"
    );
    let _ = std::fs::remove_file(&out);
}

/// `twin supervise` stopped (SIGSTOP) for 300 ms every 1.5 s while it polls
/// `twin serve` over a vsp pair every 2 ms with a 30 ms reply timeout. The
/// slave answers in a few ms, its reply waiting in the pty while the
/// supervisor stands still; the supervisor must take each stall as the slip
/// its clock counts, not as time its request waited. Read from its
/// recording: no request is retried sooner than its timeout, none (but a
/// rare one on a starved machine, fewer than the stalls) waits longer than
/// its timeout and the 5 ms the supervisor catches up (a slave slow on a
/// busy machine only makes the timeout fire on time), and the
/// slips are there. Before, the engine caught up 50 ms of each stall in a
/// burst, so the request in flight at a stall was retried or answered 50 ms
/// or more after it was sent; and a request decided on a time read across
/// a stall, before the clock slipped for it, lay ahead of every time after
/// the slip, so the next ones queued behind it and timed out (the timeout
/// ran from the decision) before their first copy was written, which then
/// went out 0 ms before its retry. A request's time is now when its bytes
/// were written to the pty, and its timeout runs from then.
#[test]
fn a_stopped_supervisor_slips_its_clock_and_waits_its_whole_timeout() {
    const TIMEOUT_S: f64 = 0.030;
    // The timeout, the catch-up, and room for the engine's own pass.
    const LONGEST_S: f64 = TIMEOUT_S + 0.010;
    // Other tests' servers would make the slave itself late.
    let _cores = support::cores_to_myself();
    let (a, b) = pair_paths("stall");
    let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let _serve = Proc::start(&[
        "serve",
        "--meb",
        s(&b),
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let out = std::env::temp_dir().join(format!("twin-{}-stall.mcap", std::process::id()));
    let supervise = Proc::start(&[
        "supervise",
        "--meb",
        s(&a),
        "--no-server",
        "--set-point",
        "1000",
        "--poll-ms",
        "2",
        "--timeout-ms",
        "30",
        "--quiet",
        "--status-every",
        "0",
        "--out",
        s(&out),
    ]);
    let pid = supervise.child.id().to_string();
    let mut stalls = 0;
    for _ in 0..5 {
        std::thread::sleep(Duration::from_millis(1200));
        let stop = Command::new("kill").args(["-STOP", &pid]).status();
        std::thread::sleep(Duration::from_millis(300));
        let cont = Command::new("kill").args(["-CONT", &pid]).status();
        assert!(stop.is_ok_and(|s| s.success()) && cont.is_ok_and(|s| s.success()));
        stalls += 1;
    }
    std::thread::sleep(Duration::from_millis(500));
    let printed = supervise.terminate();
    println!("{printed}");

    // The bus's frames in order (start, who, text), the supervisor's
    // timeouts and retries, the slips.
    let (mut frames, mut timeouts, mut slips) = (Vec::new(), Vec::new(), (0, 0.0));
    twin_recording::Recording::scan(&out, |m| {
        if m.topic == "/link/bus/frames" {
            let v = m.value()?;
            frames.push((
                v["start_s"].as_f64().unwrap_or(m.time_s()),
                v["from"].as_str().unwrap_or("").to_string(),
                v["text"].as_str().unwrap_or("").trim().to_string(),
            ));
        } else if m.topic == "/events" {
            let v = m.value()?;
            if v["kind"] == "timeout" || v["kind"] == "retry" {
                timeouts.push(format!("{:.4} s {}", m.time_s(), v["detail"]));
            }
        } else if m.topic == "/realtime/lateness" {
            let v = m.value()?;
            slips = (
                v["total"]["slips"].as_u64().unwrap_or(0),
                v["total"]["slipped_ms"].as_f64().unwrap_or(0.0),
            );
        }
        Ok(())
    })
    .expect("the recording reads");
    let _ = std::fs::remove_file(&out);

    assert!(frames.len() > 1000, "{} frames", frames.len());
    let mut late = Vec::new();
    for pair in frames.windows(2) {
        let [(t0, from0, text0), (t1, from1, text1)] = pair else {
            continue;
        };
        if from0 != "twin" {
            continue;
        }
        let waited = t1 - t0;
        if from1 != "twin" && waited > LONGEST_S {
            late.push((
                *t0,
                format!("{text0} at {t0:.4} s answered {:.1} ms later", waited * 1e3),
            ));
        }
        // The same request again with no reply between: a retry, which
        // waits the whole timeout on the session's clock.
        if from1 == "twin" && text1 == text0 {
            assert!(
                waited >= TIMEOUT_S,
                "{text0} at {t0:.4} s retried {:.1} ms later",
                waited * 1e3
            );
            if waited > LONGEST_S {
                late.push((
                    *t0,
                    format!("{text0} at {t0:.4} s retried {:.1} ms later", waited * 1e3),
                ));
            }
        }
    }
    // What a stall did wrong came once per stall (the request in flight at
    // it waited the stall out). A busy machine can also hold the port's
    // thread or the slave off the CPU for tens of milliseconds now and then
    // (seen during a parallel build), which is the machine, not the stall:
    // fewer late waits than stalls pass.
    assert!(
        (late.len() as u64) < stalls,
        "{stalls} stalls, {} waits too long: {late:?}, {} timeouts: {timeouts:?}",
        late.len(),
        timeouts.len()
    );
    // Each stall slipped the clock by nearly all of its 300 ms.
    assert!(slips.0 >= stalls, "{} slips for {stalls} stalls", slips.0);
    assert!(
        slips.1 >= 250.0 * stalls as f64,
        "{} ms lost in {stalls} stalls",
        slips.1
    );
    assert!(printed.contains("real time lost:"), "{printed}");
}

fn wait_for_speed_below(raw: &mut Raw, rpm: u16, within: Duration) {
    let deadline = Instant::now() + within;
    let mut last = 0;
    while Instant::now() < deadline {
        raw.send(&frame("@01EA0301"));
        last = reply_words(&raw.frames(1)[0])[0];
        if last < rpm {
            return;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    panic!("the braked wheel still turns at {last} rpm");
}

fn topic_counts(path: &Path) -> std::collections::BTreeMap<String, usize> {
    let bytes = std::fs::read(path).expect("the recording exists");
    let mut counts = std::collections::BTreeMap::new();
    for message in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        let message = message.expect("a readable message");
        *counts.entry(message.channel.topic.clone()).or_insert(0) += 1;
    }
    counts
}

/// A supervisor polling `twin serve` over TCP (no pty needed), with options.
fn supervisor_over_tcp(extra: &[&str]) -> (Proc, Proc, String) {
    let serve = Proc::start(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let slave = format!("tcp://{}", server_tcp(&serve));
    let mut args = vec![
        "supervise",
        "--meb",
        &slave,
        "--listen",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ];
    args.extend_from_slice(extra);
    let supervise = Proc::start(&args);
    let addr = server_tcp(&supervise);
    (serve, supervise, addr)
}

#[test]
fn garbage_half_frames_and_abrupt_disconnects_do_not_disturb_another_client() {
    let (_serve, supervise, addr) = supervisor_over_tcp(&["--partial-timeout", "1"]);
    let mut calm = Raw::connect(&addr);
    // Wait for the first poll to be in the image.
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        calm.send(&frame("@01EA0001"));
        if !calm.frames(1)[0].contains("ER") {
            break;
        }
        assert!(Instant::now() < deadline, "the supervisor never polled");
        std::thread::sleep(Duration::from_millis(50));
    }
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let reads = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut answered = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                calm.send(&frame("@01EA0002"));
                let reply = calm.frames(1).remove(0);
                assert!(
                    reply.starts_with("@01EA0002") && reply.len() == 9 + 8 + 4,
                    "{reply}"
                );
                answered += 1;
                std::thread::sleep(Duration::from_millis(10));
            }
            answered
        })
    };
    for round in 0..20 {
        let mut noisy = Raw::connect(&addr);
        let mut bad_fcs = frame("@01EA0001");
        bad_fcs[9] ^= 0x01;
        noisy.send(b"\x00\xff garbage *\n");
        noisy.send(&bad_fcs);
        noisy.send(b"@01EA00@@@\n");
        // A good frame in the middle of it is still answered.
        noisy.send(&frame("@01FD1001"));
        assert_eq!(
            noisy.frames(1),
            [String::from_utf8(frame("@01FD10010001")).unwrap()]
        );
        // Then half a frame, and the connection is dropped mid-frame.
        noisy.send(if round % 2 == 0 {
            b"@01SA0001".as_slice()
        } else {
            b"@0".as_slice()
        });
        drop(noisy);
    }
    // Half a frame held past the partial-frame timeout: that connection is closed.
    let mut stuck = Raw::connect(&addr);
    stuck.send(b"@01EA00");
    let mut buf = [0u8; 16];
    let started = Instant::now();
    let n = stuck.stream.read(&mut buf).expect("closed, not timed out");
    assert_eq!(n, 0, "expected the server to close the connection");
    let held = started.elapsed();
    assert!(
        held >= Duration::from_millis(900) && held < Duration::from_secs(3),
        "{held:?}"
    );
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let answered = reads
        .join()
        .expect("every read of the calm client was answered");
    assert!(answered > 20, "only {answered} reads");
    let printed = supervise.terminate();
    assert!(
        printed.contains("1 closed for a partial frame"),
        "{printed}"
    );
}

#[test]
fn pipelined_requests_come_back_in_order_and_read_only_clients_get_error_01() {
    let (_serve, supervise, addr) = supervisor_over_tcp(&["--read-only", "--set-point", "700"]);
    let mut raw = Raw::connect(&addr);
    let mut burst = frame("@01FA1001");
    burst.extend(frame("@01SA00010800"));
    burst.extend(frame("@01VA10010000"));
    burst.extend(frame("@01FD1001"));
    raw.send(&burst);
    let replies = raw.frames(4);
    let expected: Vec<String> = [
        "@01FA100102BC",
        "@01ER00010001",
        "@01ER10010001",
        "@01FD10010001",
    ]
    .iter()
    .map(|body| String::from_utf8(frame(body)).unwrap())
    .collect();
    assert_eq!(replies, expected);
    let url = format!("tcp://{addr}");
    let denied = client(&[&url, "write", "VA", "10", "100"]);
    assert_eq!(denied.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&denied.stderr).contains("ER 01"));
    supervise.terminate();
}

#[test]
fn client_reports_a_server_that_is_not_there_and_bad_arguments() {
    let missing = client(&["tcp://127.0.0.1:1", "read", "EA", "0", "1"]);
    assert_eq!(missing.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&missing.stderr).contains("cannot connect to tcp://127.0.0.1:1")
    );
    // Addresses are read as every link is, with the links' own words.
    for (url, says) in [
        (
            "tcp:/127.0.0.1:1",
            "misspelt TCP address, not a serial device: write `tcp://127.0.0.1:1`",
        ),
        ("tcp://127.0.0.1:70000", "port `70000` is not 0-65535"),
        ("127.0.0.1", "is not HOST:PORT (no port)"),
        (
            "tcp://127.0.0.1:1?baud=9600",
            "option `baud` is not taken here",
        ),
        ("/dev/ttyUSB0", "`/dev/ttyUSB0` is not tcp://HOST:PORT"),
    ] {
        let o = client(&[url, "read", "EA", "0", "1"]);
        assert_eq!(o.status.code(), Some(1), "{url}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(says), "{url}: {err}");
    }
    let (_serve, _supervise, addr) = supervisor_over_tcp(&[]);
    let url = format!("tcp://{addr}");
    let bad = client(&[&url, "read", "EA", "zz", "1"]);
    assert_eq!(bad.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("address `zz` is not hex"));
    wait_polled(&url);
    let watch = client(&[&url, "watch", "--count", "3", "--every", "0.1"]);
    assert!(
        watch.status.success(),
        "{}",
        String::from_utf8_lossy(&watch.stderr)
    );
    let text = String::from_utf8_lossy(&watch.stdout);
    assert_eq!(
        text.lines().filter(|l| l.contains("RPM_M")).count(),
        3,
        "{text}"
    );
    assert!(
        text.contains("loop closed, set point 0 rpm, kp 0.450, ki 2.500"),
        "{text}"
    );
    // The status words the supervisor reads every 10 cycles: SOC near 90 % (900 counts).
    let flags = client(&[&url, "read", "FA", "0", "2"]);
    assert!(
        flags.status.success(),
        "{}",
        String::from_utf8_lossy(&flags.stderr)
    );
    let text = String::from_utf8_lossy(&flags.stdout);
    let soc: u16 = text
        .lines()
        .next()
        .unwrap()
        .split_whitespace()
        .nth(3)
        .unwrap()
        .parse()
        .unwrap();
    assert!((850..=950).contains(&soc), "{text}");
    assert!(text.contains("SOC") && text.contains("ERRS"), "{text}");

    // The interactive prompt, typed on stdin.
    let mut prompt = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["client", &url])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    prompt
        .stdin
        .take()
        .unwrap()
        .write_all(b"set-point 1234\nloop off\nread VD 10\nwrite EA 0 1\nread FD 10\nvel 5000\nbogus\nhelp\nread EA 0 100\nquit\n")
        .unwrap();
    let out = prompt.wait_with_output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("loop closed, set point 1234 rpm"), "{text}");
    assert!(text.contains("loop open, set point 1234 rpm"), "{text}");
    assert!(
        text.contains("FD 10 =     0  (0x0000)  LOOP_CLOSED"),
        "{text}"
    );
    assert!(
        text.contains("error: slave 01 answered SA 00 = 5000 with ER 03"),
        "{text}"
    );
    assert!(
        text.contains("error: unrecognized subcommand 'bogus'"),
        "{text}"
    );
    // `help` lists the commands; a wrong word is refused with what it takes.
    assert!(
        text.contains("\n  set-point  VA 10: the loop's set point\n"),
        "{text}"
    );
    assert!(
        text.contains("error: invalid value '100' for '[CNT]': count `100` is not 1-99"),
        "{text}"
    );
    // A read of a written block, or the reverse, would be reply-shaped and never
    // answered: refused at once in words, and the session goes on.
    assert!(
        text.contains("error: VD is written, not read: MEB reads only EA, ED, FA and FD"),
        "{text}"
    );
    assert!(
        text.contains("error: EA is read, not written: MEB writes only SA, SD, VA and VD"),
        "{text}"
    );
}

#[test]
fn a_slave_or_a_port_that_vanishes_gets_error_04_and_the_server_keeps_serving() {
    let (a, b) = pair_paths("vanish");
    let vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let serve = Proc::start(&[
        "serve",
        "--meb",
        s(&b),
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let supervise = Proc::start(&[
        "supervise",
        "--meb",
        s(&a),
        "--listen",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
        "--timeout-ms",
        "50",
        "--retries",
        "1",
    ]);
    let url = format!("tcp://{}", server_tcp(&supervise));
    wait_polled(&url);
    let write = || {
        let out = client(&[&url, "write", "SA", "0", "100"]);
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    assert_eq!(write().0, Some(0));
    // The slave goes away: the bus is still there, the write is not answered.
    serve.terminate();
    let (code, err) = write();
    assert_eq!(code, Some(1));
    assert!(err.contains("ER 04"), "{err}");
    // The port goes away too: nothing drives the bus, the write still gets ER 04.
    vsp.terminate();
    std::thread::sleep(Duration::from_millis(300));
    let (code, err) = write();
    assert_eq!(code, Some(1));
    assert!(err.contains("ER 04"), "{err}");
    // Reads are answered from the last poll all along.
    let read = client(&[&url, "read", "EA", "0", "6"]);
    assert!(
        read.status.success(),
        "{}",
        String::from_utf8_lossy(&read.stderr)
    );
    supervise.terminate();
}

#[test]
fn supervise_closes_the_loop_over_modbus_rtu_and_serves_the_same_image() {
    let (a, b) = pair_paths("rtu");
    let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let _serve = Proc::start(&[
        "serve",
        "--modbus-rtu",
        s(&b),
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let supervise = Proc::start(&[
        "supervise",
        "--modbus-rtu",
        s(&a),
        "--listen",
        "tcp://127.0.0.1:0",
        "--set-point",
        "1200",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    assert!(
        supervise
            .output()
            .contains(&format!("  modbus-rtu {} master 01", a.display()))
    );
    let mut raw = Raw::connect(&server_tcp(&supervise));
    wait_for_speed(&mut raw, 1200.0, Duration::from_secs(20));
    // MEB writes have no Modbus form here: ER 01, the loop's variables still work.
    raw.send(&frame("@01SA00010800"));
    raw.send(&frame("@01VA100101F4"));
    raw.send(&frame("@01FA1001"));
    let expected: Vec<String> = ["@01ER00010001", "@01VA1001", "@01FA100101F4"]
        .iter()
        .map(|body| String::from_utf8(frame(body)).unwrap())
        .collect();
    assert_eq!(raw.frames(3), expected);
    wait_for_speed(&mut raw, 500.0, Duration::from_secs(20));
    supervise.terminate();
}

/// The supervisor's server closes a quiet client after --idle-timeout, and
/// at --max-clients a newcomer takes the place of one quiet for
/// --make-room-after, as `twin serve` does.
#[test]
fn quiet_remote_clients_time_out_and_make_room() {
    let (_serve, supervise, addr) = supervisor_over_tcp(&["--idle-timeout", "0.5"]);
    let mut quiet = TcpStream::connect(&addr).unwrap();
    quiet
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut got = Vec::new();
    quiet.read_to_end(&mut got).expect("closed for being idle");
    supervise.terminate();

    let (_serve, supervise, addr) =
        supervisor_over_tcp(&["--max-clients", "1", "--make-room-after", "0.5"]);
    let mut first = Raw::connect(&addr);
    first.send(&frame("@01FA1001"));
    assert_eq!(first.frames(1).len(), 1);
    std::thread::sleep(Duration::from_millis(800));
    let mut second = Raw::connect(&addr);
    second.send(&frame("@01FA1001"));
    assert_eq!(second.frames(1).len(), 1, "the newcomer is served");
    supervise.terminate();
    let bad = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args([
            "supervise",
            "--meb",
            "tcp://127.0.0.1:9",
            "--idle-timeout",
            "-1",
        ])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains("--idle-timeout -1: give seconds above 0"),
        "{}",
        String::from_utf8_lossy(&bad.stderr)
    );
}

#[test]
fn an_id_no_module_answers_gets_a_hint_from_supervise_and_client() {
    // `twin serve` answers id 01 only: id 02 is the slip of a student whose
    // module has another number.
    let serve = Proc::start(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let slave = format!("tcp://{}", server_tcp(&serve));
    let supervised = support::twin(&[
        "supervise",
        "--meb",
        &slave,
        "--id",
        "2",
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
    let hint = format!(
        "no reply from id 2 within 100 ms on {slave}: is a module with id 2 on this link? \
         A slave answers only its own id (`twin serve --id 2`"
    );
    // Said once, at the first timeout, though every poll times out.
    assert_eq!(printed.matches(&hint).count(), 1, "{printed}");
    assert!(!printed.contains(" 0 timeouts"), "{printed}");

    let asked = client(&[
        &slave,
        "--id",
        "2",
        "--timeout-ms",
        "300",
        "read",
        "EA",
        "0",
        "1",
    ]);
    assert_eq!(asked.status.code(), Some(1));
    let said = String::from_utf8_lossy(&asked.stderr);
    assert!(said.contains("no reply from"), "{said}");
    assert!(
        said.contains("is a module with id 2 there? A slave answers only its own id (--id"),
        "{said}"
    );
}

#[test]
fn help_names_the_recording_the_command_writes() {
    for command in ["serve", "supervise"] {
        let help = support::text(&support::twin(&[command, "--help"]));
        let own = format!(" {command}-2026-12-03T07-35-44.mcap");
        assert!(help.contains(&own), "twin {command} --help: {help}");
        let other = if command == "serve" {
            " supervise-2026"
        } else {
            " serve-2026"
        };
        assert!(!help.contains(other), "twin {command} --help: {help}");
    }
}
