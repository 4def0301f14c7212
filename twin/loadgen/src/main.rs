//! `serve-bench`: how fast `twin serve` answers real masters, measured in one
//! run on loopback against a bare echo (the floor) and a tokio-modbus server
//! (the reference), every server a child process over a real TCP socket or a
//! real pseudo-terminal.

#![allow(
    clippy::disallowed_methods,
    reason = "a load generator times real servers"
)]

mod child;
mod class;
mod measure;
mod pty;
mod rounds;
mod servers;

use anyhow::{Context, Result};
use child::{Server, tcp_addr};
use clap::{Parser, Subcommand};
use measure::{Dialect, Latency, latency, rate};
use pty::PtyPair;
use rounds::RateServer;
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
    /// Rounds of rate figures (each server started afresh for each figure,
    /// the recorded twin measured right between tokio-modbus and the
    /// unrecorded twin; the medians are reported).
    #[arg(long, default_value_t = 3)]
    rounds: usize,
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
    /// A class on this machine: N modules served by one `twin serve`
    /// (`[[module]]` tables) against one process per module (the
    /// `twin-serve@` template), or by each build given with --against (one
    /// process each), interleaved round by round; each module
    /// polled by its own Modbus TCP (or MEB-TCP) client at --hz, every
    /// reply checked.
    /// Prints per way the reply latency p99 and tick lateness p99 per
    /// module (median and worst), lost and wrong replies, the servers' CPU
    /// and memory and the machine's load, then the ratios.
    Class {
        /// Modules (students).
        #[arg(long, default_value_t = 35)]
        modules: usize,
        /// Requests per second per module; 0 leaves the class idle (no
        /// client connects), to measure what an idle class costs.
        #[arg(long, default_value_t = 100.0)]
        hz: f64,
        /// Seconds each variant is loaded per round.
        #[arg(long, default_value_t = 20.0)]
        seconds: f64,
        /// Rounds (each serves both variants, in alternating order).
        #[arg(long, default_value_t = 2)]
        rounds: usize,
        /// Serve without recording (the class records by default).
        #[arg(long)]
        no_record: bool,
        /// Serve and poll each module over MEB-TCP (the M3CVME tool's
        /// protocol: EA 00 six words and FA 00 two alternating) instead of
        /// Modbus TCP.
        #[arg(long)]
        meb: bool,
        /// Folder for the configurations and recordings [default: a temporary one].
        #[arg(long)]
        dir: Option<PathBuf>,
        /// Another build of `twin` to serve the class beside --twin's
        /// (repeat it): each build serves it from one process, in turn,
        /// and the ratios are each build's against --twin's. A build is
        /// named by its folder (`--against old/twin` is `old`).
        #[arg(long, value_name = "TWIN")]
        against: Vec<PathBuf>,
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
        Some(Role::Class {
            modules,
            hz,
            seconds,
            rounds,
            no_record,
            meb,
            dir,
            against,
        }) => class_bench(
            &class::ClassRun {
                builds: class::Build::labelled(
                    &std::iter::once(twin_binary(&cli))
                        .chain(against.iter().cloned())
                        .collect::<Vec<_>>(),
                ),
                modules: *modules,
                hz: *hz,
                seconds: *seconds,
                record: !*no_record,
                meb: *meb,
                dir: dir.clone().unwrap_or_else(|| {
                    std::env::temp_dir().join(format!("serve-bench-class-{}", std::process::id()))
                }),
            },
            *rounds,
            dir.is_none(),
        ),
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
    let duration = Duration::try_from_secs_f64(seconds)
        .context("--seconds must be a number of seconds, 0 or more")?;
    let addr = tcp_addr(address)?.to_string();
    let links = (0..clients.max(1))
        .map(|_| servers::connect(&addr))
        .collect::<Result<Vec<_>>>()?;
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

fn class_bench(run: &class::ClassRun, rounds: usize, temporary: bool) -> Result<()> {
    eprintln!(
        "serve-bench class: {} modules at {} Hz each over {}, {} s per way, {} rounds, {}",
        run.modules,
        run.hz,
        if run.meb { "MEB-TCP" } else { "Modbus TCP" },
        run.seconds,
        rounds,
        if run.record {
            "recorded"
        } else {
            "not recorded"
        }
    );
    if run.builds.len() > 1 {
        for b in &run.builds {
            println!("build {}: {}", b.label, b.path.display());
        }
    }
    let ways = class::ways(run);
    let mut all = Vec::new();
    for round in 0..rounds.max(1) {
        // Each round starts one way later, so no way is always first.
        let mut order = ways.clone();
        order.rotate_left(round % ways.len());
        for way in order {
            let f = class::measure(run, way, round)?;
            println!("round {}: {}", round + 1, class::summary(&f));
            all.push(f);
        }
    }
    // Each way's figure: the median over the rounds of the median module's.
    let figure = |way, g: fn(&class::ModuleFigures) -> f64| {
        let per_round: Vec<f64> = all
            .iter()
            .filter(|f| f.way == way)
            .map(|f| class::median(&f.modules.iter().map(g).collect::<Vec<_>>()))
            .collect();
        class::median(&per_round)
    };
    let whole = |way, g: fn(&class::ClassFigures) -> f64| {
        class::median(
            &all.iter()
                .filter(|f| f.way == way)
                .map(g)
                .collect::<Vec<_>>(),
        )
    };
    let lat = |m: &class::ModuleFigures| m.latency_p99_us;
    let tick = |m: &class::ModuleFigures| m.tick_p99_us.unwrap_or(f64::NAN);
    let (base, others) = ways.split_first().context("no way to serve the class")?;
    for &way in others {
        // An idle class has no replies to compare.
        let replies = if run.hz > 0.0 {
            format!(
                "reply p99 per module (median) {:.2}, ",
                figure(way, lat) / figure(*base, lat)
            )
        } else {
            String::new()
        };
        println!(
            "{} / {}: {replies}tick lateness p99 per module (median) {:.2}, server CPU {:.2}, RSS {:.2}",
            class::way_name(run, way),
            class::way_name(run, *base),
            figure(way, tick) / figure(*base, tick),
            whole(way, |f| f.server_cpu) / whole(*base, |f| f.server_cpu),
            whole(way, |f| f.rss_mib) / whole(*base, |f| f.rss_mib),
        );
    }
    if temporary {
        let _ = std::fs::remove_dir_all(&run.dir);
    }
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

struct Bench<'a> {
    cli: &'a Cli,
    latency: Vec<LatencyRow>,
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
}

fn bench(cli: &Cli) -> Result<()> {
    let duration = Duration::try_from_secs_f64(cli.seconds)
        .context("--seconds must be a number of seconds, 0 or more")?;
    let mut b = Bench {
        cli,
        latency: Vec::new(),
    };
    let scratch = std::env::temp_dir().join(format!("serve-bench-{}", std::process::id()));
    std::fs::create_dir_all(&scratch)?;
    if !cli.twin_only {
        references(&mut b)?;
    }
    if !cli.no_twin {
        twin_latency(&mut b, &scratch)?;
    }
    let mut rate_servers = rate_servers(cli, &scratch);
    for round in 1..=cli.rounds.max(1) {
        eprintln!("  rates, round {round} of {}", cli.rounds.max(1));
        rounds::measure_round(
            &mut rate_servers,
            round,
            cli.clients,
            duration,
            START_TIMEOUT,
        )?;
    }
    let _ = std::fs::remove_dir_all(&scratch);
    report(&b, &rate_servers);
    Ok(())
}

/// The echo and tokio-modbus servers' latency, over TCP and a pty.
fn references(b: &mut Bench) -> Result<()> {
    let echo = Server::start("echo", myself(&["echo-tcp"])?, START_TIMEOUT)?;
    let addr = tcp_addr(echo.link("echo-tcp")?)?.to_string();
    b.tcp_latency("echo", &addr, Dialect::EchoTcp)?;
    let _ = echo.stop();

    let mut pair = PtyPair::open()?;
    let path = pair.slave_path.display().to_string();
    let echo = Server::start("echo", myself(&["echo-pty", &path])?, START_TIMEOUT)?;
    b.pty_latency("echo", &mut pair, Dialect::EchoRtu)?;
    let _ = echo.stop();

    let reference = Server::start("tokio-modbus", myself(&["tokio-modbus"])?, START_TIMEOUT)?;
    let addr = tcp_addr(reference.link("modbus-tcp")?)?.to_string();
    b.tcp_latency("tokio-modbus 0.17", &addr, Dialect::ModbusTcp)?;
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

/// How `twin serve` is started: with turnaround 0 and no client or rate
/// limit (which a load generator would trip), on Modbus TCP and, given
/// `rtu`, Modbus RTU on that terminal; recording to a file in `scratch` or
/// not at all.
#[derive(Debug, Clone)]
struct TwinSetup {
    binary: PathBuf,
    args: Vec<String>,
    scratch: PathBuf,
}

impl TwinSetup {
    fn new(cli: &Cli, scratch: &std::path::Path) -> Self {
        Self {
            binary: twin_binary(cli),
            args: cli.twin_args.clone(),
            scratch: scratch.to_path_buf(),
        }
    }

    fn recording_file(&self) -> PathBuf {
        self.scratch.join("serve-bench.mcap")
    }

    fn command(&self, recording: &str, rtu: Option<&std::path::Path>) -> Command {
        let mut cmd = Command::new(&self.binary);
        cmd.args([
            "serve",
            "--quiet",
            "--turnaround-ms",
            "0",
            "--status-every",
            "0",
        ])
        .args(["--max-clients", "0", "--rate-limit", "0"])
        .args(["--modbus", "tcp://127.0.0.1:0"]);
        if let Some(path) = rtu {
            cmd.arg("--modbus-rtu").arg(path);
        }
        if recording == "mcap" {
            cmd.arg("--out").arg(self.recording_file());
        } else {
            cmd.arg("--no-record");
        }
        cmd.args(&self.args);
        cmd
    }
}

/// `twin serve`'s latency, recording off and on.
fn twin_latency(b: &mut Bench, scratch: &std::path::Path) -> Result<()> {
    for recording in ["off", "mcap"] {
        let mut pair = PtyPair::open()?;
        let cmd = TwinSetup::new(b.cli, scratch).command(recording, Some(&pair.slave_path));
        let name = format!("twin serve, recording {recording}");
        let server = Server::start(&name, cmd, START_TIMEOUT)?;
        let addr = tcp_addr(server.link("modbus-tcp")?)?.to_string();
        let label = format!("twin serve (rec. {recording})");
        b.tcp_latency(&label, &addr, Dialect::ModbusTcp)?;
        b.pty_latency(&label, &mut pair, Dialect::ModbusRtu)?;
        let _ = server.stop();
    }
    Ok(())
}

/// The servers whose rates are measured, in the order of each round.
fn rate_servers(cli: &Cli, scratch: &std::path::Path) -> Vec<RateServer> {
    let reference = |name: &str, role: &'static str, link, dialect| RateServer {
        name: name.to_string(),
        recording: "-",
        link,
        dialect,
        command: Box::new(move || myself(&[role])),
        recording_file: None,
        lateness: Vec::new(),
        recorded: Vec::new(),
        one: Vec::new(),
        many: Vec::new(),
    };
    let mut list = Vec::new();
    if !cli.twin_only {
        list.push(reference(
            rounds::ECHO,
            "echo-tcp",
            "echo-tcp",
            Dialect::EchoTcp,
        ));
        // The same echo on tokio: what a readiness loop costs by itself.
        list.push(reference(
            "echo (tokio)",
            "echo-tokio",
            "echo-tcp",
            Dialect::EchoTcp,
        ));
        list.push(reference(
            "tokio-modbus 0.17",
            "tokio-modbus",
            "modbus-tcp",
            Dialect::ModbusTcp,
        ));
    }
    if !cli.no_twin {
        for recording in ["off", "mcap"] {
            let setup = TwinSetup::new(cli, scratch);
            list.push(RateServer {
                name: "twin serve".into(),
                recording,
                link: "modbus-tcp",
                dialect: Dialect::ModbusTcp,
                recording_file: (recording == "mcap").then(|| setup.recording_file()),
                command: Box::new(move || Ok(setup.command(recording, None))),
                lateness: Vec::new(),
                recorded: Vec::new(),
                one: Vec::new(),
                many: Vec::new(),
            });
        }
    }
    list
}

fn us(d: Duration) -> String {
    format!("{:.1} µs", d.as_secs_f64() * 1e6)
}

fn report(b: &Bench, rate_servers: &[RateServer]) {
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
    rounds::report(rate_servers, cli.clients, cli.rounds.max(1));
    if cli.twin_only {
        println!("  goals: not judged with --twin-only (no echo or tokio-modbus figures)");
        return;
    }
    println!("  goals (turnaround 0): p99 < 1 ms and <= 3x the echo's p99; rate >= tokio-modbus");
    latency_goals(b);
    rounds::goals(rate_servers);
}

/// The latency goals, each with its verdict.
fn latency_goals(b: &Bench) {
    let find = |server: &str, link: &str| {
        b.latency
            .iter()
            .find(|r| r.server.starts_with(server) && r.link == link)
            .map(|r| r.figure.round_trip.p99())
    };
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
}
