//! Re-running a recorded run: the run's identity comes out of the
//! recording's `twin.run` metadata (the scenario TOML with the duration and
//! seed it ran with, or an open-loop run's settings and parameters), may be
//! changed field by field (`--set node.supervisor.kp=0.6`), and runs again.

use plant::PlantParams;
use std::path::{Path, PathBuf};
use toml::{Table, Value};

use crate::openloop::{self, OpenLoop};
use crate::scenario::{Scenario, ScenarioError};
use crate::virtual_run::RunError;
use twin_recording::Recording;

/// Why a recorded run cannot be read back, changed or run again.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error("{origin} has no `twin.run` metadata: it was not recorded by `twin run`")]
    NoRunMetadata { origin: String },
    #[error("{origin}: `twin.run` lacks `{field}`")]
    MissingField { origin: String, field: String },
    #[error("{origin}: `twin.run` field `{field}` is not a number")]
    NotANumber {
        origin: String,
        field: String,
        #[source]
        source: std::num::ParseFloatError,
    },
    #[error("{origin}: `twin.run` field `seed` is not an integer")]
    SeedNotInteger {
        origin: String,
        #[source]
        source: std::num::ParseIntError,
    },
    #[error("{origin}: `params_toml` is not TOML")]
    ParamsNotToml {
        origin: String,
        #[source]
        source: toml::de::Error,
    },
    #[error("{origin}: open-loop settings in `twin.run`")]
    OpenLoopSettings {
        origin: String,
        #[source]
        source: Box<ReplayError>,
    },
    #[error(
        "{origin} is a `twin {kind}` session: it ran in real time, with live masters or \
         slaves and the machine's clock, so it cannot be run again. Its recorded requests \
         can be sent to a live slave instead: `twin replay {origin} --frames-to LINK`"
    )]
    RealTime { origin: String, kind: String },
    #[error(
        "{origin} is a `twin check` run: it checked a live program over its link, so \
         there is nothing to run again. Its frames and verdicts are in it: see them with \
         `twin export {origin} --csv DIR` or `twin view {origin}`, and check the program \
         again with `twin check`"
    )]
    CheckRun { origin: String },
    #[error(
        "{origin} was recorded by a run of kind `{kind}`, which this twin ({version}) cannot \
         run again: it may come from a newer twin"
    )]
    UnknownKind {
        origin: String,
        kind: String,
        version: &'static str,
    },
    #[error("`preset` must be a preset name")]
    PresetNotNamed,
    #[error("unknown preset `{preset}`")]
    UnknownPreset { preset: String },
    #[error("`params` must be a table")]
    ParamsNotTable,
    #[error("`{field}` must be a number")]
    SettingNotANumber { field: String },
    #[error("`seed` must be a non-negative integer")]
    BadSeed,
    #[error("`{field}` must be a positive number, got {value}")]
    NotPositive { field: String, value: f64 },
    #[error("`{field}` is a fraction of VEL's 5 V range: 0 to 1, got {value}")]
    NotAFraction { field: String, value: f64 },
    #[error("`vel_step_at_s` must be 0 or more, got {value}")]
    StepBeforeStart { value: f64 },
    #[error("--set `{set}`: write PATH=VALUE, e.g. node.supervisor.kp=0.6")]
    SetSyntax { set: String },
    /// One `--set` that could not be applied.
    #[error("--set `{set}`")]
    Set {
        set: String,
        #[source]
        source: Box<ReplayError>,
    },
    #[error("`{path}` is not a dotted path")]
    NotDottedPath { path: String },
    #[error("`{path}` is a list: name a field of one of its items")]
    ListNeedsItem { path: String },
    #[error("`{path}` has no item `{pick}`: its items are {names} (or an index below {count})")]
    NoItem {
        path: String,
        pick: String,
        names: String,
        count: usize,
    },
    #[error("`{path}` is not a table")]
    NotATable { path: String },
    #[error("`{path}` is a value, not a table")]
    ValueNotTable { path: String },
    /// The run as `--set` left it, which no longer holds together.
    #[error("{origin}")]
    Edited {
        origin: String,
        #[source]
        source: Box<ReplayError>,
    },
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    #[error(transparent)]
    Params(#[from] plant::ParamsError),
    #[error(transparent)]
    Toml(#[from] toml::ser::Error),
    /// The run itself (boxed: a run's error is large, the rest are small).
    #[error(transparent)]
    Run(Box<RunError>),
}

impl From<RunError> for ReplayError {
    fn from(e: RunError) -> Self {
        ReplayError::Run(Box::new(e))
    }
}

type Result<T, E = ReplayError> = std::result::Result<T, E>;

/// What a recording says was run.
#[derive(Debug, Clone)]
pub enum RunSpec {
    Scenario(Scenario),
    OpenLoop(Box<OpenLoop>),
}

impl RunSpec {
    /// The run stored in `recording`'s metadata.
    pub fn from_recording(recording: &Recording) -> Result<Self> {
        let origin = recording.path.display().to_string();
        let Some(kind) = recording.run_field("kind") else {
            return Err(ReplayError::NoRunMetadata { origin });
        };
        match kind {
            "scenario" => {
                let text = recording.run_field("scenario_toml").ok_or_else(|| {
                    ReplayError::MissingField {
                        origin: origin.clone(),
                        field: "scenario_toml".into(),
                    }
                })?;
                Ok(Self::Scenario(Scenario::parse(
                    text,
                    &format!("{origin}, scenario_toml"),
                )?))
            }
            "open-loop" => Ok(Self::OpenLoop(open_loop_table(recording).and_then(
                |t| {
                    open_loop_from_table(&t).map_err(|source| ReplayError::OpenLoopSettings {
                        origin: origin.clone(),
                        source: Box::new(source),
                    })
                },
            )?)),
            "serve" | "supervise" => Err(ReplayError::RealTime {
                origin,
                kind: kind.to_string(),
            }),
            "check" => Err(ReplayError::CheckRun { origin }),
            other => Err(ReplayError::UnknownKind {
                origin,
                kind: other.to_string(),
                version: env!("CARGO_PKG_VERSION"),
            }),
        }
    }

    /// Change fields: `PATH=VALUE` with PATH dotted through the scenario (as
    /// in its TOML; array items by `name` or index, e.g.
    /// `module.ev1.params.wheel.brake_torque_nm=3` or `node.1.kp=0.6`) or, for
    /// an open-loop run, through its settings (`vel_fraction`, `duration_s`,
    /// `seed`, `params.motor.…`). VALUE is a TOML value; bare text is a string.
    pub fn with_overrides(self, overrides: &[String]) -> Result<Self> {
        if overrides.is_empty() {
            return Ok(self);
        }
        let table = edited(self.to_table()?, overrides)?;
        let origin = origin_of(overrides);
        match self {
            RunSpec::Scenario(_) => Ok(RunSpec::Scenario(scenario_from_table(&table, &origin)?)),
            RunSpec::OpenLoop(_) => Ok(RunSpec::OpenLoop(
                open_loop_from_table(&table).map_err(|e| edited_error(origin, e))?,
            )),
        }
    }

    /// `scenario` with `overrides` applied, as [`RunSpec::with_overrides`]
    /// changes a recorded one (`twin run --set`).
    pub fn scenario_with_overrides(scenario: Scenario, overrides: &[String]) -> Result<Scenario> {
        if overrides.is_empty() {
            return Ok(scenario);
        }
        let table = edited(Table::try_from(&scenario)?, overrides)?;
        scenario_from_table(&table, &origin_of(overrides))
    }

    /// An open-loop run's settings with `overrides` applied.
    pub fn open_loop_with_overrides(config: OpenLoop, overrides: &[String]) -> Result<OpenLoop> {
        if overrides.is_empty() {
            return Ok(config);
        }
        let spec = RunSpec::OpenLoop(Box::new(config));
        let table = edited(spec.to_table()?, overrides)?;
        Ok(*open_loop_from_table(&table).map_err(|e| edited_error(origin_of(overrides), e))?)
    }

    fn to_table(&self) -> Result<Table> {
        Ok(match self {
            RunSpec::Scenario(s) => Table::try_from(s)?,
            RunSpec::OpenLoop(o) => {
                let mut t = Table::new();
                t.insert("preset".into(), Value::String(o.preset.clone()));
                t.insert("seed".into(), Value::Integer(o.seed as i64));
                t.insert("duration_s".into(), Value::Float(o.duration_s));
                t.insert("step_s".into(), Value::Float(o.step_s));
                t.insert("vel_step_at_s".into(), Value::Float(o.vel_step_at_s));
                t.insert("vel_fraction".into(), Value::Float(o.vel_fraction));
                t.insert(
                    "vel_before_fraction".into(),
                    Value::Float(o.vel_before_fraction),
                );
                t.insert("record_hz".into(), Value::Float(o.record_hz));
                t.insert("params".into(), Value::Table(Table::try_from(&o.params)?));
                t
            }
        })
    }

    /// A line naming the run.
    pub fn describe(&self) -> String {
        match self {
            RunSpec::Scenario(s) => format!(
                "scenario {}, seed {}, {:.3} s",
                s.name, s.seed, s.duration_s
            ),
            RunSpec::OpenLoop(o) => format!(
                "open loop on the {} preset, seed {}, {:.3} s",
                o.preset, o.seed, o.duration_s
            ),
        }
    }

    /// Its length in simulated seconds.
    pub fn duration_s(&self) -> f64 {
        match self {
            RunSpec::Scenario(s) => s.duration_s,
            RunSpec::OpenLoop(o) => o.duration_s,
        }
    }

    /// Run it, recording to `out`.
    pub fn run(&self, out: &Path, progress: impl FnMut(f64)) -> Result<PathBuf> {
        Ok(match self {
            RunSpec::Scenario(s) => crate::virtual_run::run(s, out, progress)?.recording,
            RunSpec::OpenLoop(o) => openloop::run(o, out, progress)?.recording,
        })
    }
}

/// An open-loop recording's settings as a table (the shape `--set` edits).
fn open_loop_table(recording: &Recording) -> Result<Table> {
    let origin = recording.path.display().to_string();
    let field = |k: &str| {
        recording
            .run_field(k)
            .ok_or_else(|| ReplayError::MissingField {
                origin: origin.clone(),
                field: k.into(),
            })
    };
    let number = |k: &str| -> Result<f64> {
        field(k)?.parse().map_err(|source| ReplayError::NotANumber {
            origin: origin.clone(),
            field: k.into(),
            source,
        })
    };
    let mut t = Table::new();
    t.insert("preset".into(), Value::String(field("preset")?.into()));
    let seed: i64 = field("seed")?
        .parse()
        .map_err(|source| ReplayError::SeedNotInteger {
            origin: origin.clone(),
            source,
        })?;
    t.insert("seed".into(), Value::Integer(seed));
    for k in ["duration_s", "step_s", "vel_step_at_s", "vel_fraction"] {
        t.insert(k.into(), Value::Float(number(k)?));
    }
    // Recordings older than this field were all made at the default rate.
    let hz = match recording.run_field("record_hz") {
        Some(_) => number("record_hz")?,
        None => 1000.0,
    };
    t.insert("record_hz".into(), Value::Float(hz));
    // Written only when a step starts from a running wheel.
    let before = match recording.run_field("vel_before_fraction") {
        Some(_) => number("vel_before_fraction")?,
        None => 0.0,
    };
    t.insert("vel_before_fraction".into(), Value::Float(before));
    let params: Table =
        toml::from_str(field("params_toml")?).map_err(|source| ReplayError::ParamsNotToml {
            origin: origin.clone(),
            source,
        })?;
    t.insert("params".into(), Value::Table(params));
    Ok(t)
}

fn open_loop_from_table(t: &Table) -> Result<Box<OpenLoop>> {
    let preset = t
        .get("preset")
        .and_then(Value::as_str)
        .ok_or(ReplayError::PresetNotNamed)?;
    let Some(base) = PlantParams::preset(preset) else {
        return Err(ReplayError::UnknownPreset {
            preset: preset.to_string(),
        });
    };
    let params_text = toml::to_string(
        t.get("params")
            .and_then(Value::as_table)
            .ok_or(ReplayError::ParamsNotTable)?,
    )?;
    let params = PlantParams::from_toml(&params_text, Path::new("params"), &base)?;
    let mut o = OpenLoop::new(params, preset);
    let number = |k: &str| -> Result<f64> {
        let v = match t.get(k) {
            Some(Value::Float(f)) => *f,
            Some(Value::Integer(i)) => *i as f64,
            _ => return Err(ReplayError::SettingNotANumber { field: k.into() }),
        };
        Ok(v)
    };
    o.seed = t
        .get("seed")
        .and_then(Value::as_integer)
        .and_then(|s| u64::try_from(s).ok())
        .ok_or(ReplayError::BadSeed)?;
    o.duration_s = number("duration_s")?;
    o.step_s = number("step_s")?;
    o.vel_step_at_s = number("vel_step_at_s")?;
    o.vel_fraction = number("vel_fraction")?;
    o.vel_before_fraction = match t.get("vel_before_fraction") {
        Some(_) => number("vel_before_fraction")?,
        None => 0.0,
    };
    o.record_hz = number("record_hz")?;
    for (k, v) in [
        ("duration_s", o.duration_s),
        ("step_s", o.step_s),
        ("record_hz", o.record_hz),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(ReplayError::NotPositive {
                field: k.into(),
                value: v,
            });
        }
    }
    for (k, v) in [
        ("vel_fraction", o.vel_fraction),
        ("vel_before_fraction", o.vel_before_fraction),
    ] {
        if !(0.0..=1.0).contains(&v) {
            return Err(ReplayError::NotAFraction {
                field: k.into(),
                value: v,
            });
        }
    }
    if !(o.vel_step_at_s >= 0.0 && o.vel_step_at_s.is_finite()) {
        return Err(ReplayError::StepBeforeStart {
            value: o.vel_step_at_s,
        });
    }
    Ok(Box::new(o))
}

