//! Holding a run against a baseline, signal by signal, within tolerances.
//!
//! For each baseline sample `(t, b)` the run's signal is looked at over
//! `[t - time_shift, t + time_shift]` (interpolated linearly between its
//! samples); the deviation is how far `b` lies outside the range the run
//! takes there, so a run that is late by less than the time shift passes.
//! A sample passes when its deviation is at most `abs + rel·|b|`. The table
//! keeps, per signal, the sample that used most of its tolerance.

use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;

use super::Signal;
use super::signals::Signals;

/// Tolerances of one signal.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Tolerance {
    /// Absolute tolerance, in the signal's unit.
    #[serde(default = "default_abs")]
    pub abs: f64,
    /// Relative tolerance, a fraction of the baseline value.
    #[serde(default = "default_rel")]
    pub rel: f64,
    /// How far in time (s) the run may lead or lag the baseline.
    #[serde(default)]
    pub time_shift_s: f64,
    /// Leave the signal out of the comparison.
    #[serde(default)]
    pub ignore: bool,
}

/// Defaults: equal up to the rounding of a float written as JSON text, at the
/// same times. A deterministic re-run meets them; anything else should say
/// what it allows in a tolerance file.
fn default_abs() -> f64 {
    1e-9
}
fn default_rel() -> f64 {
    1e-9
}

impl Default for Tolerance {
    fn default() -> Self {
        Self {
            abs: default_abs(),
            rel: default_rel(),
            time_shift_s: 0.0,
            ignore: false,
        }
    }
}

/// A rule of a tolerance file: a signal pattern and its tolerances.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct Rule {
    pattern: String,
    #[serde(flatten)]
    tolerance: PartialTolerance,
}

/// A rule's tolerances; what it leaves out comes from `[default]`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct PartialTolerance {
    abs: Option<f64>,
    rel: Option<f64>,
    time_shift_s: Option<f64>,
    ignore: Option<bool>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct TolerancesFile {
    #[serde(default)]
    default: Option<Tolerance>,
    #[serde(default, rename = "signal")]
    signals: Vec<Rule>,
}

/// Why a tolerance file was refused, in its own terms (file, line, field).
#[derive(Debug, thiserror::Error)]
pub enum ToleranceError {
    #[error("cannot read tolerance file {}", path.display())]
    Read {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// TOML that does not parse or fit; `place` is `:LINE` where known.
    #[error("{origin}{place}: {message}")]
    Syntax {
        origin: String,
        place: String,
        message: String,
    },
    #[error("{origin}: {what}: `{name}` must be a number ≥ 0, got {value}")]
    Negative {
        origin: String,
        what: String,
        name: &'static str,
        value: f64,
    },
}

/// Tolerances per signal: a default and glob-like rules (`*` matches any run
/// of characters, `?` one). The last rule that matches a signal wins.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Tolerances {
    pub default: Tolerance,
    rules: Vec<(String, PartialTolerance)>,
}

