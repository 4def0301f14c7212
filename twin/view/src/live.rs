//! Streaming a run to rerun as it happens: an [`Observer`] that sits beside
//! the MCAP recorder (`twin_sim::observe::Tee`), for `twin run --view` and the real-time roles.

use nodes::node::NodeEvent;
use protocols::time::SimTime;
use rerun::{RecordingStream, RecordingStreamBuilder};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::blueprint::blueprint;
use super::layout::ViewLayout;
use super::logger::{PlantSample, RerunLogger};
use crate::ViewError;

type Result<T, E = ViewError> = std::result::Result<T, E>;
use twin_sim::engine::{BusSlot, ModuleSlot, NodeSlot, ObserveError, Observer};

/// The application id the viewer groups the twin's recordings under.
pub const APPLICATION_ID: &str = "ev-lab-twin";

/// How long the end of a stream may wait for a slow or vanished viewer.
const FLUSH_TIMEOUT: Duration = Duration::from_secs(5);

/// How long a viewer's port may take to accept before it counts as absent.
const PROBE_TIMEOUT: Duration = Duration::from_secs(2);

/// Where a rerun stream goes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ViewTarget {
    /// Start a viewer (`rerun` on PATH), or use the one already listening
    /// on the default port.
    Spawn,
    /// A running viewer or server, e.g. `rerun+http://127.0.0.1:9876/proxy`.
    Connect(String),
    /// An `.rrd` file.
    Save(PathBuf),
}

impl ViewTarget {
    /// `spawn`, a `rerun+http://` URL, or a file path.
    pub fn parse(text: &str) -> Self {
        if text.is_empty() || text == "spawn" {
            ViewTarget::Spawn
        } else if text.starts_with("rerun://")
            || text.starts_with("rerun+http://")
            || text.starts_with("rerun+https://")
        {
            ViewTarget::Connect(text.to_string())
        } else {
            ViewTarget::Save(PathBuf::from(text))
        }
    }
}

/// Whether a native viewer can be spawned here: `rerun` on PATH and a
/// display to open its window on.
pub fn viewer_available() -> Option<PathBuf> {
    let display = ["DISPLAY", "WAYLAND_DISPLAY"]
        .iter()
        .any(|v| std::env::var_os(v).is_some_and(|d| !d.is_empty()));
    if !display && cfg!(target_os = "linux") {
        return None;
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(if cfg!(windows) { "rerun.exe" } else { "rerun" }))
        .find(|p| p.is_file())
}

/// A recording stream to `target`, with the blueprint for `layout` sent first.
pub fn open_stream(
    target: &ViewTarget,
    name: &str,
    layout: &ViewLayout,
) -> Result<RecordingStream> {
    let builder = RecordingStreamBuilder::new(APPLICATION_ID)
        .recording_name(name)
        .with_blueprint(blueprint(layout));
    let rec = match target {
        ViewTarget::Spawn => builder.spawn()?,
        ViewTarget::Connect(url) => {
            // The SDK retries a refused connection for ever while its queue
            // fills, which would stall the run: refuse it up front instead.
            probe(url)?;
            builder.connect_grpc_opts(url.clone())?
        }
        ViewTarget::Save(path) => {
            if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir).map_err(|source| ViewError::CreateDir {
                    dir: dir.to_path_buf(),
                    source,
                })?;
            }
            builder.save(path)?
        }
    };
    Ok(rec)
}

/// A live view of a run with `layout`, for the roles that stream as they
/// run (`twin run --view`, the real-time engine): feed it beside the
/// recorder with `twin_sim::observe::Tee`. The error says what to do when no viewer can be
/// reached; a caller usually reports it and runs on without the view.
pub fn live_view(target: &ViewTarget, name: &str, layout: ViewLayout) -> Result<RerunObserver> {
    if *target == ViewTarget::Spawn && viewer_available().is_none() {
        return Err(ViewError::NoViewer);
    }
    RerunObserver::open(target, name, layout).map_err(|e| ViewError::LiveView(Box::new(e)))
}

