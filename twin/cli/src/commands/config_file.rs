//! `--config FILE`: a `twin serve` or `twin supervise` service run from a
//! TOML file. Its keys are the command's long options without the dashes
//! (`rotate-every = "1h"`, `meb = ["tcp://0.0.0.0:5700"]`, `quiet = true`),
//! so the file says everything the flags say and `--help` documents both.
//! Each value is checked by the option's own parser, and an error names the
//! file, the line and the key, as a scenario's do. An option given on the
//! command line replaces the file's (all its values, for a repeated one).
//!
//! `twin serve` also reads `[[module]]` tables: a class, one module per
//! table, each with its `name` and its own options over the file's; and an
//! `[index]` table: the class's index page for its teacher (`web`,
//! `web-token-file`), which belongs to the class, not to any module.

use anyhow::{Result, anyhow, bail};
use clap::parser::ValueSource;
use clap::{ArgAction, ArgMatches, Command};
use plant::toml_errors::{self, line_col};
use std::ffi::OsString;
use std::path::Path;
use toml::Spanned;
use toml::de::DeValue;

/// One option of the file, as command-line words (`--baud=9600`).
#[derive(Debug, Clone)]
pub struct Setting {
    /// The option's long name: `baud`.
    pub key: String,
    pub words: Vec<OsString>,
}

/// One `[[module]]` table: its name and options.
#[derive(Debug, Clone)]
pub struct ModuleTable {
    pub name: String,
    pub line: usize,
    pub settings: Vec<Setting>,
}

/// The `[index]` table: where the class's index is served, and the file
/// that keeps the teacher's token.
#[derive(Debug, Clone, PartialEq)]
pub struct IndexTable {
    pub web: std::net::SocketAddr,
    pub token_file: std::path::PathBuf,
    pub line: usize,
}

/// Where the teacher's token is kept when `[index]` names no file: in the
/// working folder, where a module's `NAME.token` is kept.
pub const TEACHER_TOKEN: &str = "teacher.token";

/// A configuration file, read and checked.
#[derive(Debug, Clone)]
pub struct ConfigFile {
    /// The file as errors name it.
    pub origin: String,
    pub settings: Vec<Setting>,
    pub modules: Vec<ModuleTable>,
    pub index: Option<IndexTable>,
}

/// Options that stand for one choice: given on the command line, one of
/// them replaces the file's others too.
const ONE_CHOICE: &[&[&str]] = &[&["out", "record-dir", "no-record"]];

/// `key` and the options that stand for the same choice.
fn one_choice(key: &str) -> Vec<&str> {
    ONE_CHOICE
        .iter()
        .find(|c| c.contains(&key))
        .map_or_else(|| vec![key], |c| c.to_vec())
}

/// Options that make no sense in a file.
const NOT_IN_FILES: &[&str] = &["config", "check", "help"];

