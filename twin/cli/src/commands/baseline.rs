//! `twin baseline`: check the embedded scenarios against their baseline
//! recordings, or re-record them on purpose.

use anyhow::{Result, bail};
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
#[derive(Debug, Args)]
pub struct BaselineArgs {
    /// Scenarios to check or record [default: every embedded scenario].
    #[arg(value_name = "SCENARIO")]
    scenarios: Vec<String>,
    /// Re-record the baselines instead of checking them.
    #[arg(long)]
    record: bool,
    /// Folder of the baseline recordings.
    #[arg(long, value_name = "DIR", default_value = baseline::DIR)]
    dir: PathBuf,
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
    // One bar per scenario, taken off before its line is printed.
    let progress = |i: usize, name: &str| {
        let total_s = baseline::scenario(name).map_or(1.0, |s| s.duration_s);
        Progress::simulated(&format!("{name} ({} of {})", i + 1, names.len()), total_s)
    };
    if args.record {
        for (i, name) in names.iter().enumerate() {
            let bar = progress(i, name);
            let path = baseline::record(&args.dir, name, |done| bar.show(done))?;
            bar.clear();
            let size = std::fs::metadata(&path)?.len();
            println!(
                "twin baseline: recorded {} ({:.1} kB)",
                path.display(),
                size as f64 / 1000.0
            );
        }
        return Ok(());
    }
    let scratch = std::env::temp_dir().join(format!("twin-baseline-{}", std::process::id()));
    std::fs::create_dir_all(&scratch)?;
    let mut failed = Vec::new();
    for (i, name) in names.iter().enumerate() {
        let started = Instant::now();
        let bar = progress(i, name);
        let result = baseline::check(
            &args.dir,
            name,
            &scratch.join(format!("{name}.mcap")),
            |done| bar.show(done),
        );
        bar.clear();
        let wall = started.elapsed().as_secs_f64();
        match result {
            Ok(c) if c.passed() => {
                let samples: usize = c.rows.iter().map(|r| r.samples).sum();
                println!(
                    "  {name:<24} pass  {} signals, {samples} samples, {wall:.2} s",
                    c.rows.len()
                );
            }
            Ok(c) => {
                println!("  {name:<24} FAIL");
                if let Some(m) = &c.span_mismatch {
                    println!("    time span differs: {m}");
                }
                print!("{}", compare::table(&c, false));
                failed.push(name.clone());
            }
            Err(e) => {
                println!("  {name:<24} ERROR {e:#}");
                failed.push(name.clone());
            }
        }
    }
    let _ = std::fs::remove_dir_all(&scratch);
    if !failed.is_empty() {
        bail!(
            "{} of {} scenario(s) do not match their baseline ({}); re-record with \
             `twin baseline --record NAME` if the change is intended",
            failed.len(),
            names.len(),
            failed.join(", ")
        );
    }
    Ok(())
}
