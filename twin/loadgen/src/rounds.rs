//! The request-rate figures, measured in rounds. In each round every
//! server is started afresh for each figure, loaded (by one client, then,
//! in a second pass, by many) and stopped, one after the other. On a shared
//! 2-core machine the rate a server gets drifts by ±15 % over a minute, and
//! by a few per cent between two sessions a second apart: so the sessions
//! a goal compares are measured back to back. In each pass the recorded
//! twin runs right between tokio-modbus and the twin with recording off,
//! and every other round the order is reversed, so neither reference is
//! always the one measured first. The medians over the rounds are reported
//! with their ranges.

use anyhow::{Context, Result};
use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use crate::child::{Server, tcp_addr};
use crate::measure::{Dialect, Rate, rate};
use crate::servers;

/// The name of the thread-per-connection echo server.
pub const ECHO: &str = "echo";

/// A server the rates are measured on.
pub struct RateServer {
    pub name: String,
    pub recording: &'static str,
    /// The protocol (`modbus-tcp`, `echo-tcp`) of the link it prints.
    pub link: &'static str,
    pub dialect: Dialect,
    /// A fresh command that starts it.
    pub command: Box<dyn Fn() -> Result<Command>>,
    /// The recording it writes, deleted after each session: its pages are
    /// then never written back to disk while another server is measured.
    pub recording_file: Option<PathBuf>,
    /// The plant's tick lateness each of its sessions printed at its end:
    /// (round, clients, line).
    pub lateness: Vec<(usize, usize, String)>,
    /// Per recorded session: the frames it said it recorded, and the
    /// requests its clients sent (each answered or counted bad).
    pub recorded: Vec<(Option<u64>, u64)>,
    pub one: Vec<Rate>,
    pub many: Vec<Rate>,
}

impl RateServer {
    pub fn is_twin(&self) -> bool {
        self.name.starts_with("twin")
    }

    /// One session: started, loaded by `clients` for `duration`, stopped.
    fn session(
        &mut self,
        round: usize,
        clients: usize,
        duration: Duration,
        timeout: Duration,
    ) -> Result<Rate> {
        let server = Server::start(&self.name, (self.command)()?, timeout)?;
        let addr = tcp_addr(server.link(self.link)?)?.to_string();
        let what = format!("{} (rec. {})", self.name, self.recording);
        eprintln!(
            "  {what}: request rate, {} for {duration:?}",
            clients_text(clients)
        );
        let links = (0..clients)
            .map(|_| servers::connect(&addr))
            .collect::<Result<Vec<_>>>()?;
        let figure = rate(links, self.dialect, duration, || server.cpu_time())
            .with_context(|| format!("{what}, {}", clients_text(clients)))?;
        // A recording drains its queue before the server exits: give it time.
        let lines = server.stop_within(STOP_LIMIT);
        if let Some(file) = &self.recording_file {
            let _ = std::fs::remove_file(file);
        }
        if self.is_twin() && self.recording != "off" {
            let sent = figure.answered + figure.bad_replies;
            self.recorded.push((frames_recorded(&lines), sent));
        }
        if self.is_twin() {
            let lateness = lines.iter().find(|l| l.contains("tick lateness"));
            self.lateness.push((
                round,
                clients,
                lateness
                    .map_or("no tick lateness printed", |l| l.trim())
                    .to_string(),
            ));
        }
        Ok(figure)
    }
}

fn clients_text(clients: usize) -> String {
    if clients == 1 {
        "1 client".into()
    } else {
        format!("{clients} clients")
    }
}

/// The order of round `round`'s sessions (counted from 1), as indexes into
/// `servers`: the references in their order, then the recorded twins, then
/// the twin with recording off; reversed in even rounds. A recorded twin
/// thus runs right after or right before tokio-modbus (the last reference)
/// and the unrecorded twin, the two rates its goals compare it with.
pub fn session_order(servers: &[RateServer], round: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..servers.len()).collect();
    order.sort_by_key(|&i| {
        let s = &servers[i];
        (s.is_twin(), s.is_twin() && s.recording == "off")
    });
    if round.is_multiple_of(2) {
        order.reverse();
    }
    order
}

