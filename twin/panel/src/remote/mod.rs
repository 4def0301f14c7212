//! The remote client panel (`twin panel tcp://HOST:PORT`), the M3CVME
//! tool's TCP client in a browser: itself an MEB-TCP client of a supervisor
//! (`twin supervise --listen`) or of any MEB slave served over TCP. A thread
//! of its own polls the slave's inputs and status words, writes the outputs
//! the page sets, and hands every frame of its connection to the hub; a
//! connection that drops is said on the page and made again every second.

pub mod layout;
pub mod state;

use serde_json::{Value, json};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::commands::Rejected;
use crate::hub::Hub;
use layout::{Layout, SWITCHES};
use nodes::firmware::MebMap;
use protocols::meb::MebCmd;
use twin_realtime::client::{ClientError, MebClient, Way};
use twin_realtime::sink::LiveFrame;
use twin_sim::error_text::in_full;

pub use state::message_state;

/// What `twin panel` is told.
#[derive(Debug, Clone)]
pub struct RemoteOptions {
    /// `tcp://HOST:PORT` of the slave or supervisor.
    pub url: String,
    /// The slave id addressed.
    pub id: u8,
    pub map: MebMap,
    /// From one poll to the next.
    pub poll: Duration,
    /// Connection and reply timeout.
    pub timeout: Duration,
}

/// Why `twin panel` cannot start.
#[derive(Debug, thiserror::Error)]
pub enum RemoteError {
    /// The first connection failed: the client's own words (the address,
    /// what refused it).
    #[error(transparent)]
    Connect(#[from] ClientError),
    #[error("cannot start the panel's connection thread")]
    Thread(#[source] std::io::Error),
    #[error("the panel's connection thread ended")]
    ThreadEnded,
}

/// The link's name on the page (its frames, its row in the links table).
pub const LINK: &str = "meb";

/// Counters of the panel's own connection.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct Counters {
    pub requests: u64,
    pub replies: u64,
    /// `ER` replies.
    pub refused: u64,
    pub timeouts: u64,
    pub reconnects: u64,
}

/// What the poller knows, copied for each stream message.
#[derive(Debug, Clone, Default)]
pub struct RemoteState {
    pub connected: bool,
    /// Why the connection is down, or the last failed exchange, in words.
    pub error: Option<String>,
    pub ea: Vec<u16>,
    pub ed: Vec<u16>,
    pub fa: Vec<u16>,
    pub status: Option<u16>,
    /// Seconds since the panel started, of the last complete poll.
    pub read_at: Option<f64>,
    /// VEL as last acknowledged.
    pub vel: Option<u16>,
    /// Each SD word holding a switch, as last acknowledged (`None`: not
    /// written by this panel yet; MEB outputs cannot be read back).
    pub sd: Vec<(u8, Option<u16>)>,
    pub counters: Counters,
}

/// Outputs the page asks for: VEL counts and switches (on = the lab's
/// active sense, see [`state::switch_on`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct OutputRequest {
    pub vel: Option<u16>,
    pub switches: Vec<(usize, bool)>,
}

type Answer = tokio::sync::oneshot::Sender<Result<Value, Rejected>>;

