//! What `twin serve` and `twin supervise` share as services: their options
//! merged from a configuration file and the command line, and SIGHUP's
//! reread of that file.

use anyhow::{Result, anyhow};
use clap::{ArgMatches, Args, Command, FromArgMatches};
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use twin_realtime::allow::{AllowList, Network};
use twin_realtime::rotate::RecordPlan;
use twin_realtime::session::OnHangup;

use super::config_file::ConfigFile;

/// The options SIGHUP rereads from the file; any other change waits for a
/// restart (links, the plant and its seed cannot change under a client).
const REREAD: &[&str] = &[
    "allow",
    "rotate-every",
    "rotate-size",
    "keep-files",
    "keep-age",
    "keep-size",
];

/// The subcommand `name` as clap defines it (for a file's keys and values).
pub fn command_of<A: Args>(name: &'static str) -> Command {
    super::take_negative_numbers(A::augment_args(Command::new(name)))
}

/// The options `words` (from a file) say, with the command line's after
/// them; the command line is this process's own, after the subcommand.
pub fn reparse<A: FromArgMatches>(command: &Command, words: Vec<OsString>) -> Result<A> {
    let mut argv: Vec<OsString> = vec![command.get_name().into()];
    argv.extend(words);
    argv.extend(std::env::args_os().skip(2));
    let matches = command
        .clone()
        .try_get_matches_from(argv)
        .map_err(|e| anyhow!("{}", clap_words(&e)))?;
    Ok(A::from_arg_matches(&matches)?)
}

/// clap's error as one of ours: its first paragraph on one line (a missing
/// option is listed on the lines after the first), without `error: `.
fn clap_words(e: &clap::Error) -> String {
    let rendered = e.render().to_string();
    let paragraph: Vec<&str> = rendered
        .lines()
        .take_while(|l| !l.trim().is_empty())
        .map(str::trim)
        .collect();
    let text = paragraph.join(" ");
    text.strip_prefix("error: ").unwrap_or(&text).to_string()
}

/// The recording plan a session's arguments give.
pub type PlanOf<A> = Box<dyn Fn(&A) -> Result<Option<RecordPlan>> + Send + Sync>;

/// How a session's options come out of its arguments, for the reread.
pub struct Reread<A> {
    pub path: PathBuf,
    pub command: Command,
    pub command_line: ArgMatches,
    /// The module of a class whose session this is.
    pub module: Option<String>,
    /// The file as the session started with it.
    pub started: ConfigFile,
    /// The session's `--allow` list, changed in place.
    pub allow: AllowList,
    pub allow_of: fn(&A) -> Vec<Network>,
    pub plan_of: PlanOf<A>,
}

impl<A: FromArgMatches + 'static> Reread<A> {
    /// SIGHUP's hook: reread the file; apply `--allow`, the rotation and
    /// the `--keep` rules; name what changed but needs a restart. A file
    /// that no longer reads leaves everything as it was, and says why.
    pub fn hook(self) -> OnHangup {
        let me = Arc::new(self);
        OnHangup::new(move || me.reread())
    }

    fn reread(&self) -> Option<RecordPlan> {
        let who = self
            .module
            .as_ref()
            .map_or_else(String::new, |m| format!(" (module {m})"));
        let shown = self.path.display();
        let newer = match ConfigFile::load(&self.path, &self.command, self.module.is_some()) {
            Ok(f) => f,
            Err(e) => {
                println!("SIGHUP{who}: {shown} not reread, serving on as before: {e:#}");
                return None;
            }
        };
        let module = self.module.as_deref();
        if let Some(name) = module
            && newer.module(name).is_none()
        {
            println!(
                "SIGHUP{who}: {shown} no longer has module {name}: serving on as before (a restart removes it)"
            );
            return None;
        }
        let words = newer.words(module.and_then(|m| newer.module(m)), &self.command_line);
        let args: A = match reparse(&self.command, words) {
            Ok(a) => a,
            Err(e) => {
                println!("SIGHUP{who}: {shown} not reread, serving on as before: {e:#}");
                return None;
            }
        };
        let plan = match (self.plan_of)(&args) {
            Ok(p) => p,
            Err(e) => {
                println!("SIGHUP{who}: {shown} not reread, serving on as before: {e:#}");
                return None;
            }
        };
        let changed = self.started.changed_keys(&newer, module);
        let (applied, waiting): (Vec<&String>, Vec<&String>) =
            changed.iter().partition(|k| REREAD.contains(&k.as_str()));
        self.allow.set((self.allow_of)(&args));
        let list = |keys: &[&String]| {
            keys.iter()
                .map(|k| format!("`{k}`"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        let mut said = format!("SIGHUP{who}: reread {shown}");
        if changed.is_empty() {
            said.push_str(": nothing changed");
        }
        if !applied.is_empty() {
            said.push_str(&format!("; applied {}", list(&applied)));
        }
        if !waiting.is_empty() {
            said.push_str(&format!(
                "; not reread while serving: {} (they take effect at the next start: systemctl restart)",
                list(&waiting)
            ));
        }
        println!("{said}");
        twin_realtime::notify::status(&said);
        plan
    }
}

/// The file named by --config, if any, read for `command`.
pub fn load(path: Option<&Path>, command: &Command, modules: bool) -> Result<Option<ConfigFile>> {
    path.map(|p| ConfigFile::load(p, command, modules))
        .transpose()
}
