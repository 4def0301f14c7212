//! The virtual-time engine with an MEB supervisor closing the EV module's
//! speed loop over the simulated RS-485 bus: bus timing, step tracking, dead
//! time, and byte-identical recordings.
//!
//! Scenarios are built as TOML text, run through `twin_sim::virtual_run::build`
//! and driven with an in-memory observer that keeps every frame, actuator
//! change, plant sample and loop report.

use e2e::{Capture, WireFrame, at, run_captured};
use protocols::meb::{MebCmd, MebRepr};
use protocols::time::{SimDuration, SimTime};
use twin_sim::scenario::Scenario;

/// The supervisor's loop after one poll cycle.
#[derive(Debug, Clone, Copy)]
struct LoopSample {
    at: SimTime,
    set_point_rpm: f64,
    measured_rpm: f64,
}

/// The supervisor's loop reports, one per poll cycle (first slave).
fn loops(capture: &Capture) -> Vec<LoopSample> {
    capture
        .telemetry
        .iter()
        .map(|(at, _, value)| {
            let slave = &value["loops"][0];
            let field = |name: &str| slave[name].as_f64().unwrap_or(f64::NAN);
            LoopSample {
                at: *at,
                set_point_rpm: field("set_point_rpm"),
                measured_rpm: field("measured_rpm"),
            }
        })
        .collect()
}

/// Runs `scenario` (TOML text) to `until_s` seconds and returns what it saw.
fn run(scenario: &str, until_s: f64) -> Capture {
    let scenario = Scenario::parse(scenario, "test scenario").expect("scenario parses");
    run_captured(&scenario, until_s).0
}

/// The default scenario, as `twin` embeds it (read here from the file itself,
/// so this test follows the file even where `twin` was built earlier).
const EV_MEB: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../recordings/scenarios/ev-meb.toml"
));

/// The supervisor's gains in `ev-meb`: every bench here uses the tuning the
/// default scenario ships with.
fn ev_meb_gains() -> (f64, f64) {
    let scenario = Scenario::parse(EV_MEB, "ev-meb.toml").expect("ev-meb parses");
    scenario
        .nodes
        .iter()
        .find_map(|n| match n {
            twin_sim::scenario::NodeSpec::Supervisor { kp, ki, .. } => Some((*kp, *ki)),
            _ => None,
        })
        .expect("ev-meb has a supervisor")
}

/// One module on an MEB bus with a supervisor: the knobs the tests turn.
#[derive(Debug, Clone)]
struct MebBench {
    baud: u32,
    poll_period_ms: f64,
    gap_ms: f64,
    /// `[time_s, rpm]` pairs.
    set_points: Vec<(f64, f64)>,
}

impl MebBench {
    fn toml(&self) -> String {
        let (kp, ki) = ev_meb_gains();
        let set_points: Vec<String> = self
            .set_points
            .iter()
            .map(|(t, rpm)| format!("[{t:?}, {rpm:?}]"))
            .collect();
        format!(
            r#"
name = "meb-test"
seed = 7
duration_s = 60.0

[[module]]
name = "ev1"
preset = "vemodule"

[[bus]]
name = "rs485"
baud = {baud}

[[node]]
kind = "ev-controller"
name = "ev1"
bus = "rs485"
module = "ev1"
id = 1
protocol = "meb"
turnaround_ms = 1.0
loop_period_ms = 1.0

[[node]]
kind = "supervisor"
name = "supervisor"
bus = "rs485"
slaves = [1]
protocol = "meb"
poll_period_ms = {poll:?}
gap_ms = {gap:?}
kp = {kp:?}
ki = {ki:?}
set_points = [{sp}]
"#,
            baud = self.baud,
            poll = self.poll_period_ms,
            gap = self.gap_ms,
            sp = set_points.join(", "),
        )
    }
}

fn meb(frame: &WireFrame) -> Option<MebRepr> {
    MebRepr::parse(&frame.bytes).ok()
}