/// Round `round` (from 1): each server's one-client session in turn, then
/// each server's session with `clients`, in [`session_order`].
pub fn measure_round(
    servers: &mut [RateServer],
    round: usize,
    clients: usize,
    duration: Duration,
    timeout: Duration,
) -> Result<()> {
    let order = session_order(servers, round);
    for &i in &order {
        let one = servers[i].session(round, 1, duration, timeout)?;
        servers[i].one.push(one);
    }
    for &i in &order {
        let many = servers[i].session(round, clients, duration, timeout)?;
        servers[i].many.push(many);
    }
    Ok(())
}

/// How long a server may take to stop (a recording drains its queue first).
const STOP_LIMIT: Duration = Duration::from_secs(20);

/// The frame count `twin serve` prints at its end:
/// `  N frames recorded on the links (requests and replies)`.
fn frames_recorded(lines: &[String]) -> Option<u64> {
    lines.iter().find_map(|l| {
        l.trim()
            .strip_suffix(" frames recorded on the links (requests and replies)")?
            .parse()
            .ok()
    })
}

/// Median, lowest and highest of `values` (not empty).
fn spread(mut values: Vec<f64>) -> (f64, f64, f64) {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    let median = crate::measure::median(values.iter().copied()).unwrap_or(f64::NAN);
    (median, values[0], values[n - 1])
}

fn per_second(rates: &[Rate]) -> (f64, f64, f64) {
    spread(rates.iter().map(|r| r.per_second).collect())
}

fn cpu(rates: &[Rate]) -> String {
    let each: Vec<f64> = rates
        .iter()
        .filter_map(|r| r.server_cpu.map(|c| c.as_secs_f64() * 1e6))
        .collect();
    if each.is_empty() {
        return "-".into();
    }
    format!("{:.1} µs", spread(each).0)
}

fn bad(s: &RateServer) -> u64 {
    s.one.iter().chain(&s.many).map(|r| r.bad_replies).sum()
}

/// The rate table: per server, the median over the rounds and the range.
pub fn report(servers: &[RateServer], clients: usize, rounds: usize) {
    println!(
        "  Modbus TCP request rate (FC04 ten registers and FC03 three, alternating), median of"
    );
    println!(
        "  {rounds} round(s) and range, each server started afresh for each figure, the recorded"
    );
    println!("  twin measured between tokio-modbus and the twin unrecorded; the server's CPU time");
    println!("  (user + system, all threads) per request answered, median");
    println!(
        "  {:<20} {:<6} {:>24} {:>9} {:>26} {:>9} {:>5}",
        "server",
        "rec.",
        "1 client",
        "cpu/req",
        format!("{clients} clients"),
        "cpu/req",
        "bad"
    );
    let figure = |(median, low, high): (f64, f64, f64)| {
        format!("{median:>7.0}/s {:>15}", format!("{low:.0}-{high:.0}"))
    };
    for s in servers.iter().filter(|s| !s.one.is_empty()) {
        println!(
            "  {:<20} {:<6} {:>24} {:>9} {:>26} {:>9} {:>5}",
            s.name,
            s.recording,
            figure(per_second(&s.one)),
            cpu(&s.one),
            figure(per_second(&s.many)),
            cpu(&s.many),
            bad(s)
        );
    }
    let twins: Vec<_> = servers
        .iter()
        .filter(|s| s.is_twin() && !s.lateness.is_empty())
        .collect();
    if !twins.is_empty() {
        println!("  the plant meanwhile (each twin rate session, whole):");
        for s in twins {
            for (round, clients, line) in &s.lateness {
                println!(
                    "    round {round}, rec. {}, {}: {line}",
                    s.recording,
                    clients_text(*clients)
                );
            }
        }
    }
}