/// A `--set` value: TOML (`3.0`, `true`, `[[0.5, 1000.0]]`, `"text"`), or
/// bare text taken as a string.
pub fn parse_value(raw: &str) -> Value {
    toml::from_str::<Table>(&format!("v = {raw}"))
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| Value::String(raw.to_string()))
}

/// Set `path` (dotted) in `table`, making missing tables on the way. In a
/// list of tables (`module`, `node`, …) the next part picks an item by its
/// `name` or by its index.
fn set_path(table: &mut Table, path: &str, value: Value) -> Result<()> {
    let parts: Vec<&str> = path.split('.').collect();
    if parts.iter().any(|p| p.is_empty()) {
        return Err(ReplayError::NotDottedPath { path: path.into() });
    }
    let mut here: &mut Table = table;
    let mut i = 0;
    loop {
        let part = parts[i];
        let walked = parts[..=i].join(".");
        if i + 1 == parts.len() {
            here.insert(part.to_string(), value);
            return Ok(());
        }
        let next = here
            .entry(part.to_string())
            .or_insert_with(|| Value::Table(Table::new()));
        here = match next {
            Value::Table(t) => t,
            Value::Array(items) => {
                i += 1;
                if i + 1 == parts.len() {
                    return Err(ReplayError::ListNeedsItem { path: walked });
                }
                let pick = parts[i];
                let names: Vec<String> = items
                    .iter()
                    .filter_map(|v| v.get("name").and_then(Value::as_str).map(String::from))
                    .collect();
                let index = match pick.parse::<usize>() {
                    Ok(n) if n < items.len() => n,
                    _ => match names.iter().position(|n| n == pick) {
                        Some(n) => n,
                        None => {
                            return Err(ReplayError::NoItem {
                                path: walked,
                                pick: pick.into(),
                                names: names.join(", "),
                                count: items.len(),
                            });
                        }
                    },
                };
                match &mut items[index] {
                    Value::Table(t) => t,
                    _ => {
                        return Err(ReplayError::NotATable {
                            path: format!("{walked}.{pick}"),
                        });
                    }
                }
            }
            _ => return Err(ReplayError::ValueNotTable { path: walked }),
        };
        i += 1;
    }
}

