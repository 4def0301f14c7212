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
//! A check with `timing = true` holds the program to the protocol's
//! timing: `--patience` leaves its deadlines as written.
//!
//! A step does one thing: `send` a frame (its FCS and `*\n` added; `fcs =
//! "bad"` sends a wrong one, `ending = "*\r\n"` another ending), send `raw`
//! text as it is, `expect` a reply (its text up to the FCS, `#` for any hex
//! digit, then `words` data words of any value; the reply's own FCS is
//! always checked), expect an `error` reply of a code to the last request,
//! expect `silence_ms` of silence, or `wait_ms`. `{id}` stands for the
//! checked slave's id, `{other}` for an id that is not its.
//!
//! The binary protocols (`protocol = "modbus-rtu"`, `"modbus-tcp"` or
//! `"modbus8"`, the Controller_network project's 8-byte frames) write
//! frames as hex bytes, spaces allowed between them: `send = "{id} 03 0000
//! 0003"` is the unit id and the PDU (the six bytes before the CRC of an
//! 8-byte frame); the CRC is added (`crc = "bad"` spoils it), or over TCP
//! the MBAP header with a transaction id the run counts. `raw` bytes go as
//! they are. `expect` is the reply's unit and PDU, `..` for a byte of any
//! value, then `bytes` data bytes of any value; its CRC (its header over
//! TCP, the transaction id included) is always checked. `exception = 2`
//! expects the exception reply of that code to the request it answers.
//! `{id}` and `{other}` are hex bytes there.
//!
//! A `bench` step looks at the plant the slave drives instead of the line
//! (`crate::bench`): `{ bench = "forward", vel = 2048 }` (or `"reverse"`),
//! `{ bench = "coasts" }`, `{ bench = "brakes" }`, `{ bench = "stopped" }`,
//! `{ bench = "inputs", inputs = "V2 I V1 RPM_M RPM_L LDR", rpm_window_ms =
//! 500 }` (the last reply's data words, `-` for one not compared). A check
//! with one is a bench check: without a bench it is not applicable.

use crate::bench::{BENCH_STEPS, BenchStep, Input};
use crate::framing::{PROTOCOLS, Protocol};
use serde::Deserialize;
use std::path::Path;

/// The suites that ship, by name: `twin check --list` prints them.
pub const BUILT_IN: &[(&str, &str)] = &[
    ("meb-slave", include_str!("../suites/meb-slave.toml")),
    (
        "modbus-rtu-slave",
        include_str!("../suites/modbus-rtu-slave.toml"),
    ),
    (
        "modbus-tcp-slave",
        include_str!("../suites/modbus-tcp-slave.toml"),
    ),
    (
        "modbus8-slave",
        include_str!("../suites/modbus8-slave.toml"),
    ),
];

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
    pub protocol: Protocol,
    pub description: String,
    pub timeout_ms: u64,
    /// How many times as long its waits are (`--patience`, 1 unless
    /// given): a reply's deadline, a silence, a wait, the quiet line
    /// between checks; a timing check's are as written.
    pub patience: f64,
    pub checks: Vec<Check>,
}

/// One check: what it is called, the requirement it holds the program to,
/// what it is worth, and its steps.
#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    pub name: String,
    pub requirement: String,
    pub points: u32,
    /// A check of the protocol's timing: its deadlines are the page's,
    /// and patience does not stretch them.
    pub timing: bool,
    pub steps: Vec<Step>,
}

impl Check {
    /// Whether a step of it looks at the bench: without one, the check
    /// is not applicable.
    pub fn is_bench(&self) -> bool {
        self.steps.iter().any(|s| matches!(s, Step::Bench(_)))
    }
}

/// One thing a check does.
#[derive(Debug, Clone, PartialEq)]
pub enum Step {
    /// A frame: its body (MEB's text up to the FCS, a binary frame's
    /// bytes before its CRC), the check bytes added (`spoil`: wrong ones),
    /// then MEB's ending.
    Send {
        body: String,
        spoil: bool,
        ending: String,
    },
    /// Bytes as they are (garbage, a partial frame).
    Raw(String),
    /// A reply whose body matches `pattern` (MEB: `#` any hex digit;
    /// binary: `..` any byte) followed by `data` data words (MEB) or bytes
    /// of any value, within `within_ms` (the suite's `timeout_ms` if not
    /// given).
    Expect {
        pattern: String,
        data: u16,
        within_ms: Option<u64>,
    },
    /// An error (MEB) or exception (Modbus) reply of `code` to the request
    /// it answers.
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
    /// The plant the slave drives, held to what the frames before said.
    Bench(BenchStep),
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
    #[serde(default)]
    timing: bool,
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
    crc: Option<String>,
    ending: Option<String>,
    raw: Option<String>,
    expect: Option<String>,
    words: Option<u8>,
    bytes: Option<u16>,
    error: Option<u8>,
    exception: Option<u8>,
    within_ms: Option<u64>,
    silence_ms: Option<u64>,
    wait_ms: Option<u64>,
    bench: Option<String>,
    vel: Option<u16>,
    inputs: Option<String>,
    rpm_window_ms: Option<u16>,
}

