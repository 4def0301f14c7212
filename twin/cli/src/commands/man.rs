//! `twin man`: manual pages made from the same definition as `--help`.

use anyhow::{Context, Result};
use clap::Args;
use clap_mangen::Man;
use std::path::{Path, PathBuf};

/// Print twin's manual page, or write the pages of twin and of every
/// subcommand into a folder.
///
/// Without --out, twin(1) goes to stdout in roff, to read at once:
///
///   twin man | man -l -
///
/// With --out, one page per command (twin.1, twin-run.1, twin-serve.1, …)
/// is written there. The folder `share/man/man1` beside the one `twin` is
/// installed in is where man finds them with no setting (it looks beside
/// every folder of PATH):
///
///   twin man --out ~/.cargo/share/man/man1 && man twin-run
#[derive(Debug, Args)]
#[command(
    verbatim_doc_comment,
    about = "Print twin's manual page, or write every command's page into a folder"
)]
pub struct ManArgs {
    /// Folder to write every page into (created if missing).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
}

/// What twin(1)'s NAME line says; its DESCRIPTION keeps the paragraph of
/// `twin --help`.
const NAME_LINE: &str = "digital twin of the EV lab bench";

/// Prints or writes the pages of `twin`'s definition `cli`.
pub fn execute(args: &ManArgs, cli: clap::Command) -> Result<()> {
    let description = cli.get_long_about().or(cli.get_about()).cloned();
    // `twin help` is no command of its own: no page, and none listed.
    let mut cli = cli.about(NAME_LINE).disable_help_subcommand(true);
    if let Some(description) = description {
        cli = cli.long_about(description);
    }
    // Names the subcommands' pages twin-run, twin-experiment-pwmcap, …
    cli.build();
    let Some(dir) = &args.out else {
        let mut page = Vec::new();
        Man::new(cli).render(&mut page)?;
        return super::print_bytes(&page);
    };
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create folder {}", dir.display()))?;
    let mut written = 0;
    write_pages(&cli, dir, &mut written)
        .with_context(|| format!("cannot write the manual pages into {}", dir.display()))?;
    println!("twin man: {written} pages in {}", dir.display());
    Ok(())
}

fn write_pages(cmd: &clap::Command, dir: &Path, written: &mut usize) -> std::io::Result<()> {
    Man::new(cmd.clone()).generate_to(dir)?;
    *written += 1;
    for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()) {
        write_pages(sub, dir, written)?;
    }
    Ok(())
}