/// The rate goal, per recording mode: the twin's medians at least
/// tokio-modbus's, and in how many rounds it got more than tokio-modbus
/// did in the same round.
pub fn goals(servers: &[RateServer]) {
    let Some(reference) = servers
        .iter()
        .find(|s| s.name.starts_with("tokio-modbus") && !s.one.is_empty())
    else {
        return;
    };
    for s in servers.iter().filter(|s| s.is_twin() && !s.one.is_empty()) {
        let ratio = |twin: &[Rate], tokio: &[Rate]| per_second(twin).0 / per_second(tokio).0;
        let won = |twin: &[Rate], tokio: &[Rate]| {
            twin.iter()
                .zip(tokio)
                .filter(|(t, r)| t.per_second >= r.per_second)
                .count()
        };
        let (one, many) = (
            ratio(&s.one, &reference.one),
            ratio(&s.many, &reference.many),
        );
        let ok = one >= 1.0 && many >= 1.0;
        println!(
            "    twin serve, recording {}: median {one:.2}x / {many:.2}x tokio-modbus's rate \
             (1 / many clients; more in {} / {} of {} rounds): {}",
            s.recording,
            won(&s.one, &reference.one),
            won(&s.many, &reference.many),
            s.one.len().min(reference.one.len()),
            if ok { "met" } else { "MISSED" }
        );
    }
    echo_ceiling(servers, reference);
    recording_goals(servers, reference);
}

/// Each round's ratio, then their median: on a machine whose speed drifts,
/// the median says what recording costs, the rounds whether every session
/// held the goal.
fn rounds_and_median(ratios: &[f64]) -> String {
    if ratios.is_empty() {
        return "no rounds".to_string();
    }
    let each = ratios
        .iter()
        .map(|r| format!("{r:.2}"))
        .collect::<Vec<_>>()
        .join(" ");
    format!("{each}x (median {:.2}x)", spread(ratios.to_vec()).0)
}

/// Each round's ratio of `server`'s many-client rate to `base`'s.
fn many_per_round(server: &RateServer, base: &RateServer) -> Vec<f64> {
    server
        .many
        .iter()
        .zip(&base.many)
        .map(|(s, b)| s.per_second / b.per_second)
        .collect()
}

/// The bare echo (a thread per connection, no Modbus, no plant) against
/// tokio-modbus, round by round: the most any server could get here, so
/// the ceiling of the goal lines that follow it, in the same run. Then each
/// twin against the echo of its round: how far below that ceiling it runs,
/// a figure that moves far less from round to round than tokio-modbus's
/// own rate does.
fn echo_ceiling(servers: &[RateServer], reference: &RateServer) {
    let Some(echo) = servers
        .iter()
        .find(|s| s.name == ECHO && !s.many.is_empty())
    else {
        return;
    };
    println!(
        "    the bare echo (the least work a server can do per request) at many clients, \
         per round: {} tokio-modbus's rate",
        rounds_and_median(&many_per_round(echo, reference))
    );
    for twin in servers.iter().filter(|s| s.is_twin() && !s.many.is_empty()) {
        println!(
            "    twin serve, recording {} at many clients, per round: {} the bare echo's rate",
            twin.recording,
            rounds_and_median(&many_per_round(twin, echo))
        );
    }
}

