//! A simavr core that may run ahead on a thread of its own.
//!
//! The engine tells a firmware node how far it may compute without an input
//! from outside (its run-ahead horizon); the node queues that cycle target
//! here, and a long-lived thread runs the core to each queued target in
//! turn while the engine goes on with the rest of the bench (the other
//! firmware node, the plant, the master). Any other use of the core first
//! waits until every queued target is reached. The targets, and so the
//! points where simavr's run is split, are the engine's choice and never the
//! scheduler's: run with a thread or inline, the core executes the same
//! instructions to the same cycles, and the recording is the same to the byte.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;

use crate::ffi::{Core, State};

/// Targets queued before the engine waits for the thread to catch up.
const MAX_QUEUED: usize = 64;
/// A target this close to the last is not worth a hand-over (25 µs at 16 MHz).
const MIN_STEP_CYCLES: u64 = 400;

static INLINE: AtomicBool = AtomicBool::new(false);

/// Whether firmware nodes built from now on run ahead on threads of their
/// own (the default) or all on the engine's thread. The run is the same to
/// the byte either way; one thread is for measuring what the others buy.
pub fn set_threaded(threaded: bool) {
    INLINE.store(!threaded, Ordering::Relaxed);
}

/// See [`set_threaded`].
pub fn threaded() -> bool {
    !INLINE.load(Ordering::Relaxed)
}

#[derive(Debug, Default)]
struct Queue {
    targets: VecDeque<u64>,
    stop: bool,
    /// simavr's last log line when the thread saw the core crash (simavr
    /// keeps it per thread).
    log: Option<String>,
}

#[derive(Debug)]
struct Shared {
    core: Mutex<Core>,
    queue: Mutex<Queue>,
    changed: Condvar,
}

/// A core, stepped inline or by its own thread.
#[derive(Debug)]
pub struct Stepper {
    shared: Arc<Shared>,
    worker: Option<JoinHandle<()>>,
    threaded: bool,
    name: String,
    /// The last target queued.
    ahead: u64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic on the other side leaves the core as it was: go on with it.
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Stepper {
    /// `threaded`: whether run-ahead targets go to a thread (else they run
    /// at once, on the caller's).
    pub fn new(core: Core, threaded: bool, name: &str) -> Self {
        Self {
            shared: Arc::new(Shared {
                core: Mutex::new(core),
                queue: Mutex::new(Queue {
                    targets: VecDeque::with_capacity(MAX_QUEUED),
                    ..Queue::default()
                }),
                changed: Condvar::new(),
            }),
            worker: None,
            threaded,
            name: name.into(),
            ahead: 0,
        }
    }

    /// The core, once every queued target is reached.
    fn core(&self) -> MutexGuard<'_, Core> {
        if self.worker.is_some() {
            let mut q = lock(&self.shared.queue);
            while !q.targets.is_empty() {
                q = self
                    .shared
                    .changed
                    .wait(q)
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
            }
        }
        lock(&self.shared.core)
    }

    /// Runs the core to `target` cycles, after all it was given to reach
    /// before, as soon as it can: on its thread, or here.
    pub fn run_ahead(&mut self, target: u64) {
        if target < self.ahead + MIN_STEP_CYCLES {
            return;
        }
        self.ahead = target;
        if !self.threaded {
            self.core().run_until(target);
            return;
        }
        if self.worker.is_none() && !self.spawn() {
            self.threaded = false;
            self.core().run_until(target);
            return;
        }
        let mut q = lock(&self.shared.queue);
        while q.targets.len() >= MAX_QUEUED {
            q = self
                .shared
                .changed
                .wait(q)
                .unwrap_or_else(std::sync::PoisonError::into_inner);
        }
        q.targets.push_back(target);
        drop(q);
        self.shared.changed.notify_all();
    }

    fn spawn(&mut self) -> bool {
        let shared = Arc::clone(&self.shared);
        let worker = std::thread::Builder::new()
            .name(format!("avr {}", self.name))
            .spawn(move || work(&shared));
        self.worker = worker.ok();
        self.worker.is_some()
    }

    pub fn run_until(&mut self, target: u64) -> State {
        self.ahead = self.ahead.max(target);
        self.core().run_until(target)
    }
    pub fn cycle(&self) -> u64 {
        self.core().cycle()
    }
    pub fn pc(&self) -> u32 {
        self.core().pc()
    }
    pub fn data(&self, addr: u16) -> u8 {
        self.core().data(addr)
    }
    pub fn uart_input(&mut self, byte: u8) {
        self.core().uart_input(byte);
    }
    pub fn uart_output(&mut self) -> Option<(u8, u64)> {
        self.core().uart_output()
    }
    pub fn adc(&mut self, channel: u8, millivolts: u32) {
        self.core().adc(channel, millivolts);
    }
    pub fn pin_input(&mut self, pin: u8, high: bool) {
        self.core().pin_input(pin, high);
    }
    pub fn pin_output(&self, pin: u8) -> (bool, u64, u64) {
        self.core().pin_output(pin)
    }
    pub fn watch(&mut self, pins: u32) {
        self.core().watch(pins);
    }
    pub fn edge(&mut self) -> Option<(u64, u8, bool)> {
        self.core().edge()
    }
    pub fn edges_dropped(&self) -> u32 {
        self.core().edges_dropped()
    }
    pub fn gdb(&mut self, port: u16) -> bool {
        self.core().gdb(port)
    }
    /// simavr's last warning or error, from whichever thread ran the core.
    pub fn last_log(&self) -> String {
        drop(self.core());
        lock(&self.shared.queue)
            .log
            .clone()
            .unwrap_or_else(Core::last_log)
    }
}

/// The thread: each queued target in turn, until told to stop.
fn work(shared: &Shared) {
    loop {
        let target = {
            let mut q = lock(&shared.queue);
            loop {
                if q.stop {
                    return;
                }
                if let Some(&t) = q.targets.front() {
                    break t;
                }
                q = shared
                    .changed
                    .wait(q)
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
            }
        };
        let state = lock(&shared.core).run_until(target);
        let mut q = lock(&shared.queue);
        if state == State::Crashed && q.log.is_none() {
            q.log = Some(Core::last_log());
        }
        q.targets.pop_front();
        drop(q);
        shared.changed.notify_all();
    }
}

impl Drop for Stepper {
    fn drop(&mut self) {
        if let Some(worker) = self.worker.take() {
            lock(&self.shared.queue).stop = true;
            self.shared.changed.notify_all();
            let _ = worker.join();
        }
    }
}
