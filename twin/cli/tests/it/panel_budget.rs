//! The panel of a real `twin serve --web` inside its own budget, over real
//! sockets: a slow request head is closed at the header timeout (the
//! shipped one, and a shortened one); a body too large for the panel gets
//! 413 at once, and one that stops short 408 at the body timeout; under a
//! low open-file limit a flood of bare connections to the panel leaves the
//! MEB clients served, and the panel serves again once the flood is gone;
//! a kept-alive connection waiting for a next request is closed while an
//! open event stream goes on; and a session raises its soft open-file
//! limit to the hard one.
//!
//! The shortened timeouts come from the `TWIN_PANEL_*_TIMEOUT_MS` knobs; a
//! lowered open-file limit from util-linux's `prlimit`, which sets it and
//! then runs the twin.

use std::io::{BufRead, BufReader, ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::support::RealTime;
use rustix::process::{Resource, Rlimit, getrlimit, setrlimit};

/// `twin serve --meb tcp://127.0.0.1:0 --web 127.0.0.1:0`, read until `ready`.
struct Served {
    child: Child,
    meb: String,
    web: SocketAddr,
    stderr: Arc<Mutex<String>>,
    _real_time: RealTime,
}

impl Served {
    /// With `env` set and, if given, the open-file limit `(soft, hard)`.
    fn start(env: &[(&str, &str)], open_files: Option<(u64, u64)>) -> Served {
        let real_time = RealTime::share_the_cores();
        let twin = env!("CARGO_BIN_EXE_twin");
        let mut command = match open_files {
            Some((soft, hard)) => {
                let mut c = Command::new("prlimit");
                c.arg(format!("--nofile={soft}:{hard}")).arg(twin);
                c
            }
            None => Command::new(twin),
        };
        command
            .args([
                "serve",
                "--meb",
                "tcp://127.0.0.1:0",
                "--web",
                "127.0.0.1:0",
            ])
            .args(["--no-record", "--quiet", "--status-every", "0"])
            .envs(env.iter().copied())
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut child = command.spawn().expect("twin serve starts");
        let stderr = crate::peers::gather(child.stderr.take().unwrap());
        let (tx, rx) = mpsc::channel();
        let stdout = child.stdout.take().unwrap();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let (mut meb, mut web) = (None, None);
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let Ok(line) = rx.recv_timeout(left) else {
                let _ = child.kill();
                panic!(
                    "no `ready` from twin serve --web: stderr {}",
                    stderr.lock().unwrap()
                );
            };
            if line == "ready" {
                break;
            }
            if let Some(url) = line.strip_prefix("panel: http://") {
                web = url.split('/').next().and_then(|a| a.parse().ok());
            }
            if let Some(rest) = line.trim_start().strip_prefix("meb tcp://") {
                meb = rest.split_whitespace().next().map(str::to_string);
            }
        }
        Served {
            child,
            meb: meb.expect("an MEB link printed"),
            web: web.expect("a panel line printed"),
            stderr,
            _real_time: real_time,
        }
    }

    fn stderr(&self) -> String {
        self.stderr.lock().unwrap().clone()
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The status and body of one raw request, and how long it took.
fn request(web: SocketAddr, raw: &str) -> (u16, String, Duration) {
    let started = Instant::now();
    let (status, body) = raw_exchange(web, raw);
    (status, body, started.elapsed())
}

/// One request written byte for byte, as no HTTP client would send it (a
/// body shorter or far longer than its Content-Length), sent whole on a
/// fresh connection (it should ask `Connection: close`): the status and
/// body of the answer; status 0 if none came within 30 s.
fn raw_exchange(addr: SocketAddr, raw: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).expect("the panel answers");
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    s.write_all(raw.as_bytes()).unwrap();
    let mut response = String::new();
    let _ = s.read_to_string(&mut response);
    let status = response
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (status, body)
}

fn get(web: SocketAddr, path: &str) -> (u16, String, Duration) {
    let started = Instant::now();
    let (status, body) = crate::support::http(web, "GET", path, None, "");
    (status, body, started.elapsed())
}

/// Connections that send a request head one byte per `every`; how long
/// each lasted before the panel closed it (`None`: still open at `give_up`).
fn slow_heads(
    web: SocketAddr,
    n: usize,
    every: Duration,
    give_up: Duration,
) -> Vec<Option<Duration>> {
    let head = b"GET /api/info HTTP/1.1\r\nHost: panel\r\nX-Slow: ";
    let started = Instant::now();
    let mut open: Vec<Option<TcpStream>> = (0..n)
        .map(|_| {
            let s = TcpStream::connect(web).expect("the panel answers");
            s.set_nonblocking(true).unwrap();
            Some(s)
        })
        .collect();
    let mut lasted = vec![None; n];
    let mut sent = 0;
    while started.elapsed() < give_up && open.iter().any(Option::is_some) {
        let byte = [head.get(sent).copied().unwrap_or(b'a')];
        sent += 1;
        for (i, slot) in open.iter_mut().enumerate() {
            let Some(s) = slot else { continue };
            let mut scratch = [0u8; 512];
            let closed = match s.read(&mut scratch) {
                Ok(0) => true,
                Ok(_) => false,
                Err(e) => e.kind() != ErrorKind::WouldBlock,
            } || s.write(&byte).is_err();
            if closed {
                lasted[i] = Some(started.elapsed());
                *slot = None;
            }
        }
        std::thread::sleep(every);
    }
    lasted
}

#[test]
fn a_request_head_sent_a_byte_a_second_is_closed_at_the_shipped_header_timeout() {
    let served = Served::start(&[], None);
    let lasted = slow_heads(
        served.web,
        3,
        Duration::from_secs(1),
        Duration::from_secs(25),
    );
    for l in &lasted {
        let l = l.expect("every slow head closed within 25 s");
        // The shipped header timeout is 10 s; the byte a second is how
        // late the closing is seen.
        assert!(
            (Duration::from_secs(9)..Duration::from_secs(13)).contains(&l),
            "closed after {l:?}, not at the 10 s header timeout: {lasted:?}"
        );
    }
    // The panel still serves a well-behaved client.
    assert_eq!(get(served.web, "/api/info").0, 200);
}

#[test]
fn slow_heads_are_closed_at_a_shortened_header_timeout_and_others_are_served_meanwhile() {
    let served = Served::start(&[("TWIN_PANEL_HEADER_TIMEOUT_MS", "1500")], None);
    let web = served.web;
    let meanwhile = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(500));
        get(web, "/api/info")
    });
    let lasted = slow_heads(web, 20, Duration::from_millis(100), Duration::from_secs(10));
    for l in &lasted {
        let l = l.expect("every slow head closed within 10 s");
        assert!(
            (Duration::from_millis(1400)..Duration::from_secs(4)).contains(&l),
            "closed after {l:?}, not at the 1.5 s header timeout: {lasted:?}"
        );
    }
    let (status, body, _) = meanwhile.join().unwrap();
    assert_eq!(status, 200, "{body}");
}

