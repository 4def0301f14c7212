//! A batch manifest: the runs to make, one entry each, in a JSON Lines file
//! (one object a line) or a TOML file (`[[run]]` tables). An entry names a
//! scenario (embedded, or a file beside the manifest), `--set`-style
//! changes, a seed and the name its outputs take:
//!
//! ```text
//! {"scenario": "ev-meb", "set": ["duration_s=2", "node.supervisor.kp=0.6"], "seed": 3, "out": "kp-0.6"}
//! ```
//!
//! Errors name the file, the line and the field.

use super::BatchError;

type Result<T, E = BatchError> = std::result::Result<T, E>;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// One run of a batch.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Entry {
    /// An embedded scenario's name or a scenario file (relative to the manifest).
    pub scenario: String,
    /// `PATH=VALUE` changes, as `twin replay --set` takes them.
    #[serde(default)]
    pub set: Vec<String>,
    /// Seed of every random draw [default: the scenario's].
    #[serde(default)]
    pub seed: Option<u64>,
    /// Name of the entry's recording and summary in the output folder
    /// [default: its index, four digits].
    #[serde(default)]
    pub out: Option<String>,
}

/// A manifest read from a file.
#[derive(Debug, Clone)]
pub struct Manifest {
    pub path: PathBuf,
    pub entries: Vec<Entry>,
    /// The line each entry starts on, for messages.
    pub lines: Vec<usize>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TomlManifest {
    #[serde(default)]
    run: Vec<Entry>,
}

impl Manifest {
    /// Read a manifest: TOML when the file ends in `.toml`, JSON Lines
    /// otherwise (blank lines and lines starting with `#` are skipped).
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| BatchError::ReadManifest {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let origin = path.display().to_string();
        let (entries, lines) = if path.extension().is_some_and(|e| e == "toml") {
            parse_toml(text, &origin)?
        } else {
            parse_json_lines(text, &origin)?
        };
        let manifest = Self {
            path: path.to_path_buf(),
            entries,
            lines,
        };
        manifest.check(&origin)?;
        Ok(manifest)
    }

    /// The name entry `index`'s outputs take.
    pub fn name(&self, index: usize) -> String {
        match &self.entries[index].out {
            Some(name) => name.clone(),
            None => format!("{index:04}"),
        }
    }

    /// The scenario an entry names, as `Scenario::load` takes it: an
    /// embedded name as it is, a file relative to the manifest's folder.
    pub fn scenario_of(&self, index: usize) -> String {
        let s = &self.entries[index].scenario;
        let embedded = twin_sim::scenario::EMBEDDED
            .iter()
            .any(|(name, _, _)| name == s);
        let path = Path::new(s);
        if embedded || path.is_absolute() {
            return s.clone();
        }
        match self.path.parent().filter(|p| !p.as_os_str().is_empty()) {
            Some(dir) => dir.join(path).display().to_string(),
            None => s.clone(),
        }
    }

    fn check(&self, origin: &str) -> Result<()> {
        let mut names: BTreeMap<String, usize> = BTreeMap::new();
        for (i, e) in self.entries.iter().enumerate() {
            let at = format!("{origin}:{}", self.lines[i]);
            if e.scenario.trim().is_empty() {
                return Err(BatchError::EmptyScenario { at });
            }
            for s in &e.set {
                if !s.contains('=') {
                    return Err(BatchError::SetNotPathValue { at, set: s.clone() });
                }
            }
            if let Some(out) = &e.out {
                let bad = out.is_empty()
                    || out.starts_with('.')
                    || out
                        .chars()
                        .any(|c| matches!(c, '/' | '\\') || c.is_control());
                if bad {
                    return Err(BatchError::BadOut {
                        at,
                        out: out.clone(),
                    });
                }
            }
            let name = self.name(i);
            if let Some(first) = names.insert(name.clone(), self.lines[i]) {
                return Err(BatchError::SameOut { at, name, first });
            }
        }
        Ok(())
    }
}

fn parse_json_lines(text: &str, origin: &str) -> Result<(Vec<Entry>, Vec<usize>)> {
    let mut entries = Vec::new();
    let mut lines = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let trimmed = line.trim();
        if trimmed.is_empty() || trimmed.starts_with('#') {
            continue;
        }
        let entry: Entry = serde_json::from_str(trimmed).map_err(|e| {
            let message = e.to_string();
            // serde_json ends its message with where it was; say it our way.
            let message = match message.rfind(" at line ") {
                Some(cut) => &message[..cut],
                None => &message,
            };
            BatchError::Syntax {
                at: format!("{origin}:{}:{}", n + 1, e.column()),
                message: message.to_string(),
            }
        })?;
        entries.push(entry);
        lines.push(n + 1);
    }
    Ok((entries, lines))
}

fn parse_toml(text: &str, origin: &str) -> Result<(Vec<Entry>, Vec<usize>)> {
    let line_of = |offset: usize| text[..offset.min(text.len())].matches('\n').count() + 1;
    let manifest: TomlManifest = toml::from_str(text).map_err(|e| {
        let place = e
            .span()
            .map_or_else(String::new, |s| format!(":{}", line_of(s.start)));
        BatchError::Syntax {
            at: format!("{origin}{place}"),
            message: e.message().trim_end().to_string(),
        }
    })?;
    // Each entry starts at its `[[run]]` header.
    let lines: Vec<usize> = text
        .lines()
        .enumerate()
        .filter(|(_, l)| l.trim_start().starts_with("[[run]]"))
        .map(|(n, _)| n + 1)
        .collect();
    let lines = (0..manifest.run.len())
        .map(|i| lines.get(i).copied().unwrap_or(1))
        .collect();
    Ok((manifest.run, lines))
}

