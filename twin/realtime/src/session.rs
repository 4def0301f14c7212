//! What every real-time session (`twin serve`, `twin supervise`) does around
//! its engine: the links' runtime, waiting for the engine thread while
//! SIGINT/SIGTERM are forwarded to it, and the totals its recording ends with.
//!
//! [`run`] takes a session through its steps in order: the runtime and the
//! clock, the engine, the role's devices and links ([`Role`]), the recording
//! and its metadata, the sink, `ready`, the engine's thread and the links'
//! tasks, the run until `--duration`, `stop` or a signal, the shutdown and the
//! totals. A role supplies what differs; [`SessionOptions`] and
//! [`SessionOutcome`] hold what every session is told and reports.

use protocols::time::{SimDuration, SimTime};
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, Sender, channel};
use std::thread::JoinHandle;
use std::time::Duration;
use tokio::runtime::{Handle, Runtime};
use tokio::signal::unix::{Signal, SignalKind, signal};

use super::allow::AllowList;
use super::io::{OpenError, SerialSettings, serial, tcp};
use super::links::{ClientLimit, ConnIds, Refused, accept_loop, serial_loop};
use super::rotate::{RecordPlan, Recordings};
use super::sink::{self, SinkConfig, SinkLink, SinkMsg, ViewOpener};
use super::{Inbound, LatenessSummary, RtClock, RtEngine, RtSummary};
use twin_recording::WriteError;

/// Why a session could not start or end as it should: what every role
/// shares (its own mistakes are its role's error, which holds these).
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("cannot start the I/O runtime")]
    Runtime(#[source] std::io::Error),
    #[error("cannot start the real-time thread")]
    EngineThread(#[source] std::io::Error),
    /// The engine's thread ended without its summary (it panicked).
    #[error("the real-time thread failed")]
    EngineFailed,
    /// The recording thread ended without its outcome (it panicked).
    #[error("the recording thread failed")]
    RecordingFailed,
    /// The recording could not be started or finished.
    #[error(transparent)]
    Recording(#[from] WriteError),
    #[error("cannot write the session's totals")]
    Totals(#[source] serde_json::Error),
}

type Result<T, E = SessionError> = std::result::Result<T, E>;

/// What every session is told, beside what its role is told (the role's
/// options hold it as `session`).
#[derive(Debug, Clone)]
pub struct SessionOptions {
    /// Stop after this long, seconds (none: until SIGINT/SIGTERM or `stop`).
    pub duration: Option<f64>,
    /// Where and how the session records (none: not recorded).
    pub record: Option<RecordPlan>,
    /// Print every frame.
    pub monitor: bool,
    /// Seconds between status lines (0: none).
    pub status_every: f64,
    /// Wait for serial paths that do not exist yet (ptys made later).
    pub wait_for_ports: bool,
    /// Plant state messages recorded per second.
    pub record_hz: f64,
    /// Real-time FIFO priority of the engine's thread (the links' thread
    /// gets one below), if asked for.
    pub rt_priority: Option<u8>,
    /// Opens the session's live view (`--view`), if it has one.
    pub view: Option<ViewOpener>,
    /// The command line, for the recording's metadata.
    pub command_line: String,
    /// The client addresses the session's TCP listeners serve (empty: any).
    pub allow: AllowList,
    /// What SIGHUP rereads before the recording starts a new file.
    pub on_hangup: Option<OnHangup>,
}

/// Called on SIGHUP (on the links' thread) before the recording starts a
/// new file: rereads what can change while serving (a configuration file)
/// and returns the recording's new plan, if any.
#[derive(Clone)]
pub struct OnHangup(Arc<dyn Fn() -> Option<RecordPlan> + Send + Sync>);

impl OnHangup {
    pub fn new(reread: impl Fn() -> Option<RecordPlan> + Send + Sync + 'static) -> Self {
        Self(Arc::new(reread))
    }
}

impl std::fmt::Debug for OnHangup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("OnHangup")
    }
}

/// What every session reports at its end (a role's outcome holds it beside
/// its own results).
#[derive(Debug)]
pub struct SessionOutcome {
    pub elapsed_s: f64,
    pub lateness: LatenessSummary,
    pub counters: crate::engine::RtCounters,
    pub refused_clients: u64,
    /// Clients refused for coming from an address `--allow` does not name.
    pub refused_not_allowed: u64,
    pub stopped_by: String,
    /// The recording's last file.
    pub recording: Option<PathBuf>,
    /// The files finished before it (rotated), oldest first.
    pub earlier_files: Vec<PathBuf>,
    /// Frames recorded on the links, both directions, over every file.
    pub frames_recorded: u64,
    /// How long the connections waited, summed, for the recording to catch up.
    pub waited_for_recording: Duration,
    /// Samples streamed to the live view (`--view`), if it ran.
    pub view_samples: Option<u64>,
    /// What the live view's viewer did not take, if anything.
    pub view_error: Option<String>,
}

/// What a session's role (`twin serve`, `twin supervise`) supplies to
/// [`run`]: its devices, its links, its metadata, and what it does while the
/// session runs and once it has stopped.
pub trait Role {
    /// One open link, as the command prints it before `ready`.
    type Link;
    /// What the role reports at the end, beside [`SessionOutcome`].
    type End;
    /// Why the role's session failed: its own mistakes, and the session's.
    type Error: From<SessionError>;
    /// The recording's `kind`.
    const KIND: &'static str;

    /// Adds the role's modules and devices to `engine`, and sets it up.
    fn build(&mut self, engine: &mut RtEngine) -> Result<(), Self::Error>;

    /// Opens the role's links (inside the runtime): each is added to
    /// `engine`, and the task that carries it to `links`.
    fn open(
        &mut self,
        engine: &mut RtEngine,
        links: &mut Links,
    ) -> impl Future<Output = Result<Vec<Self::Link>, Self::Error>>;

    /// The recording's `twin.run` metadata besides `command`, `kind` and the
    /// twin's version.
    fn metadata(&self) -> Result<BTreeMap<String, String>, Self::Error>;

    /// Once the engine and the links run: the role's own tasks.
    fn started(&mut self, runtime: &Runtime, engine: &Sender<Inbound>);

    /// Once the engine has stopped: what the role reports, and what it adds
    /// to the recording's totals.
    fn stopped(
        &mut self,
        engine: &mut RtEngine,
        totals: &mut BTreeMap<String, String>,
    ) -> Self::End;
}

/// Starts an opened link's task on the runtime, sending to the engine.
type Starter = Box<dyn FnOnce(&Handle, Sender<Inbound>)>;

/// The links a role opens: connection ids, the clients refused over a
/// limit, and the tasks that carry the links, started once the engine runs.
pub struct Links {
    pub clock: RtClock,
    pub ids: ConnIds,
    wait_for_ports: bool,
    refused: Refused,
    starters: Vec<Starter>,
}

impl std::fmt::Debug for Links {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Links")
            .field("tasks", &self.starters.len())
            .finish_non_exhaustive()
    }
}