/// What recording every frame costs at many clients, per round: at least
/// 1.1x tokio-modbus's rate and 0.9x the twin's own rate with recording off,
/// in every round; and every frame recorded, two per request.
fn recording_goals(servers: &[RateServer], reference: &RateServer) {
    let twins = || servers.iter().filter(|s| s.is_twin() && !s.many.is_empty());
    let Some(off) = twins().find(|s| s.recording == "off") else {
        return;
    };
    for s in twins().filter(|s| s.recording != "off") {
        let (vs_tokio, vs_off) = (many_per_round(s, reference), many_per_round(s, off));
        let least = |ratios: &[f64]| ratios.iter().copied().fold(f64::INFINITY, f64::min);
        let ok = least(&vs_tokio) >= 1.1 && least(&vs_off) >= 0.9;
        println!(
            "    twin serve, recording {} at many clients, per round: {} tokio-modbus's rate \
             (goal >= 1.1), {} its own rate recording off (goal >= 0.9): {}",
            s.recording,
            rounds_and_median(&vs_tokio),
            rounds_and_median(&vs_off),
            if ok { "met" } else { "MISSED" }
        );
        let kept = s
            .recorded
            .iter()
            .filter(|(frames, sent)| *frames == Some(2 * sent))
            .count();
        let counts = s
            .recorded
            .iter()
            .map(|(frames, sent)| match frames {
                Some(f) => format!("{f} of {}", 2 * sent),
                None => "none printed".into(),
            })
            .collect::<Vec<_>>()
            .join(", ");
        println!(
            "    twin serve, recording {}: frames recorded of two per request sent, per session: {counts}: {}",
            s.recording,
            if kept == s.recorded.len() {
                "every frame kept"
            } else {
                "FRAMES MISSING"
            }
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn server(name: &str, recording: &'static str) -> RateServer {
        RateServer {
            name: name.into(),
            recording,
            link: "modbus-tcp",
            dialect: Dialect::ModbusTcp,
            command: Box::new(|| Ok(Command::new("true"))),
            recording_file: None,
            lateness: Vec::new(),
            recorded: Vec::new(),
            one: Vec::new(),
            many: Vec::new(),
        }
    }

    fn names(servers: &[RateServer], round: usize) -> Vec<String> {
        session_order(servers, round)
            .into_iter()
            .map(|i| format!("{} {}", servers[i].name, servers[i].recording))
            .collect()
    }

    #[test]
    fn a_goal_line_gives_each_round_and_the_median() {
        assert_eq!(
            rounds_and_median(&[1.09, 0.96, 1.2, 1.01]),
            "1.09 0.96 1.20 1.01x (median 1.05x)"
        );
        assert_eq!(rounds_and_median(&[]), "no rounds");
    }

    fn with_rates(mut server: RateServer, rates: &[f64]) -> RateServer {
        server.many = rates
            .iter()
            .map(|&per_second| Rate {
                answered: 1,
                per_second,
                bad_replies: 0,
                server_cpu: None,
            })
            .collect();
        server
    }

    #[test]
    fn each_round_is_compared_with_the_same_round_of_the_reference() {
        let tokio = with_rates(server("tokio-modbus 0.17", "-"), &[80.0, 100.0, 90.0]);
        let echo = with_rates(server(ECHO, "-"), &[100.0, 110.0, 90.0]);
        assert_eq!(many_per_round(&echo, &tokio), [1.25, 1.1, 1.0]);
        // A round one of them lacks (a run cut short) is left out.
        let short = with_rates(server(ECHO, "-"), &[88.0]);
        assert_eq!(many_per_round(&short, &tokio), [1.1]);
    }

    #[test]
    fn the_recorded_twin_runs_between_the_two_rates_it_is_compared_with() {
        // In the order `serve-bench` lists them.
        let servers = [
            server("echo", "-"),
            server("echo (tokio)", "-"),
            server("tokio-modbus 0.17", "-"),
            server("twin serve", "off"),
            server("twin serve", "mcap"),
        ];
        let odd = [
            "echo -",
            "echo (tokio) -",
            "tokio-modbus 0.17 -",
            "twin serve mcap",
            "twin serve off",
        ];
        assert_eq!(names(&servers, 1), odd);
        assert_eq!(names(&servers, 3), odd);
        let even: Vec<_> = odd.iter().rev().map(|s| s.to_string()).collect();
        assert_eq!(names(&servers, 2), even);
        // --twin-only and --no-twin keep what is left in the same order.
        assert_eq!(
            names(&servers[3..], 1),
            ["twin serve mcap", "twin serve off"]
        );
        assert_eq!(
            names(&servers[..3], 2),
            ["tokio-modbus 0.17 -", "echo (tokio) -", "echo -"]
        );
    }
}
