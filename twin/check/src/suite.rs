//! A suite: checks, each a list of steps, read from TOML. The built-in
//! suites are files of this format too ([`BUILT_IN`]), so a teacher's own
//! suite is written the way ours are:
//!
//! ```toml
//! name = "MEB slave"
//! protocol = "meb"
//! timeout_ms = 100        # a reply's deadline, unless a step sets `within_ms`
//!
//! [[check]]
//! name = "reads the six analog inputs"
//! requirement = "MEB page, Data model and commands"
//! points = 1
//! steps = [
//!   { send = "@{id}EA0006" },
//!   { expect = "@{id}EA0006", words = 6 },
//! ]
//! ```
//!
//! A step does one thing: `send` a frame (its FCS and `*\n` added; `fcs =
//! "bad"` sends a wrong one, `ending = "*\r\n"` another ending), send `raw`
//! text as it is, `expect` a reply (its text up to the FCS, `#` for any hex
//! digit, then `words` data words of any value; the reply's own FCS is
//! always checked), expect an `error` reply of a code to the last request,
//! expect `silence_ms` of silence, or `wait_ms`. `{id}` stands for the
//! checked slave's id, `{other}` for an id that is not its.

use serde::Deserialize;
use std::path::Path;

/// The suites that ship, by name: `twin check --list` prints them.
pub const BUILT_IN: &[(&str, &str)] = &[("meb-slave", include_str!("../suites/meb-slave.toml"))];

/// A suite that cannot be used, with where and why.
#[derive(Debug, thiserror::Error)]
pub enum SuiteError {
    #[error("cannot read the suite {path}: {why}")]
    Read { path: String, why: std::io::Error },
    #[error("{path}: {why}")]
    Toml { path: String, why: String },
    #[error("{path}, line {line}: {why}")]
    Step {
        path: String,
        line: usize,
        why: String,
    },
    #[error("no built-in suite is called `{0}`: twin check --list names them")]
    Unknown(String),
}

/// A suite ready to run.
#[derive(Debug, Clone, PartialEq)]
pub struct Suite {
    pub name: String,
    pub protocol: String,
    pub description: String,
    pub timeout_ms: u64,
    pub checks: Vec<Check>,
}

/// One check: what it is called, the requirement it holds the program to,
/// what it is worth, and its steps.
#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    pub name: String,
    pub requirement: String,
    pub points: u32,
    pub steps: Vec<Step>,
}

