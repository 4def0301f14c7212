//! Measuring the engine: how many simulated seconds it covers per wall-clock
//! second, with and without the MCAP recording.
//!
//! The engine itself never reads a clock; only this front end does, around
//! whole runs: the wall clock, and the process's CPU time (user and system
//! time of every thread, the recording's writer thread included), which a
//! shared machine disturbs far less than the wall clock.

use protocols::time::{SimDuration, SimTime};
use std::path::{Path, PathBuf};
use std::time::Instant;

use twin_sim::scenario::Scenario;
use twin_sim::virtual_run;

/// Why a run of the bench could not be measured.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Build(#[from] twin_sim::nodes_build::BuildError),
    #[error(transparent)]
    Engine(#[from] twin_sim::engine::EngineError),
    #[error(transparent)]
    Run(#[from] virtual_run::RunError),
    /// Stopped as asked (Ctrl-C) before its end.
    #[error(transparent)]
    Interrupted(#[from] twin_sim::interrupt::Interrupted),
    #[error("cannot read {}", path.display())]
    RecordingSize {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("no run was measured")]
    NoRun,
}

type Result<T, E = BenchError> = std::result::Result<T, E>;

/// The scenarios `twin bench` runs when none is named: the default one-module
/// speed loop and the ten-module bus.
pub const DEFAULT_SCENARIOS: [&str; 2] = ["ev-meb", "ten-modules"];

/// One timed run.
#[derive(Debug, Clone, PartialEq)]
pub struct Measurement {
    /// Simulated seconds covered.
    pub simulated_s: f64,
    /// Wall-clock seconds it took (building the engine included).
    pub wall_s: f64,
    /// CPU seconds the process spent on it, user and system, all threads
    /// (building the engine included; 0 where unknown): with [`best_of`],
    /// the mean of the runs, which blurs the CPU clock's 10 ms ticks.
    pub cpu_s: f64,
    /// Frames sent on all buses.
    pub frames: u64,
    /// Discrete events the engine handled (see [`twin_sim::engine::Engine::events`]);
    /// `None` for a recorded run, which goes through [`virtual_run::run`].
    pub events: Option<u64>,
    /// Size of the recording in bytes, for a recorded run.
    pub recording_bytes: Option<u64>,
}

impl Measurement {
    /// Simulated seconds per wall-clock second.
    pub fn real_time_factor(&self) -> f64 {
        self.simulated_s / self.wall_s.max(1e-9)
    }

    /// CPU milliseconds per simulated second.
    pub fn cpu_ms_per_simulated_s(&self) -> f64 {
        self.cpu_s * 1e3 / self.simulated_s.max(1e-9)
    }
}

/// The CPU time this process has used so far (s): every thread's user and
/// system time, those of threads that have ended included (the recording's
/// writer thread), as `/proc/self/stat` counts them: in clock ticks (10 ms),
/// so a figure needs runs of a second or more to be read to a few per cent.
/// `None` where there is no such file.
pub fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The command name, in parentheses, may hold spaces: count after it.
    let after_name = &stat[stat.rfind(')')? + 1..];
    let mut fields = after_name.split_whitespace();
    // Fields 14 and 15 of the line (utime, stime); `state` is field 3.
    let utime: u64 = fields.nth(11)?.parse().ok()?;
    let stime: u64 = fields.next()?.parse().ok()?;
    let ticks = rustix::param::clock_ticks_per_second().max(1);
    Some((utime + stime) as f64 / ticks as f64)
}

/// Wall-clock and CPU time of what happens between [`Stopwatch::start`]
/// and [`Stopwatch::stop`].
#[derive(Debug, Clone, Copy)]
struct Stopwatch {
    wall: Instant,
    cpu_s: Option<f64>,
}

impl Stopwatch {
    fn start() -> Self {
        Self {
            wall: Instant::now(),
            cpu_s: process_cpu_s(),
        }
    }

    /// Wall-clock and CPU seconds since the start (CPU: 0 where unknown).
    fn stop(self) -> (f64, f64) {
        let wall_s = self.wall.elapsed().as_secs_f64();
        let cpu_s = match (self.cpu_s, process_cpu_s()) {
            (Some(start), Some(end)) => (end - start).max(0.0),
            _ => 0.0,
        };
        (wall_s, cpu_s)
    }
}

/// Run `scenario` without recording: build, run to its end, discard everything.
/// `progress` gets the fraction of the run done (every few thousand events).
pub fn run_discarding(scenario: &Scenario, mut progress: impl FnMut(f64)) -> Result<Measurement> {
    let started = Stopwatch::start();
    let mut engine = virtual_run::build(scenario)?;
    let end = SimTime::ZERO + SimDuration::from_secs_f64(scenario.duration_s);
    engine.run_until(end, &mut twin_sim::engine::DiscardObserver, |t| {
        progress(t.as_secs_f64() / scenario.duration_s)
    })?;
    if engine.interrupted() {
        let at_s = engine.now().as_secs_f64();
        return Err(BenchError::Interrupted(twin_sim::interrupt::Interrupted {
            at_s,
            recording: None,
        }));
    }
    let (wall_s, cpu_s) = started.stop();
    Ok(Measurement {
        simulated_s: engine.now().as_secs_f64(),
        wall_s,
        cpu_s,
        frames: engine.frames_sent,
        events: Some(engine.events),
        recording_bytes: None,
    })
}

/// Run `scenario` as `twin run` does, recording to `out` (left in place);
/// `progress` gets the fraction of the run done.
pub fn run_recording(
    scenario: &Scenario,
    out: &Path,
    progress: impl FnMut(f64),
) -> Result<Measurement> {
    let started = Stopwatch::start();
    let outcome = virtual_run::run(scenario, out, progress)?;
    // The writer thread has ended: its CPU time is the process's.
    let (wall_s, cpu_s) = started.stop();
    let recording_bytes = std::fs::metadata(&outcome.recording)
        .map_err(|source| BenchError::RecordingSize {
            path: outcome.recording.clone(),
            source,
        })?
        .len();
    Ok(Measurement {
        simulated_s: outcome.simulated_s,
        wall_s,
        cpu_s,
        frames: outcome.frames,
        events: None,
        recording_bytes: Some(recording_bytes),
    })
}

/// The fastest of `repeat` runs (at least one): the one least disturbed by
/// whatever else the machine was doing; its CPU time the mean of the runs'
/// (what the work costs, which other processes change far less than the
/// wall clock, read in ticks that a mean blurs).
pub fn best_of<E: From<BenchError>>(
    repeat: u32,
    mut run: impl FnMut() -> Result<Measurement, E>,
) -> Result<Measurement, E> {
    let mut best = Best::default();
    for _ in 0..repeat.max(1) {
        best.add(run()?);
    }
    Ok(best.take()?)
}

/// [`best_of`] for two kinds of run at once, run in turn (`a b a b …`), so
/// that a machine whose speed drifts over the minutes weighs on both alike
/// and their ratio is not the drift's.
pub fn best_of_alternating<E: From<BenchError>>(
    repeat: u32,
    mut a: impl FnMut() -> Result<Measurement, E>,
    mut b: impl FnMut() -> Result<Measurement, E>,
) -> Result<Alternated, E> {
    let (mut best_a, mut best_b) = (Best::default(), Best::default());
    let mut pairs = Vec::new();
    for _ in 0..repeat.max(1) {
        let (ma, mb) = (a()?, b()?);
        pairs.push(PairRatio {
            wall: mb.real_time_factor() / ma.real_time_factor().max(1e-12),
            // Unknown (no `/proc`): left out of the spread.
            cpu: if ma.cpu_s > 0.0 && mb.cpu_s > 0.0 {
                ma.cpu_s / mb.cpu_s
            } else {
                f64::NAN
            },
        });
        best_a.add(ma);
        best_b.add(mb);
    }
    Ok(Alternated {
        a: best_a.take()?,
        b: best_b.take()?,
        pairs,
    })
}

/// What [`best_of_alternating`] measured.
#[derive(Debug, Clone, PartialEq)]
pub struct Alternated {
    /// The fastest run of the first kind, with the mean CPU time of its runs.
    pub a: Measurement,
    /// The same for the second kind.
    pub b: Measurement,
    /// Pair by pair (a run of each kind, one after the other), in order.
    pub pairs: Vec<PairRatio>,
}

/// One pair's second run against its first: how fast it went (simulated
/// seconds per wall-clock second) and how little CPU time it took, each as
/// a ratio where 1 means "as the first".
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairRatio {
    pub wall: f64,
    pub cpu: f64,
}

// Two runs one after the other see much the same machine, so their ratio is
// steadier than the fastest runs': a burst of other work that slows one run
// weighs on one pair, and the median drops it.
impl Alternated {
    /// The median, lowest and highest of the pairs' wall-clock ratios.
    pub fn wall_spread(&self) -> Option<Spread> {
        Spread::of(self.pairs.iter().map(|p| p.wall).collect())
    }

    /// The same of their CPU-time ratios (`None` where CPU time is unknown).
    pub fn cpu_spread(&self) -> Option<Spread> {
        Spread::of(self.pairs.iter().map(|p| p.cpu).collect())
    }
}

/// Median, lowest and highest of some ratios. The median is serve-bench's
/// (`measure::median`: the mean of the two middle values), written again
/// here because that binary's crate builds codecs only and is no library.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    pub median: f64,
    pub low: f64,
    pub high: f64,
}