#[test]
fn a_body_too_large_is_refused_at_once_and_one_that_stops_short_at_the_body_timeout() {
    let served = Served::start(&[("TWIN_PANEL_BODY_TIMEOUT_MS", "1500")], None);
    // 10 GB declared, 2 bytes sent: refused before a byte is read.
    let (status, body, took) = request(
        served.web,
        "POST /api/force HTTP/1.1\r\nHost: panel\r\nContent-Type: application/json\r\nContent-Length: 10000000000\r\n\r\n{}",
    );
    assert_eq!(status, 413, "{body}");
    assert!(body.contains("small JSON objects"), "said in words: {body}");
    assert!(
        took < Duration::from_secs(2),
        "answered and closed after {took:?}"
    );
    // 100 bytes declared, 2 sent: the panel waits the body timeout, no more.
    let (status, body, took) = request(
        served.web,
        "POST /api/force HTTP/1.1\r\nHost: panel\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{}",
    );
    assert_eq!(status, 408, "{body}");
    assert!(body.contains("did not arrive"), "said in words: {body}");
    assert!(
        (Duration::from_millis(1400)..Duration::from_secs(5)).contains(&took),
        "answered and closed after {took:?}, not at the 1.5 s body timeout"
    );
    // A command within the limits is still taken (it is judged, not refused
    // for its size).
    let (status, body, _) = request(
        served.web,
        "POST /api/force HTTP/1.1\r\nHost: panel\r\nContent-Type: application/json\r\nContent-Length: 2\r\nConnection: close\r\n\r\n{}",
    );
    assert!(
        status != 413 && status != 408 && status != 0,
        "{status} {body}"
    );
}