fn origin_of(overrides: &[String]) -> String {
    format!("the run after --set {}", overrides.join(" --set "))
}

fn edited(mut table: Table, overrides: &[String]) -> Result<Table> {
    for o in overrides {
        let Some((path, raw)) = o.split_once('=') else {
            return Err(ReplayError::SetSyntax { set: o.clone() });
        };
        set_path(&mut table, path.trim(), parse_value(raw.trim())).map_err(|source| {
            ReplayError::Set {
                set: o.clone(),
                source: Box::new(source),
            }
        })?;
    }
    Ok(table)
}

fn scenario_from_table(table: &Table, origin: &str) -> Result<Scenario> {
    let text = toml::to_string(table)?;
    Scenario::parse(&text, "the edited scenario")
        .map_err(|e| edited_error(origin.to_string(), e.into()))
}

/// `error` in the run as `--set` left it (`origin`).
fn edited_error(origin: String, error: ReplayError) -> ReplayError {
    ReplayError::Edited {
        origin,
        source: Box::new(error),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_paths_through_tables_and_named_items() {
        let mut t: Table = toml::from_str(
            "seed = 1\n[[node]]\nname = \"a\"\nkp = 1.0\n[[node]]\nname = \"b\"\nkp = 2.0\n",
        )
        .unwrap();
        set_path(&mut t, "node.b.kp", parse_value("0.5")).unwrap();
        set_path(&mut t, "node.0.params.wheel.mass_kg", parse_value("3")).unwrap();
        set_path(&mut t, "seed", parse_value("7")).unwrap();
        assert_eq!(t["node"][1]["kp"].as_float(), Some(0.5));
        assert_eq!(
            t["node"][0]["params"]["wheel"]["mass_kg"].as_integer(),
            Some(3)
        );
        assert_eq!(t["seed"].as_integer(), Some(7));
        let e = set_path(&mut t, "node.c.kp", parse_value("1"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("items are a, b"), "{e}");
        let e = set_path(&mut t, "seed.x", parse_value("1"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("`seed` is a value"), "{e}");
        assert_eq!(parse_value("meb"), Value::String("meb".into()));
    }
}
