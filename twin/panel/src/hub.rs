//! Where the panel's two inputs meet its stream clients. The live view
//! (on the sink's thread) drops frames and events here; every stream period
//! the producer ([`crate::http`]) takes them with the engine's state, builds
//! one message and hands the same text to every client.

use serde_json::Value;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};
use tokio::sync::broadcast;

use crate::PanelRole;
use twin_realtime::sink::LiveFrame;

/// Frames held between two stream messages; past this the oldest are
/// dropped and counted as skipped (a bus faster than a page can show).
pub const FRAMES_HELD: usize = 4096;
/// Events held between two messages.
const EVENTS_HELD: usize = 256;
/// Stream messages a slow client may fall behind before it skips some.
const CLIENT_BACKLOG: usize = 64;
/// Trend points kept for a page opened late: 30 s at up to 50 Hz.
const TREND_POINTS: usize = 1500;

/// One frame as the live view saw it.
#[derive(Debug, Default, Clone)]
pub struct HeldFrame {
    pub link: String,
    /// `twin`, or the peer that sent it (`client 3`, `slave 01`).
    pub from: String,
    /// Who it was for: `twin`, or the peer it went to.
    pub to: String,
    pub start: f64,
    pub end: f64,
    pub bytes: Vec<u8>,
}

/// One event of a node or a connection.
#[derive(Debug, Clone, serde::Serialize)]
pub struct HeldEvent {
    pub node: String,
    pub t: f64,
    pub kind: String,
    pub detail: String,
}

#[derive(Debug, Default)]
struct Held {
    frames: VecDeque<HeldFrame>,
    /// Frames taken, kept for reuse so the live view allocates nothing per frame.
    spare: Vec<HeldFrame>,
    events: VecDeque<HeldEvent>,
    /// Tick lateness over the engine's last second: p99 and max, µs.
    lateness: Option<(f64, f64)>,
}

/// The panel's shared state.
#[derive(Debug)]
pub struct Hub {
    pub role: PanelRole,
    held: Mutex<Held>,
    /// Frames dropped before any client could be sent them.
    skipped: AtomicU64,
    /// Frames seen since start.
    frames_total: AtomicU64,
    /// The last message, as streamed (`GET /api/state`).
    latest: RwLock<Arc<str>>,
    /// The trend, oldest first: `[t, set_point, hall, light, wheel]`.
    trend: Mutex<VecDeque<[Option<f64>; 5]>>,
    stream: broadcast::Sender<Arc<str>>,
    /// Stream clients connected now.
    pub clients: AtomicUsize,
    /// Messages produced since start.
    pub messages: AtomicU64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Hub {
    pub fn new(role: PanelRole) -> Self {
        let (stream, _) = broadcast::channel(CLIENT_BACKLOG);
        Self {
            role,
            held: Mutex::new(Held::default()),
            skipped: AtomicU64::new(0),
            frames_total: AtomicU64::new(0),
            latest: RwLock::new(Arc::from("{}")),
            trend: Mutex::new(VecDeque::new()),
            stream,
            clients: AtomicUsize::new(0),
            messages: AtomicU64::new(0),
        }
    }

    /// Holds one frame (the live view's side).
    pub fn push_frame(&self, f: &LiveFrame<'_>) {
        self.frames_total.fetch_add(1, Ordering::Relaxed);
        let mut held = lock(&self.held);
        let mut frame = if held.frames.len() >= FRAMES_HELD {
            self.skipped.fetch_add(1, Ordering::Relaxed);
            held.frames.pop_front().unwrap_or_default()
        } else {
            held.spare.pop().unwrap_or_default()
        };
        frame.link.clear();
        frame.link.push_str(f.link);
        frame.from.clear();
        frame.from.push_str(f.from);
        frame.to.clear();
        frame.to.push_str(f.to);
        frame.start = f.start;
        frame.end = f.end;
        frame.bytes.clear();
        frame.bytes.extend_from_slice(f.bytes);
        held.frames.push_back(frame);
    }

    pub fn push_event(&self, node: &str, t: f64, kind: &str, detail: &str) {
        let mut held = lock(&self.held);
        if held.events.len() >= EVENTS_HELD {
            held.events.pop_front();
        }
        held.events.push_back(HeldEvent {
            node: node.into(),
            t: crate::seconds(t),
            kind: kind.into(),
            detail: detail.into(),
        });
    }

    pub fn set_lateness(&self, p99_us: f64, max_us: f64) {
        lock(&self.held).lateness = Some((p99_us, max_us));
    }

    /// Everything held since the last call (the producer's side): frames
    /// are handed to `each` and then kept for reuse.
    pub fn take(&self, mut each: impl FnMut(&HeldFrame)) -> (Vec<HeldEvent>, Option<(f64, f64)>) {
        let mut frames = std::mem::take(&mut lock(&self.held).frames);
        for f in &frames {
            each(f);
        }
        let mut held = lock(&self.held);
        let room = FRAMES_HELD.saturating_sub(held.spare.len());
        held.spare.extend(frames.drain(..).take(room));
        let events = held.events.drain(..).collect();
        (events, held.lateness)
    }

    /// Frames dropped before they could be streamed, and frames seen.
    pub fn frame_counts(&self) -> (u64, u64) {
        (
            self.skipped.load(Ordering::Relaxed),
            self.frames_total.load(Ordering::Relaxed),
        )
    }

    /// Publishes one message to every client and as the latest state.
    pub fn publish(&self, message: String, mut trend: [Option<f64>; 5]) {
        trend[0] = trend[0].map(crate::seconds);
        let message: Arc<str> = Arc::from(message);
        if let Ok(mut latest) = self.latest.write() {
            *latest = message.clone();
        }
        {
            let mut points = lock(&self.trend);
            if points.len() >= TREND_POINTS {
                points.pop_front();
            }
            points.push_back(trend);
        }
        self.messages.fetch_add(1, Ordering::Relaxed);
        let _ = self.stream.send(message);
    }

    pub fn latest(&self) -> Arc<str> {
        self.latest
            .read()
            .map(|l| l.clone())
            .unwrap_or_else(|_| Arc::from("{}"))
    }

    /// The trend's last `seconds`, as JSON rows.
    pub fn trend(&self, seconds: f64) -> Value {
        let points = lock(&self.trend);
        let last = points.back().and_then(|p| p[0]).unwrap_or(0.0);
        let rows: Vec<Value> = points
            .iter()
            .filter(|p| p[0].is_some_and(|t| t >= last - seconds))
            .map(|p| serde_json::json!(p))
            .collect();
        serde_json::json!({ "columns": ["t", "set_point", "hall_rpm", "light_rpm", "wheel_rpm"], "rows": rows })
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Arc<str>> {
        self.stream.subscribe()
    }
}