/// One thing a check does.
#[derive(Debug, Clone, PartialEq)]
pub enum Step {
    /// A frame: its text up to the FCS, which is added (`good`) or spoilt,
    /// then the ending.
    Send {
        body: String,
        bad_fcs: bool,
        ending: String,
    },
    /// Bytes as they are (garbage, a partial frame).
    Raw(String),
    /// A reply whose text up to the FCS matches `pattern` (`#`: any hex
    /// digit) followed by `words` data words, within `within_ms` (the
    /// suite's `timeout_ms` if not given).
    Expect {
        pattern: String,
        words: u8,
        within_ms: Option<u64>,
    },
    /// An error reply of `code` to the last request sent.
    Error {
        code: u8,
        within_ms: Option<u64>,
    },
    /// Nothing at all for this long.
    Silence {
        ms: u64,
    },
    Wait {
        ms: u64,
    },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SuiteToml {
    name: String,
    protocol: String,
    #[serde(default)]
    description: String,
    #[serde(default = "default_timeout")]
    timeout_ms: u64,
    #[serde(default, rename = "check")]
    checks: Vec<CheckToml>,
}

fn default_timeout() -> u64 {
    100
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CheckToml {
    name: String,
    requirement: String,
    #[serde(default = "one")]
    points: u32,
    steps: Vec<toml::Spanned<StepToml>>,
}

fn one() -> u32 {
    1
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct StepToml {
    send: Option<String>,
    fcs: Option<String>,
    ending: Option<String>,
    raw: Option<String>,
    expect: Option<String>,
    words: Option<u8>,
    error: Option<u8>,
    within_ms: Option<u64>,
    silence_ms: Option<u64>,
    wait_ms: Option<u64>,
}

impl Suite {
    /// A built-in suite by name, or a teacher's file.
    pub fn load(name_or_path: &str) -> Result<Self, SuiteError> {
        if let Some((name, text)) = BUILT_IN.iter().find(|(n, _)| *n == name_or_path) {
            return Self::parse(text, &format!("the built-in suite {name}"));
        }
        let path = Path::new(name_or_path);
        if !path.exists() && !name_or_path.contains(['/', '.']) {
            return Err(SuiteError::Unknown(name_or_path.into()));
        }
        let text = std::fs::read_to_string(path).map_err(|why| SuiteError::Read {
            path: name_or_path.into(),
            why,
        })?;
        Self::parse(&text, name_or_path)
    }

    /// A suite from its TOML `text`; `path` names it in errors.
    pub fn parse(text: &str, path: &str) -> Result<Self, SuiteError> {
        let raw: SuiteToml = toml::from_str(text).map_err(|e| SuiteError::Toml {
            path: path.into(),
            why: e.to_string().trim_end().to_string(),
        })?;
        let line_of = |offset: usize| text[..offset.min(text.len())].lines().count().max(1);
        let mut checks = Vec::with_capacity(raw.checks.len());
        for check in raw.checks {
            let mut steps = Vec::with_capacity(check.steps.len());
            let mut sent = false;
            for spanned in check.steps {
                let line = line_of(spanned.span().start);
                let step = step(spanned.into_inner(), sent).map_err(|why| SuiteError::Step {
                    path: path.into(),
                    line,
                    why: format!("check `{}`: {why}", check.name),
                })?;
                sent |= matches!(step, Step::Send { .. } | Step::Raw(_));
                steps.push(step);
            }
            checks.push(Check {
                name: check.name,
                requirement: check.requirement,
                points: check.points,
                steps,
            });
        }
        if raw.protocol != "meb" {
            return Err(SuiteError::Toml {
                path: path.into(),
                why: format!(
                    "protocol `{}`: this version checks MEB programs (protocol = \"meb\")",
                    raw.protocol
                ),
            });
        }
        Ok(Suite {
            name: raw.name,
            protocol: raw.protocol,
            description: raw.description,
            timeout_ms: raw.timeout_ms,
            checks,
        })
    }

    /// The points of every check.
    pub fn points(&self) -> u32 {
        self.checks.iter().map(|c| c.points).sum()
    }
}

/// The one action of a step, checked.
fn step(s: StepToml, sent: bool) -> Result<Step, String> {
    let actions = [
        s.send.is_some(),
        s.raw.is_some(),
        s.expect.is_some(),
        s.error.is_some(),
        s.silence_ms.is_some(),
        s.wait_ms.is_some(),
    ];
    let count = actions.iter().filter(|a| **a).count();
    if count != 1 {
        return Err(format!(
            "a step does one thing (send, raw, expect, error, silence_ms or wait_ms); this one does {count}"
        ));
    }
    let only_with = |given: bool, field: &str, action: &str| {
        if given {
            Err(format!("`{field}` goes with `{action}` only"))
        } else {
            Ok(())
        }
    };
    if s.send.is_none() {
        only_with(s.fcs.is_some(), "fcs", "send")?;
        only_with(s.ending.is_some(), "ending", "send")?;
    }
    if s.expect.is_none() {
        only_with(s.words.is_some(), "words", "expect")?;
    }
    if s.expect.is_none() && s.error.is_none() {
        only_with(s.within_ms.is_some(), "within_ms", "expect or error")?;
    }
    let within_ms = s.within_ms;
    if let Some(body) = s.send {
        if !body.starts_with('@') {
            return Err(format!("send `{body}`: a frame starts with @"));
        }
        let bad_fcs = match s.fcs.as_deref() {
            None | Some("good") => false,
            Some("bad") => true,
            Some(other) => return Err(format!("fcs `{other}`: \"good\" or \"bad\"")),
        };
        let ending = s.ending.unwrap_or_else(|| "*\n".into());
        return Ok(Step::Send {
            body,
            bad_fcs,
            ending,
        });
    }
    if let Some(raw) = s.raw {
        return Ok(Step::Raw(raw));
    }
    if (s.expect.is_some() || s.error.is_some()) && !sent {
        return Err("a reply is expected before anything was sent".into());
    }
    if let Some(pattern) = s.expect {
        if !pattern.starts_with('@') {
            return Err(format!("expect `{pattern}`: a reply starts with @"));
        }
        return Ok(Step::Expect {
            pattern,
            words: s.words.unwrap_or(0),
            within_ms,
        });
    }
    if let Some(code) = s.error {
        if !(1..=4).contains(&code) {
            return Err(format!("error {code}: MEB's error codes are 1 to 4"));
        }
        return Ok(Step::Error { code, within_ms });
    }
    if let Some(ms) = s.silence_ms {
        return Ok(Step::Silence { ms });
    }
    Ok(Step::Wait {
        ms: s.wait_ms.unwrap_or(0),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_suites_parse() {
        for (name, text) in BUILT_IN {
            let suite = Suite::parse(text, name).unwrap();
            assert!(suite.checks.len() > 10, "{name}");
        }
    }

    #[test]
    fn a_step_that_does_two_things_is_refused_with_its_line() {
        let text = "name = \"x\"\nprotocol = \"meb\"\n\n[[check]]\nname = \"c\"\nrequirement = \"r\"\nsteps = [\n  { send = \"@{id}EA0001\" },\n  { expect = \"@{id}EA0001\", silence_ms = 5 },\n]\n";
        let e = Suite::parse(text, "mine.toml").unwrap_err().to_string();
        assert_eq!(
            e,
            "mine.toml, line 9: check `c`: a step does one thing (send, raw, expect, error, silence_ms or wait_ms); this one does 2"
        );
    }

    #[test]
    fn a_misspelt_field_is_named_with_its_line() {
        let text = "name = \"x\"\nprotocol = \"meb\"\n[[check]]\nname = \"c\"\nrequirement = \"r\"\nsteps = [{ sned = \"@01EA0001\" }]\n";
        let e = Suite::parse(text, "mine.toml").unwrap_err().to_string();
        assert!(
            e.starts_with("mine.toml: TOML parse error at line 6"),
            "{e}"
        );
        assert!(e.contains("unknown field `sned`"), "{e}");
    }

    #[test]
    fn a_reply_before_any_request_is_refused() {
        let text = "name = \"x\"\nprotocol = \"meb\"\n[[check]]\nname = \"c\"\nrequirement = \"r\"\nsteps = [{ error = 2 }]\n";
        let e = Suite::parse(text, "mine.toml").unwrap_err().to_string();
        assert!(
            e.contains("line 6") && e.contains("before anything was sent"),
            "{e}"
        );
    }
}