/// The turnaround every scenario here gives the module's controller.
const TURNAROUND: SimDuration = SimDuration::from_millis(1);
/// The controller's loop period (the scenarios' `loop_period_ms`).
const FIRMWARE_LOOP: SimDuration = SimDuration::from_millis(1);

/// The supervisor's input reads that got their reply: (request, reply).
fn read_exchanges(frames: &[WireFrame]) -> Vec<(&WireFrame, &WireFrame)> {
    frames
        .windows(2)
        .filter_map(|pair| {
            let (request, reply) = (&pair[0], &pair[1]);
            let (q, r) = (meb(request)?, meb(reply)?);
            let is_read = request.from == "supervisor" && q.cmd == MebCmd::EA && q.data.is_empty();
            let answers = reply.from == "ev1" && r.cmd == MebCmd::EA && r.data.len() == 6;
            (is_read && answers).then_some((request, reply))
        })
        .collect()
}

/// A supervisor polling back to back (poll period 0) with set point 0: after
/// the start-up write and one `VEL = 0` write only input reads cross the bus,
/// so each exchange should take exactly (13 + 37 bytes) × 10 / baud plus the
/// 1 ms turnaround plus the gap, and the rate is its inverse.
fn back_to_back_polling_reaches_the_wire_rate(baud: u32, gap_ms: f64, seconds: u32) {
    let bench = MebBench {
        baud,
        poll_period_ms: 0.0,
        gap_ms,
        set_points: vec![(0.0, 0.0)],
    };
    // The first second is start-up; the rate is counted over the rest.
    let settle = 1.0;
    let capture = run(&bench.toml(), settle + f64::from(seconds));
    let after_settling = |f: &WireFrame| f.start >= at(settle);
    let writes = capture
        .frames
        .iter()
        .filter(|f| after_settling(f) && f.from == "supervisor")
        .filter(|f| meb(f).is_none_or(|m| m.cmd != MebCmd::EA))
        .count();
    assert_eq!(writes, 0, "only reads after settling");

    let exchanges: Vec<_> = read_exchanges(&capture.frames)
        .into_iter()
        .filter(|(request, _)| after_settling(request))
        .collect();
    let (request_len, reply_len) = (13usize, 37usize);
    let gap = SimDuration::from_secs_f64(gap_ms / 1000.0);
    let exchange_wire = SimDuration::bit_times(10 * (request_len + reply_len) as u64, baud);
    let period = exchange_wire + TURNAROUND + gap;
    for (request, reply) in &exchanges {
        assert_eq!(
            (request.bytes.len(), reply.bytes.len()),
            (request_len, reply_len)
        );
        // The reply starts one turnaround after the request's last stop bit
        // and the pair occupies the line for exactly the wire time.
        assert_eq!(reply.start - request.end, TURNAROUND, "{baud} baud");
        assert_eq!(reply.end - request.start, exchange_wire + TURNAROUND);
    }
    // Never faster than the wire allows: every request starts at least one
    // full exchange period after the previous one.
    for pair in exchanges.windows(2) {
        let spacing = pair[1].0.start - pair[0].0.start;
        assert!(
            spacing >= period,
            "{baud} baud, gap {gap_ms} ms: requests {} s apart, the exchange needs {} s",
            spacing.as_secs_f64(),
            period.as_secs_f64()
        );
    }
    // And at least 95 % of that rate, counted per simulated second.
    let wire_rate = 1.0 / period.as_secs_f64();
    for second in 0..seconds {
        let from = at(settle + f64::from(second));
        let to = at(settle + f64::from(second + 1));
        let completed = exchanges
            .iter()
            .filter(|(_, reply)| reply.end >= from && reply.end < to)
            .count() as f64;
        assert!(
            completed >= 0.95 * wire_rate && completed <= wire_rate.floor() + 1.0,
            "{baud} baud, gap {gap_ms} ms, second {second}: {completed} exchanges, \
             the wire allows {wire_rate:.2}/s"
        );
    }
}