impl Links {
    fn new(clock: RtClock, wait_for_ports: bool) -> Self {
        Self {
            clock,
            ids: ConnIds::default(),
            wait_for_ports,
            refused: Refused::default(),
            starters: Vec::new(),
        }
    }

    /// Starts `task` on the runtime once the engine runs.
    pub fn start(&mut self, task: impl FnOnce(&Handle, Sender<Inbound>) + 'static) {
        self.starters.push(Box::new(task));
    }

    /// Listens on `addr` for the clients of link `link` from the
    /// addresses `allow` names, up to `limit`; returns the address bound
    /// (port 0: the port chosen).
    pub async fn listen(
        &mut self,
        addr: SocketAddr,
        link: usize,
        limit: Option<ClientLimit>,
        allow: AllowList,
    ) -> Result<SocketAddr, OpenError> {
        let listener = tcp::bind(addr).await?;
        let local = listener
            .local_addr()
            .map_err(|source| OpenError::Listen { addr, source })?;
        let (ids, clock, refused) = (self.ids.clone(), self.clock.clone(), self.refused.clone());
        self.start(move |rt, inbound| {
            rt.spawn(accept_loop(
                listener, link, limit, allow, ids, clock, inbound, refused,
            ));
        });
        Ok(local)
    }

    /// Opens the serial device or pty at `path` as link `link`; with
    /// `--wait-for-ports`, waits for a path that does not exist yet.
    pub async fn serial(
        &mut self,
        path: &Path,
        settings: SerialSettings,
        link: usize,
    ) -> Result<(), OpenError> {
        if self.wait_for_ports && !path.exists() {
            println!("waiting for {} to appear ...", path.display());
            // A stop while waiting ends the wait: once another module of a
            // class has taken SIGTERM and SIGINT over, their default action
            // no longer ends the process.
            let (mut term, mut int) = (
                signal(SignalKind::terminate()).ok(),
                signal(SignalKind::interrupt()).ok(),
            );
            while !path.exists() {
                tokio::select! {
                    () = tokio::time::sleep(Duration::from_millis(100)) => {}
                    Some(()) = next(&mut term) => {
                        return Err(stopped_waiting("SIGTERM", path));
                    }
                    Some(()) = next(&mut int) => {
                        return Err(stopped_waiting("SIGINT", path));
                    }
                }
            }
        }
        let port = serial::open(path, &settings)?;
        let (ids, clock, path) = (self.ids.clone(), self.clock.clone(), path.to_path_buf());
        self.start(move |rt, inbound| {
            rt.spawn(serial_loop(path, settings, port, link, ids, clock, inbound));
        });
        Ok(())
    }
}