impl Tolerances {
    /// Parse a tolerance file's text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, ToleranceError> {
        let file: TolerancesFile = toml::from_str(text).map_err(|e| {
            let line = e
                .span()
                .map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
            let place = line.map_or_else(String::new, |l| format!(":{l}"));
            // Every number of the file is a float: serde's Rust name for
            // it is no word of the user's.
            let message = e
                .message()
                .trim()
                .replace("expected f64", "expected a number");
            ToleranceError::Syntax {
                origin: origin.to_string(),
                place,
                message,
            }
        })?;
        let default = file.default.unwrap_or_default();
        let check = |what: &str, t: &PartialTolerance| -> Result<(), ToleranceError> {
            for (name, v) in [
                ("abs", t.abs),
                ("rel", t.rel),
                ("time_shift_s", t.time_shift_s),
            ] {
                if let Some(v) = v
                    && !(v.is_finite() && v >= 0.0)
                {
                    return Err(ToleranceError::Negative {
                        origin: origin.to_string(),
                        what: what.to_string(),
                        name,
                        value: v,
                    });
                }
            }
            Ok(())
        };
        check(
            "[default]",
            &PartialTolerance {
                abs: Some(default.abs),
                rel: Some(default.rel),
                time_shift_s: Some(default.time_shift_s),
                ignore: None,
            },
        )?;
        for r in &file.signals {
            check(&format!("signal `{}`", r.pattern), &r.tolerance)?;
        }
        Ok(Self {
            default,
            rules: file
                .signals
                .into_iter()
                .map(|r| (r.pattern, r.tolerance))
                .collect(),
        })
    }

    /// Read a tolerance file.
    pub fn load(path: &Path) -> Result<Self, ToleranceError> {
        let text = std::fs::read_to_string(path).map_err(|source| ToleranceError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// The tolerances of `signal`.
    pub fn of(&self, signal: &str) -> Tolerance {
        let mut t = self.default;
        if let Some((_, r)) = self.rules.iter().rev().find(|(p, _)| glob(p, signal)) {
            t.abs = r.abs.unwrap_or(t.abs);
            t.rel = r.rel.unwrap_or(t.rel);
            t.time_shift_s = r.time_shift_s.unwrap_or(t.time_shift_s);
            t.ignore = r.ignore.unwrap_or(t.ignore);
        }
        t
    }
}

/// Whether `text` matches `pattern` (`*` any run of characters, `?` one).
pub fn glob(pattern: &str, text: &str) -> bool {
    let p: Vec<char> = pattern.chars().collect();
    let t: Vec<char> = text.chars().collect();
    // Classic backtracking matcher: remember the last `*` and retry from it.
    let (mut i, mut j) = (0, 0);
    let mut star: Option<(usize, usize)> = None;
    while j < t.len() {
        if i < p.len() && (p[i] == '?' || p[i] == t[j]) {
            i += 1;
            j += 1;
        } else if i < p.len() && p[i] == '*' {
            star = Some((i, j));
            i += 1;
        } else if let Some((si, sj)) = star {
            i = si + 1;
            j = sj + 1;
            star = Some((si, sj + 1));
        } else {
            return false;
        }
    }
    p[i..].iter().all(|&c| c == '*')
}

/// The outcome for one signal.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    pub signal: String,
    /// Time of the worst sample (s).
    pub time_s: f64,
    /// The run's value there (interpolated); `None` when the run lacks the signal.
    pub run: Option<f64>,
    pub baseline: f64,
    pub deviation: f64,
    /// The tolerance at the worst sample: `abs + rel·|baseline|`.
    pub tolerance: f64,
    pub time_shift_s: f64,
    /// The first baseline sample beyond tolerance (s), if any.
    pub first_beyond_s: Option<f64>,
    /// Baseline samples compared.
    pub samples: usize,
    pub pass: bool,
}

/// A whole comparison.
#[derive(Debug, Clone, PartialEq)]
pub struct Comparison {
    pub rows: Vec<Row>,
    /// Signals the run has and the baseline has not (not a failure).
    pub only_in_run: Vec<String>,
    /// Signals left out by an `ignore` rule.
    pub ignored: usize,
    /// Baseline samples after this time were not compared (s): the end of the
    /// shorter recording when one of them is cut short.
    pub compared_until_s: f64,
    /// Why the time span is limited, if it is.
    pub span_note: Option<String>,
    /// The recordings cover different spans and neither was cut short.
    pub span_mismatch: Option<String>,
}

impl Comparison {
    pub fn passed(&self) -> bool {
        self.span_mismatch.is_none() && self.rows.iter().all(|r| r.pass)
    }
    pub fn failures(&self) -> impl Iterator<Item = &Row> {
        self.rows.iter().filter(|r| !r.pass)
    }
}

/// Compare `run` with `baseline` (each read with [`Signals::read`]).
pub fn compare(run: &Signals, baseline: &Signals, tolerances: &Tolerances) -> Comparison {
    let (run_signals, base_signals) = (&run.by_name, &baseline.by_name);
    let (run, baseline) = (&run.recording, &baseline.recording);
    let (run_end, base_end) = (run.end_s(), baseline.end_s());
    let mut compared_until_s = f64::INFINITY;
    let mut span_note = None;
    let mut span_mismatch = None;
    if run.ends_early() || baseline.ends_early() {
        compared_until_s = run_end.min(base_end);
        let which: Vec<&str> = [(run, "the run"), (baseline, "the baseline")]
            .iter()
            .filter(|(r, _)| r.ends_early())
            .map(|(_, n)| *n)
            .collect();
        span_note = Some(format!(
            "{} {} cut short: compared up to {compared_until_s:.3} s",
            which.join(" and "),
            if which.len() > 1 { "are" } else { "is" }
        ));
    } else if (run_end - base_end).abs() > 1e-9 {
        span_mismatch = Some(format!(
            "the run ends at {run_end:.3} s and the baseline at {base_end:.3} s"
        ));
        compared_until_s = run_end.min(base_end);
    }
    let mut rows = Vec::new();
    let mut ignored = 0;
    for (name, base) in base_signals {
        let tol = tolerances.of(name);
        if tol.ignore {
            ignored += 1;
            continue;
        }
        let row = match run_signals.get(name) {
            Some(r) => compare_signal(name, &sorted(r), &sorted(base), &tol, compared_until_s),
            // First sampled after the stretch both recordings cover: a run
            // that ends sooner cannot have it, and is not wrong for that.
            None if base.times.first().is_some_and(|t| *t > compared_until_s) => continue,
            None => Row {
                signal: name.clone(),
                time_s: base.times.first().copied().unwrap_or(0.0),
                run: None,
                baseline: base.values.first().copied().unwrap_or(f64::NAN),
                deviation: f64::INFINITY,
                tolerance: tol.abs,
                time_shift_s: tol.time_shift_s,
                first_beyond_s: base.times.first().copied(),
                samples: 0,
                pass: false,
            },
        };
        rows.push(row);
    }
    let only_in_run = run_signals
        .keys()
        .filter(|k| !base_signals.contains_key(*k) && !tolerances.of(k).ignore)
        .cloned()
        .collect();
    Comparison {
        rows,
        only_in_run,
        ignored,
        compared_until_s,
        span_note,
        span_mismatch,
    }
}

