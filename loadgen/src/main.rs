//! `serve-bench`: how fast `twin serve` answers real masters, measured in one
//! run on loopback against a bare echo (the floor) and a tokio-modbus server
//! (the reference), every server a child process over a real TCP socket or a
//! real pseudo-terminal.

mod child;
mod measure;
mod pty;
mod servers;

use anyhow::{Context, Result};
use child::{Server, tcp_addr};
use clap::{Parser, Subcommand};
use measure::{Dialect, Latency, Rate, latency, rate};
use pty::PtyPair;
use std::path::PathBuf;
use std::process::{Command, ExitCode};
use std::time::Duration;

/// Reply latency and request rate of `twin serve` (Modbus TCP, and Modbus RTU
/// over a pseudo-terminal) against a bare echo server and tokio-modbus 0.17
/// servers (TCP, and RTU through tokio-serial), measured the same way in the same run. Latency runs from the
/// request's last byte written to the reply's first byte read; rates count
/// checked replies of clients sending back to back (FC04 and FC03 alternating).
#[derive(Debug, Parser)]
#[command(name = "serve-bench", version, max_term_width = 100)]
struct Cli {
    #[command(subcommand)]
    role: Option<Role>,
    /// The twin binary (default: `twin` beside this program, else on PATH).
    #[arg(long)]
    twin: Option<PathBuf>,
    /// Requests per latency figure.
    #[arg(long, default_value_t = 20_000)]
    requests: usize,
    /// Seconds per request-rate figure.
    #[arg(long, default_value_t = 3.0)]
    seconds: f64,
    /// Clients of the many-client rate figure.
    #[arg(long, default_value_t = 8)]
    clients: usize,
    /// Extra arguments for `twin serve` (repeat it), e.g. `--twin-arg=--turnaround-ms=0`.
    #[arg(long = "twin-arg", allow_hyphen_values = true)]
    twin_args: Vec<String>,
    /// Skip the twin (measure only the echo and tokio-modbus servers).
    #[arg(long, conflicts_with = "twin_only")]
    no_twin: bool,
    /// Measure only the twin (to compare two builds of it quickly).
    #[arg(long)]
    twin_only: bool,
}

#[derive(Debug, Subcommand)]
enum Role {
    /// (internal) echo server over TCP on a free port.
    #[command(hide = true)]
    EchoTcp,
    /// (internal) echo server over TCP, a tokio task per connection.
    #[command(hide = true)]
    EchoTokio,
    /// (internal) echo server on a terminal device.
    #[command(hide = true)]
    EchoPty { path: PathBuf },
    /// (internal) tokio-modbus TCP server on a free port.
    #[command(hide = true)]
    TokioModbus,
    /// (internal) tokio-modbus RTU server on a terminal device.
    #[command(hide = true)]
    TokioModbusRtu { path: PathBuf },
    /// Load any Modbus TCP server (unit 1, FC04 registers 0-9 and FC03 0-2
    /// alternating) and print the request rate it sustains, e.g. to profile
    /// a server with `perf stat -p` meanwhile.
    Load {
        /// The server, e.g. `tcp://127.0.0.1:5020`.
        address: String,
        /// Clients sending back to back, one thread each.
        #[arg(long, default_value_t = 8)]
        clients: usize,
        /// Seconds to load it for.
        #[arg(long, default_value_t = 3.0)]
        seconds: f64,
        /// The server echoes: expect each request back unchanged.
        #[arg(long)]
        echo: bool,
    },
}

