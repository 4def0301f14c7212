//! The real `twin` binary as the CLI tests start it: run to its end
//! ([`twin`]), or a subcommand that prints its links and then `ready`, its
//! stdout collected in the background, stopped by SIGTERM, by its own
//! `--duration`, or killed when the test drops it ([`Proc`]); and the scratch
//! folders the tests write in; and the machine's cores, shared between the
//! tests of this binary ([`RealTime`], [`cores_to_myself`]).

use std::cell::RefCell;
use std::io::{BufRead, BufReader, Read};
use std::marker::PhantomData;
use std::path::PathBuf;
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Arc, Mutex, PoisonError, RwLock, RwLockReadGuard, RwLockWriteGuard};
use std::time::{Duration, Instant};

/// The two cores, as the tests of this one binary share them. The trycmd
/// runs (the book's pages, the command cases) start dozens of processes on
/// every core at once, and a few tests time a live server to the
/// millisecond: those take the cores to themselves ([`cores_to_myself`]).
/// Any other test with a live server shares them with the other such tests
/// (as it did when each file was a binary of its own), never with those.
static CORES: RwLock<()> = RwLock::new(());

/// What this thread holds of [`CORES`].
enum Hold {
    Nothing,
    Shared {
        _guard: RwLockReadGuard<'static, ()>,
    },
    Whole {
        _guard: RwLockWriteGuard<'static, ()>,
    },
}

thread_local! {
    /// This thread's hold on [`CORES`] and how many [`RealTime`]s count on
    /// it: a test that starts two servers takes its share once (a second
    /// read of a lock that a writer waits for would wait for ever), and a
    /// test that has the cores to itself takes no share at all.
    static HELD: RefCell<(usize, Hold)> = const { RefCell::new((0, Hold::Nothing)) };
}

/// Held by every live server a test starts ([`Proc`], `peers::Serve`). Not
/// `Send`: it is given back on the thread that took it.
#[derive(Debug)]
pub struct RealTime(PhantomData<*const ()>);

impl RealTime {
    pub fn share_the_cores() -> RealTime {
        HELD.with_borrow_mut(|(n, hold)| {
            if matches!(hold, Hold::Nothing) {
                *hold = Hold::Shared {
                    _guard: CORES.read().unwrap_or_else(PoisonError::into_inner),
                };
            }
            *n += 1;
        });
        RealTime(PhantomData)
    }
}

impl Drop for RealTime {
    fn drop(&mut self) {
        HELD.with_borrow_mut(|(n, hold)| {
            *n -= 1;
            if *n == 0 && matches!(hold, Hold::Shared { .. }) {
                *hold = Hold::Nothing;
            }
        });
    }
}

/// The cores to this test alone, until it drops this: it waits for the
/// live servers of other tests to end, and none starts meanwhile. Taken
/// first thing in the test, before any server of its own.
#[derive(Debug)]
pub struct CoresToMyself(PhantomData<*const ()>);

pub fn cores_to_myself() -> CoresToMyself {
    HELD.with_borrow_mut(|(n, hold)| {
        assert!(
            *n == 0 && matches!(hold, Hold::Nothing),
            "take the cores before starting a server"
        );
        *hold = Hold::Whole {
            _guard: CORES.write().unwrap_or_else(PoisonError::into_inner),
        };
    });
    CoresToMyself(PhantomData)
}

impl Drop for CoresToMyself {
    fn drop(&mut self) {
        HELD.with_borrow_mut(|(_, hold)| *hold = Hold::Nothing);
    }
}

/// A running `twin` subcommand.
pub struct Proc {
    pub child: Child,
    lines: Arc<Mutex<Vec<String>>>,
    what: String,
    _real_time: RealTime,
}

impl Proc {
    /// Starts `twin ARGS` with stdin closed and waits for its `ready` line.
    pub fn start(args: &[&str]) -> Proc {
        Self::spawn(args, Stdio::null())
    }