/// A signal in time order (they are already, save for a stray one).
fn sorted(s: &Signal) -> std::borrow::Cow<'_, Signal> {
    if s.times.is_sorted() {
        return std::borrow::Cow::Borrowed(s);
    }
    let mut pairs: Vec<(f64, f64)> = s
        .times
        .iter()
        .copied()
        .zip(s.values.iter().copied())
        .collect();
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    std::borrow::Cow::Owned(Signal {
        times: pairs.iter().map(|p| p.0).collect(),
        values: pairs.iter().map(|p| p.1).collect(),
        hold: s.hold,
    })
}

fn compare_signal(name: &str, run: &Signal, base: &Signal, tol: &Tolerance, until: f64) -> Row {
    let mut worst = Row {
        signal: name.to_string(),
        time_s: base.times.first().copied().unwrap_or(0.0),
        run: None,
        baseline: base.values.first().copied().unwrap_or(f64::NAN),
        deviation: 0.0,
        tolerance: tol.abs,
        time_shift_s: tol.time_shift_s,
        first_beyond_s: None,
        samples: 0,
        pass: true,
    };
    let mut worst_ratio = -1.0;
    // A run late by up to the time shift has not reached the baseline's last
    // `time_shift` seconds yet: those samples cannot be judged.
    let until = match run.times.last() {
        Some(&end) if tol.time_shift_s > 0.0 => until.min(end - tol.time_shift_s),
        _ => until,
    };
    for (&t, &b) in base.times.iter().zip(&base.values) {
        if t > until + 1e-12 {
            break;
        }
        worst.samples += 1;
        let (lo, hi) = range_over(run, t - tol.time_shift_s, t + tol.time_shift_s);
        let deviation = if b < lo {
            lo - b
        } else if b > hi {
            b - hi
        } else {
            0.0
        };
        let tolerance = tol.abs + tol.rel * b.abs();
        if deviation > tolerance && worst.first_beyond_s.is_none() {
            worst.first_beyond_s = Some(t);
        }
        let ratio = if deviation == 0.0 {
            0.0
        } else if tolerance > 0.0 {
            deviation / tolerance
        } else {
            f64::INFINITY
        };
        if ratio > worst_ratio {
            worst_ratio = ratio;
            worst.time_s = t;
            worst.baseline = b;
            worst.run = run.at(t);
            worst.deviation = deviation;
            worst.tolerance = tolerance;
            worst.pass = deviation <= tolerance;
        }
    }
    worst
}

/// The range of values `s` takes over `[from, to]`: its interpolated values
/// at both ends and every sample in between.
fn range_over(s: &Signal, from: f64, to: f64) -> (f64, f64) {
    let (Some(a), Some(b)) = (s.at(from), s.at(to)) else {
        return (f64::NAN, f64::NAN);
    };
    let (mut lo, mut hi) = (a.min(b), a.max(b));
    let start = s.times.partition_point(|&x| x < from);
    for (&t, &v) in s.times[start..].iter().zip(&s.values[start..]) {
        if t > to {
            break;
        }
        lo = lo.min(v);
        hi = hi.max(v);
    }
    (lo, hi)
}