const START_TIMEOUT: Duration = Duration::from_secs(20);

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.role {
        Some(Role::EchoTcp) => servers::echo_tcp(),
        Some(Role::EchoTokio) => servers::echo_tokio(),
        Some(Role::EchoPty { path }) => servers::echo_pty(path),
        Some(Role::TokioModbus) => servers::tokio_modbus_tcp(),
        Some(Role::TokioModbusRtu { path }) => servers::tokio_modbus_rtu(path),
        Some(Role::Load {
            address,
            clients,
            seconds,
            echo,
        }) => load(address, *clients, *seconds, *echo),
        None => bench(&cli),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn load(address: &str, clients: usize, seconds: f64, echo: bool) -> Result<()> {
    let addr = address.strip_prefix("tcp://").unwrap_or(address);
    let links = (0..clients.max(1))
        .map(|_| servers::connect(addr))
        .collect::<Result<Vec<_>>>()?;
    let duration = Duration::try_from_secs_f64(seconds).context("--seconds")?;
    let dialect = if echo {
        Dialect::EchoTcp
    } else {
        Dialect::ModbusTcp
    };
    let r =
        rate(links, dialect, duration, || None).with_context(|| format!("loading {address}"))?;
    println!(
        "{address}: {} requests answered, {:.0}/s, from {} clients over {seconds} s, {} bad replies",
        r.answered,
        r.per_second,
        clients.max(1),
        r.bad_replies
    );
    Ok(())
}

fn myself(role: &[&str]) -> Result<Command> {
    let mut cmd = Command::new(std::env::current_exe().context("locating serve-bench")?);
    cmd.args(role);
    Ok(cmd)
}

fn twin_binary(cli: &Cli) -> PathBuf {
    if let Some(path) = &cli.twin {
        return path.clone();
    }
    let beside = std::env::current_exe()
        .ok()
        .and_then(|p| p.parent().map(|d| d.join("twin")));
    match beside {
        Some(p) if p.exists() => p,
        _ => PathBuf::from("twin"),
    }
}

/// One row of the latency table.
struct LatencyRow {
    server: String,
    link: &'static str,
    figure: Latency,
}

/// One row of the rate table.
struct RateRow {
    server: String,
    recording: &'static str,
    one: Rate,
    many: Rate,
}

struct Bench<'a> {
    cli: &'a Cli,
    latency: Vec<LatencyRow>,
    rates: Vec<RateRow>,
    /// Per twin session, the plant's tick lateness it printed at the end.
    lateness: Vec<String>,
}

impl Bench<'_> {
    fn tcp_latency(&mut self, server: &str, addr: &str, dialect: Dialect) -> Result<()> {
        eprintln!(
            "  {server}: latency over TCP, {} requests",
            self.cli.requests
        );
        let mut link = servers::connect(addr)?;
        let figure = latency(&mut link, dialect, self.cli.requests)
            .with_context(|| format!("{server} over TCP"))?;
        self.latency.push(LatencyRow {
            server: server.to_string(),
            link: "tcp",
            figure,
        });
        Ok(())
    }

    fn pty_latency(&mut self, server: &str, pair: &mut PtyPair, dialect: Dialect) -> Result<()> {
        eprintln!(
            "  {server}: latency over a pty, {} requests",
            self.cli.requests
        );
        let figure = latency(&mut pair.master, dialect, self.cli.requests)
            .with_context(|| format!("{server} over a pty"))?;
        self.latency.push(LatencyRow {
            server: server.to_string(),
            link: "pty",
            figure,
        });
        Ok(())
    }

    fn tcp_rates(
        &mut self,
        server: &str,
        process: &Server,
        recording: &'static str,
        addr: &str,
        dialect: Dialect,
    ) -> Result<()> {
        let cpu = || process.cpu_time();
        let duration = Duration::from_secs_f64(self.cli.seconds);
        let connect =
            |n: usize| -> Result<Vec<_>> { (0..n).map(|_| servers::connect(addr)).collect() };
        eprintln!("  {server}: request rate, 1 client, {duration:?}");
        let one = rate(connect(1)?, dialect, duration, cpu)
            .with_context(|| format!("{server}, one client"))?;
        eprintln!(
            "  {server}: request rate, {} clients, {duration:?}",
            self.cli.clients
        );
        let many = rate(connect(self.cli.clients)?, dialect, duration, cpu)
            .with_context(|| format!("{server}, {} clients", self.cli.clients))?;
        self.rates.push(RateRow {
            server: server.to_string(),
            recording,
            one,
            many,
        });
        Ok(())
    }
}

fn bench(cli: &Cli) -> Result<()> {
    let mut b = Bench {
        cli,
        latency: Vec::new(),
        rates: Vec::new(),
        lateness: Vec::new(),
    };

    if !cli.twin_only {
        references(&mut b)?;
    }
    if !cli.no_twin {
        twin(&mut b)?;
    }
    report(&b);
    Ok(())
}

