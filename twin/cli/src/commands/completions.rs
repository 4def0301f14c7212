//! `twin completions`: the shell's tab completion for `twin`, made from the
//! same definition as `--help`, so it never lags behind the options.

use anyhow::Result;
use clap::Args;
use clap_complete::Shell;

/// Print a shell's tab-completion script for twin.
///
/// Completes the subcommands, their options, file names, and the values of
/// options that take one of a few (`--detector`, `--cable-model`, …).
/// Install it where the shell looks, then open a new shell:
///
///   bash:  twin completions bash > ~/.local/share/bash-completion/completions/twin
///          (loaded by the bash-completion package; without it, put
///          `source <(twin completions bash)` in ~/.bashrc)
///
///   zsh:   twin completions zsh > ~/.zfunc/_twin
///          with `fpath+=~/.zfunc` before `compinit` in ~/.zshrc
///
///   fish:  twin completions fish > ~/.config/fish/completions/twin.fish
///
///   elvish, PowerShell: put the output in your rc.elv or $PROFILE.
#[derive(Debug, Args)]
#[command(
    verbatim_doc_comment,
    about = "Print a shell's tab-completion script for twin"
)]
pub struct CompletionsArgs {
    /// The shell to complete in.
    #[arg(value_enum)]
    shell: Shell,
}

/// Writes the script for `twin`'s definition `cli` to stdout.
pub fn execute(args: &CompletionsArgs, mut cli: clap::Command) -> Result<()> {
    let name = cli.get_name().to_string();
    let mut script = Vec::new();
    clap_complete::generate(args.shell, &mut cli, name, &mut script);
    super::print_bytes(&script)
}
