//! The request-rate figures, measured in rounds: in each round every server
//! is started afresh, loaded by one client and then by many, and stopped,
//! one after the other. On a shared 2-core machine the rate a server gets
//! drifts by ±15 % over a minute; measured in one block per server, the
//! last server measured would carry the drift. Interleaved, each round
//! compares servers seconds apart, and the medians over the rounds are
//! reported with their ranges.

use anyhow::{Context, Result};
use std::process::Command;
use std::time::Duration;

use crate::child::{Server, tcp_addr};
use crate::measure::{Dialect, Rate, rate};
use crate::servers;

/// A server the rates are measured on.
pub struct RateServer {
    pub name: String,
    pub recording: &'static str,
    /// The protocol (`modbus-tcp`, `echo-tcp`) of the link it prints.
    pub link: &'static str,
    pub dialect: Dialect,
    /// A fresh command that starts it.
    pub command: Box<dyn Fn() -> Result<Command>>,
    /// The plant's tick lateness each of its sessions printed at its end.
    pub lateness: Vec<String>,
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

    /// One round: started, one client then `clients`, stopped.
    pub fn measure(&mut self, clients: usize, duration: Duration, timeout: Duration) -> Result<()> {
        let server = Server::start(&self.name, (self.command)()?, timeout)?;
        let addr = tcp_addr(server.link(self.link)?)?.to_string();
        let cpu = || server.cpu_time();
        let connect =
            |n: usize| -> Result<Vec<_>> { (0..n).map(|_| servers::connect(&addr)).collect() };
        let what = format!("{} (rec. {})", self.name, self.recording);
        eprintln!("  {what}: request rate, 1 client, then {clients}, {duration:?} each");
        let one = rate(connect(1)?, self.dialect, duration, cpu)
            .with_context(|| format!("{what}, one client"))?;
        let many = rate(connect(clients)?, self.dialect, duration, cpu)
            .with_context(|| format!("{what}, {clients} clients"))?;
        self.one.push(one);
        self.many.push(many);
        // A recording drains its queue before the server exits: give it time.
        let lines = server.stop_within(STOP_LIMIT);
        if self.is_twin() && self.recording != "off" {
            let sent = [one, many].iter().map(|r| r.answered + r.bad_replies).sum();
            self.recorded.push((frames_recorded(&lines), sent));
        }
        if self.is_twin() {
            let lateness = lines.iter().find(|l| l.contains("tick lateness"));
            self.lateness.push(
                lateness
                    .map_or("no tick lateness printed", |l| l.trim())
                    .to_string(),
            );
        }
        Ok(())
    }
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
    let median = if n % 2 == 1 {
        values[n / 2]
    } else {
        (values[n / 2 - 1] + values[n / 2]) / 2.0
    };
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
    println!("  {rounds} round(s) and range, each round every server started afresh in turn; the");
    println!("  server's CPU time (user + system, all threads) per request answered, median");
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
            for (round, line) in s.lateness.iter().enumerate() {
                println!("    round {}, rec. {}: {line}", round + 1, s.recording);
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
    recording_goals(servers, reference);
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
        let per_round = |base: &RateServer| -> Vec<f64> {
            s.many
                .iter()
                .zip(&base.many)
                .map(|(t, b)| t.per_second / b.per_second)
                .collect()
        };
        let (vs_tokio, vs_off) = (per_round(reference), per_round(off));
        let shown = |ratios: &[f64]| {
            ratios
                .iter()
                .map(|r| format!("{r:.2}"))
                .collect::<Vec<_>>()
                .join(" ")
        };
        let least = |ratios: &[f64]| ratios.iter().copied().fold(f64::INFINITY, f64::min);
        let ok = least(&vs_tokio) >= 1.1 && least(&vs_off) >= 0.9;
        println!(
            "    twin serve, recording {} at many clients, per round: {}x tokio-modbus's rate \
             (goal >= 1.1), {}x its own rate recording off (goal >= 0.9): {}",
            s.recording,
            shown(&vs_tokio),
            shown(&vs_off),
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