#[test]
fn back_to_back_polling_at_115200_baud_reaches_the_wire_rate() {
    // 50 bytes take 4.340 ms at 115200 baud: 187.3 exchanges/s with no gap.
    back_to_back_polling_reaches_the_wire_rate(115_200, 0.0, 3);
    back_to_back_polling_reaches_the_wire_rate(115_200, 2.0, 3);
}

#[test]
fn back_to_back_polling_at_9600_baud_reaches_the_wire_rate() {
    // 50 bytes take 52.08 ms at 9600 baud: 18.84 exchanges/s with no gap.
    back_to_back_polling_reaches_the_wire_rate(9_600, 0.0, 5);
    back_to_back_polling_reaches_the_wire_rate(9_600, 5.0, 5);
}

/// The supervisor's set-point schedule in a scenario.
fn schedule(scenario: &Scenario) -> Vec<[f64; 2]> {
    scenario
        .nodes
        .iter()
        .find_map(|n| match n {
            twin_sim::scenario::NodeSpec::Supervisor { set_points, .. } => Some(set_points.clone()),
            _ => None,
        })
        .expect("the scenario has a supervisor")
}

#[test]
fn embedded_ev_meb_loop_tracks_its_set_point_steps_within_2_percent() {
    let scenario = Scenario::parse(EV_MEB, "ev-meb.toml").expect("ev-meb parses");
    let steps = schedule(&scenario);
    let capture = run(EV_MEB, scenario.duration_s);
    let mut checked = 0;
    for (i, &[from_s, rpm]) in steps.iter().enumerate() {
        let until_s = steps.get(i + 1).map_or(scenario.duration_s, |next| next[0]);
        if rpm <= 0.0 {
            continue;
        }
        // Settled: from 2 s after the step (it settles in about 0.8 s) to the next.
        let settled_from = from_s + 2.0;
        assert!(
            until_s - settled_from >= 1.0,
            "step at {from_s} s is too short to judge"
        );
        let in_step = |t: SimTime| t >= at(from_s) && t < at(until_s);
        let settled = |t: SimTime| t >= at(settled_from) && t < at(until_s);
        let mut worst_true = 0.0f64;
        let mut peak = 0.0f64;
        for (t, sensors) in &capture.plant {
            if in_step(*t) {
                peak = peak.max(sensors.wheel_rpm);
            }
            if settled(*t) {
                worst_true = worst_true.max((sensors.wheel_rpm - rpm).abs() / rpm);
            }
        }
        let mut worst_measured = 0.0f64;
        let mut cycles = 0;
        for l in loops(&capture).iter().filter(|l| settled(l.at)) {
            assert_eq!(
                l.set_point_rpm, rpm,
                "the schedule's set point at {:?}",
                l.at
            );
            worst_measured = worst_measured.max((l.measured_rpm - rpm).abs() / rpm);
            cycles += 1;
        }
        assert!(cycles > 50, "{cycles} poll cycles while settled");
        assert!(
            worst_true < 0.02,
            "step to {rpm} rpm: true wheel speed off by {:.2} %",
            100.0 * worst_true
        );
        assert!(
            worst_measured < 0.02,
            "step to {rpm} rpm: measured speed off by {:.2} %",
            100.0 * worst_measured
        );
        // The tuning claims no real overshoot; a stiffer loop overshoots ~20 %.
        assert!(
            peak < 1.05 * rpm,
            "step to {rpm} rpm peaked at {peak:.0} rpm"
        );
        checked += 1;
    }
    assert!(
        checked >= 2,
        "ev-meb has {checked} set-point steps to judge"
    );
}

