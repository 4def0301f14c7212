//! The module's controller on the supervisor's bus, as the twin plays it
//! while a server is checked: the twin's own MEB slave (`SlaveFrontend`
//! over a `RegisterImage`, the code `twin serve` runs) on a serial port or
//! pseudo-terminal, on a thread of its own, every frame kept with its time.
//! No plant: the inputs hold what the check puts there, so a client's read
//! can be held to them.

use crate::framing::shown_text as shown;
use crate::run::Way;
use crate::wire::{Wire, WireError};
use nodes::firmware::{Framing, RegisterImage, SlaveFrontend};
use protocols::meb::MebRepr;
use protocols::time::{SimDuration, SimTime};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// One frame on the bus: a request the supervisor sent (`Received` by the
/// twin's slave) or the slave's reply (`Sent`).
#[derive(Debug, Clone)]
pub struct BusFrame {
    /// Seconds since the check started.
    pub at: f64,
    pub way: Way,
    pub text: String,
    /// The bytes, for the recording.
    pub bytes: Vec<u8>,
    /// The frame, when it is a well-formed one.
    pub repr: Option<MebRepr>,
}

#[derive(Debug)]
struct State {
    image: RegisterImage,
    frames: Vec<BusFrame>,
    /// Why the bus stopped (its port failed).
    error: Option<String>,
}

#[derive(Debug)]
struct Shared {
    stop: AtomicBool,
    state: Mutex<State>,
}

/// The slave on the bus, running until dropped.
#[derive(Debug)]
pub struct Bus {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl Bus {
    /// Opens `link` and answers as slave `id` from now on, its analog
    /// inputs `inputs` from the first reply (a request the supervisor left
    /// on the line before is answered with them too); times are seconds
    /// since `started`.
    pub fn open(link: &str, id: u8, inputs: [u16; 6], started: Instant) -> Result<Bus, WireError> {
        let wire = Wire::open(link)?;
        // The M3CVME module's converters: a 12-bit DAC and ADC.
        let mut image = RegisterImage::new(12, 12, 2048, 100);
        image.inputs = inputs;
        let shared = Arc::new(Shared {
            stop: AtomicBool::new(false),
            state: Mutex::new(State {
                image,
                frames: Vec::new(),
                error: None,
            }),
        });
        let inner = shared.clone();
        let thread = std::thread::Builder::new()
            .name("check-bus".into())
            .spawn(move || serve(wire, id, started, &inner))
            .map_err(|why| WireError::Io {
                link: link.into(),
                why,
            })?;
        Ok(Bus {
            shared,
            thread: Some(thread),
        })
    }

    fn state(&self) -> MutexGuard<'_, State> {
        self.shared
            .state
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// Puts `inputs` in the slave's analog inputs (EA 00-05).
    pub fn set_inputs(&self, inputs: [u16; 6]) {
        self.state().image.inputs = inputs;
    }

    /// The slave's analog inputs now.
    pub fn inputs(&self) -> [u16; 6] {
        self.state().image.inputs
    }

    /// The frames from `since` (seconds) on.
    pub fn frames_since(&self, since: f64) -> Vec<BusFrame> {
        self.frames_between(since, f64::INFINITY)
    }

    /// The frames from `from` (seconds) to before `to`.
    pub fn frames_between(&self, from: f64, to: f64) -> Vec<BusFrame> {
        self.state()
            .frames
            .iter()
            .filter(|f| f.at >= from && f.at < to)
            .cloned()
            .collect()
    }

    /// Why the bus stopped, if it did.
    pub fn error(&self) -> Option<String> {
        self.state().error.clone()
    }
}

impl Drop for Bus {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

fn serve(mut wire: Wire, id: u8, started: Instant, shared: &Shared) {
    let mut frontend = SlaveFrontend::new(Framing::Meb, id);
    let mut incoming = Vec::new();
    // The bytes of the frame being heard, and when its first came.
    let mut line: Vec<u8> = Vec::new();
    let mut line_at = 0.0;
    let mut reply = [0u8; 512];
    while !shared.stop.load(Ordering::Relaxed) {
        incoming.clear();
        match wire.receive(&mut incoming, Instant::now() + Duration::from_millis(20)) {
            Ok(0) => continue,
            Ok(_) => {}
            Err(e) => {
                lock(shared).error = Some(e.to_string());
                return;
            }
        }
        let elapsed = started.elapsed();
        let at = elapsed.as_secs_f64();
        let now = SimTime(SimDuration::from_secs_f64(at).0);
        let mut state = lock(shared);
        for &b in &incoming {
            if line.is_empty() {
                line_at = at;
            }
            line.push(b);
            if b == b'\n' || line.len() > 512 {
                let frame = bus_frame(line_at, Way::Received, &line);
                state.frames.push(frame);
                line.clear();
            }
        }
        frontend.handle_bytes(&mut state.image, now, &incoming);
        let mut replies = Vec::new();
        while let Some(n) = frontend.poll_transmit(&mut reply) {
            let bytes = reply.get(..n).unwrap_or_default().to_vec();
            state.frames.push(bus_frame(at, Way::Sent, &bytes));
            replies.push(bytes);
        }
        drop(state);
        for bytes in replies {
            if let Err(e) = wire.send(&bytes) {
                lock(shared).error = Some(e.to_string());
                return;
            }
        }
    }
}

fn lock(shared: &Shared) -> MutexGuard<'_, State> {
    shared.state.lock().unwrap_or_else(PoisonError::into_inner)
}

fn bus_frame(at: f64, way: Way, bytes: &[u8]) -> BusFrame {
    BusFrame {
        at,
        way,
        text: shown(bytes),
        bytes: bytes.to_vec(),
        repr: MebRepr::parse(bytes).ok(),
    }
}
