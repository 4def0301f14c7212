//! What a user sets up after `cargo install`: the shells' tab completion and
//! the manual pages, both made by `twin` from its own definition.

use crate::support;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use support::twin;

fn stdout_of(args: &[&str]) -> String {
    let o = twin(args);
    assert!(
        o.status.success(),
        "twin {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout).expect("UTF-8")
}

fn scratch(name: &str) -> PathBuf {
    support::scratch("install-cli", name)
}

/// What bash offers for the words typed so far, through the script's own
/// completion function, as bash does on Tab.
fn bash_completes(script: &Path, words: &[&str]) -> Vec<String> {
    let line = words.join(" ");
    let program = format!(
        "source '{}'\nCOMP_WORDS=({line})\nCOMP_CWORD={}\nCOMP_LINE='{line}'\nCOMP_POINT=${{#COMP_LINE}}\n\
         _twin twin '{}' '{}'\nprintf '%s\\n' \"${{COMPREPLY[@]}}\"\n",
        script.display(),
        words.len() - 1,
        words[words.len() - 1],
        words[words.len() - 2],
    );
    let o = Command::new("bash")
        .args(["--norc", "--noprofile", "-c", &program])
        .output()
        .expect("bash runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| l.trim().to_string())
        .filter(|l| !l.is_empty())
        .collect()
}

#[test]
fn bash_completes_the_subcommands_and_their_options() {
    let script = stdout_of(&["completions", "bash"]);
    for sub in [
        "run",
        "serve",
        "supervise",
        "baseline",
        "completions",
        "man",
    ] {
        assert!(script.contains(sub), "the bash script lacks {sub}");
    }
    let path = scratch("twin.bash");
    std::fs::write(&path, &script).expect("script written");
    let offered = bash_completes(&path, &["twin", "su"]);
    assert_eq!(offered, ["supervise"], "twin su<Tab>");
    let offered = bash_completes(&path, &["twin", "run", "--dur"]);
    assert_eq!(offered, ["--duration"], "twin run --dur<Tab>");
    let offered = bash_completes(&path, &["twin", "completions", "f"]);
    assert_eq!(offered, ["fish"], "twin completions f<Tab>");
}

#[test]
fn zsh_fish_elvish_and_powershell_get_scripts_of_their_own() {
    let zsh = stdout_of(&["completions", "zsh"]);
    assert!(
        zsh.starts_with("#compdef twin"),
        "{}",
        &zsh[..zsh.len().min(200)]
    );
    let fish = stdout_of(&["completions", "fish"]);
    assert!(fish.contains("complete -c twin"), "fish script");
    assert!(fish.contains("serve"), "fish script lacks serve");
    for shell in ["elvish", "powershell"] {
        assert!(
            stdout_of(&["completions", shell]).contains("supervise"),
            "{shell}"
        );
    }
}

// An unknown shell is refused with the ones there are: tests/cmd/install-refusals.trycmd.

/// Formats a page with groff as man does, warnings on: what it prints, and
/// its complaints.
fn groff(page: &[u8]) -> (String, String) {
    let mut child = Command::new("groff")
        .args(["-man", "-Tutf8", "-ww", "-rLL=100n"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("groff runs (apt-get install groff-base)");
    child
        .stdin
        .take()
        .unwrap()
        .write_all(page)
        .expect("page fed");
    let o = child.wait_with_output().expect("groff ends");
    assert!(o.status.success(), "groff failed");
    // groff marks bold and underlined text with backspaces on a tty device.
    let text: String = String::from_utf8_lossy(&o.stdout)
        .split('\u{8}')
        .enumerate()
        .map(|(i, s)| if i == 0 { s } else { s.get(1..).unwrap_or("") })
        .collect();
    (text, String::from_utf8_lossy(&o.stderr).into_owned())
}

#[test]
fn the_manual_page_is_roff_that_groff_formats_without_a_warning() {
    let page = stdout_of(&["man"]);
    assert!(
        page.contains(".TH twin 1"),
        "{}",
        &page[..page.len().min(300)]
    );
    let (text, warnings) = groff(page.as_bytes());
    assert!(warnings.is_empty(), "groff warns: {warnings}");
    assert!(text.contains("NAME"), "{text}");
    assert!(
        text.contains("twin - digital twin of the EV lab bench"),
        "{text}"
    );
    assert!(
        text.contains("DESCRIPTION") && text.contains("PWM-capture link"),
        "{text}"
    );
    for sub in ["twin-run(1)", "twin-serve(1)", "twin-completions(1)"] {
        assert!(text.contains(sub), "the page lacks {sub}: {text}");
    }
}

#[test]
fn man_out_writes_a_page_per_command_that_man_reads() {
    let dir = scratch("man1");
    let _ = std::fs::remove_dir_all(&dir);
    let said = stdout_of(&["man", "--out", dir.to_str().unwrap()]);
    for page in [
        "twin.1",
        "twin-run.1",
        "twin-serve.1",
        "twin-experiment.1",
        "twin-experiment-pwmcap.1",
        "twin-man.1",
    ] {
        assert!(dir.join(page).exists(), "no {page} in {}", dir.display());
    }
    let count = std::fs::read_dir(&dir).unwrap().count();
    assert!(
        said.contains(&format!("{count} pages in {}", dir.display())),
        "{said}"
    );

    let run = std::fs::read(dir.join("twin-run.1")).unwrap();
    let (text, warnings) = groff(&run);
    assert!(warnings.is_empty(), "groff warns on twin-run.1: {warnings}");
    assert!(text.contains("--duration"), "{text}");
    // As a user reads it: man on the file itself, no pager.
    let o = Command::new("man")
        .args(["-l", "-P", "cat"])
        .arg(dir.join("twin-experiment-pwmcap.1"))
        .env("MANWIDTH", "100")
        .output()
        .expect("man runs (apt-get install man-db)");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("--cable-model"), "{text}");
}

#[test]
fn a_reader_that_goes_early_ends_twin_quietly() {
    for args in [&["completions", "zsh"][..], &["man"][..]] {
        // `twin … | head -c 0`: the pipe's reading end is closed before
        // twin writes a byte.
        let (reader, writer) = std::io::pipe().expect("pipe");
        drop(reader);
        let o = Command::new(env!("CARGO_BIN_EXE_twin"))
            .args(args)
            .stdout(writer)
            .output()
            .expect("twin runs");
        assert_eq!(o.status.code(), Some(141), "twin {}", args.join(" "));
        assert!(
            o.stderr.is_empty(),
            "{}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
}
