//! The numbers of a scenario held to what a bench can have: a run of 1e308
//! seconds, a poll period of 0 or infinity, a NaN set-point time or two
//! slaves answering to one id would run (or never end) and mean nothing.
//! Every range says in its error why it is what it is. Errors name the field
//! as `field@owner` (the field after the line naming its node), as
//! [`Scenario::parse`] reports them with file and line.

use std::collections::BTreeMap;

use super::{NodeSpec, Scenario};

/// The longest simulated run: a day of bench time (about 5 GB of
/// recording for one module). Longer studies are several runs.
pub const MAX_DURATION_S: f64 = 86_400.0;

/// A field's error: the field (`field@owner` for a node's), and what is wrong.
type Fault = (String, String);

/// An inclusive range of a number, with what it stands for in the lab.
struct Range {
    low: f64,
    high: f64,
    /// Whether `low` itself is allowed (0 ms of turnaround is; a 0 ms
    /// poll period is not).
    low_allowed: bool,
    why: &'static str,
}

const fn range(low: f64, high: f64, low_allowed: bool, why: &'static str) -> Range {
    Range {
        low,
        high,
        low_allowed,
        why,
    }
}

const DURATION: Range = range(0.0, MAX_DURATION_S, false, "a simulated day at most");
const PLANT_STEP: Range = range(1e-6, 0.01, true, "the motor's currents need 10 ms or less");
const RECORD_HZ: Range = range(0.0, 100_000.0, false, "samples per simulated second");
const TURNAROUND_MS: Range = range(0.0, 1000.0, true, "a board answers within a second");
const LOOP_MS: Range = range(0.0, 1000.0, false, "a firmware loop period");
const PERIOD_MS: Range = range(0.0, 60_000.0, false, "a minute at most");
/// 0 polls back to back, as fast as the wire allows.
const POLL_MS: Range = range(0.0, 60_000.0, true, "0 for back to back, a minute at most");
const GAP_MS: Range = range(0.0, 60_000.0, true, "a minute at most");
const DELAY_MS: Range = range(0.0, 60_000.0, true, "a minute at most");
const GAIN: Range = range(-1e6, 1e6, true, "a PI gain");
const RPM: Range = range(-100_000.0, 100_000.0, true, "far beyond any bench motor");
const START_S: Range = range(0.0, MAX_DURATION_S, true, "within the run");
// A board that takes longer to start is not booting: it is broken.
const BOOT_MS: Range = range(0.0, 60_000.0, true, "at most a minute");
const RETRIES: u32 = 100;

impl Range {
    fn check(&self, v: f64) -> Result<(), String> {
        let above_low = if self.low_allowed {
            v >= self.low
        } else {
            v > self.low
        };
        if v.is_finite() && above_low && v <= self.high {
            return Ok(());
        }
        let low = if self.low_allowed { "from" } else { "above" };
        Err(format!(
            "must be {low} {} up to {} ({}), got {}",
            self.low,
            self.high,
            self.why,
            shown(v)
        ))
    }
}

/// A number as a user would write it in TOML: `1e308` rather than its 309
/// digits, `nan` and `inf` as TOML spells them.
pub fn shown(v: f64) -> String {
    if v.is_nan() {
        "nan".into()
    } else if v.is_infinite() {
        if v > 0.0 { "inf" } else { "-inf" }.into()
    } else if v != 0.0 && !(1e-4..1e9).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        v.to_string()
    }
}

/// Check the scenario's numbers and slave ids.
pub fn check(s: &Scenario) -> Result<(), Fault> {
    let top = |field: &str, r: &Range, v: f64| r.check(v).map_err(|m| (field.to_string(), m));
    top("duration_s", &DURATION, s.duration_s)?;
    top("plant_step_s", &PLANT_STEP, s.plant_step_s)?;
    top("record_hz", &RECORD_HZ, s.record_hz)?;
    for b in &s.buses {
        if !(7..=12).contains(&b.bits_per_char) {
            return Err((
                format!("bits_per_char@{}", b.name),
                format!(
                    "of bus `{}` must be 7 to 12 (10 for 8N1, 11 for 8E1 or 8N2), got {}",
                    b.name, b.bits_per_char
                ),
            ));
        }
    }
    for n in &s.nodes {
        node(n)?;
    }
    for f in &s.faults {
        for (field, v) in [("from_s", f.from_s), ("until_s", f.until_s)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err((
                    field.to_string(),
                    format!(
                        "of the fault on `{}` must be a time from 0 s, got {}",
                        f.node,
                        shown(v)
                    ),
                ));
            }
        }
        DELAY_MS
            .check(f.delay_ms)
            .map_err(|m| ("delay_ms".to_string(), m))?;
    }
    one_slave_per_id(s)
}