impl ConfigFile {
    /// Reads `path` for `command` (the subcommand's own definition);
    /// `[[module]]` tables only when `modules` is true.
    pub fn load(path: &Path, command: &Command, modules: bool) -> Result<Self> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|e| anyhow!("cannot read the configuration {origin}: {e}"))?;
        Self::parse(&text, &origin, command, modules)
    }

    pub fn parse(text: &str, origin: &str, command: &Command, modules: bool) -> Result<Self> {
        let at = |span: Option<std::ops::Range<usize>>| {
            span.map_or_else(String::new, |s| format!(":{}", line_col(text, s.start).0))
        };
        let root = toml_errors::parse(text)
            .map_err(|e| anyhow!("{origin}{}: {}", at(e.span.clone()), e.message))?;
        let DeValue::Table(table) = root.get_ref() else {
            bail!("{origin}: not a TOML table of options");
        };
        let mut file = ConfigFile {
            origin: origin.to_string(),
            settings: Vec::new(),
            modules: Vec::new(),
            index: None,
        };
        for (key, value) in table.iter() {
            let line = line_col(text, key.span().start).0;
            let name = key.get_ref().as_ref();
            if name == "module" {
                if !modules {
                    bail!("{origin}:{line}: `module`: only `twin serve` serves a class of modules");
                }
                file.modules = read_modules(text, origin, command, value)?;
                continue;
            }
            if name == "index" {
                if !modules {
                    bail!(
                        "{origin}:{line}: `index`: only `twin serve` serves a class and its index"
                    );
                }
                file.index = Some(read_index(text, origin, value)?);
                continue;
            }
            file.settings
                .push(setting(origin, command, name, line, value)?);
        }
        if let Some(index) = &file.index
            && file.modules.is_empty()
        {
            bail!(
                "{origin}:{}: `index`: the index lists a class's modules; give each a [[module]] table",
                index.line
            );
        }
        let mut names = std::collections::BTreeMap::new();
        for m in &file.modules {
            if let Some(first) = names.insert(m.name.clone(), m.line) {
                bail!(
                    "{origin}:{}: `name`: module `{}` is named twice (first on line {first})",
                    m.line,
                    m.name
                );
            }
        }
        Ok(file)
    }

    /// The command line a module (or, without modules, the session) runs
    /// with: the file's options, then the module's over them, then those
    /// of the command line, which replace both.
    pub fn words(&self, module: Option<&ModuleTable>, command_line: &ArgMatches) -> Vec<OsString> {
        let module_keys: Vec<&str> = module
            .map(|m| m.settings.iter().map(|s| s.key.as_str()).collect())
            .unwrap_or_default();
        let given = |key: &str| {
            one_choice(key).iter().any(|k| {
                command_line.value_source(&k.replace('-', "_")) == Some(ValueSource::CommandLine)
            })
        };
        let module_has = |key: &str| one_choice(key).iter().any(|k| module_keys.contains(k));
        let mut words = Vec::new();
        for s in &self.settings {
            if !given(&s.key) && !module_has(&s.key) {
                words.extend(s.words.iter().cloned());
            }
        }
        if let Some(m) = module {
            for s in &m.settings {
                if !given(&s.key) {
                    words.extend(s.words.iter().cloned());
                }
            }
        }
        words
    }
}

/// The `[[module]]` tables: each a `name` and options.
fn read_modules(
    text: &str,
    origin: &str,
    command: &Command,
    value: &Spanned<DeValue<'_>>,
) -> Result<Vec<ModuleTable>> {
    let line = line_col(text, value.span().start).0;
    let DeValue::Array(tables) = value.get_ref() else {
        bail!("{origin}:{line}: `module`: give each module as a [[module]] table");
    };
    let mut modules = Vec::new();
    for table in tables.iter() {
        let line = line_col(text, table.span().start).0;
        let DeValue::Table(entries) = table.get_ref() else {
            bail!("{origin}:{line}: `module`: give each module as a [[module]] table");
        };
        let mut name = None;
        let mut settings = Vec::new();
        for (key, value) in entries.iter() {
            let key_line = line_col(text, key.span().start).0;
            let key = key.get_ref().as_ref();
            if key == "name" {
                let Some(n) = value.get_ref().as_str() else {
                    bail!("{origin}:{key_line}: `name` must be a string, the module's name");
                };
                if let Err(why) = twin_sim::scenario::check_name(n) {
                    bail!("{origin}:{key_line}: `name` {why} (it names the module's recordings)");
                }
                name = Some(n.to_string());
                continue;
            }
            if key == "module" {
                bail!("{origin}:{key_line}: `module`: modules do not hold modules");
            }
            settings.push(setting(origin, command, key, key_line, value)?);
        }
        let Some(name) = name else {
            bail!("{origin}:{line}: a [[module]] needs a `name` (it names its recordings)");
        };
        modules.push(ModuleTable {
            name,
            line,
            settings,
        });
    }
    Ok(modules)
}

/// The `[index]` table: `web = "ADDR"` and, if wanted, `web-token-file`.
fn read_index(text: &str, origin: &str, value: &Spanned<DeValue<'_>>) -> Result<IndexTable> {
    let line = line_col(text, value.span().start).0;
    let DeValue::Table(entries) = value.get_ref() else {
        bail!(
            "{origin}:{line}: `index`: give the class's index as an [index] table (web, web-token-file)"
        );
    };
    let mut web = None;
    let mut token_file = None;
    for (key, value) in entries.iter() {
        let key_line = line_col(text, key.span().start).0;
        let key = key.get_ref().as_ref();
        let Some(text) = value.get_ref().as_str() else {
            bail!(
                "{origin}:{key_line}: `{key}` must be a string, got {}",
                shown(value.get_ref())
            );
        };
        match key {
            "web" => {
                web = Some(text.parse::<std::net::SocketAddr>().map_err(|_| {
                    anyhow!(
                        "{origin}:{key_line}: `web`: `{text}` is not an address and port (0.0.0.0:8100, 127.0.0.1:8100)"
                    )
                })?);
            }
            "web-token-file" => token_file = Some(std::path::PathBuf::from(text)),
            other => bail!(
                "{origin}:{key_line}: `index`: unknown key `{other}`; the index takes `web` and `web-token-file`"
            ),
        }
    }
    let Some(web) = web else {
        bail!("{origin}:{line}: `index` needs `web`, the address its page is served on");
    };
    Ok(IndexTable {
        web,
        token_file: token_file.unwrap_or_else(|| TEACHER_TOKEN.into()),
        line,
    })
}