/// The table a user reads: one line per signal, failures first.
pub fn table(c: &Comparison, all: bool) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "  {:<48} {:>9} {:>9} {:>12} {:>12} {:>10} {:>10}  result",
        "signal", "beyond s", "worst s", "run", "baseline", "deviation", "tolerance"
    );
    // Failures first, earliest first: the first one is usually the cause.
    let mut rows: Vec<&Row> = c.rows.iter().collect();
    rows.sort_by(|a, b| {
        a.pass.cmp(&b.pass).then(
            a.first_beyond_s
                .unwrap_or(0.0)
                .total_cmp(&b.first_beyond_s.unwrap_or(0.0)),
        )
    });
    for r in rows.into_iter().filter(|r| all || !r.pass) {
        let run = r.run.map_or_else(|| "missing".to_string(), num);
        let _ = writeln!(
            out,
            "  {:<48} {:>9} {:>9.3} {:>12} {:>12} {:>10} {:>10}  {}",
            r.signal,
            r.first_beyond_s
                .map_or_else(|| "-".into(), |t| format!("{t:.3}")),
            r.time_s,
            run,
            num(r.baseline),
            num(r.deviation),
            num(r.tolerance),
            if r.pass { "pass" } else { "FAIL" }
        );
    }
    out
}

/// A number in at most about 10 characters.
fn num(v: f64) -> String {
    if v == 0.0 || (1e-3..1e7).contains(&v.abs()) {
        let s = format!("{v:.6}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        s.chars().take(12).collect()
    } else if v.is_finite() {
        format!("{v:.3e}")
    } else {
        format!("{v}")
    }
}

/// Group per-signal rows into a map (for tests and tools).
pub fn by_signal(c: &Comparison) -> BTreeMap<&str, &Row> {
    c.rows.iter().map(|r| (r.signal.as_str(), r)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glob_patterns() {
        assert!(glob(
            "/plant/*/sensors.wheel_rpm",
            "/plant/ev1/sensors.wheel_rpm"
        ));
        assert!(glob("*", ""));
        assert!(glob("/bus/*", "/bus/rs485/frames.len"));
        assert!(glob("a?c", "abc"));
        assert!(!glob("a?c", "ac"));
        assert!(!glob("/plant/*/sensors.soc", "/plant/ev1/sensors.soc_x"));
        assert!(glob("*.energy.*", "/plant/ev1/sensors.energy.battery_out"));
    }

    #[test]
    fn last_matching_rule_wins_and_fills_from_the_default() {
        let t = Tolerances::parse(
            "[default]\nabs = 0.5\n[[signal]]\npattern = \"*rpm\"\nrel = 0.01\n\
             [[signal]]\npattern = \"*.wheel_rpm\"\ntime_shift_s = 0.02\n",
            "t.toml",
        )
        .unwrap();
        let w = t.of("/plant/ev1/sensors.wheel_rpm");
        assert_eq!((w.abs, w.rel, w.time_shift_s), (0.5, 1e-9, 0.02));
        let m = t.of("/plant/ev1/sensors.motor_rpm");
        assert_eq!((m.abs, m.rel, m.time_shift_s), (0.5, 0.01, 0.0));
        let e = Tolerances::parse("[[signal]]\npattern = \"x\"\nabs = -1\n", "t.toml").unwrap_err();
        assert!(
            matches!(e, ToleranceError::Negative { name: "abs", .. }),
            "{e:?}"
        );
        assert_eq!(
            e.to_string(),
            "t.toml: signal `x`: `abs` must be a number ≥ 0, got -1"
        );
        let e = Tolerances::parse("[default]\nabz = 1\n", "t.toml").unwrap_err();
        assert!(matches!(e, ToleranceError::Syntax { .. }), "{e:?}");
        let e = e.to_string();
        assert!(e.starts_with("t.toml:2"), "{e}");
        let e = Tolerances::parse("[default]\nabs = \"small\"\n", "t.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("expected a number"), "{e}");
        assert!(!e.contains("f64"), "{e}");
    }

    #[test]
    fn a_time_shift_forgives_a_late_ramp() {
        let base = Signal {
            times: (0..=100).map(|i| i as f64 * 0.01).collect(),
            values: (0..=100).map(|i| i as f64).collect(),
            hold: false,
        };
        // The same ramp 20 ms late: 2 units behind everywhere.
        let late = Signal {
            times: base.times.clone(),
            values: base.values.iter().map(|v| (v - 2.0).max(0.0)).collect(),
            hold: false,
        };
        let strict = Tolerance::default();
        let row = compare_signal("x", &late, &base, &strict, f64::INFINITY);
        assert!(!row.pass);
        assert!((row.deviation - 2.0).abs() < 1e-9, "{row:?}");
        let shifted = Tolerance {
            time_shift_s: 0.02,
            ..strict
        };
        let row = compare_signal("x", &late, &base, &shifted, f64::INFINITY);
        assert!(row.pass, "{row:?}");
        let row = compare_signal("x", &base, &base, &strict, f64::INFINITY);
        assert!(row.pass && row.deviation == 0.0);
    }
}