/// A node's periods, timeouts, gains and set points.
fn node(n: &NodeSpec) -> Result<(), Fault> {
    let name = n.name();
    let at = |field: &str, r: &Range, v: f64| {
        r.check(v)
            .map_err(|m| (format!("{field}@{name}"), format!("of node `{name}` {m}")))
    };
    match n {
        NodeSpec::EvController {
            turnaround_ms,
            loop_period_ms,
            ..
        } => {
            at("turnaround_ms", &TURNAROUND_MS, *turnaround_ms)?;
            at("loop_period_ms", &LOOP_MS, *loop_period_ms)?;
        }
        NodeSpec::MotorNode { turnaround_ms, .. } | NodeSpec::LightNode { turnaround_ms, .. } => {
            at("turnaround_ms", &TURNAROUND_MS, *turnaround_ms)?;
        }
        NodeSpec::Supervisor {
            poll_period_ms,
            gap_ms,
            reply_timeout_ms,
            retries,
            kp,
            ki,
            set_points,
            ..
        } => {
            at("poll_period_ms", &POLL_MS, *poll_period_ms)?;
            at("gap_ms", &GAP_MS, *gap_ms)?;
            at("reply_timeout_ms", &PERIOD_MS, *reply_timeout_ms)?;
            at("kp", &GAIN, *kp)?;
            at("ki", &GAIN, *ki)?;
            check_retries(name, *retries)?;
            check_set_points(name, set_points)?;
        }
        NodeSpec::ControllerNetworkMaster {
            reply_timeout_ms,
            start_s,
            ..
        } => {
            if let Some(t) = reply_timeout_ms {
                at("reply_timeout_ms", &PERIOD_MS, *t)?;
            }
            if let Some(t) = start_s {
                at("start_s", &START_S, *t)?;
            }
        }
        NodeSpec::ParallelMaster {
            update_period_ms,
            reply_timeout_ms,
            retries,
            kp,
            ki,
            set_points,
            loop_period_ms,
            turnaround_ms,
            ..
        } => {
            at("update_period_ms", &PERIOD_MS, *update_period_ms)?;
            at("reply_timeout_ms", &PERIOD_MS, *reply_timeout_ms)?;
            at("kp", &GAIN, *kp)?;
            at("ki", &GAIN, *ki)?;
            at("loop_period_ms", &LOOP_MS, *loop_period_ms)?;
            at("turnaround_ms", &TURNAROUND_MS, *turnaround_ms)?;
            check_retries(name, *retries)?;
            check_set_points(name, set_points)?;
        }
        NodeSpec::PwmSlave {
            loop_period_ms,
            turnaround_ms,
            ..
        } => {
            at("loop_period_ms", &LOOP_MS, *loop_period_ms)?;
            at("turnaround_ms", &TURNAROUND_MS, *turnaround_ms)?;
        }
        // The firmware's own file, map and clock are checked where it is
        // loaded, which names the file and the field.
        NodeSpec::Firmware { boot_ms, .. } => at("boot_ms", &BOOT_MS, *boot_ms)?,
    }
    Ok(())
}

fn check_retries(name: &str, retries: u32) -> Result<(), Fault> {
    if retries > RETRIES {
        return Err((
            format!("retries@{name}"),
            format!("of node `{name}` must be 0 to {RETRIES}, got {retries}"),
        ));
    }
    Ok(())
}

/// `[time_s, rpm]` pairs: times from 0 s in order, speeds a motor can mean.
fn check_set_points(name: &str, set_points: &[[f64; 2]]) -> Result<(), Fault> {
    let field = format!("set_points@{name}");
    let mut previous = 0.0;
    for (i, [time_s, rpm]) in set_points.iter().copied().enumerate() {
        let which = format!(
            "of node `{name}`: set point {} ([{}, {}])",
            i + 1,
            shown(time_s),
            shown(rpm)
        );
        if !(time_s.is_finite() && time_s >= previous) {
            return Err((
                field,
                format!(
                    "{which} has a time that is not a number of seconds from 0 after the one before"
                ),
            ));
        }
        if let Err(m) = RPM.check(rpm) {
            return Err((field, format!("{which}: its rpm {m}")));
        }
        previous = time_s;
    }
    Ok(())
}