/// The option `key = value` as command-line words, checked by the option's
/// own parser.
fn setting(
    origin: &str,
    command: &Command,
    key: &str,
    line: usize,
    value: &Spanned<DeValue<'_>>,
) -> Result<Setting> {
    let place = format!("{origin}:{line}");
    if NOT_IN_FILES.contains(&key) {
        bail!("{place}: `{key}` is an option of the command line, not of a configuration file");
    }
    let Some(arg) = command
        .get_arguments()
        .find(|a| a.get_long() == Some(key) && !a.is_hide_set())
    else {
        let hint = closest(command, key)
            .map(|k| format!(" (did you mean `{k}`?)"))
            .unwrap_or_default();
        bail!(
            "{place}: unknown option `{key}`{hint}; the keys are the long options of `twin {} --help`",
            command.get_name()
        );
    };
    let flag = format!("--{key}");
    let words: Vec<OsString> = match arg.get_action() {
        ArgAction::SetTrue => match value.get_ref() {
            DeValue::Boolean(true) => vec![flag.clone().into()],
            DeValue::Boolean(false) => Vec::new(),
            other => bail!(
                "{place}: `{key}` must be true or false, got {}",
                shown(other)
            ),
        },
        ArgAction::Append => {
            let items: Vec<&Spanned<DeValue<'_>>> = match value.get_ref() {
                DeValue::Array(items) => items.iter().collect(),
                _ => vec![value],
            };
            let mut words = Vec::new();
            for item in items {
                let Some(text) = scalar(item.get_ref()) else {
                    bail!(
                        "{place}: `{key}` takes strings or numbers, one per value, got {}",
                        shown(item.get_ref())
                    );
                };
                words.push(format!("{flag}={text}").into());
            }
            words
        }
        _ => {
            let Some(text) = scalar(value.get_ref()) else {
                bail!(
                    "{place}: `{key}` takes one value, got {}",
                    shown(value.get_ref())
                );
            };
            vec![format!("{flag}={text}").into()]
        }
    };
    // The option's own parser judges the value, as on the command line.
    let mut argv: Vec<OsString> = vec![command.get_name().into()];
    argv.extend(words.iter().cloned());
    // Alone, an option that needs another (`web-token-file` needs `web`)
    // misses it; whether the file gives both is judged with the whole file.
    if let Err(e) = command.clone().try_get_matches_from(argv)
        && e.kind() != clap::error::ErrorKind::MissingRequiredArgument
    {
        bail!("{place}: `{key}`{}", clap_reason(&e, &flag));
    }
    Ok(Setting {
        key: key.to_string(),
        words,
    })
}

/// A scalar value as a command-line word.
fn scalar(value: &DeValue<'_>) -> Option<String> {
    match value {
        DeValue::String(s) => Some(s.to_string()),
        DeValue::Integer(i) => i64::from_str_radix(&i.as_str().replace('_', ""), i.radix())
            .ok()
            .map(|n| n.to_string()),
        DeValue::Float(f) => {
            let raw = f.as_str().replace('_', "");
            raw.parse::<f64>().ok().map(|_| raw)
        }
        _ => None,
    }
}

/// A value as the errors show it: in TOML's words.
fn shown(value: &DeValue<'_>) -> String {
    match value {
        DeValue::String(s) => format!("the string \"{s}\""),
        DeValue::Integer(i) => format!("the number {}", i.as_str()),
        DeValue::Float(f) => format!("the number {}", f.as_str()),
        DeValue::Boolean(b) => format!("{b}"),
        DeValue::Datetime(d) => format!("the date {d}"),
        DeValue::Array(_) => "a list".into(),
        DeValue::Table(_) => "a table".into(),
    }
}

