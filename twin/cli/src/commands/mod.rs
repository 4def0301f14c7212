//! One file per subcommand; each parses its arguments and calls library code.

pub mod baseline;
pub mod batch;
pub mod bench;
pub mod calibrate;
pub mod check;
pub mod client;
pub mod compare;
pub mod completions;
mod config_file;
pub mod experiment;
pub mod export;
mod live_view;
mod node_summary;
mod numbers;
mod output;
pub mod panel;
pub use numbers::take_negative_numbers;
pub mod man;
mod plant_args;
mod progress;
mod record_args;
pub mod recover;
pub mod replay;
pub mod run;
pub mod scope;
pub mod serve;
mod service;
mod service_args;
pub mod step;
pub mod supervise;
pub mod sweep;
pub mod view;
pub mod vsp;
mod web_args;

/// The last lines of a real-time session's report (`twin serve`, `twin
/// supervise`): its connections, where it was recorded, the live view.
fn print_session_end(
    outcome: &twin_realtime::session::SessionOutcome,
    earlier: Option<&output::Earlier>,
) {
    let c = &outcome.counters;
    println!(
        "  {} connections ({} refused over the limit, {} refused by --allow, {} closed for a partial frame, {} for the rate limit, {} idle, {} to make room); {} bytes in, {} frames out",
        c.connections,
        outcome.refused_clients,
        outcome.refused_not_allowed,
        c.closed_partial_timeout,
        c.closed_rate_limit,
        c.closed_idle,
        c.closed_for_room,
        c.bytes_in,
        c.frames_out
    );
    if let Some(path) = &outcome.recording {
        let earlier_files = match outcome.earlier_files.len() {
            0 => String::new(),
            1 => " (after 1 earlier file)".to_string(),
            n => format!(" (after {n} earlier files)"),
        };
        println!(
            "recording: {}{}{earlier_files}",
            path.display(),
            output::Earlier::note(earlier)
        );
        println!(
            "  {} frames recorded on the links (requests and replies)",
            outcome.frames_recorded
        );
        let waited = outcome.waited_for_recording;
        if !waited.is_zero() {
            println!(
                "  the connections waited {:.3} s in all for the recording to catch up (the machine was busy; nothing was lost)",
                waited.as_secs_f64()
            );
        }
    }
    match (outcome.view_samples, outcome.view_error.as_deref()) {
        (Some(_), Some(e)) => eprintln!("live view: {e}"),
        (Some(samples), None) => println!("live view: {samples} samples streamed to rerun"),
        _ => {}
    }
}

/// Writes a generated file (a completion script, a manual page) to stdout.
/// A reader that has gone (`twin man | head`) ends the program as SIGPIPE
/// would, quietly, like the panic hook in `main` does for `println!`.
fn print_bytes(bytes: &[u8]) -> anyhow::Result<()> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    match out.write_all(bytes).and_then(|()| out.flush()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => std::process::exit(141),
        written => Ok(written?),
    }
}

/// Ctrl-C or SIGTERM during a virtual run stops it where it has got to and
/// finishes its recording (a second Ctrl-C quits at once, the recording
/// then cut short: `twin recover` makes it whole).
pub fn finish_recordings_on_signals() {
    use tokio::signal::unix::{SignalKind, signal};
    let spawned = std::thread::Builder::new()
        .name("signals".into())
        .spawn(|| {
            let Ok(runtime) = tokio::runtime::Builder::new_current_thread()
                .enable_io()
                .build()
            else {
                return;
            };
            runtime.block_on(async {
                let (Ok(mut interrupt), Ok(mut terminate)) = (
                    signal(SignalKind::interrupt()),
                    signal(SignalKind::terminate()),
                ) else {
                    return;
                };
                loop {
                    let name = tokio::select! {
                        _ = interrupt.recv() => "Ctrl-C",
                        _ = terminate.recv() => "SIGTERM",
                    };
                    if twin_sim::interrupt::requested() {
                        eprintln!("\n{name} again: quitting without finishing the recording");
                        std::process::exit(130);
                    }
                    eprintln!("\n{name}: stopping the run and finishing its recording");
                    twin_sim::interrupt::request();
                }
            });
        });
    if let Err(e) = spawned {
        eprintln!("note: Ctrl-C will not finish the recording ({e})");
    }
}

/// A timeout option in seconds: 0 for never; a negative, infinite or NaN
/// one is refused rather than taken for never.
fn timeout(flag: &str, seconds: f64) -> anyhow::Result<Option<protocols::time::SimDuration>> {
    if seconds == 0.0 {
        return Ok(None);
    }
    // A week: past that, 0 (never) is what is meant.
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 604_800.0) {
        anyhow::bail!(
            "{flag} {seconds}: give seconds above 0 up to a week (604800), or 0 for never"
        );
    }
    Ok(Some(protocols::time::SimDuration::from_secs_f64(seconds)))
}
