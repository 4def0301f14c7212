//! What every real-time session (`twin serve`, `twin supervise`) does around
//! its engine: the links' runtime, waiting for the engine thread while
//! SIGINT/SIGTERM are forwarded to it, and the totals its recording ends with.

use anyhow::{Context, Result};
use nodes::time::SimTime;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::mpsc::{Receiver, Sender};
use std::thread::JoinHandle;
use std::time::Duration;
use tokio::runtime::Runtime;
use tokio::signal::unix::{Signal, SignalKind, signal};

use super::{Inbound, RtEngine, RtSummary};
use twin_recording::record::Recorder;

/// The runtime the listeners and serial ports run on (a TCP connection has
/// a thread of its own, see [`super::tcp_thread`]): a worker per core (up
/// to four), so several serial ports are answered at once.
pub fn links_runtime() -> Result<Runtime> {
    let workers = std::thread::available_parallelism().map_or(2, |n| n.get().clamp(1, 4));
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(workers)
        .enable_io()
        .enable_time()
        .thread_name("twin-links")
        .build()
        .context("cannot start the I/O runtime")
}

/// The session's recording, with its `twin.run` metadata (`kind` and the
/// twin's version added to `fields`); none without a path. Call it once every
/// link is open: a session that cannot start leaves an earlier recording of
/// the same name as it was.
pub fn create_recording(
    path: Option<&Path>,
    kind: &str,
    mut fields: BTreeMap<String, String>,
) -> Result<Option<Recorder>> {
    let Some(path) = path else { return Ok(None) };
    let mut recorder = Recorder::create_with_level(path, twin_recording::record::REALTIME_ZSTD_LEVEL)?;
    fields.insert("kind".into(), kind.into());
    fields.insert("twin_version".into(), env!("CARGO_PKG_VERSION").into());
    recorder.write_metadata("twin.run", fields)?;
    Ok(Some(recorder))
}

/// Each link's name and protocol, as the sink labels its frames.
pub fn link_labels(engine: &RtEngine) -> Vec<(String, &'static str)> {
    engine
        .links
        .iter()
        .map(|l| (l.name.clone(), l.protocol))
        .collect()
}

/// Runs `engine` on its own thread until `end` or a stop, under SCHED_FIFO at
/// `priority` when one is given (a warning in the monitor if it cannot be had).
pub fn spawn_engine(
    mut engine: RtEngine,
    inbound: Receiver<Inbound>,
    end: Option<SimTime>,
    priority: Option<u8>,
) -> Result<JoinHandle<(RtSummary, RtEngine)>> {
    std::thread::Builder::new()
        .name("twin-realtime".into())
        .spawn(move || {
            if let Some(priority) = priority
                && let Err(why) = super::clock::raise_this_thread(priority)
            {
                engine.say(format!("warning: no real-time priority: {why}"));
            }
            let summary = engine.run(&inbound, end);
            (summary, engine)
        })
        .context("cannot start the real-time thread")
}

/// Drives the links on `runtime` until the engine thread ends (its
/// `--duration`, a `stop` typed on the console, or a signal: SIGINT and
/// SIGTERM are handed to the engine as a stop, so the recording is finished),
/// then returns what the thread returned.
pub fn run_until_stopped<T>(
    runtime: &Runtime,
    engine_thread: JoinHandle<T>,
    engine: Sender<Inbound>,
) -> Result<T> {
    runtime.block_on(async {
        let mut term = signal(SignalKind::terminate()).ok();
        let mut int = signal(SignalKind::interrupt()).ok();
        loop {
            tokio::select! {
                Some(()) = next(&mut term) => {
                    let _ = engine.send(Inbound::Stop("SIGTERM".into()));
                }
                Some(()) = next(&mut int) => {
                    let _ = engine.send(Inbound::Stop("SIGINT".into()));
                }
                () = tokio::time::sleep(Duration::from_millis(20)) => {
                    if engine_thread.is_finished() { break; }
                }
            }
        }
    });
    engine_thread
        .join()
        .map_err(|_| anyhow::anyhow!("the real-time thread failed"))
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
            serde_json::to_string(&summary.lateness)?,
        ),
        ("counters".into(), serde_json::to_string(&summary.counters)?),
        ("refused_clients".into(), refused_clients.to_string()),
        ("stopped_by".into(), summary.stopped_by.clone()),
    ]))
}
