//! What a recording says was run, from its `twin.run` metadata: what made
//! it (a scenario run, an open-loop run, a step response, a real-time
//! session), on which scenario or bench, with which seed and duration, and
//! every setting of the scenario or the bench's parameters as a dotted path
//! (`node.supervisor.kp`, `params.motor.kv_rpm_per_volt`).
//!
//! `twin compare` holds two identities against each other before any
//! signal, so that recordings of different runs are named as such; `twin
//! run` names what a file it replaces held.

use std::collections::BTreeMap;
use std::fmt;
use toml::Value;

use super::Recording;

/// The fields that say *what* was run: recordings that differ in one of
/// them come from different runs, and their signals do not match up.
const WHAT_RAN: [&str; 4] = ["kind", "experiment", "scenario", "preset"];

/// Fields that say nothing about the run itself.
const NOT_THE_RUN: [&str; 2] = ["twin_version", "pwm_calibration"];

/// A recording's run, flattened to dotted paths and their values.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Identity {
    fields: BTreeMap<String, String>,
}

/// One setting two recordings differ in.
#[derive(Debug, Clone, PartialEq)]
pub struct Difference {
    pub field: String,
    /// Its value in the first recording and the second; `None` when one lacks it.
    pub first: Option<String>,
    pub second: Option<String>,
}

impl Difference {
    /// Whether this difference makes the recordings runs of different
    /// things (another scenario, bench or kind of run).
    pub fn of_what_ran(&self) -> bool {
        WHAT_RAN.contains(&self.field.as_str())
    }

    /// Whether this is the seed or the simulated duration, which say how a
    /// run ran rather than what it ran.
    pub fn of_seed_or_length(&self) -> bool {
        ["seed", "duration_s"].contains(&self.field.as_str())
    }
}

impl Identity {
    /// The run `recording` holds; empty when it has no `twin.run` record.
    pub fn of(recording: &Recording) -> Self {
        let mut fields = BTreeMap::new();
        let Some(run) = recording.metadata.get(super::topics::RUN_METADATA) else {
            return Self { fields };
        };
        for (key, value) in run {
            if NOT_THE_RUN.contains(&key.as_str()) {
                continue;
            }
            // A scenario's TOML is the run itself (its paths at the top, as
            // `--set` names them); a bench's parameters go under `params.`.
            let prefix = match key.as_str() {
                "scenario_toml" => Some(""),
                "params" | "params_toml" => Some("params."),
                _ => None,
            };
            match prefix.and_then(|p| toml::from_str::<toml::Table>(value).ok().map(|t| (p, t))) {
                Some((prefix, table)) => flatten(prefix, &Value::Table(table), &mut fields),
                None => {
                    fields.insert(key.clone(), value.clone());
                }
            }
        }
        // A scenario's TOML names it `name`; the run's record `scenario`.
        fields.remove("name");
        Self { fields }
    }

    /// Whether the recording has no `twin.run` record (another program's).
    pub fn is_empty(&self) -> bool {
        self.fields.is_empty()
    }

    /// The field at a dotted path.
    pub fn get(&self, field: &str) -> Option<&str> {
        self.fields.get(field).map(String::as_str)
    }

    /// What made the recording, in a user's words.
    pub fn what(&self) -> String {
        let kind = self.get("kind");
        match (kind, self.get("experiment")) {
            (None, _) => "a recording with no `twin.run` record".into(),
            (Some("scenario"), Some("step")) => "a closed-loop step response".into(),
            (Some("open-loop"), Some("step")) => "an open-loop step response".into(),
            (Some("scenario"), _) => "a scenario run".into(),
            (Some("open-loop"), _) => "an open-loop run".into(),
            (Some(k @ ("serve" | "supervise")), _) => format!("a `twin {k}` session"),
            (Some(k), _) => format!("a run of kind `{k}`"),
        }
    }

    /// One line naming the run: `a scenario run of ev-meb, seed 1, 10 s`.
    pub fn describe(&self) -> String {
        let mut s = self.what();
        if let Some(name) = self.get("scenario") {
            s += &format!(" of {name}");
        } else if let Some(preset) = self.get("preset") {
            s += &format!(" on the {preset} preset");
        }
        if let Some(seed) = self.get("seed") {
            s += &format!(", seed {seed}");
        }
        if let Some(d) = self.get("duration_s") {
            // `10` for a scenario's `10.0` and an open-loop run's `10` alike.
            let shown = d
                .parse::<f64>()
                .map_or_else(|_| d.to_string(), |d| d.to_string());
            s += &format!(", {shown} s");
        }
        s
    }

