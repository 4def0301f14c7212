//! `twin check client`: a session with the student's remote client. The
//! twin listens as the supervisor's server, prints the checklist, says
//! each item as it sees it done, and reports when the session ends.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::io::{BufRead, Write as _};
use std::sync::mpsc;
use std::time::{Duration, Instant};
use twin_check::client::{CHECKLIST, Session};
use twin_check::{Outcome, report};

#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  twin check client                                (then connect the client to tcp://127.0.0.1:5701)\n  twin check client --listen tcp://0.0.0.0:5701     (a phone on the lab's network)\n  twin check client --duration 300 --html report.html"
)]
pub struct ClientArgs {
    /// Where the twin listens for the client (port 0: any free port,
    /// printed). Only this machine can connect unless HOST says otherwise.
    #[arg(
        long,
        default_value = "tcp://127.0.0.1:5701",
        value_name = "tcp://HOST:PORT"
    )]
    listen: String,
    /// The slave id whose image the client reads and writes.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=99))]
    id: u8,
    /// End the session after this many seconds, whatever is left
    /// [default: when every item is seen, or on Enter or Ctrl-D].
    #[arg(long, value_name = "SECONDS")]
    duration: Option<f64>,
    #[command(flatten)]
    reports: super::reports::ReportArgs,
}

/// A session, from the checklist to the report.
pub fn execute(args: &ClientArgs) -> Result<()> {
    if args.reports.roster.is_some() {
        bail!("a class of clients is not checked yet: give one --listen");
    }
    let Some(addr) = args.listen.strip_prefix("tcp://") else {
        bail!(
            "the twin listens on TCP: give --listen tcp://HOST:PORT, not `{}`",
            args.listen
        );
    };
    if let Some(d) = args.duration
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--duration must be a number of seconds above 0, not {d}");
    }
    let mut session = Session::listen(addr, args.id)
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    let link = format!("tcp://{}", session.addr());
    println!(
        "twin check client: slave {:02}'s image served to the client",
        args.id
    );
    println!("  meb {link} server");
    println!("Do this in the client, in order (Enter or Ctrl-D ends the session):");
    for (i, item) in CHECKLIST.iter().enumerate() {
        println!("  {}. {}", i + 1, item.todo);
    }
    println!("ready");
    let _ = std::io::stdout().flush();
    let ended = stdin_ended();
    let until = args
        .duration
        .map(|d| Instant::now() + Duration::from_secs_f64(d));
    loop {
        for (i, outcome) in session.poll() {
            let verdict = match outcome {
                Outcome::Pass => "seen".to_string(),
                Outcome::Fail(why) => format!("seen, wrong: {why}"),
                Outcome::NotJudged(_) | Outcome::NotApplicable(_) => continue,
            };
            println!("  {}. {verdict}", i + 1);
            let _ = std::io::stdout().flush();
        }
        if session.done() || ended.try_recv().is_ok() || until.is_some_and(|u| Instant::now() > u) {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let run = session.finish(&link);
    print!("{}", report::text(&run));
    args.reports.record("client", "", &run)?;
    args.reports.reports_and_verdict(&run)
}

/// A message when stdin gives a line or ends (Enter, Ctrl-D, a closed pipe).
fn stdin_ended() -> mpsc::Receiver<()> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = std::io::stdin().lock().read_line(&mut line);
        let _ = tx.send(());
    });
    rx
}