/// Which entries to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Selection {
    One(usize),
    /// Shard `k` of `n`: the entries whose index is `k` modulo `n`, so that
    /// shards of a sweep share its long and short runs alike.
    Shard {
        k: usize,
        n: usize,
    },
    All,
}

impl Selection {
    /// The indices it picks from `count` entries.
    pub fn indices(self, count: usize) -> Result<Vec<usize>> {
        match self {
            Selection::One(i) if i < count => Ok(vec![i]),
            Selection::One(index) => Err(BatchError::PastTheEnd {
                index,
                count,
                last: count.saturating_sub(1),
            }),
            Selection::Shard { k, n } => Ok((k..count).step_by(n).collect()),
            Selection::All => Ok((0..count).collect()),
        }
    }

    /// `k/n`, 0-based `k` below `n`.
    pub fn parse_shard(text: &str) -> Result<Self> {
        let parsed = text
            .split_once('/')
            .and_then(|(k, n)| Some((k.trim().parse().ok()?, n.trim().parse().ok()?)));
        match parsed {
            Some((k, n)) if n > 0 && k < n => Ok(Selection::Shard { k, n }),
            _ => Err(BatchError::NotAShard {
                text: text.to_string(),
            }),
        }
    }
}

/// The environment variables through which schedulers hand an array task
/// its index, in the order they are looked at: Slurm job arrays, Kubernetes
/// Indexed Jobs, AWS Batch array jobs. All count from 0.
pub const SCHEDULER_INDEX_VARIABLES: [&str; 3] = [
    "SLURM_ARRAY_TASK_ID",
    "JOB_COMPLETION_INDEX",
    "AWS_BATCH_JOB_ARRAY_INDEX",
];

/// The index a scheduler gave this task, and the variable it came in, from
/// `var` (the process's environment, or a test's).
pub fn scheduler_index(
    var: impl Fn(&str) -> Option<String>,
) -> Result<Option<(usize, &'static str)>> {
    for name in SCHEDULER_INDEX_VARIABLES {
        if let Some(value) = var(name) {
            return match value.trim().parse::<usize>() {
                Ok(i) => Ok(Some((i, name))),
                Err(_) => Err(BatchError::NotAnIndex {
                    variable: name,
                    value,
                }),
            };
        }
    }
    Ok(None)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_lines_and_toml_give_the_same_entries() {
        let json = "# a sweep\n{\"scenario\": \"ev-meb\", \"set\": [\"node.supervisor.kp=0.6\"], \"seed\": 3, \"out\": \"a\"}\n\n{\"scenario\": \"x.toml\"}\n";
        let toml = "[[run]]\nscenario = \"ev-meb\"\nset = [\"node.supervisor.kp=0.6\"]\nseed = 3\nout = \"a\"\n\n[[run]]\nscenario = \"x.toml\"\n";
        let a = Manifest::parse(json, Path::new("dir/m.jsonl")).unwrap();
        let b = Manifest::parse(toml, Path::new("dir/m.toml")).unwrap();
        assert_eq!(a.entries, b.entries);
        assert_eq!(a.lines, vec![2, 4]);
        assert_eq!(b.lines, vec![1, 7]);
        assert_eq!(a.name(1), "0001");
        assert_eq!(a.scenario_of(0), "ev-meb");
        assert_eq!(a.scenario_of(1), "dir/x.toml");
    }

    #[test]
    fn errors_name_file_line_and_field() {
        let e = Manifest::parse(
            "{\"scenario\": \"ev-meb\"}\n{\"scenario\": \"ev-meb\", \"sed\": 3}\n",
            Path::new("m.jsonl"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("m.jsonl:2:"), "{e}");
        assert!(e.contains("unknown field `sed`"), "{e}");
        let e = Manifest::parse(
            "[[run]]\nscenario = \"ev-meb\"\n\n[[run]]\nscenario = \"ev-meb\"\nseed = \"x\"\n",
            Path::new("m.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("m.toml:6:"), "{e}");
        let e = Manifest::parse(
            "{\"scenario\": \"ev-meb\", \"out\": \"a\"}\n{\"scenario\": \"ev-meb\", \"out\": \"a\"}\n",
            Path::new("m.jsonl"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("m.jsonl:2: `out` `a`") && e.contains("line 1"),
            "{e}"
        );
        let e = Manifest::parse(
            "{\"scenario\": \"ev-meb\", \"set\": [\"kp\"]}",
            Path::new("m"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("m:1: `set`"), "{e}");
    }

    #[test]
    fn selections_and_scheduler_variables() {
        assert_eq!(
            Selection::parse_shard("1/3").unwrap().indices(8).unwrap(),
            vec![1, 4, 7]
        );
        assert!(Selection::parse_shard("3/3").is_err());
        assert!(Selection::One(8).indices(8).is_err());
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| v.to_string())
            }
        };
        assert_eq!(
            scheduler_index(env(&[("JOB_COMPLETION_INDEX", "4")])).unwrap(),
            Some((4, "JOB_COMPLETION_INDEX"))
        );
        assert_eq!(scheduler_index(env(&[])).unwrap(), None);
        assert!(scheduler_index(env(&[("SLURM_ARRAY_TASK_ID", "x")])).is_err());
    }
}