    /// Every field the two differ in: what ran first, then the seed and
    /// the duration, then the other settings in path order.
    pub fn differences(&self, other: &Identity) -> Vec<Difference> {
        let mut keys: Vec<&String> = self.fields.keys().chain(other.fields.keys()).collect();
        keys.sort();
        keys.dedup();
        let rank = |k: &str| match WHAT_RAN.iter().position(|w| *w == k) {
            Some(i) => i,
            None if k == "seed" => WHAT_RAN.len(),
            None if k == "duration_s" => WHAT_RAN.len() + 1,
            None => WHAT_RAN.len() + 2,
        };
        keys.sort_by_key(|k| rank(k));
        keys.into_iter()
            .filter(|k| self.fields.get(*k) != other.fields.get(*k))
            .map(|k| Difference {
                field: k.clone(),
                first: self.fields.get(k).cloned(),
                second: other.fields.get(k).cloned(),
            })
            .collect()
    }
}

impl fmt::Display for Difference {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let shown = |v: &Option<String>| match v {
            Some(v) if v.chars().count() > 40 => {
                format!("{}…", v.chars().take(40).collect::<String>())
            }
            Some(v) => v.clone(),
            None => "(none)".into(),
        };
        write!(
            f,
            "{}, baseline {}",
            shown(&self.first),
            shown(&self.second)
        )
    }
}

/// `value` as dotted paths under `prefix`; a list's items by their `name`
/// when they have one (`node.supervisor.kp`), else by index.
fn flatten(prefix: &str, value: &Value, out: &mut BTreeMap<String, String>) {
    match value {
        Value::Table(t) => {
            for (k, v) in t {
                flatten(&format!("{prefix}{k}."), v, out);
            }
        }
        Value::Array(items) if items.iter().all(Value::is_table) && !items.is_empty() => {
            for (i, item) in items.iter().enumerate() {
                match (item.get("name").and_then(Value::as_str), item) {
                    // Named by its name, which is then no setting of its own.
                    (Some(name), Value::Table(t)) => {
                        let mut rest = t.clone();
                        rest.remove("name");
                        flatten(&format!("{prefix}{name}."), &Value::Table(rest), out);
                    }
                    _ => flatten(&format!("{prefix}{i}."), item, out),
                }
            }
        }
        other => {
            let key = prefix.trim_end_matches('.').to_string();
            let text = match other {
                Value::String(s) => s.clone(),
                v => v.to_string(),
            };
            out.insert(key, text);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn identity(run: &[(&str, &str)]) -> Identity {
        let mut recording = Recording {
            path: "r.mcap".into(),
            metadata: BTreeMap::new(),
            channels: Vec::new(),
            chunks: 0,
            truncated: None,
            end_ns: 0,
        };
        recording.metadata.insert(
            super::super::topics::RUN_METADATA.into(),
            run.iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect(),
        );
        Identity::of(&recording)
    }

    #[test]
    fn scenarios_differ_first_in_what_ran_then_seed_duration_and_settings() {
        let scenario = |name: &str, kp: f64, d: f64| {
            format!(
                "name = \"{name}\"\nseed = 1\nduration_s = {d}\n[[node]]\nname = \"supervisor\"\nkp = {kp}\n"
            )
        };
        let a_toml = scenario("ev-meb", 0.5, 10.0);
        let b_toml = scenario("controller-network", 0.45, 30.0);
        let a = identity(&[
            ("kind", "scenario"),
            ("scenario", "ev-meb"),
            ("seed", "1"),
            ("scenario_toml", &a_toml),
            ("twin_version", "0.1.0"),
        ]);
        let b = identity(&[
            ("kind", "scenario"),
            ("scenario", "controller-network"),
            ("seed", "1"),
            ("scenario_toml", &b_toml),
            ("twin_version", "0.2.0"),
        ]);
        let d = a.differences(&b);
        let fields: Vec<&str> = d.iter().map(|d| d.field.as_str()).collect();
        assert_eq!(fields, ["scenario", "duration_s", "node.supervisor.kp"]);
        assert!(d[0].of_what_ran() && !d[1].of_what_ran());
        assert_eq!(d[2].to_string(), "0.5, baseline 0.45");
        assert_eq!(a.describe(), "a scenario run of ev-meb, seed 1, 10 s");
        assert!(a.differences(&a).is_empty());
    }

    #[test]
    fn a_session_is_named_as_one() {
        let s = identity(&[("kind", "serve"), ("seed", "1")]);
        assert_eq!(s.what(), "a `twin serve` session");
        let none = Identity::default();
        assert!(s.differences(&none)[0].of_what_ran());
    }
}