    /// Starts `twin ARGS` with `stdin` and waits for its `ready` line (30 s
    /// at most: then the test fails with what the program printed).
    pub fn spawn(args: &[&str], stdin: Stdio) -> Proc {
        let real_time = RealTime::share_the_cores();
        let mut child = Command::new(env!("CARGO_BIN_EXE_twin"))
            .args(args)
            .stdin(stdin)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("twin starts");
        let stdout = child.stdout.take().expect("stdout");
        let lines = Arc::new(Mutex::new(Vec::new()));
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let collected = lines.clone();
        std::thread::spawn(move || {
            let mut ready = Some(ready_tx);
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                collected.lock().unwrap().push(line.clone());
                if line == "ready"
                    && let Some(tx) = ready.take()
                {
                    let _ = tx.send(());
                }
            }
        });
        let what = format!("twin {}", args.join(" "));
        if ready_rx.recv_timeout(Duration::from_secs(30)).is_err() {
            let _ = child.kill();
            let mut err = String::new();
            if let Some(mut e) = child.stderr.take() {
                let _ = e.read_to_string(&mut err);
            }
            panic!(
                "no `ready` from {what}: stdout {:?}, stderr {err}",
                lines.lock().unwrap()
            );
        }
        Proc {
            child,
            lines,
            what,
            _real_time: real_time,
        }
    }

    /// Everything printed so far.
    pub fn output(&self) -> String {
        self.lines.lock().unwrap().join("\n")
    }

    /// The link lines printed before `ready` (two spaces, the protocol, the
    /// address, the rest), split into their fields.
    pub fn links(&self) -> Vec<Vec<String>> {
        self.lines
            .lock()
            .unwrap()
            .iter()
            .take_while(|l| *l != "ready")
            .filter_map(|l| l.strip_prefix("  "))
            .map(|l| l.split_whitespace().map(str::to_string).collect())
            .collect()
    }

    /// The HOST:PORT of the first link line `  PROTOCOL tcp://HOST:PORT …`.
    pub fn tcp_of(&self, protocol: &str) -> String {
        let links = self.links();
        let link = links
            .iter()
            .find(|f| f.first().is_some_and(|p| p == protocol))
            .unwrap_or_else(|| panic!("no {protocol} link printed by {}: {links:?}", self.what));
        host_port(&link[1]).to_string()
    }

    /// Whether stdout shows `needle` within a few seconds (the printing
    /// thread runs behind the sockets).
    pub fn printed(&self, needle: &str) -> bool {
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if self.output().contains(needle) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        false
    }

    /// SIGTERM, a clean exit within 20 s, and everything it printed.
    pub fn terminate(mut self) -> String {
        let pid = self.child.id().to_string();
        assert!(
            Command::new("kill")
                .args(["-TERM", &pid])
                .status()
                .expect("kill runs")
                .success()
        );
        self.exit_within(Duration::from_secs(20), "on SIGTERM");
        // Let the reader thread take the last lines.
        std::thread::sleep(Duration::from_millis(100));
        self.output()
    }

    /// Waits for the process to end by itself (its `--duration`).
    pub fn wait(mut self) {
        self.exit_within(Duration::from_secs(30), "by itself");
    }

    fn exit_within(&mut self, limit: Duration, how: &str) {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(status) = self.child.try_wait().expect("wait") {
                assert!(
                    status.success(),
                    "{} exited {status}: {}",
                    self.what,
                    self.output()
                );
                return;
            }
            assert!(
                Instant::now() < deadline,
                "{} did not stop {how}: {}",
                self.what,
                self.output()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The `HOST:PORT` of a link the twin printed as `tcp://HOST:PORT`.
pub fn host_port(link: &str) -> &str {
    link.strip_prefix("tcp://")
        .unwrap_or_else(|| panic!("`{link}` is not a TCP link"))
}

/// `twin ARGS`, run to its end with its output collected.
pub fn twin(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(args)
        .output()
        .expect("twin runs")
}

/// What a finished `twin` printed, stdout then stderr.
pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// The file `name` in this test binary's scratch folder for `area`,
/// `$TMPDIR/twin-AREA-PID`. The first call of the process removes the
/// scratch folders that earlier runs left, of every area (their process
/// gone), so runs do not pile up.
pub fn scratch(area: &str, name: &str) -> PathBuf {
    static SWEPT: std::sync::Once = std::sync::Once::new();
    let tmp = std::env::temp_dir();
    SWEPT.call_once(|| {
        let Ok(entries) = std::fs::read_dir(&tmp) else {
            return;
        };
        for e in entries.flatten() {
            let file_name = e.file_name();
            let Some(pid) = file_name
                .to_str()
                .and_then(|n| n.strip_prefix("twin-"))
                .and_then(|rest| rest.rsplit_once('-'))
                .and_then(|(_, pid)| pid.parse::<u32>().ok())
            else {
                continue;
            };
            if pid != std::process::id() && !std::path::Path::new(&format!("/proc/{pid}")).exists()
            {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    });
    let dir = tmp.join(format!("twin-{area}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("scratch folder");
    dir.join(name)
}

/// A fresh, empty folder `name` in the scratch folder for `area`.
pub fn folder(area: &str, name: &str) -> PathBuf {
    let dir = scratch(area, name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch folder");
    dir
}

/// One request to a panel at `host` (HOST:PORT), with its token as a
/// bearer when given and `body` as JSON when not empty: the status and the
/// body, a refusal's too.
pub fn http(
    host: impl std::fmt::Display,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: &str,
) -> (u16, String) {
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(30)))
        .build()
        .into();
    let mut request = ureq::http::Request::builder()
        .method(method)
        .uri(format!("http://{host}{path}"));
    if let Some(token) = token {
        request = request.header("Authorization", format!("Bearer {token}"));
    }
    let answer = if body.is_empty() {
        agent.run(request.body(()).unwrap())
    } else {
        let request = request.header("Content-Type", "application/json");
        agent.run(request.body(body).unwrap())
    };
    let answer = answer.unwrap_or_else(|e| panic!("{method} http://{host}{path}: {e}"));
    let status = answer.status().as_u16();
    (
        status,
        answer.into_body().read_to_string().unwrap_or_default(),
    )
}
