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
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;

use crate::ffi::{Core, State};

/// Targets queued before the engine waits for the thread to catch up.
const MAX_QUEUED: usize = 64;
/// A target this close to the last is not worth a hand-over (25 µs at 16 MHz).
const MIN_STEP_CYCLES: u64 = 400;
/// How long the engine spins on a core that is about to reach its target
/// before it sleeps on the condition variable: waking a sleeping thread costs
/// tens of microseconds here, about what the core's last stretch takes.
const SPIN_ROUNDS: u32 = 2_000;

/// How firmware cores are run (see [`set_mode`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// A core runs ahead on a thread of its own (the default).
    Threaded,
    /// A core runs ahead to the same targets, on the engine's thread.
    OneThread,
    /// A core never runs ahead: it is run only when the engine hands the
    /// node an input. The reference the horizons are checked against.
    NoRunAhead,
}

static MODE: AtomicU8 = AtomicU8::new(0);

/// How firmware nodes built from now on run their cores. The run is the
/// same to the byte in every mode; the others are for measuring what the
/// threads buy and for checking that no core ever ran past an input.
pub fn set_mode(mode: Mode) {
    MODE.store(mode as u8, Ordering::Relaxed);
}

/// See [`set_mode`].
pub fn mode() -> Mode {
    match MODE.load(Ordering::Relaxed) {
        1 => Mode::OneThread,
        2 => Mode::NoRunAhead,
        _ => Mode::Threaded,
    }
}

/// Whether firmware nodes built from now on run ahead on threads of their
/// own (the default) or all on the engine's thread.
pub fn set_threaded(threaded: bool) {
    set_mode(if threaded {
        Mode::Threaded
    } else {
        Mode::OneThread
    });
}

/// See [`set_threaded`].
pub fn threaded() -> bool {
    mode() == Mode::Threaded
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
    /// Targets queued and not yet reached, readable without the lock.
    queued: AtomicUsize,
    /// Who sleeps on `changed` (set under the queue's lock): a notify is a
    /// system call, made only when someone is there to wake.
    worker_asleep: AtomicBool,
    engine_waits: AtomicBool,
}

/// A core, stepped inline or by its own thread.
#[derive(Debug)]
pub struct Stepper {
    shared: Arc<Shared>,
    worker: Option<JoinHandle<()>>,
    mode: Mode,
    name: String,
    /// The last target queued.
    ahead: u64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic on the other side leaves the core as it was: go on with it.
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Stepper {
    /// `mode`: where run-ahead targets go (a thread, the caller's, nowhere).
    pub fn new(core: Core, mode: Mode, name: &str) -> Self {
        Self {
            shared: Arc::new(Shared {
                core: Mutex::new(core),
                queue: Mutex::new(Queue {
                    targets: VecDeque::with_capacity(MAX_QUEUED),
                    ..Queue::default()
                }),
                changed: Condvar::new(),
                queued: AtomicUsize::new(0),
                worker_asleep: AtomicBool::new(false),
                engine_waits: AtomicBool::new(false),
            }),
            worker: None,
            mode,
            name: name.into(),
            ahead: 0,
        }
    }

    /// The core, once every queued target is reached.
    fn core(&self) -> MutexGuard<'_, Core> {
        if self.worker.is_some() && self.shared.queued.load(Ordering::Acquire) > 0 {
            self.wait_reached();
        }
        lock(&self.shared.core)
    }

    fn wait_reached(&self) {
        for _ in 0..SPIN_ROUNDS {
            if self.shared.queued.load(Ordering::Acquire) == 0 {
                return;
            }
            std::hint::spin_loop();
        }
        let mut q = lock(&self.shared.queue);
        while !q.targets.is_empty() {
            q = self.sleep(q);
        }
    }

    /// The engine's side: sleeps until the thread says something changed.
    fn sleep<'a>(&'a self, q: MutexGuard<'a, Queue>) -> MutexGuard<'a, Queue> {
        self.shared.engine_waits.store(true, Ordering::Relaxed);
        let q = self
            .shared
            .changed
            .wait(q)
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        self.shared.engine_waits.store(false, Ordering::Relaxed);
        q
    }

    /// Runs the core to `target` cycles, after all it was given to reach
    /// before, as soon as it can: on its thread, or here.
    pub fn run_ahead(&mut self, target: u64) {
        if self.mode == Mode::NoRunAhead || target < self.ahead + MIN_STEP_CYCLES {
            return;
        }
        self.ahead = target;
        if self.mode == Mode::OneThread {
            self.core().run_until(target);
            return;
        }
        if self.worker.is_none() && !self.spawn() {
            self.mode = Mode::OneThread;
            self.core().run_until(target);
            return;
        }
        let mut q = lock(&self.shared.queue);
        while q.targets.len() >= MAX_QUEUED {
            q = self.sleep(q);
        }
        q.targets.push_back(target);
        self.shared.queued.fetch_add(1, Ordering::Release);
        let wake = self.shared.worker_asleep.load(Ordering::Relaxed);
        drop(q);
        // A running thread finds the target when it finishes the one it has.
        if wake {
            self.shared.changed.notify_all();
        }
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
                shared.worker_asleep.store(true, Ordering::Relaxed);
                q = shared
                    .changed
                    .wait(q)
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
                shared.worker_asleep.store(false, Ordering::Relaxed);
            }
        };
        let state = lock(&shared.core).run_until(target);
        let mut q = lock(&shared.queue);
        if state == State::Crashed && q.log.is_none() {
            q.log = Some(Core::last_log());
        }
        q.targets.pop_front();
        shared.queued.fetch_sub(1, Ordering::Release);
        let wake = shared.engine_waits.load(Ordering::Relaxed);
        drop(q);
        if wake {
            shared.changed.notify_all();
        }
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