/// The echo and tokio-modbus servers.
fn references(b: &mut Bench) -> Result<()> {
    let echo = Server::start("echo", myself(&["echo-tcp"])?, START_TIMEOUT)?;
    let addr = tcp_addr(echo.link("echo-tcp")?)?.to_string();
    b.tcp_latency("echo", &addr, Dialect::EchoTcp)?;
    b.tcp_rates("echo", &echo, "-", &addr, Dialect::EchoTcp)?;
    let _ = echo.stop();

    // The same echo on tokio: what a readiness loop costs by itself.
    let echo = Server::start("echo", myself(&["echo-tokio"])?, START_TIMEOUT)?;
    let addr = tcp_addr(echo.link("echo-tcp")?)?.to_string();
    b.tcp_rates("echo (tokio)", &echo, "-", &addr, Dialect::EchoTcp)?;
    let _ = echo.stop();

    let mut pair = PtyPair::open()?;
    let path = pair.slave_path.display().to_string();
    let echo = Server::start("echo", myself(&["echo-pty", &path])?, START_TIMEOUT)?;
    b.pty_latency("echo", &mut pair, Dialect::EchoRtu)?;
    let _ = echo.stop();

    let reference = Server::start("tokio-modbus", myself(&["tokio-modbus"])?, START_TIMEOUT)?;
    let addr = tcp_addr(reference.link("modbus-tcp")?)?.to_string();
    b.tcp_latency("tokio-modbus 0.17", &addr, Dialect::ModbusTcp)?;
    b.tcp_rates(
        "tokio-modbus 0.17",
        &reference,
        "-",
        &addr,
        Dialect::ModbusTcp,
    )?;
    let _ = reference.stop();

    let mut pair = PtyPair::open()?;
    let path = pair.slave_path.display().to_string();
    let reference = Server::start(
        "tokio-modbus",
        myself(&["tokio-modbus-rtu", &path])?,
        START_TIMEOUT,
    )?;
    b.pty_latency("tokio-modbus 0.17", &mut pair, Dialect::ModbusRtu)?;
    let _ = reference.stop();
    Ok(())
}

/// `twin serve`, recording off and on.
fn twin(b: &mut Bench) -> Result<()> {
    let cli = b.cli;
    {
        let twin = twin_binary(cli);
        let scratch = std::env::temp_dir().join(format!("serve-bench-{}", std::process::id()));
        std::fs::create_dir_all(&scratch)?;
        for recording in ["off", "mcap"] {
            let mut pair = PtyPair::open()?;
            let mut cmd = Command::new(&twin);
            // Turnaround 0 (serial links default to 1 ms); no client limit
            // or rate limit, which a load generator would trip.
            cmd.args([
                "serve",
                "--quiet",
                "--turnaround-ms",
                "0",
                "--status-every",
                "0",
            ])
            .args(["--max-clients", "0", "--rate-limit", "0"])
            .args(["--modbus", "tcp://127.0.0.1:0", "--modbus-rtu"])
            .arg(&pair.slave_path);
            if recording == "mcap" {
                cmd.arg("--out").arg(scratch.join("serve-bench.mcap"));
            } else {
                cmd.arg("--no-record");
            }
            cmd.args(&cli.twin_args);
            let name = format!("twin serve, recording {recording}");
            let server = Server::start(&name, cmd, START_TIMEOUT)?;
            let addr = tcp_addr(server.link("modbus-tcp")?)?.to_string();
            let label = format!("twin serve (rec. {recording})");
            b.tcp_latency(&label, &addr, Dialect::ModbusTcp)?;
            b.pty_latency(&label, &mut pair, Dialect::ModbusRtu)?;
            b.tcp_rates("twin serve", &server, recording, &addr, Dialect::ModbusTcp)?;
            // The plant ran in real time all along: its tick lateness.
            let lines = server.stop();
            let lateness = lines.iter().find(|l| l.contains("tick lateness"));
            b.lateness.push(format!(
                "{label}: {}",
                lateness.map_or("no tick lateness printed", |l| l.trim())
            ));
        }
        let _ = std::fs::remove_dir_all(&scratch);
    }
    Ok(())
}