/// Two slaves answering to one id on one bus both reply to every request
/// for it and collide: the bench's wiring would never be set up so.
fn one_slave_per_id(s: &Scenario) -> Result<(), Fault> {
    let mut seen: BTreeMap<(&str, u8), &str> = BTreeMap::new();
    for n in &s.nodes {
        let id = match n {
            NodeSpec::EvController { id, .. } | NodeSpec::PwmSlave { id, .. } => *id,
            // The Controller_network firmware's fixed addresses.
            NodeSpec::MotorNode { .. } => 1,
            NodeSpec::LightNode { .. } => 2,
            _ => continue,
        };
        if let Some(first) = seen.insert((n.bus(), id), n.name()) {
            return Err((
                format!("id@{}", n.name()),
                format!(
                    "{id} of node `{}` is already the id of `{first}` on bus `{}`: each slave on a bus needs its own",
                    n.name(),
                    n.bus()
                ),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use crate::scenario::Scenario;

    /// A bench with a controller and a supervisor; `{…}` lines are swapped.
    const BENCH: &str = r#"name = "x"
duration_s = 5.0

[[module]]
name = "m"

[[bus]]
name = "b"

[[node]]
kind = "ev-controller"
name = "ctl"
bus = "b"
module = "m"
turnaround_ms = 1.0

[[node]]
kind = "supervisor"
name = "sup"
bus = "b"
slaves = [1]
poll_period_ms = 10.0
kp = 0.4
ki = 1.0
set_points = [[0.0, 0.0], [0.5, 1500.0]]
"#;

    fn error_of(from: &str, to: &str) -> String {
        assert!(BENCH.contains(from), "{from}");
        let text = BENCH.replace(from, to);
        match Scenario::parse(&text, "bench.toml") {
            Ok(_) => panic!("`{to}` was taken"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn the_bench_itself_is_taken() {
        Scenario::parse(BENCH, "bench.toml").expect("a sound bench");
    }

    #[test]
    fn numbers_no_bench_can_have_are_refused_with_line_and_field() {
        for (from, to, line, said) in [
            (
                "duration_s = 5.0",
                "duration_s = 1e308",
                2,
                "`duration_s` must be above 0 up to 86400 (a simulated day at most), got 1e308",
            ),
            ("duration_s = 5.0", "duration_s = nan", 2, "got nan"),
            (
                "duration_s = 5.0",
                "duration_s = 0.0",
                2,
                "`duration_s` must be above 0",
            ),
            (
                "poll_period_ms = 10.0",
                "poll_period_ms = inf",
                22,
                "`poll_period_ms` of node `sup` must be from 0 up to 60000 (0 for back to back, a minute at most), got inf",
            ),
            (
                "poll_period_ms = 10.0",
                "poll_period_ms = -1.0",
                22,
                "`poll_period_ms` of node `sup`",
            ),
            (
                "turnaround_ms = 1.0",
                "turnaround_ms = 1e308",
                15,
                "`turnaround_ms` of node `ctl` must be from 0 up to 1000",
            ),
            ("kp = 0.4", "kp = nan", 23, "`kp` of node `sup`"),
            (
                "[0.5, 1500.0]",
                "[nan, 1500.0]",
                25,
                "`set_points` of node `sup`: set point 2 ([nan, 1500])",
            ),
            (
                "[0.5, 1500.0]",
                "[0.5, 1e308]",
                25,
                "its rpm must be from -100000 up to 100000",
            ),
            (
                "[[0.0, 0.0], [0.5",
                "[[1.0, 0.0], [0.5",
                25,
                "after the one before",
            ),
        ] {
            let e = error_of(from, to);
            assert!(e.starts_with(&format!("bench.toml:{line}: ")), "{to}: {e}");
            assert!(e.contains(said), "{to}: {e}");
        }
    }

    #[test]
    fn two_slaves_with_one_id_on_a_bus_are_refused() {
        let second = "[[node]]\nkind = \"ev-controller\"\nname = \"ctl2\"\nbus = \"b\"\nmodule = \"m\"\n\n[[node]]\nkind = \"supervisor\"";
        let e = error_of("[[node]]\nkind = \"supervisor\"", second);
        assert!(e.starts_with("bench.toml:19: "), "{e}");
        assert!(
            e.contains("`id` 1 of node `ctl2` is already the id of `ctl` on bus `b`"),
            "{e}"
        );
        // Its own id, and it is taken.
        let own = second.replace("module = \"m\"\n\n", "module = \"m\"\nid = 2\n\n");
        let text = BENCH.replace("[[node]]\nkind = \"supervisor\"", &own);
        Scenario::parse(&text, "bench.toml").expect("ids 1 and 2");
    }
}
