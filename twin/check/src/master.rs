//! `twin check master`: the student's program is the bus master (a
//! supervisor) and the twin plays its slaves. A master suite is TOML too,
//! but its checks are situations rather than steps: for a few seconds the
//! twin's first slave behaves one way (answers, answers slowly, in two
//! pieces, after junk, with an error, with a bad FCS or another slave's
//! id, or not at all) and the master's requests in that time are judged by
//! what the MEB page requires of a master in it ([`judge`]).
//!
//! ```toml
//! name = "MEB master"
//! protocol = "meb"
//! role = "master"
//! timeout_ms = 100        # the master's reply timeout the page sets
//!
//! [[check]]
//! name = "waits for a slow reply"
//! requirement = "MEB page, Timing"
//! seconds = 2
//! slave = { slow_ms = 60 }
//! ```
//!
//! The replies come from the controller's own slave code
//! (`nodes::firmware::SlaveFrontend`, the default map) over a register
//! image at power-up: no bench behind it, so the values are the image's.

mod heard;
mod judge;
mod line;
mod play;

use serde::Deserialize;

pub use line::{LineError, MasterLine};
pub use play::{MasterOptions, run_master, unreachable};

use crate::suite::{SuiteError, source};

/// The master suites that ship, by name.
pub const BUILT_IN: &[(&str, &str)] = &[("meb-master", include_str!("../suites/meb-master.toml"))];

/// How the twin's first slave behaves during a check.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Behaviour {
    /// As the controller's firmware does.
    Answers,
    /// The reply starts this many ms after the request.
    Slow(u64),
    /// The reply in two writes this many ms apart.
    Split(u64),
    /// These bytes, then the reply.
    Junk(String),
    /// Every request refused with this MEB error code.
    Error(u8),
    /// The reply with its FCS spoilt.
    BadFcs,
    /// The reply with another slave's id.
    WrongId,
    /// No reply at all.
    Silent,
}

/// One situation and what it is worth.
#[derive(Debug, Clone, PartialEq)]
pub struct Situation {
    pub name: String,
    pub requirement: String,
    pub points: u32,
    pub seconds: f64,
    pub slave: Behaviour,
}

