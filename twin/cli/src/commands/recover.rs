//! `twin recover`: a recording cut short made whole.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use twin_recording::recover;

/// Turn a recording cut short into a complete MCAP file every reader opens.
///
/// A run killed before it finished (kill -9, a crash) leaves its recording
/// without the summary at its end: readers read it through, up to its last
/// whole chunk, but those that go by the summary find none. A file cut in the
/// middle of a record (power lost, a copy taken half-way) only the twin reads;
/// other MCAP readers (the Python `mcap` package, Foxglove) refuse it. This copies every record that can still be read (schemas,
/// channels, messages, metadata, attachments, with their ids, sequence numbers
/// and times) into a new file with its summary, as `mcap recover` of the MCAP
/// tools does: a damaged chunk is left out and the copy goes on after it.
/// The original is never changed.
#[derive(Debug, Args)]
pub struct RecoverArgs {
    /// The recording cut short.
    #[arg(value_name = "RUN.mcap")]
    recording: PathBuf,
    /// Where to write the complete copy [default: RUN.recovered.mcap beside RUN.mcap].
    #[arg(long, value_name = "PATH")]
    out: Option<PathBuf>,
}

pub fn execute(args: &RecoverArgs) -> Result<()> {
    let out = args.out.clone().unwrap_or_else(|| {
        let stem = args
            .recording
            .file_stem()
            .map_or_else(|| "run".into(), |s| s.to_string_lossy().into_owned());
        args.recording
            .with_file_name(format!("{stem}.recovered.mcap"))
    });
    if same_file(&args.recording, &out) {
        bail!("--out must not be the recording being recovered: the original is kept as it is");
    }
    let earlier = super::output::Earlier::at(&out);
    let r = recover::recover(&args.recording, &out)?;
    println!(
        "twin recover: {} -> {}{}",
        args.recording.display(),
        out.display(),
        super::output::Earlier::note(earlier.as_ref())
    );
    println!(
        "  {} messages on {} channels, {} metadata record(s), {} attachment(s), from {} complete chunk(s)",
        r.messages, r.channels, r.metadata, r.attachments, r.chunks
    );
    if !r.damaged_chunks.is_empty() {
        let list: Vec<String> = r.damaged_chunks.iter().map(u64::to_string).collect();
        println!("  left out damaged chunk(s): {}", list.join(", "));
    }
    if r.strays > 0 {
        println!(
            "  left out {} message(s) on channels the file never declares",
            r.strays
        );
    }
    match (&r.stopped, r.was_complete) {
        (_, true) => println!("  the recording was complete already: the copy holds the same data"),
        (Some(why), false) => println!("  the data stops there: {why}"),
        (None, false) => {}
    }
    if r.messages == 0 {
        bail!(
            "{} holds no message that can be read: the copy has none either",
            args.recording.display()
        );
    }
    Ok(())
}

/// Whether `a` and `b` name one file (the copy must not overwrite its source).
fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}
