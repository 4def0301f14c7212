//! Baseline recordings: every embedded scenario, cut down as
//! `recordings/baselines/baselines.toml` says (shorter, fewer plant
//! samples), recorded once on purpose and compared with a fresh run in CI,
//! so a change in the physics or a protocol shows up as a named signal and
//! time.

use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::scenario::{EMBEDDED, Scenario, ScenarioError};
use crate::virtual_run::RunError;
use twin_recording::compare::{self, Comparison, Tolerances};
use twin_recording::{ReadError, Signals};

/// Why a baseline could not be recorded or checked.
#[derive(Debug, thiserror::Error)]
pub enum BaselineError {
    #[error("recordings/baselines/baselines.toml")]
    Settings(#[source] toml::de::Error),
    #[error(
        "recordings/baselines/baselines.toml names `{name}`, which is not an embedded scenario"
    )]
    NotEmbedded { name: String },
    #[error("no embedded scenario `{name}`: baselines exist for {names}")]
    NoScenario { name: String, names: String },
    #[error("no baseline for `{name}` at {}: record it with `twin baseline --record {name}`", path.display())]
    NoBaseline { name: String, path: PathBuf },
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// A baseline or a fresh run's recording that cannot be read.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// The run itself (boxed: a run's error is large, the rest are small).
    #[error(transparent)]
    Run(Box<RunError>),
}

impl From<RunError> for BaselineError {
    fn from(e: RunError) -> Self {
        BaselineError::Run(Box::new(e))
    }
}

type Result<T, E = BaselineError> = std::result::Result<T, E>;

/// The cut-down settings, built into the binary like the scenarios.
pub const SETTINGS: &str = include_str!("../../../recordings/baselines/baselines.toml");

/// Where the baselines live, relative to the repository root.
pub const DIR: &str = "recordings/baselines";

/// The baselines of the repository this twin was built from, when that
/// folder is still there: the ones `twin baseline` checks wherever it runs.
pub fn repository_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(DIR);
    let dir = dir.canonicalize().ok()?;
    dir.join("baselines.toml").is_file().then_some(dir)
}

/// Where [`repository_dir`] looks.
pub fn repository_dir_expected() -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    root.canonicalize().unwrap_or(root).join(DIR)
}

#[derive(Debug, Clone, Copy, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct CutDown {
    duration_s: Option<f64>,
    record_hz: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Settings {
    #[serde(default)]
    default: CutDown,
    #[serde(default)]
    scenario: BTreeMap<String, CutDown>,
}

fn settings() -> Result<Settings> {
    let s: Settings = toml::from_str(SETTINGS).map_err(BaselineError::Settings)?;
    if let Some(unknown) = s.scenario.keys().find(|k| !names().contains(&k.as_str())) {
        return Err(BaselineError::NotEmbedded {
            name: unknown.clone(),
        });
    }
    Ok(s)
}

/// The scenarios that have baselines: every embedded one.
pub fn names() -> Vec<&'static str> {
    EMBEDDED.iter().map(|(n, _, _)| *n).collect()
}

/// The scenario a baseline records: the embedded one, cut down.
pub fn scenario(name: &str) -> Result<Scenario> {
    let Some((_, _, text)) = EMBEDDED.iter().find(|(n, _, _)| *n == name) else {
        return Err(BaselineError::NoScenario {
            name: name.into(),
            names: names().join(", "),
        });
    };
    let mut s = Scenario::parse(text, &format!("embedded scenario {name}"))?;
    let settings = settings()?;
    let own = settings.scenario.get(name).copied().unwrap_or_default();
    if let Some(d) = own.duration_s.or(settings.default.duration_s) {
        s.duration_s = d;
    }
    if let Some(hz) = own.record_hz.or(settings.default.record_hz) {
        s.record_hz = hz;
    }
    Ok(s)
}

/// The baseline file of `name` in `dir`.
pub fn path(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{name}.mcap"))
}

/// Record the baseline of `name` into `dir`; `progress` gets the fraction
/// of the run done.
pub fn record(dir: &Path, name: &str, progress: impl FnMut(f64)) -> Result<PathBuf> {
    let s = scenario(name)?;
    Ok(crate::virtual_run::run(&s, &path(dir, name), progress)?.recording)
}

/// Run `name` afresh (recording to `scratch`) and compare it with its
/// baseline in `dir`; `progress` gets the fraction of the run done.
pub fn check(
    dir: &Path,
    name: &str,
    scratch: &Path,
    progress: impl FnMut(f64),
) -> Result<Comparison> {
    let baseline_path = path(dir, name);
    if !baseline_path.exists() {
        return Err(BaselineError::NoBaseline {
            name: name.into(),
            path: baseline_path,
        });
    }
    let baseline = Signals::read(&baseline_path)?;
    let s = scenario(name)?;
    let fresh = crate::virtual_run::run(&s, scratch, progress)?.recording;
    let run = Signals::read(&fresh)?;
    Ok(compare::compare(&run, &baseline, &Tolerances::default()))
}