/// Set-point steps at random phases of the poll cycle and the dead time of
/// each: from the step to the first change of `vel_volts` at the plant's
/// input that the step caused.
///
/// The supervisor's cycle: a cycle starts every poll period `P` (none
/// overruns here), its input read completes one exchange time `E` later at
/// `r_k`, the PI runs on that reply with the set point scheduled at `r_k`, and
/// the changed `VEL` goes out after the gap `G` and lands in the controller's
/// image when the write request's last stop bit arrives, `W` after it started.
/// The controller applies the image at its next loop tick, within its loop
/// period `L` (at once if the tick falls on that very instant: the engine
/// delivers bytes before it ticks firmware). A step at `s` in `(r_k, r_{k+1}]`
/// is seen at `r_{k+1} = r_k + P`, so
///
/// `G + W <= dead time < P + G + W + L`
///
/// which is inside the required bound (one poll period + gap + the write's wire
/// time and turnaround + one firmware loop period; the read's own exchange
/// time `E` does not add, because the set point is sampled when the reply
/// arrives, not when the request leaves). Over phases uniform in the cycle
/// the mean is `P/2 + G + W + c`, `c` in `[0, L)` fixed by where the cycle
/// falls on the firmware's tick grid.
fn step_dead_times(poll_ms: f64, steps: usize, seed: u64) -> (Vec<SimDuration>, SimDuration) {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let (low, high) = (1000.0, 2000.0);
    // Steps 2 s apart (a multiple of every poll period here), each at a
    // random phase: jittered strata over one 50 ms span, so both poll periods
    // see phases spread evenly over their cycle.
    let step_times: Vec<f64> = (0..steps)
        .map(|i| {
            let stratum = (i as f64 + rng.random::<f64>()) / steps as f64;
            2.0 + 2.0 * i as f64 + 0.05 * stratum
        })
        .collect();
    let mut set_points = vec![(0.0, low)];
    for (i, &t) in step_times.iter().enumerate() {
        set_points.push((t, if i % 2 == 0 { high } else { low }));
    }
    let gap_ms = 0.25;
    let bench = MebBench {
        baud: 115_200,
        poll_period_ms: poll_ms,
        gap_ms,
        set_points,
    };
    let end = step_times.last().copied().unwrap_or(0.0) + 1.0;
    let capture = run(&bench.toml(), end);

    let write_len = capture
        .frames
        .iter()
        .filter(|f| f.from == "supervisor" && meb(f).is_some_and(|m| m.cmd == MebCmd::SA))
        .map(|f| f.bytes.len())
        .max()
        .expect("VEL writes");
    assert_eq!(write_len, 17, "an SA write of one word is 17 bytes");
    let write_wire = SimDuration::bit_times(10 * 17, 115_200);
    let poll = SimDuration::from_secs_f64(poll_ms / 1000.0);
    let gap = SimDuration::from_secs_f64(gap_ms / 1000.0);
    let bound = poll + gap + write_wire + FIRMWARE_LOOP;
    let floor = gap + write_wire;

    // The step moves VEL by kp × 1000 rpm (450 counts) at once; nothing else
    // moves it by half that between two writes (the integral adds at most
    // ki × 1000 rpm × P, 125 counts at 50 ms).
    let (kp, _) = ev_meb_gains();
    let jump_volts = 0.5 * kp * (high - low) * 5.0 / 4095.0;
    let mut dead_times = Vec::with_capacity(steps);
    for (i, &t) in step_times.iter().enumerate() {
        let step = at(t);
        let upward = i % 2 == 0;
        let mut before = capture
            .actuators
            .iter()
            .take_while(|(when, _)| *when < step)
            .last()
            .map_or(0.0, |(_, a)| a.vel_volts);
        let caused = capture
            .actuators
            .iter()
            .skip_while(|(when, _)| *when < step)
            .find(|(_, a)| {
                let change = a.vel_volts - before;
                before = a.vel_volts;
                let toward_step = if upward { change } else { -change };
                toward_step >= jump_volts
            })
            .map(|(when, _)| *when)
            .unwrap_or_else(|| panic!("no VEL jump after the step at {t} s"));
        let dead = caused - step;
        assert!(
            dead >= floor && dead < bound,
            "poll {poll_ms} ms, step at {t:.4} s: dead time {:.3} ms outside [{:.3}, {:.3}) ms",
            dead.as_secs_f64() * 1e3,
            floor.as_secs_f64() * 1e3,
            bound.as_secs_f64() * 1e3
        );
        dead_times.push(dead);
    }
    (dead_times, floor)
}