/// A master suite ready to run.
#[derive(Debug, Clone, PartialEq)]
pub struct MasterSuite {
    pub name: String,
    pub protocol: String,
    pub description: String,
    /// The master's reply timeout the protocol sets, ms.
    pub timeout_ms: u64,
    pub checks: Vec<Situation>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SuiteToml {
    name: String,
    protocol: String,
    role: Option<String>,
    #[serde(default)]
    description: String,
    #[serde(default = "hundred")]
    timeout_ms: u64,
    #[serde(default, rename = "check")]
    checks: Vec<toml::Spanned<SituationToml>>,
}

fn hundred() -> u64 {
    100
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SituationToml {
    name: String,
    requirement: String,
    #[serde(default = "one")]
    points: u32,
    #[serde(default = "two")]
    seconds: f64,
    slave: toml::Value,
}

fn one() -> u32 {
    1
}

fn two() -> f64 {
    2.0
}

impl MasterSuite {
    /// A built-in master suite by name, or a teacher's file.
    pub fn load(name_or_path: &str) -> Result<Self, SuiteError> {
        let (text, path) = source(name_or_path, BUILT_IN)?;
        Self::parse(&text, &path)
    }

    /// A master suite from its TOML `text`; `path` names it in errors.
    pub fn parse(text: &str, path: &str) -> Result<Self, SuiteError> {
        let whole = |why: String| SuiteError::Toml {
            path: path.into(),
            why,
        };
        let raw: SuiteToml =
            toml::from_str(text).map_err(|e| whole(e.to_string().trim_end().to_string()))?;
        if raw.role.as_deref() != Some("master") {
            return Err(whole(
                "not a master's suite: a master suite says role = \"master\" (a slave's suite goes to `twin check slave --suite`)".into(),
            ));
        }
        if raw.protocol != "meb" {
            return Err(whole(format!(
                "protocol `{}`: this version checks MEB masters (protocol = \"meb\")",
                raw.protocol
            )));
        }
        if !(1..=10_000).contains(&raw.timeout_ms) {
            return Err(whole(format!(
                "timeout_ms {}: 1 to 10000 ms",
                raw.timeout_ms
            )));
        }
        // A table's span may begin on the blank line before its header.
        let line_of = |offset: usize| {
            let rest = text.get(offset..).unwrap_or("");
            let start = offset + (rest.len() - rest.trim_start().len());
            text.get(..start).unwrap_or(text).matches('\n').count() + 1
        };
        let mut checks = Vec::with_capacity(raw.checks.len());
        for spanned in raw.checks {
            let line = line_of(spanned.span().start);
            let c = spanned.into_inner();
            let at = |why: String| SuiteError::Step {
                path: path.into(),
                line,
                why: format!("check `{}`: {why}", c.name),
            };
            if !(0.5..=600.0).contains(&c.seconds) {
                return Err(at(format!("seconds {}: 0.5 to 600", c.seconds)));
            }
            let slave = behaviour(c.slave, raw.timeout_ms).map_err(at)?;
            checks.push(Situation {
                name: c.name,
                requirement: c.requirement,
                points: c.points,
                seconds: c.seconds,
                slave,
            });
        }
        if checks.first().is_none_or(|c| c.slave != Behaviour::Answers) {
            return Err(whole(
                "the first check must be one where the slave answers (slave = \"answers\"): the others are judged against how the master polls then".into(),
            ));
        }
        Ok(MasterSuite {
            name: raw.name,
            protocol: raw.protocol,
            description: raw.description,
            timeout_ms: raw.timeout_ms,
            checks,
        })
    }

    pub fn points(&self) -> u32 {
        self.checks.iter().map(|c| c.points).sum()
    }
}

const WORDS: &str = "\"answers\", \"bad-fcs\", \"wrong-id\" or \"silent\", or a table of one of slow_ms, split_ms, junk, error";

fn behaviour(slave: toml::Value, timeout_ms: u64) -> Result<Behaviour, String> {
    let table = match slave {
        toml::Value::String(word) => {
            return match word.as_str() {
                "answers" => Ok(Behaviour::Answers),
                "bad-fcs" => Ok(Behaviour::BadFcs),
                "wrong-id" => Ok(Behaviour::WrongId),
                "silent" => Ok(Behaviour::Silent),
                other => Err(format!("slave `{other}`: {WORDS}")),
            };
        }
        toml::Value::Table(table) => table,
        _ => return Err(format!("slave: {WORDS}")),
    };
    let mut keys = table.iter();
    let (Some((key, value)), None) = (keys.next(), keys.next()) else {
        return Err(format!("slave: one behaviour, {WORDS}"));
    };
    let ms = || match value.as_integer() {
        Some(ms) if (0..i64::from(u32::MAX)).contains(&ms) => Ok(ms as u64),
        _ => Err(format!("slave: {key} is a number of ms")),
    };
    match key.as_str() {
        "slow_ms" | "split_ms" => {
            let ms = ms()?;
            if ms >= timeout_ms {
                return Err(format!(
                    "{ms} ms is not within the master's {timeout_ms} ms timeout: a reply that late is no reply"
                ));
            }
            Ok(if key == "slow_ms" {
                Behaviour::Slow(ms)
            } else {
                Behaviour::Split(ms)
            })
        }
        "junk" => match value.as_str() {
            Some(junk) if !junk.is_empty() && !junk.contains('\n') => {
                Ok(Behaviour::Junk(junk.into()))
            }
            _ => Err("junk: some bytes, without a line feed (that would end a frame)".into()),
        },
        "error" => match value.as_integer() {
            Some(code @ 1..=4) => Ok(Behaviour::Error(code as u8)),
            _ => Err(format!("error {value}: MEB's error codes are 1 to 4")),
        },
        other => Err(format!("slave: `{other}` is no behaviour: {WORDS}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_master_suites_parse() {
        for (name, text) in BUILT_IN {
            let suite = MasterSuite::parse(text, name).unwrap();
            assert!(suite.checks.len() >= 8, "{name}");
        }
    }

    #[test]
    fn a_behaviour_out_of_the_timeout_is_refused_with_its_line() {
        let text = "name = \"x\"\nprotocol = \"meb\"\nrole = \"master\"\n\n[[check]]\nname = \"a\"\nrequirement = \"r\"\nslave = \"answers\"\n\n[[check]]\nname = \"late\"\nrequirement = \"r\"\nslave = { slow_ms = 150 }\n";
        let e = MasterSuite::parse(text, "mine.toml")
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "mine.toml, line 10: check `late`: 150 ms is not within the master's 100 ms timeout: a reply that late is no reply"
        );
    }

    #[test]
    fn a_slave_suite_is_told_apart() {
        let text = "name = \"x\"\nprotocol = \"meb\"\n";
        let e = MasterSuite::parse(text, "mine.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a master's suite"), "{e}");
    }

    #[test]
    fn an_unknown_behaviour_is_named() {
        let text = "name = \"x\"\nprotocol = \"meb\"\nrole = \"master\"\n[[check]]\nname = \"a\"\nrequirement = \"r\"\nslave = \"sulks\"\n";
        let e = MasterSuite::parse(text, "mine.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 4") && e.contains("slave `sulks`"), "{e}");
    }
}
