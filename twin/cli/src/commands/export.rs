//! `twin export`: a recording as CSV files.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;
use twin_recording::export;

/// Write every channel of a recording as CSV, for spreadsheets, MATLAB and Python.
///
/// One file per channel, named after its topic (`/plant/ev1/sensors` →
/// `plant_ev1_sensors.csv`): a `time_s` column (simulated seconds) and one column
/// per field, nested fields flattened with dots (`energy.battery_out`,
/// `loops.0.measured_rpm`). Booleans are 1 and 0. A recording cut short is
/// exported up to its last complete chunk; a channel in an encoding the twin
/// does not read (another tool's) is left out, and the listing says so. Files
/// of the same name in DIR are replaced, and the listing says which.
#[derive(Debug, Args)]
pub struct ExportArgs {
    /// The recording.
    #[arg(value_name = "RUN.mcap")]
    recording: PathBuf,
    /// Folder to write the CSV files into (created if needed).
    #[arg(long, value_name = "DIR")]
    csv: PathBuf,
}

pub fn execute(args: &ExportArgs) -> Result<()> {
    let existed: Vec<PathBuf> = std::fs::read_dir(&args.csv)
        .map(|entries| entries.filter_map(|e| Some(e.ok()?.path())).collect())
        .unwrap_or_default();
    let export::Exported {
        recording,
        written,
        skipped,
    } = export::to_csv(&args.recording, &args.csv)?;
    if let Some(why) = &recording.truncated {
        println!("note: {}: {why}", args.recording.display());
    }
    println!(
        "twin export: {} channels of {} into {}",
        written.len(),
        args.recording.display(),
        args.csv.display()
    );
    for w in &written {
        println!(
            "  {:<28} {:>7} rows {:>4} columns  {}{}",
            w.topic,
            w.rows,
            w.columns,
            w.path.display(),
            if existed.contains(&w.path) {
                " (replaced the one there before)"
            } else {
                ""
            }
        );
    }
    for s in &skipped {
        println!("  {:<28} left out: {}", s.topic, s.why);
    }
    Ok(())
}
