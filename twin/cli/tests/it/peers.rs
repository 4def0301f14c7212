//! What the real-peer tests share: `twin serve` as a child process (started,
//! read until `ready`, stopped with SIGTERM), crossed pseudo-terminal pairs
//! from socat, peers run with a time limit. Every wait is bounded, so a broken
//! server fails a test instead of hanging CI.

use crate::support::RealTime;
use rustix::process::{Pid, Signal, kill_process};
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub const START_TIMEOUT: Duration = Duration::from_secs(30);

/// One link `twin serve` printed: protocol, address and slave id.
#[derive(Debug, Clone)]
pub struct Link {
    pub protocol: String,
    pub address: String,
    pub id: String,
}

/// A running `twin serve`.
#[derive(Debug)]
pub struct Serve {
    child: Child,
    pub links: Vec<Link>,
    stderr: Arc<Mutex<String>>,
    /// Every line printed after `ready` (the monitor, status lines).
    stdout: Arc<Mutex<String>>,
    _real_time: RealTime,
}

impl Serve {
    pub fn start(args: &[&str]) -> Serve {
        let real_time = RealTime::share_the_cores();
        // Never the default serve.mcap in the working directory.
        let record: &[&str] = if args.contains(&"--out") {
            &[]
        } else {
            &["--no-record"]
        };
        let mut child = Command::new(env!("CARGO_BIN_EXE_twin"))
            .arg("serve")
            .args(args)
            .args(record)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("twin serve starts");
        let stdout = child.stdout.take().unwrap();
        let stderr = gather(child.stderr.take().unwrap());
        let (tx, rx) = mpsc::channel();
        let after_ready = Arc::new(Mutex::new(String::new()));
        let kept = after_ready.clone();
        std::thread::spawn(move || {
            let mut ready = false;
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if ready {
                    let mut kept = kept.lock().unwrap();
                    kept.push_str(&line);
                    kept.push('\n');
                } else {
                    ready = line == "ready";
                    let _ = tx.send(line);
                }
            }
        });
        let deadline = Instant::now() + START_TIMEOUT;
        let mut links = Vec::new();
        let mut seen = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(line) if line == "ready" => break,
                Ok(line) => {
                    if let Some(rest) = line.strip_prefix("  ") {
                        let w: Vec<&str> = rest.split_whitespace().collect();
                        if w.len() >= 2 {
                            links.push(Link {
                                protocol: w[0].to_string(),
                                address: w[1].to_string(),
                                id: w.get(2).unwrap_or(&"").to_string(),
                            });
                        }
                    }
                    seen.push(line);
                }
                Err(_) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    std::thread::sleep(Duration::from_millis(100));
                    panic!(
                        "twin serve {args:?} did not print `ready` within {START_TIMEOUT:?}\nstdout: {seen:#?}\nstderr: {}",
                        stderr.lock().unwrap()
                    );
                }
            }
        }
        Serve {
            child,
            links,
            stderr,
            stdout: after_ready,
            _real_time: real_time,
        }
    }

    /// `host:port` of the first TCP link of `protocol`.
    pub fn tcp(&self, protocol: &str) -> String {
        crate::support::host_port(&self.link(protocol).address).to_string()
    }

    pub fn port(&self, protocol: &str) -> u16 {
        let addr = self.tcp(protocol);
        addr.rsplit(':').next().unwrap().parse().expect("a port")
    }

    pub fn link(&self, protocol: &str) -> &Link {
        self.links
            .iter()
            .find(|l| l.protocol == protocol)
            .unwrap_or_else(|| panic!("twin serve printed no {protocol} link: {:?}", self.links))
    }

    /// Still running (it must survive whatever a test threw at it).
    pub fn assert_running(&mut self) {
        if let Some(status) = self.child.try_wait().expect("try_wait") {
            panic!(
                "twin serve exited ({status}); stderr:\n{}",
                self.stderr.lock().unwrap()
            );
        }
    }

    /// The server's process id (to stop and continue it).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// What it printed after `ready` so far.
    pub fn stdout(&self) -> String {
        self.stdout.lock().unwrap().clone()
    }

    /// SIGTERM, and waits (up to a minute) for the server to have finished
    /// its recording and exited; its lines then come with [`Serve::expect_line`].
    pub fn terminate(&mut self) {
        let _ = kill_process(Pid::from_child(&self.child), Signal::TERM);
        let stopped = wait_for(Duration::from_secs(60), Duration::from_millis(20), || {
            self.child.try_wait().ok().flatten()
        });
        assert!(
            stopped.is_some(),
            "twin serve did not stop within 60 s of SIGTERM"
        );
    }

    /// Waits up to `timeout` for a line printed after `ready` that contains
    /// `text`; the line. Fails, showing what was printed, if none comes.
    pub fn expect_line(&self, text: &str, timeout: Duration) -> String {
        wait_for(timeout, Duration::from_millis(20), || {
            self.stdout()
                .lines()
                .find(|l| l.contains(text))
                .map(str::to_string)
        })
        .unwrap_or_else(|| {
            panic!(
                "no line with `{text}` within {timeout:?}; printed:\n{}",
                self.stdout()
            )
        })
    }
}

