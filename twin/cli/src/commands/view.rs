//! `twin view`: look at a recording in rerun.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use twin_view::{self as view, ViewTarget};

/// Show a recording in the rerun viewer.
///
/// Turns RUN.mcap (written by `twin run`, `twin serve`, `twin supervise` or
/// `twin check`) into a rerun recording laid out for the lab: the set point,
/// the motor's (hall) rpm and the light sensor's rpm on one plot; V1, V2, I
/// and SOC; the raw photoresistor signal with the dips the firmware's
/// detector finds in it; every bus frame and event as a text log; simulated
/// time (session time for a real-time session, with its tick lateness) as the
/// timeline. A check's recording shows its link's frames as a text log.
///
/// With a viewer installed (`rerun` on PATH and a display) it opens one;
/// otherwise, or with `--save`, it writes an .rrd file (beside the recording
/// unless named) and tells how to open it. The viewer that matches is PyPI
/// `rerun-sdk==0.36.3`: `pip install rerun-sdk==0.36.3`, then `rerun FILE.rrd`.
#[derive(Debug, Args)]
pub struct ViewArgs {
    /// A recording written by `twin run`, `twin serve`, `twin supervise` or
    /// `twin check`.
    #[arg(value_name = "RUN.mcap")]
    recording: PathBuf,
    /// Write an .rrd file instead of opening a viewer
    /// [default: RUN.rrd beside the recording].
    #[arg(long, value_name = "FILE.rrd")]
    save: Option<Option<PathBuf>>,
    /// Stream to a running viewer instead, e.g. rerun+http://127.0.0.1:9876/proxy.
    #[arg(long, value_name = "URL", conflicts_with = "save")]
    connect: Option<String>,
}

pub fn execute(args: &ViewArgs) -> Result<()> {
    if !args.recording.is_file() {
        bail!(
            "no recording {}: give the .mcap file that `twin run`, `twin serve` or `twin supervise` wrote",
            args.recording.display()
        );
    }
    let beside = view::live::rrd_beside(&args.recording);
    let (target, why) = match (&args.save, &args.connect) {
        (Some(None), _) => (ViewTarget::Save(beside), None),
        (Some(Some(path)), _) => (ViewTarget::Save(path.clone()), None),
        (None, Some(url)) => (ViewTarget::Connect(url.clone()), None),
        (None, None) => match view::viewer_available() {
            Some(_) => (ViewTarget::Spawn, None),
            None => (
                ViewTarget::Save(beside),
                Some("no rerun viewer to open here (`rerun` on PATH and a display)"),
            ),
        },
    };
    let converted = view::convert(&args.recording, &target)?;
    let read = &converted.read;
    let messages: u64 = read.messages.values().sum();
    let samples: u64 = converted.samples.values().sum();
    println!(
        "twin view: {}: {} messages on {} channels, {:.3} s simulated -> {} samples on {} entities",
        args.recording.display(),
        messages,
        read.messages.len(),
        read.end_s,
        samples,
        converted.samples.len()
    );
    if messages == 0 {
        if let ViewTarget::Save(path) = &target {
            // An .rrd of nothing would only look like a result.
            let _ = std::fs::remove_file(path);
        }
        let why = read
            .stopped_early
            .as_ref()
            .map_or_else(String::new, |r| format!(" ({r})"));
        bail!(
            "{} holds no messages{why}: there is nothing to show",
            args.recording.display()
        );
    }
    for (entity, n) in &converted.samples {
        println!("  {entity:40} {n:7}");
    }
    if let Some(reason) = &read.stopped_early {
        println!(
            "  the recording ends early ({reason}): shown up to {:.3} s, its last complete chunk",
            read.end_s
        );
    }
    for (what, n) in &read.skipped {
        println!("  skipped {n} unreadable message(s): {what}");
    }
    match &target {
        ViewTarget::Save(path) => {
            if let Some(why) = why {
                println!("  {why}: saved instead");
            }
            println!("rerun recording: {}", path.display());
            println!(
                "open it with `rerun {}` (the viewer: pip install rerun-sdk==0.36.3)",
                path.display()
            );
        }
        ViewTarget::Spawn => println!("sent to the rerun viewer"),
        ViewTarget::Connect(url) => println!("sent to the rerun viewer at {url}"),
    }
    Ok(())
}