fn mean_ms(durations: &[SimDuration]) -> f64 {
    let sum: f64 = durations.iter().map(|d| d.as_secs_f64()).sum();
    1e3 * sum / durations.len() as f64
}

#[test]
fn dead_time_stays_within_one_poll_cycle_and_its_mean_grows_by_half_the_period() {
    let steps = 40;
    let (fast, floor) = step_dead_times(10.0, steps, 0x5eed);
    let (slow, _) = step_dead_times(50.0, steps, 0x5eed);
    let (fast_mean, slow_mean) = (mean_ms(&fast), mean_ms(&slow));
    let worst = |d: &[SimDuration]| d.iter().max().map_or(0.0, |d| d.as_secs_f64() * 1e3);
    println!(
        "dead time: mean {fast_mean:.3} ms (worst {:.3}) at 10 ms, {slow_mean:.3} ms (worst {:.3}) at 50 ms",
        worst(&fast),
        worst(&slow)
    );
    // The mean is P/2 + G + W + c with c in [0, 1 ms).
    let floor_ms = floor.as_secs_f64() * 1e3;
    for (poll_ms, mean) in [(10.0, fast_mean), (50.0, slow_mean)] {
        let expected = poll_ms / 2.0 + floor_ms;
        assert!(
            mean > expected - 1.0 && mean < expected + 2.0,
            "poll {poll_ms} ms: mean dead time {mean:.3} ms, expected {expected:.3} ms + up to 1 ms"
        );
    }
    // 40 ms more poll period, half of it more dead time on average.
    let growth = slow_mean - fast_mean;
    assert!(
        (growth - 20.0).abs() <= 0.25 * 20.0,
        "mean dead time {fast_mean:.3} ms at 10 ms, {slow_mean:.3} ms at 50 ms"
    );
    // The worst case reaches well into the cycle: the bound is not slack.
    let worst_slow = worst(&slow);
    assert!(
        worst_slow > 0.9 * 50.0,
        "worst dead time {worst_slow:.3} ms at 50 ms"
    );
}

/// Runs `scenario` through `twin_sim::virtual_run::run` and returns the bytes of
/// its recording (the file is removed again) and the frames corrupted on the
/// way.
fn recording_bytes(scenario: &Scenario, name: &str) -> (Vec<u8>, u64) {
    let path = std::env::temp_dir().join(format!(
        "e2e-engine-loop-{}-{name}.mcap",
        std::process::id()
    ));
    let outcome = twin_sim::virtual_run::run(scenario, &path, |_| {}).expect("run records");
    assert!(outcome.frames > 0, "{name}: frames were recorded");
    let bytes = std::fs::read(&outcome.recording).expect("recording readable");
    std::fs::remove_file(&outcome.recording).expect("recording removed");
    let corrupted = outcome.buses.iter().map(|b| b.2.frames_corrupted).sum();
    (bytes, corrupted)
}

#[test]
fn same_scenario_and_seed_give_byte_identical_recordings() {
    let mut quiet = Scenario::load("ev-meb").expect("embedded ev-meb");
    quiet.duration_s = 2.0;
    let (first, clean) = recording_bytes(&quiet, "quiet-1");
    let (second, _) = recording_bytes(&quiet, "quiet-2");
    assert_eq!(clean, 0, "no noise, no corrupted frames");
    assert!(
        first.len() > 10_000,
        "a 2 s run records {} bytes",
        first.len()
    );
    assert!(first == second, "two runs of one scenario and seed differ");

    let mut noisy = quiet.clone();
    noisy.seed = 2;
    for bus in &mut noisy.buses {
        bus.bit_error_rate = 1e-3;
    }
    let (third, corrupted) = recording_bytes(&noisy, "noisy-1");
    let (fourth, _) = recording_bytes(&noisy, "noisy-2");
    assert!(
        corrupted > 0,
        "bit errors at 1e-3 corrupt some frames in 2 s"
    );
    assert!(
        third == fourth,
        "bit errors are seeded: the noisy run repeats too"
    );
    assert!(
        third != first,
        "another seed with bit errors gives another recording"
    );
}
