//! `twin replay`: re-run a recording's scenario and check the new run
//! against it; or send its master frames to a live slave.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;
use twin::recording::{Recording, diff};
use twin::replay::RunSpec;

use super::run::Progress;

/// Re-run the scenario stored in a recording and check that the new run matches.
///
/// The recording's `twin.run` metadata holds the scenario (with the duration and
/// seed it ran with) and the twin's version. An unchanged replay must give the
/// same bytes; otherwise the first signal and time where the replay departs are
/// printed, with the value recorded and replayed, and the exit code is non-zero.
/// `--set PATH=VALUE` changes a field of the stored scenario first (dotted as in
/// its TOML, list items by name or index): `--set node.supervisor.kp=0.6`,
/// `--set module.ev1.params.wheel.brake_torque_nm=3`, `--set seed=2`.
#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// The recording to replay.
    #[arg(value_name = "RUN.mcap")]
    recording: PathBuf,
    /// Change a field of the stored scenario before re-running (repeatable).
    #[arg(long = "set", value_name = "PATH=VALUE")]
    overrides: Vec<String>,
    /// Where to write the replay's recording [default: RUN.replay.mcap beside RUN.mcap].
    #[arg(long, value_name = "PATH")]
    out: Option<PathBuf>,
}

pub fn execute(args: &ReplayArgs) -> Result<()> {
    let recorded = Recording::read(&args.recording)?;
    let spec = RunSpec::from_recording(&recorded)?;
    let version = recorded.run_field("twin_version").unwrap_or("unknown");
    println!(
        "twin replay: {} ({}, recorded by twin {version})",
        args.recording.display(),
        spec.describe()
    );
    if version != env!("CARGO_PKG_VERSION") {
        println!(
            "  note: this is twin {}; a different version may run differently",
            env!("CARGO_PKG_VERSION")
        );
    }
    if let Some(why) = &recorded.truncated {
        println!("  note: the recording is cut short ({why}); only what it holds is compared");
    }
    let spec = spec.with_overrides(&args.overrides)?;
    for o in &args.overrides {
        println!("  changed: {o}");
    }
    let out = args.out.clone().unwrap_or_else(|| {
        let stem = args
            .recording
            .file_stem()
            .map_or_else(|| "run".into(), |s| s.to_string_lossy().into_owned());
        args.recording.with_file_name(format!("{stem}.replay.mcap"))
    });
    if out == args.recording {
        bail!("--out must not be the recording being replayed");
    }
    let started = Instant::now();
    let mut progress = Progress::new();
    let path = spec.run(&out, |done| progress.show(done))?;
    progress.clear();
    println!(
        "  replayed in {:.2} s wall time into {}",
        started.elapsed().as_secs_f64(),
        path.display()
    );
    let a = std::fs::read(&args.recording)?;
    let b = std::fs::read(&path)?;
    if a == b {
        println!(
            "  byte-identical: the replay matches the recording exactly ({} bytes, {} messages)",
            a.len(),
            recorded.message_count()
        );
        return Ok(());
    }
    let replayed = Recording::read(&path)?;
    match diff::first_departure(&recorded, &replayed) {
        Some(d) => {
            println!(
                "  DEPARTS at {:.6} s on {}: recorded {}, replayed {}",
                d.time_s, d.signal, d.recorded, d.replayed
            );
            if d.other_fields > 0 {
                println!(
                    "    {} other field(s) of that message differ too",
                    d.other_fields
                );
            }
            println!("    {} channel(s) depart in all", d.channels_departing);
            bail!(
                "the replay departs from the recording at {:.6} s on {}",
                d.time_s,
                d.signal
            );
        }
        None if recorded.truncated.is_some() => {
            println!(
                "  every message the cut-short recording holds matches the replay ({} messages)",
                recorded.message_count()
            );
            Ok(())
        }
        None => {
            let keys = metadata_differences(&recorded, &replayed);
            println!(
                "  every message matches, but the files differ{}",
                if keys.is_empty() {
                    " in their layout".to_string()
                } else {
                    format!(" in metadata: {}", keys.join(", "))
                }
            );
            bail!("the replay is not byte-identical to the recording");
        }
    }
}

fn metadata_differences(a: &Recording, b: &Recording) -> Vec<String> {
    let mut keys = Vec::new();
    for (name, fields) in a.metadata.iter().chain(&b.metadata) {
        for k in fields.keys() {
            let get = |r: &Recording| r.metadata.get(name).and_then(|m| m.get(k)).cloned();
            let key = format!("{name}.{k}");
            if get(a) != get(b) && !keys.contains(&key) {
                keys.push(key);
            }
        }
    }
    keys
}