impl Drop for Serve {
    fn drop(&mut self) {
        let _ = kill_process(Pid::from_child(&self.child), Signal::TERM);
        // On SIGTERM the server finishes its recording, draining what the
        // sink thread still holds: after a flood of frames, in a
        // debug build on a loaded machine, that has taken more than 5 s. A
        // kill before then leaves a cut file, which the tests would misread
        // as a recording the server broke.
        let started = Instant::now();
        while started.elapsed() < Duration::from_secs(60) {
            if let Ok(Some(_)) = self.child.try_wait() {
                if started.elapsed() > Duration::from_secs(5) {
                    eprintln!("twin serve took {:?} to stop on SIGTERM", started.elapsed());
                }
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        eprintln!("twin serve did not stop within 60 s of SIGTERM: killed");
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A fresh directory for one test's files.
pub fn scratch(test: &str) -> PathBuf {
    crate::support::folder("peers", test)
}

/// A crossed pseudo-terminal pair from socat: bytes written to `a` are read
/// from `b` and the other way round. Both ends are raw, no echo.
#[derive(Debug)]
pub struct PtyPair {
    child: Child,
    pub a: PathBuf,
    pub b: PathBuf,
}

impl PtyPair {
    pub fn new(dir: &Path) -> PtyPair {
        let a = dir.join("ttyA");
        let b = dir.join("ttyB");
        let child = Command::new("socat")
            .arg(format!("pty,raw,echo=0,link={}", a.display()))
            .arg(format!("pty,raw,echo=0,link={}", b.display()))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("socat runs (apt-get install socat)");
        let deadline = Instant::now() + Duration::from_secs(10);
        while !(a.exists() && b.exists()) {
            assert!(Instant::now() < deadline, "socat made no pty pair in 10 s");
            std::thread::sleep(Duration::from_millis(10));
        }
        PtyPair { child, a, b }
    }
}

impl Drop for PtyPair {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A pseudo-terminal whose master end the test holds, with no relay process
/// between: the server opens `path` (the slave), the test reads and writes
/// `master`. Dropping it closes the master: the server's port vanishes.
#[derive(Debug)]
pub struct DirectPty {
    pub master: std::fs::File,
    pub path: PathBuf,
}

impl DirectPty {
    pub fn new() -> DirectPty {
        use rustix::pty::{OpenptFlags, grantpt, openpt, ptsname, unlockpt};
        use rustix::termios::{OptionalActions, tcgetattr, tcsetattr};
        let master = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY).expect("posix_openpt");
        grantpt(&master).expect("grantpt");
        unlockpt(&master).expect("unlockpt");
        let name = ptsname(&master, Vec::new()).expect("ptsname");
        let path = PathBuf::from(name.to_string_lossy().into_owned());
        let mut t = tcgetattr(&master).expect("tcgetattr");
        t.make_raw();
        tcsetattr(&master, OptionalActions::Now, &t).expect("tcsetattr");
        DirectPty {
            master: std::fs::File::from(master),
            path,
        }
    }
}

/// Runs `cmd` to completion, killing it (and failing) after `timeout`.
pub fn run_timeout(cmd: &mut Command, timeout: Duration) -> Output {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{cmd:?} starts: {e}"));
    let deadline = Instant::now() + timeout;
    loop {
        if child.try_wait().expect("try_wait").is_some() {
            return child.wait_with_output().expect("output");
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let out = child.wait_with_output().expect("output");
            panic!(
                "{cmd:?} still running after {timeout:?}\nstdout: {}\nstderr: {}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Python peer scripts live beside this file.
pub fn script(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/peers")
        .join(name)
}

/// Polls `f` every `period` until it returns `Some`, for at most `timeout`.
pub fn wait_for<T>(
    timeout: Duration,
    period: Duration,
    mut f: impl FnMut() -> Option<T>,
) -> Option<T> {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(v) = f() {
            return Some(v);
        }
        if Instant::now() > deadline {
            return None;
        }
        std::thread::sleep(period);
    }
}

/// Waits up to `wait` for `link` to have bytes to read.
pub fn readable(link: &std::fs::File, wait: Duration) -> bool {
    use rustix::event::{PollFd, PollFlags, Timespec, poll};
    let t = Timespec {
        tv_sec: wait.as_secs() as i64,
        tv_nsec: i64::from(wait.subsec_nanos()),
    };
    let mut fds = [PollFd::new(link, PollFlags::IN)];
    poll(&mut fds, Some(&t)).unwrap() > 0
}

/// Everything `pipe` (a child's standard error) says, gathered on a thread
/// of its own so that the child never blocks on a full pipe.
pub fn gather(mut pipe: impl Read + Send + 'static) -> Arc<Mutex<String>> {
    let said = Arc::new(Mutex::new(String::new()));
    let sink = said.clone();
    std::thread::spawn(move || {
        let mut buf = [0u8; 4096];
        while let Ok(n) = pipe.read(&mut buf) {
            if n == 0 {
                break;
            }
            sink.lock()
                .unwrap()
                .push_str(&String::from_utf8_lossy(&buf[..n]));
        }
    });
    said
}
