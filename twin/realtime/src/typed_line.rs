//! A line typed at a prompt (the serve console's, `twin client`'s) read as
//! a command line by clap: the words without a program name, `help` and
//! mistakes in clap's words, as every `twin` subcommand's.

use clap::Parser;
use clap::error::ErrorKind;
use std::io::IsTerminal;

/// What a line asked for.
#[derive(Debug)]
pub enum Typed<T> {
    /// Nothing: an empty line.
    Blank,
    /// `help` (or `help COMMAND`): the text to show.
    Help(String),
    /// A command, its words checked.
    Command(T),
}

/// Reads `line` as `T`; `Err` is the mistake in clap's words, ready to print
/// (styled only when stdout is a terminal).
pub fn read<T: Parser>(line: &str) -> Result<Typed<T>, String> {
    let words: Vec<&str> = line.split_whitespace().collect();
    if words.is_empty() {
        return Ok(Typed::Blank);
    }
    match T::try_parse_from(&words) {
        Ok(command) => Ok(Typed::Command(command)),
        // clap hands the help over as an error; here it is what was asked for.
        Err(e) if e.kind() == ErrorKind::DisplayHelp => Ok(Typed::Help(shown(&e))),
        // A command typed without the words it needs (`fault`) is a
        // question: the same answer as `help fault`, not clap's shorter one.
        Err(e) if e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => {
            let asked = std::iter::once("help").chain(words.iter().copied());
            Ok(Typed::Help(match T::try_parse_from(asked) {
                Err(help) if help.kind() == ErrorKind::DisplayHelp => shown(&help),
                _ => shown(&e),
            }))
        }
        Err(e) => Err(shown(&e)),
    }
}

/// An error (or the help) as text: clap's styles on a terminal, plain in a
/// pipe or a file; without clap's last newline, the caller's to add.
fn shown(e: &clap::Error) -> String {
    let text = e.render();
    let text = if std::io::stdout().is_terminal() {
        text.ansi().to_string()
    } else {
        text.to_string()
    };
    text.trim_end().to_string()
}

/// `on` or `off`, as the prompts' switches take it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

impl OnOff {
    pub fn is_on(self) -> bool {
        self == OnOff::On
    }
}