#[test]
fn a_kept_alive_connection_is_closed_when_idle_and_an_open_event_stream_is_not() {
    let served = Served::start(
        &[
            ("TWIN_PANEL_HEADER_TIMEOUT_MS", "1000"),
            ("TWIN_PANEL_IDLE_TIMEOUT_MS", "1000"),
        ],
        None,
    );
    let mut stream = TcpStream::connect(served.web).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    stream
        .write_all(b"GET /api/stream HTTP/1.1\r\nHost: panel\r\n\r\n")
        .unwrap();
    let mut kept = TcpStream::connect(served.web).unwrap();
    kept.set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    kept.write_all(b"GET /api/info HTTP/1.1\r\nHost: panel\r\n\r\n")
        .unwrap();
    let started = Instant::now();
    // The answer, then the end of the connection: it waited idle for a next
    // request no longer than the header timeout.
    let mut answer = Vec::new();
    kept.read_to_end(&mut answer)
        .expect("the idle connection is closed, not left open");
    let idle_for = started.elapsed();
    assert!(
        String::from_utf8_lossy(&answer).starts_with("HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&answer)
    );
    assert!(
        (Duration::from_millis(900)..Duration::from_secs(4)).contains(&idle_for),
        "closed {idle_for:?} after its answer, not at the 1 s timeout"
    );
    // The stream, three times both timeouts later, still brings updates.
    let mut seen = Vec::new();
    let mut buf = [0u8; 65536];
    while started.elapsed() < Duration::from_secs(3) {
        let n = stream.read(&mut buf).expect("the stream goes on");
        assert!(n > 0, "the stream was closed after {:?}", started.elapsed());
        seen.extend_from_slice(&buf[..n]);
    }
    seen.clear();
    let late = Instant::now();
    while late.elapsed() < Duration::from_millis(500) {
        let n = stream.read(&mut buf).expect("the stream goes on");
        assert!(n > 0, "the stream was closed after {:?}", started.elapsed());
        seen.extend_from_slice(&buf[..n]);
    }
    let updates = String::from_utf8_lossy(&seen)
        .matches("event: update")
        .count();
    assert!(updates >= 3, "{updates} updates in the last 0.5 s of 3.5 s");
}

/// The twin's own soft limit raised to its hard one, so that the flood
/// below (more connections than the served twin may have) fits here.
fn raise_my_open_files() -> u64 {
    let Rlimit { current, maximum } = getrlimit(Resource::Nofile);
    let _ = setrlimit(
        Resource::Nofile,
        Rlimit {
            current: maximum,
            maximum,
        },
    );
    getrlimit(Resource::Nofile)
        .current
        .or(current)
        .unwrap_or(u64::MAX)
}

fn has_prlimit() -> bool {
    let found = Command::new("prlimit")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !found {
        eprintln!("SKIPPED: prlimit (util-linux) is not installed here");
    }
    found
}

/// An MEB client's request for register 00 of slave 01, and its reply.
fn meb_served(addr: &str) -> Result<String, String> {
    let mut s = TcpStream::connect_timeout(&addr.parse().unwrap(), Duration::from_secs(2))
        .map_err(|e| format!("connect: {e}"))?;
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let body = "@01EA0001";
    let fcs = body.bytes().fold(0u8, |x, b| x ^ b);
    s.write_all(format!("{body}{fcs:02X}*\n").as_bytes())
        .map_err(|e| format!("write: {e}"))?;
    let mut line = String::new();
    BufReader::new(&s)
        .read_line(&mut line)
        .map_err(|e| format!("no reply: {e}"))?;
    if line.starts_with("@01EA00") {
        Ok(line)
    } else {
        Err(format!("not a reply: {line:?}"))
    }
}

#[test]
fn a_flood_of_panel_connections_leaves_the_meb_clients_their_descriptors() {
    if !has_prlimit() {
        return;
    }
    const FDS: u64 = 256;
    const FLOOD: usize = 400;
    assert!(
        raise_my_open_files() > FLOOD as u64 + 64,
        "this test needs {FLOOD} sockets of its own"
    );
    // Long enough that the flood outlasts the checks below.
    let served = Served::start(
        &[("TWIN_PANEL_HEADER_TIMEOUT_MS", "60000")],
        Some((FDS, FDS)),
    );
    // Bare connections: they send nothing and stay open, more of them than
    // the twin may open files.
    let flood: Vec<TcpStream> = (0..FLOOD)
        .filter_map(|_| TcpStream::connect_timeout(&served.web, Duration::from_millis(500)).ok())
        .collect();
    assert!(flood.len() > FDS as usize, "only {} connected", flood.len());
    let served_clients: Vec<Result<String, String>> =
        (0..3).map(|_| meb_served(&served.meb)).collect();
    assert!(
        served_clients.iter().all(Result::is_ok),
        "MEB clients during the flood: {served_clients:?}\nstderr: {}",
        served.stderr()
    );
    // A newcomer to the full panel is told so at once.
    let (status, body, took) = get(served.web, "/api/info");
    assert!(
        status == 503 || status == 0,
        "a full panel refuses: {status} {body}"
    );
    assert!(took < Duration::from_secs(2), "refused after {took:?}");
    drop(flood);
    let again = crate::peers::wait_for(Duration::from_secs(10), Duration::from_millis(100), || {
        (get(served.web, "/api/info").0 == 200).then_some(())
    });
    assert!(
        again.is_some(),
        "the panel serves again once the flood is gone"
    );
    let said = crate::peers::wait_for(Duration::from_secs(15), Duration::from_millis(100), || {
        served.stderr().contains("refused").then_some(())
    });
    assert!(said.is_some(), "refusals said: {}", served.stderr());
    let lines = served
        .stderr()
        .lines()
        .filter(|l| l.contains("refused"))
        .count();
    assert!(
        lines <= 3,
        "refusals counted, not a line each: {}",
        served.stderr()
    );
}

#[test]
fn a_session_raises_its_soft_open_file_limit_to_the_hard_one() {
    if !has_prlimit() {
        return;
    }
    let hard = getrlimit(Resource::Nofile)
        .maximum
        .unwrap_or(4096)
        .min(4096);
    assert!(
        hard > 256,
        "the hard limit here ({hard}) leaves nothing to raise"
    );
    let served = Served::start(&[], Some((256, hard)));
    let limits = std::fs::read_to_string(format!("/proc/{}/limits", served.child.id()))
        .expect("the twin's limits");
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .expect("an open-file line");
    let numbers: Vec<&str> = line.split_whitespace().skip(3).take(2).collect();
    assert_eq!(
        numbers,
        [hard.to_string(), hard.to_string()],
        "soft raised to hard: {line}"
    );
}
