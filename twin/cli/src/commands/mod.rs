//! One file per subcommand; each parses its arguments and calls library code.

pub mod baseline;
pub mod bench;
pub mod client;
pub mod compare;
pub mod experiment;
pub mod export;
mod live_view;
mod plant_args;
pub mod replay;
pub mod run;
pub mod serve;
pub mod step;
pub mod supervise;
pub mod sweep;
pub mod view;
pub mod vsp;

/// The last lines of a real-time session's report (`twin serve`, `twin
/// supervise`): its connections, where it was recorded, the live view.
fn print_session_end(outcome: &twin_realtime::session::SessionOutcome) {
    let c = &outcome.counters;
    println!(
        "  {} connections ({} refused over the limit, {} closed for a partial frame, {} for the rate limit, {} idle, {} to make room); {} bytes in, {} frames out",
        c.connections,
        outcome.refused_clients,
        c.closed_partial_timeout,
        c.closed_rate_limit,
        c.closed_idle,
        c.closed_for_room,
        c.bytes_in,
        c.frames_out
    );
    if let Some(path) = &outcome.recording {
        println!("recording: {}", path.display());
    }
    match (outcome.view_samples, outcome.view_error.as_deref()) {
        (Some(_), Some(e)) => eprintln!("live view: {e}"),
        (Some(samples), None) => println!("live view: {samples} samples streamed to rerun"),
        _ => {}
    }
}