/// What clap said was wrong with a value, without its own framing
/// (`error: invalid value 'x' for '--baud <BAUD>': …`).
fn clap_reason(e: &clap::Error, flag: &str) -> String {
    use std::error::Error as _;
    if let Some(source) = e.source() {
        let why = source.to_string();
        return if why.starts_with("must ") {
            format!(" {why}")
        } else {
            format!(": {why}")
        };
    }
    let rendered = e.render().to_string();
    let first = rendered.lines().next().unwrap_or_default();
    let first = first.strip_prefix("error: ").unwrap_or(first);
    // `for '--baud <BAUD>'` names the flag; the file names the key.
    let first = match first.find(&format!("'{flag}")) {
        Some(i) => {
            let end = first[i + 1..].find('\'').map_or(first.len(), |j| i + j + 2);
            format!("{}{}", &first[..i], &first[end..])
        }
        None => first.to_string(),
    };
    format!(": {}", first.replace("  ", " ").trim())
}

/// The option closest to a misspelt `key`, if one is close.
fn closest(command: &Command, key: &str) -> Option<String> {
    command
        .get_arguments()
        .filter(|a| !a.is_hide_set())
        .filter_map(|a| a.get_long())
        .map(|long| (edit_distance(long, key), long))
        .filter(|(d, long)| *d <= 2.max(long.len() / 4))
        .min()
        .map(|(_, long)| long.to_string())
}

fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut previous = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let here = row[j + 1];
            row[j + 1] = (previous + usize::from(ca != *cb))
                .min(row[j] + 1)
                .min(here + 1);
            previous = here;
        }
    }
    row[b.len()]
}

impl ConfigFile {
    /// The options in effect for `module` (or the whole file), by key: a
    /// module's over the file's.
    fn effective(&self, module: Option<&str>) -> std::collections::BTreeMap<String, Vec<OsString>> {
        let mut keys: std::collections::BTreeMap<String, Vec<OsString>> = self
            .settings
            .iter()
            .map(|s| (s.key.clone(), s.words.clone()))
            .collect();
        if let Some(m) = module.and_then(|name| self.modules.iter().find(|m| m.name == name)) {
            for s in &m.settings {
                keys.insert(s.key.clone(), s.words.clone());
            }
        }
        keys
    }

    /// The keys whose values differ between `self` and `newer`, for
    /// `module` (or the whole file), in key order.
    pub fn changed_keys(&self, newer: &ConfigFile, module: Option<&str>) -> Vec<String> {
        let (old, new) = (self.effective(module), newer.effective(module));
        let mut keys: Vec<String> = old
            .keys()
            .chain(new.keys())
            .filter(|k| old.get(*k) != new.get(*k))
            .cloned()
            .collect();
        keys.sort();
        keys.dedup();
        keys
    }

    /// The module named `name`.
    pub fn module(&self, name: &str) -> Option<&ModuleTable> {
        self.modules.iter().find(|m| m.name == name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn serve(text: &str) -> Result<ConfigFile> {
        let command = super::super::service::command_of::<super::super::serve::ServeArgs>("serve");
        ConfigFile::parse(text, "class.toml", &command, true)
    }

    #[test]
    fn the_index_table_belongs_to_a_class() {
        let module = "\n[[module]]\nname = \"student01\"\nmeb = [\"tcp://0.0.0.0:5701\"]\n";
        let file = serve(&format!("[index]\nweb = \"0.0.0.0:8100\"\n{module}")).unwrap();
        let index = file.index.unwrap();
        assert_eq!(index.web, "0.0.0.0:8100".parse().unwrap());
        assert_eq!(index.token_file, std::path::PathBuf::from(TEACHER_TOKEN));
        assert!(file.settings.is_empty(), "the index is no module's option");
        for (text, said) in [
            (
                "[index]\nweb = \"0.0.0.0:8100\"\n",
                "give each a [[module]] table",
            ),
            (
                &format!("[index]\nweb-token-file = \"t\"\n{module}"),
                "needs `web`",
            ),
            (
                &format!("[index]\nweb = \"8100\"\n{module}"),
                "not an address and port",
            ),
            (
                &format!("[index]\nweb = \"0.0.0.0:8100\"\nallow = \"x\"\n{module}"),
                "unknown key `allow`",
            ),
        ] {
            let err = format!("{:#}", serve(text).unwrap_err());
            assert!(err.contains(said), "{text}: {err}");
        }
    }

    #[test]
    fn misspelt_options_are_matched_to_the_closest() {
        assert_eq!(edit_distance("kee-files", "keep-files"), 1);
        assert_eq!(edit_distance("", "abc"), 3);
        assert_eq!(edit_distance("rotate-size", "rotate-size"), 0);
    }
}