/// Whether something listens at the host and port of a `rerun+http://` URL.
fn probe(url: &str) -> Result<()> {
    let rest = url.split_once("://").map_or(url, |(_, rest)| rest);
    let authority = rest.split('/').next().unwrap_or(rest);
    let addrs: Vec<SocketAddr> = authority
        .to_socket_addrs()
        .map_err(|source| ViewError::NotAViewerUrl {
            url: url.to_string(),
            source,
        })?
        .collect();
    if addrs
        .iter()
        .any(|a| TcpStream::connect_timeout(a, PROBE_TIMEOUT).is_ok())
    {
        Ok(())
    } else {
        Err(ViewError::NotListening {
            authority: authority.to_string(),
        })
    }
}

/// Streams everything the engine reports to rerun. A viewer that goes away
/// does not stop the run: the stream drops what it cannot deliver.
#[derive(Debug)]
pub struct RerunObserver {
    pub logger: RerunLogger,
}

impl RerunObserver {
    /// A live view of a run with `layout`, streamed to `target`.
    pub fn open(target: &ViewTarget, name: &str, layout: ViewLayout) -> Result<Self> {
        let rec = open_stream(target, name, &layout)?;
        Ok(Self {
            logger: RerunLogger::new(rec, layout)?,
        })
    }

    /// Deliver what is still buffered, waiting at most a few seconds for
    /// the viewer.
    pub fn finish(self) -> Result<()> {
        self.logger
            .stream()
            .flush_with_timeout(FLUSH_TIMEOUT)
            .map_err(ViewError::Unflushed)
    }
}

fn secs(t: SimTime) -> f64 {
    t.as_secs_f64()
}

impl Observer for RerunObserver {
    fn plant(&mut self, now: SimTime, module: &ModuleSlot) -> Result<(), ObserveError> {
        let sample = PlantSample::from(module.plant.sensors());
        self.logger.plant(&module.name, secs(now), &sample);
        Ok(())
    }

    fn frame(
        &mut self,
        bus: &BusSlot,
        from: &NodeSlot,
        start: SimTime,
        end: SimTime,
        bytes: &[u8],
    ) -> Result<(), ObserveError> {
        self.logger
            .frame(&bus.name, &from.name, secs(start), secs(end), bytes);
        Ok(())
    }

    fn event(&mut self, node: &NodeSlot, event: &NodeEvent) -> Result<(), ObserveError> {
        self.logger
            .event(&node.name, secs(event.at), event.kind, &event.detail);
        Ok(())
    }

    fn telemetry(
        &mut self,
        now: SimTime,
        node: &NodeSlot,
        report: &twin_recording::topics::LoopReport,
    ) -> Result<(), ObserveError> {
        self.logger
            .master_loop(&node.name, secs(now), &report.to_value());
        Ok(())
    }

    fn readings(
        &mut self,
        now: SimTime,
        node: &NodeSlot,
        readings: &twin_recording::topics::ReadingsSample,
    ) -> Result<(), ObserveError> {
        self.logger.readings(&node.name, secs(now), readings);
        Ok(())
    }

    /// A firmware node's records, through the same path `twin view` reads
    /// them by (their JSON), so the live view and the file agree.
    fn firmware(
        &mut self,
        node: &str,
        record: twin_sim::engine::FirmwareRecord<'_>,
    ) -> Result<(), ObserveError> {
        use crate::logger::firmware::{FirmwareIo, UartBurst};
        use twin_sim::engine::FirmwareRecord;
        match record {
            FirmwareRecord::Uart(_, burst) => {
                let b: UartBurst = through_json(&burst)?;
                self.logger.firmware_uart(node, &b);
            }
            FirmwareRecord::Io(at, io) => {
                let io: FirmwareIo = through_json(&io)?;
                self.logger.firmware_io(node, secs(at), &io);
            }
        }
        Ok(())
    }
}

/// `value` read back as `T` through its JSON, as `twin view` reads a
/// recording's firmware records.
fn through_json<T: serde::de::DeserializeOwned>(
    value: &impl serde::Serialize,
) -> Result<T, ObserveError> {
    serde_json::to_value(value)
        .and_then(serde_json::from_value)
        .map_err(|e| ObserveError::Other(Box::new(e)))
}

/// The `.rrd` that `twin view` writes for `recording`: beside it, same stem.
pub fn rrd_beside(recording: &Path) -> PathBuf {
    recording.with_extension("rrd")
}