impl Spread {
    fn of(mut values: Vec<f64>) -> Option<Self> {
        values.retain(|v| v.is_finite());
        values.sort_by(f64::total_cmp);
        let n = values.len();
        let median = match n {
            0 => return None,
            _ if n % 2 == 1 => values[n / 2],
            _ => (values[n / 2 - 1] + values[n / 2]) / 2.0,
        };
        Some(Self {
            median,
            low: values[0],
            high: values[n - 1],
        })
    }
}

/// The fastest run so far and the CPU time of all of them.
#[derive(Default)]
struct Best {
    fastest: Option<Measurement>,
    cpu_s: f64,
    runs: u32,
}

impl Best {
    fn add(&mut self, m: Measurement) {
        self.cpu_s += m.cpu_s;
        self.runs += 1;
        if self.fastest.as_ref().is_none_or(|f| m.wall_s < f.wall_s) {
            self.fastest = Some(m);
        }
    }

    fn take(self) -> Result<Measurement> {
        let mut best = self.fastest.ok_or(BenchError::NoRun)?;
        best.cpu_s = self.cpu_s / f64::from(self.runs.max(1));
        Ok(best)
    }
}

/// A recording path in the temporary folder that no other process uses.
pub fn scratch_recording(scenario: &str) -> PathBuf {
    let stem: String = scenario
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .collect();
    std::env::temp_dir().join(format!("twin-bench-{}-{stem}.mcap", std::process::id()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn short(name: &str, seconds: f64) -> Scenario {
        let mut s = Scenario::load(name).expect("scenario loads");
        s.duration_s = seconds;
        s
    }

    #[test]
    fn ten_modules_is_ten_controllers_polled_by_one_supervisor_at_10_hz() {
        let s = short("ten-modules", 2.0);
        assert_eq!(s.modules.len(), 10);
        assert_eq!(s.buses.len(), 1, "all ten on one bus");
        let mut engine = virtual_run::build(&s).expect("builds");
        assert_eq!(engine.nodes.len(), 11);
        let end = SimTime::ZERO + SimDuration::from_secs_f64(s.duration_s);
        engine
            .run_until(end, &mut twin_sim::engine::DiscardObserver, |_| {})
            .expect("runs");
        let supervisor = engine
            .nodes
            .iter()
            .find(|n| n.name == "supervisor")
            .and_then(|n| n.node.final_state())
            .expect("the supervisor reports its loops");
        // A 100 ms cycle over 2 s: 20 cycles (the last may still be running).
        let cycles = supervisor["cycles"].as_u64().expect("cycles");
        assert!((19..=20).contains(&cycles), "{cycles} cycles in 2 s");
        let loops = supervisor["loops"].as_array().expect("loops");
        assert_eq!(loops.len(), 10);
        for (l, id) in loops.iter().zip(1..) {
            assert_eq!(l["slave"], id);
            // At least the speed read of every cycle was answered; none lost.
            let replies = l["replies"].as_u64().expect("replies");
            assert!(replies >= cycles, "slave {id}: {replies} replies");
            assert_eq!(l["lost"], 0, "slave {id}");
        }
    }

    fn measured(wall_s: f64, cpu_s: f64) -> Measurement {
        Measurement {
            simulated_s: 10.0,
            wall_s,
            cpu_s,
            frames: 0,
            events: None,
            recording_bytes: None,
        }
    }

    #[test]
    fn alternating_runs_take_turns_and_keep_each_kinds_fastest() {
        let order = std::cell::RefCell::new(String::new());
        let walls_a = [3.0, 1.0, 2.0];
        let walls_b = [5.0, 6.0, 4.0];
        let (mut i, mut j) = (0, 0);
        let runs = best_of_alternating::<BenchError>(
            3,
            || {
                order.borrow_mut().push('a');
                i += 1;
                Ok(measured(walls_a[i - 1], 1.0 * i as f64))
            },
            || {
                order.borrow_mut().push('b');
                j += 1;
                Ok(measured(walls_b[j - 1], 2.0))
            },
        )
        .unwrap();
        assert_eq!(order.into_inner(), "ababab");
        assert_eq!((runs.a.wall_s, runs.b.wall_s), (1.0, 4.0));
        // CPU time: the mean of each kind's runs.
        assert_eq!((runs.a.cpu_s, runs.b.cpu_s), (2.0, 2.0));
        // Pair by pair: 3/5, 1/6, 2/4 of the rate; 1/2, 2/2, 3/2 of the CPU.
        let close = |x: f64, y: f64| (x - y).abs() < 1e-12;
        let expected = [(0.6, 0.5), (1.0 / 6.0, 1.0), (0.5, 1.5)];
        assert_eq!(runs.pairs.len(), 3);
        for (p, (wall, cpu)) in runs.pairs.iter().zip(expected) {
            assert!(close(p.wall, wall) && close(p.cpu, cpu), "{p:?}");
        }
        let (wall, cpu) = (runs.wall_spread().unwrap(), runs.cpu_spread().unwrap());
        assert!(close(wall.median, 0.5) && close(wall.low, 1.0 / 6.0) && close(wall.high, 0.6));
        assert!(close(cpu.median, 1.0) && close(cpu.low, 0.5) && close(cpu.high, 1.5));
        let failed = best_of_alternating::<BenchError>(
            2,
            || Ok(measured(1.0, 1.0)),
            || Err(BenchError::NoRun),
        );
        assert!(failed.is_err());
        // No CPU time to read: no CPU spread, the wall clock's still.
        let unknown = best_of_alternating::<BenchError>(
            2,
            || Ok(measured(1.0, 0.0)),
            || Ok(measured(2.0, 0.0)),
        )
        .unwrap();
        assert!(unknown.cpu_spread().is_none());
        assert_eq!(unknown.wall_spread().map(|s| s.median), Some(0.5));
    }

    #[test]
    fn a_spread_of_an_even_count_takes_the_middle_two() {
        let s = Spread::of(vec![0.9, 0.7, f64::NAN, 0.8, 1.0]).unwrap();
        assert!((s.median - 0.85).abs() < 1e-12, "{s:?}");
        assert_eq!((s.low, s.high), (0.7, 1.0));
        assert!(Spread::of(vec![f64::INFINITY]).is_none());
    }

    #[test]
    fn recording_does_not_change_the_run() {
        let s = short("ten-modules", 1.0);
        let discarded = run_discarding(&s, |_| {}).expect("runs");
        let out = scratch_recording("unit-test");
        let recorded = run_recording(&s, &out, |_| {}).expect("runs and records");
        let _ = std::fs::remove_file(&out);
        assert_eq!(discarded.simulated_s, 1.0);
        assert_eq!(recorded.simulated_s, 1.0);
        assert_eq!(discarded.frames, recorded.frames);
        assert!(discarded.frames > 0);
        assert!(discarded.events.is_some_and(|e| e > discarded.frames));
        assert!(recorded.recording_bytes.is_some_and(|b| b > 0));
        assert!(discarded.real_time_factor() > 0.0);
        // The CPU clock reads (its ticks are too coarse for a 1 s run's
        // figure to be more than non-negative).
        assert!(process_cpu_s().is_some_and(|s| s > 0.0));
        assert!(discarded.cpu_s >= 0.0 && recorded.cpu_s >= 0.0);
    }

    #[test]
    fn ten_modules_records_byte_identically_twice() {
        let s = short("ten-modules", 0.5);
        let (a, b) = (scratch_recording("det-a"), scratch_recording("det-b"));
        run_recording(&s, &a, |_| {}).expect("first run");
        run_recording(&s, &b, |_| {}).expect("second run");
        let (x, y) = (std::fs::read(&a), std::fs::read(&b));
        let _ = (std::fs::remove_file(&a), std::fs::remove_file(&b));
        let (x, y) = (x.expect("first recording"), y.expect("second recording"));
        assert!(!x.is_empty());
        assert!(x == y, "same scenario and seed, different bytes");
    }

    #[test]
    fn best_of_keeps_the_fastest_run_and_the_mean_cpu() {
        let mut walls = [0.3, 0.1, 0.2].into_iter();
        let mut cpus = [0.25, 0.15, 0.05].into_iter();
        let best = best_of::<BenchError>(3, || {
            Ok(Measurement {
                simulated_s: 1.0,
                wall_s: walls.next().unwrap_or(1.0),
                cpu_s: cpus.next().unwrap_or(1.0),
                frames: 0,
                events: None,
                recording_bytes: None,
            })
        })
        .expect("measures");
        assert_eq!(best.wall_s, 0.1);
        assert_eq!(best.real_time_factor(), 10.0);
        assert!((best.cpu_s - 0.15).abs() < 1e-12, "{}", best.cpu_s);
        assert!((best.cpu_ms_per_simulated_s() - 150.0).abs() < 1e-9);
    }
}