fn stopped_waiting(signal: &'static str, path: &Path) -> OpenError {
    OpenError::StoppedWaiting {
        signal,
        path: path.to_path_buf(),
    }
}

/// Runs a session of `role`: `ready` gets the open links once they all are
/// (the command prints them and `ready`). Returns once the session has
/// stopped and its recording is finished.
pub fn run<R: Role>(
    options: &SessionOptions,
    mut role: R,
    ready: impl FnOnce(&[R::Link]),
) -> Result<(SessionOutcome, R::End), R::Error> {
    // Every client is a descriptor: a service's soft limit of 1024 would
    // cap the links long before the machine does.
    if let Some(Err(e)) = super::fd_limit::raise_once() {
        eprintln!("warning: {e}");
    }
    let runtime = links_runtime(options.rt_priority)?;
    let clock = RtClock::start();
    let record_period = SimDuration::from_secs_f64(1.0 / options.record_hz.max(1.0));
    // The sink starts once the links are open and named; its channel is made
    // first so the engine can hold its sender.
    let (tx, rx) = channel::<SinkMsg>();
    let mut engine = RtEngine::new(
        clock.clone(),
        SimDuration::from_millis(1),
        record_period,
        tx,
    );
    role.build(&mut engine)?;
    let mut links = Links::new(clock, options.wait_for_ports);
    let open = runtime.block_on(role.open(&mut engine, &mut links))?;
    let mut metadata = role.metadata()?;
    metadata.insert("command".into(), options.command_line.clone());
    let recording = match &options.record {
        Some(plan) => {
            let (mut files, mut recorder) =
                Recordings::start(plan.clone(), R::KIND, metadata).map_err(SessionError::from)?;
            // A sketch's ELF goes into the session's files, as into a run's.
            let firmware = engine
                .devices
                .iter()
                .filter_map(|d| d.node.firmware_file())
                .collect();
            files
                .keep_firmware(firmware, &mut recorder)
                .map_err(SessionError::from)?;
            Some((files, recorder))
        }
        None => None,
    };
    let modules: Vec<String> = engine.modules.iter().map(|m| m.name.clone()).collect();
    let view = options.view.as_ref().and_then(|v| v.open(&modules));
    engine.set_samples_wanted(recording.is_some() || view.is_some());
    let sink_handle = sink::spawn_with(
        SinkConfig {
            modules,
            links: link_labels(&engine),
            monitor: options.monitor,
            recording,
            view,
        },
        rx,
    );
    let sink_tx = engine.sink();

    // Taken over before `ready` is said: a service manager's stop right
    // after READY=1 must still finish the recording, not kill the process.
    let signals = Signals::install(&runtime);
    ready(&open);

    let (inbound_tx, inbound_rx) = channel::<Inbound>();
    let end = options
        .duration
        .map(|s| SimTime::ZERO + SimDuration::from_secs_f64(s));
    // Both threads ask for the priority; when the host refuses it, it
    // refuses both, and one warning says so.
    let refused = Arc::new(AtomicBool::new(false));
    let engine_thread = spawn_engine_with(
        engine,
        inbound_rx,
        end,
        options.rt_priority,
        Arc::clone(&refused),
    )?;
    for start in std::mem::take(&mut links.starters) {
        start(runtime.handle(), inbound_tx.clone());
    }
    role.started(&runtime, &inbound_tx);
    // This thread drives the runtime and its signals: a reply waits for it
    // too. The runtime's own threads raised themselves as they started.
    if let Some(priority) = options.rt_priority
        && let Err(why) = super::clock::raise_this_thread(links_priority(priority))
        && !refused.swap(true, Ordering::Relaxed)
    {
        let _ = sink_tx.send(SinkMsg::Say(refused_warning(priority, &why)));
    }

    let (summary, mut engine) = run_until_stopped(
        &runtime,
        signals,
        engine_thread,
        inbound_tx.clone(),
        Some(sink_tx.clone()),
        options.on_hangup.clone(),
    )?;
    let mut role_totals = BTreeMap::new();
    let role_end = role.stopped(&mut engine, &mut role_totals);
    drop(engine);
    runtime.shutdown_timeout(Duration::from_millis(200));

    let refused_clients = links.refused.over_limit.load(Ordering::Relaxed);
    let refused_not_allowed = links.refused.not_allowed.load(Ordering::Relaxed);
    let mut totals = totals(&summary, refused_clients)?;
    totals.insert(
        "refused_not_allowed".into(),
        refused_not_allowed.to_string(),
    );
    totals.extend(role_totals);
    let _ = sink_tx.send(SinkMsg::Finish(totals));
    drop(sink_tx);
    let sunk = sink_handle
        .join()
        .map_err(|_| SessionError::RecordingFailed)?
        .map_err(SessionError::from)?;
    let outcome = SessionOutcome {
        elapsed_s: summary.elapsed.as_secs_f64(),
        lateness: summary.lateness,
        counters: summary.counters,
        refused_clients,
        refused_not_allowed,
        stopped_by: summary.stopped_by,
        recording: sunk.recording,
        earlier_files: sunk.earlier_files,
        frames_recorded: sunk.frames_recorded,
        waited_for_recording: summary.waited_for_recording,
        view_samples: sunk.view_samples,
        view_error: sunk.view_error,
    };
    Ok((outcome, role_end))
}

