//! `twin check master`: the student's program is the bus master (a
//! supervisor) and the twin plays its slaves. A master suite is TOML too,
//! but its checks are situations rather than steps: for a few seconds the
//! twin's first slave behaves one way (answers, answers slowly, in two
//! pieces, after junk, with an error, with a bad FCS or CRC or another
//! slave's id, or not at all) and the master's requests in that time are
//! judged by what its protocol requires of a master in it ([`judge`]).
//! The bus is MEB, Modbus RTU or TCP, or the Controller_network project's
//! 8-byte Modbus; what differs between them is in [`dialect`].
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
//! (`nodes::firmware::SlaveFrontend`: MEB's default map, the Modbus map)
//! over a register image at power-up, or from the Controller_network
//! project's motor and light nodes: no bench behind them, so the values
//! are the image's.

mod dialect;
mod heard;
mod judge;
mod line;
mod play;

use serde::Deserialize;

pub use line::{LineError, MasterLine};
pub use play::{MasterOptions, run_master, unreachable};

use crate::framing::{PROTOCOLS, Protocol};
use crate::suite::{SuiteError, source};

/// The master suites that ship, by name.
pub const BUILT_IN: &[(&str, &str)] = &[
    ("meb-master", include_str!("../suites/meb-master.toml")),
    (
        "modbus-rtu-master",
        include_str!("../suites/modbus-rtu-master.toml"),
    ),
    (
        "modbus-tcp-master",
        include_str!("../suites/modbus-tcp-master.toml"),
    ),
    (
        "modbus8-master",
        include_str!("../suites/modbus8-master.toml"),
    ),
];

/// How the twin's first slave behaves during a check.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Behaviour {
    /// As the controller's firmware does.
    Answers,
    /// The reply starts this many ms after the request.
    Slow(u64),
    /// The reply in two writes this many ms apart.
    Split(u64),
    /// These bytes, then (after this many ms of silence) the reply.
    Junk(Vec<u8>, u64),
    /// Every request refused with this MEB error or Modbus exception code.
    Error(u8),
    /// The reply with its FCS or CRC spoilt.
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
    pub protocol: Protocol,
    pub description: String,
    /// The master's reply timeout the protocol sets, ms.
    pub timeout_ms: u64,
    /// The slaves the twin plays unless told others.
    pub ids: Vec<u8>,
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
    #[serde(default)]
    ids: Vec<u8>,
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
        let Some(protocol) = Protocol::from_name(&raw.protocol) else {
            return Err(whole(format!(
                "protocol `{}`: a master suite speaks {PROTOCOLS}",
                raw.protocol
            )));
        };
        let ids = if raw.ids.is_empty() { vec![1] } else { raw.ids };
        if let Some(id) = ids.iter().find(|id| !protocol.ids().contains(id)) {
            return Err(whole(format!(
                "ids: {id} is no slave id of {} ({} to {})",
                raw.protocol,
                protocol.ids().start(),
                protocol.ids().end()
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
            let slave = behaviour(protocol, c.slave, raw.timeout_ms).map_err(at)?;
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
            protocol,
            description: raw.description,
            timeout_ms: raw.timeout_ms,
            ids,
            checks,
        })
    }

    pub fn points(&self) -> u32 {
        self.checks.iter().map(|c| c.points).sum()
    }
}

const WORDS: &str = "\"answers\", \"bad-fcs\" (\"bad-crc\"), \"wrong-id\" or \"silent\", or a table of one of slow_ms, split_ms, junk (with gap_ms), error";

fn behaviour(protocol: Protocol, slave: toml::Value, timeout_ms: u64) -> Result<Behaviour, String> {
    let table = match slave {
        toml::Value::String(word) => {
            return match word.as_str() {
                "answers" => Ok(Behaviour::Answers),
                "bad-fcs" | "bad-crc" if protocol == Protocol::ModbusTcp => {
                    Err("a Modbus TCP frame has no check bytes to spoil (TCP checks them)".into())
                }
                "bad-fcs" | "bad-crc" => Ok(Behaviour::BadFcs),
                "wrong-id" => Ok(Behaviour::WrongId),
                "silent" => Ok(Behaviour::Silent),
                other => Err(format!("slave `{other}`: {WORDS}")),
            };
        }
        toml::Value::Table(table) => table,
        _ => return Err(format!("slave: {WORDS}")),
    };
    let gap_ms = match table.get("gap_ms").map(toml::Value::as_integer) {
        None => 0,
        Some(Some(ms)) if (0..=1000).contains(&ms) && table.contains_key("junk") => ms as u64,
        Some(_) => return Err("gap_ms: 0 to 1000 ms of silence after `junk`, with it".into()),
    };
    let mut keys = table.iter().filter(|(k, _)| *k != "gap_ms");
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
        "junk" if protocol.is_text() => match value.as_str() {
            Some(junk) if !junk.is_empty() && !junk.contains('\n') => {
                Ok(Behaviour::Junk(junk.into(), gap_ms))
            }
            _ => Err("junk: some bytes, without a line feed (that would end a frame)".into()),
        },
        "junk" => match value.as_str().map(|text| protocol.check_raw(text)) {
            Some(Ok(())) => Ok(Behaviour::Junk(
                protocol.raw(value.as_str().unwrap_or_default()),
                gap_ms,
            )),
            Some(Err(why)) => Err(format!("junk: {why}")),
            None => Err("junk: hex bytes, e.g. \"FF 00\"".into()),
        },
        "error" if protocol.is_text() => match value.as_integer() {
            Some(code @ 1..=4) => Ok(Behaviour::Error(code as u8)),
            _ => Err(format!("error {value}: MEB's error codes are 1 to 4")),
        },
        "error" => match value.as_integer() {
            Some(code @ 1..=255) => Ok(Behaviour::Error(code as u8)),
            _ => Err(format!("error {value}: a Modbus exception code, 1 to 255")),
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
            assert!(suite.checks.len() >= 5, "{name}");
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
    fn a_bad_crc_over_tcp_is_refused_and_the_8_byte_suite_plays_both_nodes() {
        let text = "name = \"x\"\nprotocol = \"modbus-tcp\"\nrole = \"master\"\n[[check]]\nname = \"a\"\nrequirement = \"r\"\nslave = \"answers\"\n[[check]]\nname = \"b\"\nrequirement = \"r\"\nslave = \"bad-crc\"\n";
        let e = MasterSuite::parse(text, "mine.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 8") && e.contains("no check bytes"), "{e}");
        let eight = MasterSuite::load("modbus8-master").unwrap();
        assert_eq!(
            (eight.protocol, eight.ids.as_slice()),
            (Protocol::Modbus8, &[1, 2][..])
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