/// The text of a built-in suite of `built_in` by name, or of a teacher's
/// file, with how errors name it.
pub(crate) fn source(
    name_or_path: &str,
    built_in: &[(&str, &'static str)],
) -> Result<(std::borrow::Cow<'static, str>, String), SuiteError> {
    if let Some((name, text)) = built_in.iter().find(|(n, _)| *n == name_or_path) {
        return Ok(((*text).into(), format!("the built-in suite {name}")));
    }
    let path = Path::new(name_or_path);
    if !path.exists() && !name_or_path.contains(['/', '.']) {
        return Err(SuiteError::Unknown(name_or_path.into()));
    }
    let text = std::fs::read_to_string(path).map_err(|why| SuiteError::Read {
        path: name_or_path.into(),
        why,
    })?;
    Ok((text.into(), name_or_path.into()))
}

impl Suite {
    /// A built-in suite by name, or a teacher's file.
    pub fn load(name_or_path: &str) -> Result<Self, SuiteError> {
        let (text, path) = source(name_or_path, BUILT_IN)?;
        Self::parse(&text, &path)
    }

    /// A suite from its TOML `text`; `path` names it in errors.
    pub fn parse(text: &str, path: &str) -> Result<Self, SuiteError> {
        let raw: SuiteToml = toml::from_str(text).map_err(|e| SuiteError::Toml {
            path: path.into(),
            why: e.to_string().trim_end().to_string(),
        })?;
        let Some(protocol) = Protocol::from_name(&raw.protocol) else {
            return Err(SuiteError::Toml {
                path: path.into(),
                why: format!("protocol `{}`: a suite speaks {PROTOCOLS}", raw.protocol),
            });
        };
        // A step at the start of its line is on the line after the last
        // newline before it.
        let line_of = |offset: usize| {
            1 + text.as_bytes()[..offset.min(text.len())]
                .iter()
                .filter(|&&b| b == b'\n')
                .count()
        };
        let mut checks = Vec::with_capacity(raw.checks.len());
        for check in raw.checks {
            let mut steps = Vec::with_capacity(check.steps.len());
            let mut sent = false;
            for spanned in check.steps {
                let line = line_of(spanned.span().start);
                let step =
                    step(protocol, spanned.into_inner(), sent).map_err(|why| SuiteError::Step {
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
                timing: check.timing,
                steps,
            });
        }
        Ok(Suite {
            name: raw.name,
            protocol,
            description: raw.description,
            timeout_ms: raw.timeout_ms,
            patience: 1.0,
            checks,
        })
    }

    /// The points of every check.
    pub fn points(&self) -> u32 {
        self.checks.iter().map(|c| c.points).sum()
    }

    /// The points of the checks that need no bench.
    pub fn points_without_bench(&self) -> u32 {
        self.checks
            .iter()
            .filter(|c| !c.is_bench())
            .map(|c| c.points)
            .sum()
    }
}

/// The one action of a step, checked against the suite's protocol.
fn step(protocol: Protocol, s: StepToml, sent: bool) -> Result<Step, String> {
    let actions = [
        s.send.is_some(),
        s.raw.is_some(),
        s.expect.is_some(),
        s.error.is_some(),
        s.exception.is_some(),
        s.silence_ms.is_some(),
        s.wait_ms.is_some(),
        s.bench.is_some(),
    ];
    let count = actions.iter().filter(|a| **a).count();
    if count != 1 {
        return Err(format!(
            "a step does one thing (send, raw, expect, {}, silence_ms, wait_ms or bench); this one does {count}",
            if protocol.is_text() {
                "error"
            } else {
                "exception"
            }
        ));
    }
    not_in_protocol(protocol, &s)?;
    if let Some(what) = s.bench {
        return bench_step(&what, s.vel, s.inputs, s.rpm_window_ms, sent);
    }
    for (given, field) in [
        (s.vel.is_some(), "vel"),
        (s.inputs.is_some(), "inputs"),
        (s.rpm_window_ms.is_some(), "rpm_window_ms"),
    ] {
        if given {
            return Err(format!("`{field}` goes with `bench` only"));
        }
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
        only_with(s.crc.is_some(), "crc", "send")?;
        only_with(s.ending.is_some(), "ending", "send")?;
    }
    if s.expect.is_none() {
        only_with(s.words.is_some(), "words", "expect")?;
        only_with(s.bytes.is_some(), "bytes", "expect")?;
    }
    let reply = if protocol.is_text() {
        "error"
    } else {
        "exception"
    };
    if s.expect.is_none() && s.error.is_none() && s.exception.is_none() {
        only_with(
            s.within_ms.is_some(),
            "within_ms",
            &format!("expect or {reply}"),
        )?;
    }
    let within_ms = s.within_ms;
    if let Some(body) = s.send {
        protocol.check_send(&body)?;
        let (field, check) = match (s.fcs, s.crc) {
            (Some(fcs), _) => ("fcs", fcs),
            (_, Some(crc)) => ("crc", crc),
            _ => ("", "good".into()),
        };
        let spoil = match check.as_str() {
            "good" => false,
            "bad" => true,
            other => return Err(format!("{field} `{other}`: \"good\" or \"bad\"")),
        };
        let ending = s.ending.unwrap_or_else(|| "*\n".into());
        return Ok(Step::Send {
            body,
            spoil,
            ending,
        });
    }
    if let Some(raw) = s.raw {
        protocol
            .check_raw(&raw)
            .map_err(|why| format!("raw: {why}"))?;
        return Ok(Step::Raw(raw));
    }
    if (s.expect.is_some() || s.error.is_some() || s.exception.is_some()) && !sent {
        return Err("a reply is expected before anything was sent".into());
    }
    if let Some(pattern) = s.expect {
        protocol
            .check_pattern(&pattern)
            .map_err(|why| format!("expect: {why}"))?;
        let data = match (s.words, s.bytes) {
            (Some(words), _) => u16::from(words),
            (_, Some(bytes)) => bytes,
            _ => 0,
        };
        return Ok(Step::Expect {
            pattern,
            data,
            within_ms,
        });
    }
    if let Some(code) = s.error {
        if !(1..=4).contains(&code) {
            return Err(format!("error {code}: MEB's error codes are 1 to 4"));
        }
        return Ok(Step::Error { code, within_ms });
    }
    if let Some(code) = s.exception {
        if code == 0 {
            return Err("exception 0: Modbus exception codes start at 1".into());
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

/// A `bench` step and its fields.
fn bench_step(
    what: &str,
    vel: Option<u16>,
    inputs: Option<String>,
    rpm_window_ms: Option<u16>,
    sent: bool,
) -> Result<Step, String> {
    let turns = matches!(what, "forward" | "reverse");
    if vel.is_some() != turns {
        return Err(if turns {
            format!("bench `{what}` needs `vel`, the VEL written (0 to 4095)")
        } else {
            format!("`vel` goes with bench `forward` or `reverse`, not `{what}`")
        });
    }
    if inputs.is_some() != (what == "inputs") || (rpm_window_ms.is_some() && what != "inputs") {
        return Err(if what == "inputs" {
            "bench `inputs` needs `inputs`, the words the last reply carries (e.g. \"V2 I V1 RPM_M RPM_L LDR\")".into()
        } else {
            format!("`inputs` and `rpm_window_ms` go with bench `inputs`, not `{what}`")
        });
    }
    let step = match what {
        "forward" | "reverse" => {
            let vel = vel.unwrap_or(0);
            if vel > crate::bench::model::DAC_MAX {
                return Err(format!("vel {vel}: VEL is 0 to 4095"));
            }
            BenchStep::Turns {
                vel,
                reverse: what == "reverse",
            }
        }
        "coasts" => BenchStep::Coasts,
        "brakes" => BenchStep::Brakes,
        "stopped" => BenchStep::Stopped,
        "inputs" => {
            if !sent {
                return Err("bench `inputs` compares a reply: nothing was sent before it".into());
            }
            let words = inputs
                .unwrap_or_default()
                .split_whitespace()
                .map(|w| {
                    Input::from_name(w).ok_or_else(|| {
                        format!("inputs: `{w}` is no input (V2, I, V1, RPM_M, RPM_L, LDR, or - for one not compared)")
                    })
                })
                .collect::<Result<Vec<_>, _>>()?;
            if words.is_empty() {
                return Err("inputs: name at least one input".into());
            }
            let rpm_window_ms = rpm_window_ms.unwrap_or(100);
            if !RPM_WIN_MS.contains(&rpm_window_ms) {
                return Err(format!(
                    "rpm_window_ms {rpm_window_ms}: RPM_WIN is 1 to 1000 ms"
                ));
            }
            BenchStep::Inputs {
                words,
                rpm_window_ms,
            }
        }
        other => return Err(format!("bench `{other}`: a bench step is {BENCH_STEPS}")),
    };
    Ok(Step::Bench(step))
}

/// RPM_WIN's range (the MEB page's).
const RPM_WIN_MS: std::ops::RangeInclusive<u16> = 1..=1000;

/// A field that belongs to another protocol, named with the one to use.
fn not_in_protocol(protocol: Protocol, s: &StepToml) -> Result<(), String> {
    let misplaced: Vec<(bool, &str)> = match protocol {
        Protocol::Meb => vec![
            (
                s.crc.is_some(),
                "`crc` is for the binary protocols: an MEB frame's check is its FCS (`fcs`)",
            ),
            (
                s.bytes.is_some(),
                "`bytes` is for the binary protocols: an MEB reply's data is counted in `words`",
            ),
            (
                s.exception.is_some(),
                "`exception` is for the Modbus protocols: MEB replies `error`",
            ),
        ],
        _ => vec![
            (
                s.fcs.is_some(),
                "`fcs` is MEB's: a Modbus frame's check is its CRC (`crc`)",
            ),
            (
                s.ending.is_some(),
                "`ending` is MEB's: a Modbus frame has none",
            ),
            (
                s.words.is_some(),
                "`words` is MEB's: a Modbus reply's data is counted in `bytes`",
            ),
            (
                s.error.is_some(),
                "`error` is MEB's: a Modbus slave answers an `exception`",
            ),
        ],
    };
    if let Some((_, why)) = misplaced.iter().find(|(given, _)| *given) {
        return Err((*why).into());
    }
    if protocol == Protocol::ModbusTcp && s.crc.is_some() {
        return Err("`crc`: Modbus TCP frames carry no CRC (the MBAP header frames them)".into());
    }
    Ok(())
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
            "mine.toml, line 9: check `c`: a step does one thing (send, raw, expect, error, silence_ms, wait_ms or bench); this one does 2"
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

    fn one_check(protocol: &str, steps: &str) -> String {
        format!(
            "name = \"x\"\nprotocol = \"{protocol}\"\n[[check]]\nname = \"c\"\nrequirement = \"r\"\nsteps = [\n{steps}\n]\n"
        )
    }

    #[test]
    fn a_binary_step_reads_hex_bytes_and_its_counts() {
        let text = one_check(
            "modbus-rtu",
            "{ send = \"{id} 04 0000 000A\", crc = \"bad\" },\n{ expect = \"{id} 04 14\", bytes = 20 },\n{ exception = 2 },",
        );
        let suite = Suite::parse(&text, "mine.toml").unwrap();
        assert_eq!(suite.protocol, Protocol::ModbusRtu);
        let steps = &suite.checks[0].steps;
        assert!(matches!(&steps[0], Step::Send { spoil: true, .. }));
        assert!(matches!(&steps[1], Step::Expect { data: 20, .. }));
        assert!(matches!(&steps[2], Step::Error { code: 2, .. }));
    }

    #[test]
    fn a_binary_suites_mistakes_are_named_with_their_line() {
        let cases = [
            (
                "modbus-rtu",
                "{ send = \"{id} 04 00G0 000A\" },",
                "line 7: check `c`: `G0` in `00G0` is not a hex byte",
            ),
            (
                "modbus-rtu",
                "{ send = \"{id} 04 000 000A\" },",
                "`000` has an odd number of hex digits",
            ),
            (
                "modbus8",
                "{ send = \"01 03 0001\" },",
                "an 8-byte Modbus frame is six bytes",
            ),
            (
                "modbus-tcp",
                "{ send = \"01 03 0001 0001\", crc = \"bad\" },",
                "Modbus TCP frames carry no CRC",
            ),
            (
                "modbus-rtu",
                "{ send = \"01 03 0001 0001\", fcs = \"bad\" },",
                "`fcs` is MEB's",
            ),
            (
                "meb",
                "{ send = \"@{id}EA0001\" },\n{ exception = 2 },",
                "line 8: check `c`: `exception` is for the Modbus protocols",
            ),
            (
                "modbus-rtu",
                "{ send = \"01 03 0001 0001\" },\n{ expect = \"01 03 02\", words = 1 },",
                "`words` is MEB's",
            ),
        ];
        for (protocol, steps, why) in cases {
            let e = Suite::parse(&one_check(protocol, steps), "mine.toml")
                .unwrap_err()
                .to_string();
            assert!(e.starts_with("mine.toml, line "), "{e}");
            assert!(e.contains(why), "{protocol} {steps}: {e}");
        }
        let e = Suite::parse(&one_check("modbus", ""), "mine.toml")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("protocol `modbus`: a suite speaks \"meb\", \"modbus-rtu\""),
            "{e}"
        );
    }
}