/// The panel's handle on its poller.
#[derive(Debug)]
pub struct Remote {
    pub options: RemoteOptions,
    pub layout: Layout,
    started: Instant,
    state: Mutex<RemoteState>,
    commands: Mutex<Sender<(OutputRequest, Answer)>>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Remote {
    /// Connects once (so a wrong address or a slave that is not there is
    /// said at start), then polls on a thread of its own, feeding `hub`.
    pub fn start(options: RemoteOptions, hub: Arc<Hub>) -> Result<Arc<Self>, RemoteError> {
        let layout = Layout::new(&options.map);
        let (tx, rx) = channel();
        let sd = layout.sd_words.iter().map(|&w| (w, None)).collect();
        let remote = Arc::new(Self {
            layout,
            options,
            started: Instant::now(),
            state: Mutex::new(RemoteState {
                sd,
                ..RemoteState::default()
            }),
            commands: Mutex::new(tx),
        });
        let poller = remote.clone();
        let (first_tx, first_rx) = channel();
        // The connection lives on the poller's thread (its monitor is not Send).
        std::thread::Builder::new()
            .name("twin-panel-client".into())
            .spawn(
                move || match MebClient::connect(&poller.options.url, poller.options.timeout) {
                    Ok(first) => {
                        let _ = first_tx.send(Ok(()));
                        poller.run(first, rx, hub);
                    }
                    Err(e) => {
                        let _ = first_tx.send(Err(RemoteError::Connect(e)));
                    }
                },
            )
            .map_err(RemoteError::Thread)?;
        first_rx.recv().map_err(|_| RemoteError::ThreadEnded)??;
        Ok(remote)
    }

    /// Seconds since the panel started.
    pub fn now(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    pub fn state(&self) -> RemoteState {
        lock(&self.state).clone()
    }

    /// Writes `request` on the slave; answers once it acknowledged.
    pub async fn write(&self, request: OutputRequest) -> Result<Value, Rejected> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        if lock(&self.commands).send((request, tx)).is_err() {
            return Err(unavailable("the panel's connection has ended".into()));
        }
        let wait = self.options.timeout * 4 + Duration::from_secs(1);
        match tokio::time::timeout(wait, rx).await {
            Ok(Ok(answer)) => answer,
            _ => Err(unavailable(format!(
                "no answer from {} in time",
                self.options.url
            ))),
        }
    }

    /// The poller: connected, it polls; dropped, it says why and retries.
    fn run(
        self: Arc<Self>,
        first: MebClient,
        commands: Receiver<(OutputRequest, Answer)>,
        hub: Arc<Hub>,
    ) {
        let mut client = Some(first);
        loop {
            let Some(mut c) = client.take() else {
                // Down: refuse writes while waiting a second, then try again.
                let until = Instant::now() + Duration::from_secs(1);
                while let Some(left) = until.checked_duration_since(Instant::now()) {
                    match commands.recv_timeout(left) {
                        Ok((_, answer)) => {
                            let why = lock(&self.state).error.clone().unwrap_or_default();
                            let _ = answer.send(Err(unavailable(format!(
                                "not connected to {}: {why}; retrying every second",
                                self.options.url
                            ))));
                        }
                        Err(RecvTimeoutError::Timeout) => {}
                        Err(RecvTimeoutError::Disconnected) => return,
                    }
                }
                match MebClient::connect(&self.options.url, self.options.timeout) {
                    Ok(c) => {
                        let mut s = lock(&self.state);
                        s.counters.reconnects += 1;
                        // The slave may have restarted meanwhile (power-up
                        // outputs) or another master written them: what this
                        // panel wrote before is no longer known to hold.
                        s.vel = None;
                        for word in &mut s.sd {
                            word.1 = None;
                        }
                        drop(s);
                        hub.push_event("panel", self.now(), "connected", &self.options.url);
                        client = Some(c);
                    }
                    Err(e) => {
                        lock(&self.state).error = Some(in_full(&e));
                    }
                }
                continue;
            };
            let monitor_hub = hub.clone();
            let started = self.started;
            let slave = format!("slave {:02}", self.options.id);
            c.set_monitor(move |way, _, bytes| {
                let t = started.elapsed().as_secs_f64();
                let (from, to) = match way {
                    Way::Sent => ("twin", slave.as_str()),
                    Way::Received => (slave.as_str(), "twin"),
                };
                monitor_hub.push_frame(&LiveFrame {
                    link: LINK,
                    from,
                    to,
                    start: t,
                    end: t,
                    bytes,
                });
            });
            {
                let mut s = lock(&self.state);
                s.connected = true;
                s.error = None;
            }
            let why = self.poll_connected(&mut c, &commands);
            match why {
                None => return,
                Some(why) => {
                    hub.push_event("panel", self.now(), "disconnected", &why);
                    let mut s = lock(&self.state);
                    s.connected = false;
                    s.error = Some(why);
                }
            }
        }
    }

    /// Polls until the connection is lost (`Some(why)`) or the panel ends.
    fn poll_connected(
        &self,
        c: &mut MebClient,
        commands: &Receiver<(OutputRequest, Answer)>,
    ) -> Option<String> {
        let mut failures = 0u32;
        let mut next = Instant::now();
        loop {
            // Writes first: the page waits for them. But only until the
            // poll is due: a slider dragged sends writes back to back, and
            // the inputs and status must still be read between them.
            loop {
                let left = next.saturating_duration_since(Instant::now());
                if left.is_zero() {
                    break;
                }
                match commands.recv_timeout(left) {
                    Ok((request, answer)) => {
                        let result = self.apply(c, &request);
                        let lost = result.as_ref().err().and_then(|e| e.lost.clone());
                        let _ = answer.send(result.map_err(|e| e.rejected));
                        if let Some(why) = lost {
                            return Some(why);
                        }
                    }
                    Err(RecvTimeoutError::Timeout) => break,
                    Err(RecvTimeoutError::Disconnected) => return None,
                }
            }
            next = Instant::now() + self.options.poll;
            match self.poll_once(c) {
                Ok(()) => failures = 0,
                Err(Failed {
                    lost: Some(why), ..
                }) => return Some(why),
                Err(Failed { rejected, .. }) => {
                    failures += 1;
                    lock(&self.state).error = Some(rejected.message);
                    // A slave that stays silent is as good as gone.
                    if failures >= 5 {
                        return Some(format!(
                            "no usable reply to 5 polls in a row from {} (slave {:02})",
                            self.options.url, self.options.id
                        ));
                    }
                }
            }
        }
    }

    /// One exchange, counted; an error says whether the connection is lost.
    fn exchange<T>(
        &self,
        c: &mut MebClient,
        f: impl FnOnce(&mut MebClient) -> Result<T, ClientError>,
    ) -> Result<T, Failed> {
        lock(&self.state).counters.requests += 1;
        match f(c) {
            Ok(v) => {
                lock(&self.state).counters.replies += 1;
                Ok(v)
            }
            Err(e) => {
                let text = in_full(&e);
                let mut s = lock(&self.state);
                let lost = if matches!(e, ClientError::Refused { .. }) {
                    s.counters.refused += 1;
                    None
                } else if matches!(e, ClientError::NoReply { .. }) {
                    s.counters.timeouts += 1;
                    None
                } else {
                    Some(text.clone())
                };
                Err(Failed {
                    rejected: Rejected {
                        status: if lost.is_some() { 503 } else { 502 },
                        field: None,
                        message: text,
                    },
                    lost,
                })
            }
        }
    }

    fn poll_once(&self, c: &mut MebClient) -> Result<(), Failed> {
        let id = self.options.id;
        let l = &self.layout;
        let ea = self.read_runs(c, MebCmd::EA, &l.ea_reads)?;
        let ed = self.read_runs(c, MebCmd::ED, &l.ed_reads)?;
        let fa = self.read_runs(c, MebCmd::FA, &l.fa_reads)?;
        let status = self.exchange(c, |c| c.read(id, MebCmd::FD, 0, 1))?;
        let at = self.now();
        let mut s = lock(&self.state);
        s.ea = ea;
        s.ed = ed;
        s.fa = fa;
        s.status = status.first().copied();
        s.read_at = Some(at);
        s.error = None;
        Ok(())
    }

    /// The words of `cmd` at every address of `runs`, read a run at a
    /// time, placed by address (0 where the map places nothing).
    fn read_runs(
        &self,
        c: &mut MebClient,
        cmd: MebCmd,
        runs: &[(u8, u8)],
    ) -> Result<Vec<u16>, Failed> {
        let id = self.options.id;
        let end = runs
            .iter()
            .map(|&(a, n)| usize::from(a) + usize::from(n))
            .max()
            .unwrap_or(0);
        let mut words = vec![0; end];
        for &(first, count) in runs {
            let read = self.exchange(c, |c| c.read(id, cmd, first, count))?;
            for (slot, word) in words.iter_mut().skip(usize::from(first)).zip(read) {
                *slot = word;
            }
        }
        Ok(words)
    }

    fn apply(&self, c: &mut MebClient, request: &OutputRequest) -> Result<Value, Failed> {
        let id = self.options.id;
        let refused = |field: &str, message: String| Failed {
            rejected: Rejected {
                status: 409,
                field: Some(field.into()),
                message,
            },
            lost: None,
        };
        if let Some(vel) = request.vel {
            let addr = self.layout.vel.ok_or_else(|| {
                refused("vel", "vel: the I/O map places no VEL (SA) to write".into())
            })?;
            self.exchange(c, |c| c.write(id, MebCmd::SA, addr, &[vel]))?;
            lock(&self.state).vel = Some(vel);
        }
        // Each SD word touched is written whole: the switches it holds as
        // this panel last wrote them (off at first), with the changes.
        let mut words: Vec<(u8, u16)> = Vec::new();
        for &(i, on) in &request.switches {
            let (name, home_word, home_bit) = SWITCHES[i];
            let place = self.layout.switches[i].ok_or_else(|| {
                refused(
                    name,
                    format!("{name}: the I/O map places no {name} to write"),
                )
            })?;
            let word = match words.iter_mut().find(|(w, _)| *w == place.word) {
                Some((_, v)) => v,
                None => {
                    let start = self.sd_word(place.word);
                    words.push((place.word, start));
                    &mut words.last_mut().expect("just pushed").1
                }
            };
            let pin_high = state::pin_for(home_word, home_bit, on);
            if pin_high {
                *word |= 1 << place.bit;
            } else {
                *word &= !(1 << place.bit);
            }
        }
        for (addr, value) in words {
            self.exchange(c, |c| c.write(id, MebCmd::SD, addr, &[value]))?;
            let mut s = lock(&self.state);
            if let Some(slot) = s.sd.iter_mut().find(|(w, _)| *w == addr) {
                slot.1 = Some(value);
            }
        }
        Ok(json!({ "ok": true, "t": crate::seconds(self.now()) }))
    }

    /// The SD word `addr` as last written, or every switch it holds off
    /// (forward, for FR).
    fn sd_word(&self, addr: u8) -> u16 {
        if let Some(Some(v)) = lock(&self.state)
            .sd
            .iter()
            .find(|(w, _)| *w == addr)
            .map(|s| s.1)
        {
            return v;
        }
        let mut word = 0u16;
        for (i, place) in self.layout.switches.iter().enumerate() {
            let Some(place) = place.filter(|p| p.word == addr) else {
                continue;
            };
            let (_, home_word, home_bit) = SWITCHES[i];
            let off_pin = state::pin_for(home_word, home_bit, false);
            if off_pin {
                word |= 1 << place.bit;
            }
        }
        word
    }
}

/// A failed exchange: what the page is told, and whether the connection is lost.
struct Failed {
    rejected: Rejected,
    lost: Option<String>,
}

fn unavailable(message: String) -> Rejected {
    Rejected {
        status: 503,
        field: None,
        message,
    }
}