/// The runtime the listeners and serial ports run on (a TCP connection has
/// a thread of its own, see [`super::tcp_thread`]): a worker per core (up
/// to four), so several serial ports are answered at once. With
/// `priority`, its threads take the links' real-time priority as they
/// start: the serial ports' tasks run on them, not on the thread that
/// blocks on the runtime (a refusal is said once, by that thread).
pub fn links_runtime(priority: Option<u8>) -> Result<Runtime> {
    let workers = std::thread::available_parallelism().map_or(2, |n| n.get().clamp(1, 4));
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    builder
        .worker_threads(workers)
        .enable_io()
        .enable_time()
        .thread_name("twin-links");
    if let Some(priority) = priority {
        let links = links_priority(priority);
        builder.on_thread_start(move || {
            let _ = super::clock::raise_this_thread(links);
        });
    }
    builder.build().map_err(SessionError::Runtime)
}

/// The links' priority: one below the plant's, so a busy link never holds
/// off a tick.
fn links_priority(plant: u8) -> u8 {
    plant.saturating_sub(1).max(1)
}

/// Each link's name and protocol, as the sink labels its frames.
pub fn link_labels(engine: &RtEngine) -> Vec<SinkLink> {
    engine
        .links
        .iter()
        .map(|l| SinkLink {
            name: l.name.clone(),
            protocol: l.protocol,
            silence: l.spec.silence(),
            twin_is_master: l.twin_is_master,
        })
        .collect()
}

/// Runs `engine` on its own thread until `end` or a stop, under SCHED_FIFO at
/// `priority` when one is given (a warning in the monitor if it cannot be had).
pub fn spawn_engine(
    engine: RtEngine,
    inbound: Receiver<Inbound>,
    end: Option<SimTime>,
    priority: Option<u8>,
) -> Result<JoinHandle<(RtSummary, RtEngine)>> {
    spawn_engine_with(engine, inbound, end, priority, Arc::default())
}

/// What a refused `--rt-priority` says: what the session risks, and how
/// the host grants it.
fn refused_warning(priority: u8, why: &str) -> String {
    format!(
        "warning: no real-time priority, so a busy machine can delay ticks, edges and \
         replies ({why}); run as root, grant CAP_SYS_NICE, or raise the rtprio limit to \
         {priority} (`ulimit -r`, LimitRTPRIO= in a systemd unit)"
    )
}

