//! `twin check client`: a session with the student's remote client. The
//! twin listens as the supervisor's server, prints the checklist, says
//! each item as it sees it done, and reports when the session ends.

use anyhow::{Context, Result, bail};
use clap::Args;
use protocols::link::{LinkSpec, LinkSpecError};
use std::io::{BufRead, Write as _};
use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
use twin_check::client::{CHECKLIST, NAME, SUITE, Session, unreachable};
use twin_check::{Outcome, Protocol, class, report};

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

/// A session, from the checklist to the report; or a class's sessions
/// from a roster.
pub fn execute(args: &ClientArgs) -> Result<()> {
    if let Some(d) = args.duration
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--duration must be a number of seconds above 0, not {d}");
    }
    if let Some(roster) = &args.reports.roster {
        return class(args, roster);
    }
    let addr = listen_addr(&args.listen).context("--listen")?;
    let mut session = Session::listen(addr, args.id)
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    let link = format!("tcp://{}", session.addr());
    println!(
        "twin check client: slave {:02}'s image served to the client",
        args.id
    );
    println!("  meb {link} server");
    checklist();
    let ended = stdin_ended();
    let until = args
        .duration
        .map(|d| Instant::now() + Duration::from_secs_f64(d));
    held(&mut session, until, &ended, |i, outcome| {
        let verdict = match outcome {
            Outcome::Pass => "seen".to_string(),
            Outcome::Fail(why) => format!("seen, wrong: {why}"),
            Outcome::NotJudged(_) | Outcome::NotApplicable(_) => return,
        };
        println!("  {}. {verdict}", i + 1);
        let _ = std::io::stdout().flush();
    });
    let run = session.finish(&link);
    print!("{}", report::text(&run));
    args.reports.record("client", "", &run)?;
    args.reports.reports_and_verdict(&run)
}

/// Where the twin listens for a client: a link's own reading of
/// `tcp://HOST:PORT` (so a misspelt one gets the links' suggestion); the
/// twin serves a client over TCP only.
fn listen_addr(link: &str) -> Result<SocketAddr, LinkSpecError> {
    LinkSpec::parse_tcp_peer(link, "a client's session takes no options")
}

/// The checklist, then `ready`: the clients may connect.
fn checklist() {
    println!("Do this in the client, in order (Enter or Ctrl-D ends the session):");
    for (i, item) in CHECKLIST.iter().enumerate() {
        println!("  {}. {}", i + 1, item.todo);
    }
    println!("ready");
    let _ = std::io::stdout().flush();
}

/// Holds the session until every item is seen, stdin ends, or `until`;
/// `seen` is told each item as it is seen.
fn held(
    session: &mut Session,
    until: Option<Instant>,
    ended: &AtomicBool,
    mut seen: impl FnMut(usize, &Outcome),
) {
    loop {
        for (i, outcome) in session.poll() {
            seen(i, &outcome);
        }
        if session.done()
            || ended.load(Ordering::Relaxed)
            || until.is_some_and(|u| Instant::now() > u)
        {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A class's sessions, all at once (a client is a person's to drive, so
/// none waits for another's): each student's link is where the twin
/// listens for their client. Every session ends as a single one does;
/// Enter or Ctrl-D ends them all.
fn class(args: &ClientArgs, roster: &Path) -> Result<()> {
    let students = class::load_roster(roster, args.id, Protocol::Meb)?;
    class::no_bench(&students, roster, "client")?;
    let mut sessions = Vec::with_capacity(students.len());
    println!(
        "twin check client: {} students' clients, each served its slave's image",
        students.len()
    );
    let width = students
        .iter()
        .map(|s| s.name.chars().count())
        .max()
        .unwrap_or(0);
    for student in &students {
        let at = || format!("{}, line {}", roster.display(), student.line);
        let addr = listen_addr(&student.link)
            .with_context(|| format!("{}: `{}`'s client", at(), student.name))?;
        // A port taken is the student's to fix, not the class's: their
        // run says so and the others go on.
        let session = Session::listen(addr, student.id).map_err(|e| e.to_string());
        let shown = match &session {
            Ok(s) => format!("meb tcp://{} server, slave {:02}", s.addr(), student.id),
            Err(why) => format!("cannot listen on {}: {why}", student.link),
        };
        println!("  {:width$}  {shown}", student.name);
        sessions.push(Mutex::new(Some(session)));
    }
    checklist();
    let ended = stdin_ended();
    let until = args
        .duration
        .map(|d| Instant::now() + Duration::from_secs_f64(d));
    let options = super::class::Class {
        suite_name: SUITE,
        suite_arg: NAME,
        role: "client",
        out: args.reports.out.as_deref(),
        jobs: u16::try_from(students.len()).unwrap_or(u16::MAX),
        suite_toml: (!args.reports.no_record).then_some(""),
    };
    super::class::run(&options, &students, |student| {
        let taken = students
            .iter()
            .position(|s| std::ptr::eq(s, student))
            .and_then(|i| sessions.get(i))
            .and_then(|s| s.lock().unwrap_or_else(PoisonError::into_inner).take());
        match taken {
            Some(Ok(mut session)) => {
                held(&mut session, until, &ended, |_, _| {});
                let link = format!("tcp://{}", session.addr());
                let connected = session.connected();
                let mut run = session.finish(&link);
                if !connected {
                    run.error = Some(format!("no client connected to {link} during the session"));
                }
                run
            }
            Some(Err(why)) => unreachable(
                &student.link,
                student.id,
                format!("cannot listen on {}: {why}", student.link),
            ),
            None => unreachable(&student.link, student.id, "checked twice".into()),
        }
    })
}

/// Set when stdin gives a line or ends (Enter, Ctrl-D, a closed pipe).
fn stdin_ended() -> Arc<AtomicBool> {
    let ended = Arc::new(AtomicBool::new(false));
    let flag = ended.clone();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = std::io::stdin().lock().read_line(&mut line);
        flag.store(true, Ordering::Relaxed);
    });
    ended
}
