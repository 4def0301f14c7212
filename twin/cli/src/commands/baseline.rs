//! `twin baseline`: check the embedded scenarios against their baseline
//! recordings, or re-record them on purpose.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;
use twin_recording::compare;
use twin_sim::baseline;

use super::progress::Progress;

/// Check every embedded scenario against its baseline recording, or re-record baselines.
///
/// Each embedded scenario is run cut down as `recordings/baselines/baselines.toml`
/// says (shorter, fewer plant samples) and compared, signal by signal, with
/// `recordings/baselines/NAME.mcap` at the default tolerances of `twin compare`
/// (a deterministic re-run matches to the last digit). A departure is printed as
/// the signal and time where it starts. After a change that is meant to move the
/// physics or a protocol, re-record with `--record` and commit the files.
///
/// The baselines are those of the repository this twin was built from, wherever
/// it runs; `--dir` names another folder. `--record` writes only into a folder
/// that exists, so that it never starts a new set of baselines by mistake, and a
/// baseline that is missing is reported as missing.
#[derive(Debug, Args)]
pub struct BaselineArgs {
    /// Scenarios to check or record [default: every embedded scenario].
    #[arg(value_name = "SCENARIO")]
    scenarios: Vec<String>,
    /// Re-record the baselines instead of checking them.
    #[arg(long)]
    record: bool,
    /// Folder of the baseline recordings [default: recordings/baselines of the
    /// repository this twin was built from].
    #[arg(long, value_name = "DIR")]
    dir: Option<PathBuf>,
}

pub fn execute(args: &BaselineArgs) -> Result<()> {
    let names: Vec<String> = if args.scenarios.is_empty() {
        baseline::names().into_iter().map(String::from).collect()
    } else {
        args.scenarios.clone()
    };
    let known = baseline::names();
    if let Some(unknown) = names.iter().find(|n| !known.contains(&n.as_str())) {
        bail!(
            "no embedded scenario `{unknown}`: baselines exist for {}",
            known.join(", ")
        );
    }
    let dir = folder(args)?;
    // One bar per scenario, taken off before its line is printed.
    let progress = |i: usize, name: &str| {
        let total_s = baseline::scenario(name).map_or(1.0, |s| s.duration_s);
        Progress::simulated(&format!("{name} ({} of {})", i + 1, names.len()), total_s)
    };
    if args.record {
        for (i, name) in names.iter().enumerate() {
            let existed = baseline::path(&dir, name).exists();
            let bar = progress(i, name);
            let path = baseline::record(&dir, name, |done| bar.show(done))?;
            bar.clear();
            let size = std::fs::metadata(&path)?.len();
            println!(
                "twin baseline: {} {} ({:.1} kB){}",
                if existed { "re-recorded" } else { "recorded" },
                path.display(),
                size as f64 / 1000.0,
                if existed {
                    ""
                } else {
                    ", a new baseline: there was none"
                }
            );
        }
        return Ok(());
    }
    println!("twin baseline: the baselines in {}", dir.display());
    let scratch = std::env::temp_dir().join(format!("twin-baseline-{}", std::process::id()));
    std::fs::create_dir_all(&scratch)?;
    let (mut failed, mut missing) = (Vec::new(), Vec::new());
    // The names in one column: 24 wide, or as wide as the longest.
    let width = names.iter().map(String::len).max().unwrap_or(0).max(24);
    for (i, name) in names.iter().enumerate() {
        if !baseline::path(&dir, name).exists() {
            println!("  {name:<width$} MISSING  no {name}.mcap there");
            missing.push(name.clone());
            continue;
        }
        let started = Instant::now();
        let bar = progress(i, name);
        let result = baseline::check(&dir, name, &scratch.join(format!("{name}.mcap")), |done| {
            bar.show(done)
        });
        bar.clear();
        let wall = started.elapsed().as_secs_f64();
        match result {
            Ok(c) if c.passed() => {
                let samples: usize = c.rows.iter().map(|r| r.samples).sum();
                println!(
                    "  {name:<width$} pass  {} signals, {samples} samples, {wall:.2} s",
                    c.rows.len()
                );
            }
            Ok(c) => {
                println!("  {name:<width$} FAIL");
                if let Some(m) = &c.span_mismatch {
                    println!("    time span differs: {m}");
                }
                print!("{}", compare::table(&c, false));
                failed.push(name.clone());
            }
            Err(e) => {
                // With its causes, as `main` prints an error.
                println!("  {name:<width$} ERROR {:#}", anyhow::Error::from(e));
                failed.push(name.clone());
            }
        }
    }
    let _ = std::fs::remove_dir_all(&scratch);
    let mut problems = Vec::new();
    if !failed.is_empty() {
        problems.push(format!(
            "{} of {} scenario(s) do not match their baseline ({}); if the change is meant, \
             re-record with `twin baseline --record {}` and commit the files",
            failed.len(),
            names.len(),
            failed.join(", "),
            failed.join(" ")
        ));
    }
    if !missing.is_empty() {
        problems.push(format!(
            "{} of {} scenario(s) have no baseline in {} ({}); a scenario new to the twin gets \
             one with `twin baseline --record {}{}`, committed with it",
            missing.len(),
            names.len(),
            dir.display(),
            missing.join(", "),
            missing.join(" "),
            dir_flag(args)
        ));
    }
    if !problems.is_empty() {
        bail!("{}", problems.join("; "));
    }
    Ok(())
}

/// The folder of the baselines: `--dir`, or the repository's. It must exist:
/// checking an empty place would only report every baseline missing, and
/// recording into a new one would start a set that then passes against itself.
fn folder(args: &BaselineArgs) -> Result<PathBuf> {
    let Some(dir) = &args.dir else {
        return baseline::repository_dir().with_context(|| {
            format!(
                "no baseline recordings: this twin looks for them in the repository it was built \
                 from, {}, which is not there any more; give the folder that holds them with \
                 --dir DIR (recordings/baselines in a checkout of the twin)",
                baseline::repository_dir_expected().display()
            )
        });
    };
    if dir.is_dir() {
        return Ok(dir.clone());
    }
    if args.record {
        bail!(
            "no folder {}: --record writes into an existing set of baselines and does not start \
             a new one by mistake; to start one there, create the folder first (mkdir -p {})",
            dir.display(),
            dir.display()
        );
    }
    bail!(
        "no folder {}: give the folder that holds the baseline recordings \
         (recordings/baselines in a checkout of the twin), or leave --dir out for the \
         repository's",
        dir.display()
    )
}

/// ` --dir DIR` when one was given, for advice that repeats it.
fn dir_flag(args: &BaselineArgs) -> String {
    args.dir
        .as_ref()
        .map_or_else(String::new, |d| format!(" --dir {}", d.display()))
}