fn us(d: Duration) -> String {
    format!("{:.1} µs", d.as_secs_f64() * 1e6)
}

fn report(b: &Bench) {
    let cli = b.cli;
    println!(
        "serve-bench: loopback, {} requests per latency figure, {} s per rate figure",
        cli.requests, cli.seconds
    );
    println!(
        "  reply latency: from the request's last byte written (reply) or from the start of its"
    );
    println!("  write (round trip) to the reply's first byte read");
    println!(
        "  {:<28} {:<5} {:>10} {:>10} {:>10} {:>11} {:>10} {:>10} {:>5}",
        "server", "link", "median", "p99", "max", "rt median", "rt p99", "rt mean", "bad"
    );
    for row in &b.latency {
        let (f, rt) = (&row.figure.reply, &row.figure.round_trip);
        println!(
            "  {:<28} {:<5} {:>10} {:>10} {:>10} {:>11} {:>10} {:>10} {:>5}",
            row.server,
            row.link,
            us(f.median()),
            us(f.p99()),
            us(f.max()),
            us(rt.median()),
            us(rt.p99()),
            us(rt.mean()),
            row.figure.bad_replies
        );
    }
    println!("  Modbus TCP request rate (FC04 ten registers and FC03 three, alternating)");
    println!("  and the server's CPU time (user + system, all threads) per request answered");
    println!(
        "  {:<28} {:<9} {:>12} {:>9} {:>12} {:>9} {:>5}",
        "server",
        "recording",
        "1 client",
        "cpu/req",
        format!("{} clients", cli.clients),
        "cpu/req",
        "bad"
    );
    let cpu = |r: &Rate| r.server_cpu.map_or("-".to_string(), us);
    for row in &b.rates {
        println!(
            "  {:<28} {:<9} {:>10.0}/s {:>9} {:>10.0}/s {:>9} {:>5}",
            row.server,
            row.recording,
            row.one.per_second,
            cpu(&row.one),
            row.many.per_second,
            cpu(&row.many),
            row.one.bad_replies + row.many.bad_replies
        );
    }
    if !b.lateness.is_empty() {
        println!("  the plant meanwhile (each twin session, whole):");
        for line in &b.lateness {
            println!("    {line}");
        }
    }
    goals(b);
}

/// The goals, each with its verdict.
fn goals(b: &Bench) {
    let find = |server: &str, link: &str| {
        b.latency
            .iter()
            .find(|r| r.server.starts_with(server) && r.link == link)
            .map(|r| r.figure.round_trip.p99())
    };
    if b.cli.twin_only {
        println!("  goals: not judged with --twin-only (no echo or tokio-modbus figures)");
        return;
    }
    println!("  goals (turnaround 0): p99 < 1 ms and <= 3x the echo's p99; rate >= tokio-modbus");
    for row in b.latency.iter().filter(|r| r.server.starts_with("twin")) {
        let p99 = row.figure.reply.p99();
        let rt_p99 = row.figure.round_trip.p99();
        let echo = find("echo", row.link);
        // The ratio compares round trips: on loopback the echo's reply is
        // often in before its request's write() has returned.
        let ratio = echo.map(|e| rt_p99.as_secs_f64() / e.as_secs_f64());
        let ok = rt_p99 < Duration::from_millis(1) && ratio.is_some_and(|r| r <= 3.0);
        println!(
            "    {} {}: p99 {}, round trip p99 {} = {:.1}x the echo's: {}",
            row.server,
            row.link,
            us(p99),
            us(rt_p99),
            ratio.unwrap_or(f64::NAN),
            if ok { "met" } else { "MISSED" }
        );
    }
    let reference = b
        .rates
        .iter()
        .find(|r| r.server.starts_with("tokio-modbus"));
    for row in b.rates.iter().filter(|r| r.server.starts_with("twin")) {
        if let Some(t) = reference {
            let ok =
                row.one.per_second >= t.one.per_second && row.many.per_second >= t.many.per_second;
            println!(
                "    twin serve, recording {}: {:.2}x / {:.2}x tokio-modbus's rate: {}",
                row.recording,
                row.one.per_second / t.one.per_second,
                row.many.per_second / t.many.per_second,
                if ok { "met" } else { "MISSED" }
            );
        }
    }
}
