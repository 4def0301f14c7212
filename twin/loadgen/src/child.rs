//! A server under test as a child process: started, read until it says
//! `ready`, stopped with SIGTERM. Every server (the twin, the echo, the
//! tokio-modbus reference) announces its links the same way:
//! `  <protocol> <address> [...]` lines, then `ready`.

use anyhow::{Context, Result, bail};
use protocols::link::LinkSpec;
use rustix::process::{Pid, Signal, kill_process};
use std::io::{BufRead, BufReader, Read};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

#[derive(Debug)]
pub struct Server {
    pub name: String,
    child: Child,
    /// (protocol, address) of each link it printed.
    pub links: Vec<(String, String)>,
    /// The fourth word of each link line, if any (a class's module name).
    pub link_names: Vec<String>,
    /// Its standard output, line by line, after `ready`.
    lines: mpsc::Receiver<String>,
}

impl Server {
    /// The CPU time the server's process has used so far (user and
    /// system, all threads), from `/proc`; `None` where that cannot be read.
    pub fn cpu_time(&self) -> Option<Duration> {
        let stat = std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).ok()?;
        // Fields after the command name (which may hold spaces) in parentheses:
        // state is field 3, utime and stime fields 14 and 15.
        let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
        let ticks = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
        let per_second = rustix::param::clock_ticks_per_second().max(1);
        Some(Duration::from_secs_f64(ticks as f64 / per_second as f64))
    }

    pub fn start(name: &str, mut cmd: Command, timeout: Duration) -> Result<Self> {
        cmd.stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut child = cmd
            .spawn()
            .with_context(|| format!("starting {name}: {cmd:?}"))?;
        let stdout = child.stdout.take().expect("piped");
        let mut stderr = child.stderr.take().expect("piped");
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    // Keep draining so the child never blocks on a full pipe.
                    continue;
                }
            }
        });
        let (etx, erx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut text = String::new();
            let _ = stderr.read_to_string(&mut text);
            let _ = etx.send(text);
        });
        let deadline = Instant::now() + timeout;
        let mut links = Vec::new();
        let mut link_names = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(line) if line == "ready" => break,
                Ok(line) => {
                    if let Some(rest) = line.strip_prefix("  ") {
                        let mut words = rest.split_whitespace();
                        if let (Some(p), Some(a)) = (words.next(), words.next()) {
                            links.push((p.to_string(), a.to_string()));
                            link_names.push(words.nth(1).unwrap_or_default().to_string());
                        }
                    }
                }
                Err(_) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    let err = erx.recv_timeout(Duration::from_secs(1)).unwrap_or_default();
                    bail!("{name} did not print `ready` within {timeout:?}: {err}");
                }
            }
        }
        Ok(Self {
            name: name.to_string(),
            child,
            links,
            link_names,
            lines: rx,
        })
    }

    /// Address of the first link of `protocol`.
    pub fn link(&self, protocol: &str) -> Result<&str> {
        self.links
            .iter()
            .find(|(p, _)| p == protocol)
            .map(|(_, a)| a.as_str())
            .with_context(|| format!("{} printed no {protocol} link: {:?}", self.name, self.links))
    }

    /// Resident memory of the server's process, KiB, from `/proc`.
    pub fn rss_kib(&self) -> Option<u64> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).ok()?;
        let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
        line.split_whitespace().nth(1)?.parse().ok()
    }

    /// SIGTERM, then SIGKILL if it does not stop within two seconds; the
    /// lines it printed after `ready`.
    pub fn stop(self) -> Vec<String> {
        self.stop_within(Duration::from_secs(2))
    }

    /// SIGTERM, then SIGKILL if it does not stop within `limit`; the lines
    /// it printed after `ready`.
    pub fn stop_within(mut self, limit: Duration) -> Vec<String> {
        let _ = kill_process(Pid::from_child(&self.child), Signal::TERM);
        let deadline = Instant::now() + limit;
        let mut stopped = false;
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                stopped = true;
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        if !stopped {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
        // The reader thread ends with the pipe; what it had is all there is.
        let mut lines = Vec::new();
        while let Ok(line) = self.lines.recv_timeout(Duration::from_millis(500)) {
            lines.push(line);
        }
        lines
    }
}

/// `tcp://127.0.0.1:40123` → `127.0.0.1:40123`, read as the twin reads
/// its links.
pub fn tcp_addr(link: &str) -> Result<SocketAddr> {
    Ok(LinkSpec::parse_tcp_peer(
        link,
        "a server's address takes no options",
    )?)
}