/// [`spawn_engine`], the warning of a refused priority said only if
/// `refused` was not set already (by the links' thread).
fn spawn_engine_with(
    mut engine: RtEngine,
    inbound: Receiver<Inbound>,
    end: Option<SimTime>,
    priority: Option<u8>,
    refused: Arc<AtomicBool>,
) -> Result<JoinHandle<(RtSummary, RtEngine)>> {
    std::thread::Builder::new()
        .name("twin-realtime".into())
        .spawn(move || {
            if let Some(priority) = priority
                && let Err(why) = super::clock::raise_this_thread(priority)
                && !refused.swap(true, Ordering::Relaxed)
            {
                engine.say(refused_warning(priority, &why));
            }
            let summary = engine.run(&inbound, end);
            (summary, engine)
        })
        .map_err(SessionError::EngineThread)
}

/// Drives the links on `runtime` until the engine thread ends (its
/// `--duration`, a `stop` typed on the console, or a signal: SIGINT and
/// SIGTERM are handed to the engine as a stop, so the recording is finished;
/// SIGHUP asks `sink` for a new recording file), then returns what the
/// thread returned.
pub fn run_until_stopped<T: Send + 'static>(
    runtime: &Runtime,
    signals: Signals,
    engine_thread: JoinHandle<T>,
    engine: Sender<Inbound>,
    sink: Option<Sender<SinkMsg>>,
    on_hangup: Option<OnHangup>,
) -> Result<T> {
    let Signals {
        mut term,
        mut int,
        mut hup,
    } = signals;
    // Waited for on a thread of the blocking pool rather than looked at on
    // a timer: an idle class woke 35 runtimes 50 times a second for it.
    let mut joined = runtime.spawn_blocking(move || engine_thread.join());
    let joined = runtime.block_on(async {
        loop {
            tokio::select! {
                Some(()) = next(&mut hup) => {
                    let plan = on_hangup.as_ref().and_then(|reread| (reread.0)());
                    if let Some(sink) = &sink {
                        if let Some(plan) = plan {
                            let _ = sink.send(SinkMsg::Replan(plan));
                        }
                        let _ = sink.send(SinkMsg::Rotate("SIGHUP".into()));
                    }
                }
                Some(()) = next(&mut term) => {
                    super::notify::stopping("SIGTERM: finishing the recording");
                    let _ = engine.send(Inbound::Stop("SIGTERM".into()));
                }
                Some(()) = next(&mut int) => {
                    super::notify::stopping("SIGINT: finishing the recording");
                    let _ = engine.send(Inbound::Stop("SIGINT".into()));
                }
                joined = &mut joined => break joined,
            }
        }
    });
    match joined {
        Ok(Ok(ended)) => Ok(ended),
        _ => Err(SessionError::EngineFailed),
    }
}

/// SIGTERM, SIGINT and SIGHUP, each taken over from its default action
/// (none: it could not be installed).
#[derive(Debug)]
pub struct Signals {
    term: Option<Signal>,
    int: Option<Signal>,
    hup: Option<Signal>,
}

impl Signals {
    /// Takes the three signals over, on `runtime`'s driver.
    pub fn install(runtime: &Runtime) -> Signals {
        let _entered = runtime.enter();
        Signals {
            term: signal(SignalKind::terminate()).ok(),
            int: signal(SignalKind::interrupt()).ok(),
            hup: signal(SignalKind::hangup()).ok(),
        }
    }
}

/// The next delivery of `signal`; never, if it could not be installed.
async fn next(signal: &mut Option<Signal>) -> Option<()> {
    match signal {
        Some(s) => s.recv().await,
        None => std::future::pending().await,
    }
}

/// The totals a session's recording ends with (its `twin.realtime` record).
pub fn totals(summary: &RtSummary, refused_clients: u64) -> Result<BTreeMap<String, String>> {
    Ok(BTreeMap::from([
        (
            "elapsed_s".into(),
            format!("{:.3}", summary.elapsed.as_secs_f64()),
        ),
        (
            "tick_lateness".into(),
            serde_json::to_string(&summary.lateness).map_err(SessionError::Totals)?,
        ),
        (
            "counters".into(),
            serde_json::to_string(&summary.counters).map_err(SessionError::Totals)?,
        ),
        ("refused_clients".into(), refused_clients.to_string()),
        ("stopped_by".into(), summary.stopped_by.clone()),
        (
            "waited_for_recording_s".into(),
            format!("{:.3}", summary.waited_for_recording.as_secs_f64()),
        ),
    ]))
}
