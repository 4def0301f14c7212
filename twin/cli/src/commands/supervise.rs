//! `twin supervise`: the supervisor and TCP server, in real time on real links.

use anyhow::{Result, bail};
use clap::{ArgMatches, Args, ValueEnum};
use nodes::master::SpeedSource;
use nodes::master::image_server::ImageServerConfig;
use protocols::time::SimDuration;
use std::io::Write;
use std::path::PathBuf;
use twin_realtime::allow::AllowList;
use twin_realtime::session::SessionOptions;
use twin_realtime::supervise::{self, SuperviseOptions};
use twin_view::{Session, ViewLayout};

/// Supervise the EV module over MEB and serve remote MEB clients over TCP.
///
/// The master polls the controller on the --meb link (a serial port, a pty
/// such as one end of `twin vsp`, or tcp://HOST:PORT of an MEB slave) every
/// --poll-ms: it writes the start-up outputs (module enabled, brake
/// released), reads EA 00-05 and closes a PI speed loop on the hall rpm by
/// writing VEL (SA 00), or holds a manual VEL with --open-loop. Remote clients
/// (`twin client`, a student's program) connect to --listen and are answered
/// from the supervisor's image as docs/protocols/meb.md says: reads from the last poll,
/// writes forwarded on the bus and acknowledged when the slave acknowledged
/// them, the loop's set point and gains as VA 10-12 / VD 10 (read back as
/// FA 10-12 / FD 10). Prints its links then `ready`; shows every frame on
/// both sides and a status line per slave; records to MCAP; stops on
/// SIGINT/SIGTERM or after --duration.
#[derive(Debug, Args)]
#[command(
    mut_arg("out", super::record_args::named("supervise")),
    after_help = "Examples:\n  twin vsp /tmp/ttyV0 /tmp/ttyV1 &\n  twin serve --meb /tmp/ttyV1 &\n  twin supervise --meb /tmp/ttyV0 --listen tcp://127.0.0.1:5701 --set-point 1500\n  twin supervise --meb tcp://127.0.0.1:5700 --listen tcp://127.0.0.1:0 --open-loop 2048\n  twin client tcp://127.0.0.1:5701 read EA 3 1"
)]
pub struct SuperviseArgs {
    /// The bus, spoken in MEB: serial device or pty (options after `?`, e.g.
    /// /tmp/ttyV0?baud=9600&parity=E), or tcp://HOST:PORT of an MEB slave.
    #[arg(long, value_name = "LINK", conflicts_with = "modbus_rtu")]
    meb: Option<String>,
    /// The bus, spoken in Modbus RTU (docs/protocols/modbus-map.md): serial device or
    /// pty. Remote clients still speak MEB to the server; writes other than
    /// the loop's variables get ER 01 (they have no Modbus form here).
    #[arg(long, value_name = "LINK")]
    modbus_rtu: Option<String>,
    /// Serve remote MEB clients here (port 0: any free port, printed); repeat
    /// for several. Only this machine can connect unless HOST says otherwise
    /// (tcp://0.0.0.0:5701 for every interface).
    #[arg(
        long,
        value_name = "tcp://HOST:PORT",
        default_value = "tcp://127.0.0.1:5701"
    )]
    listen: Vec<String>,
    /// No TCP server: the supervisor alone.
    #[arg(long, conflicts_with = "listen")]
    no_server: bool,
    /// Baud rate of the serial bus (unless the link gives one).
    #[arg(long, default_value_t = 115_200, value_parser = super::numbers::whole::<u32>)]
    baud: u32,
    /// Slave id to poll; repeat for several (each has its own loop).
    #[arg(long = "id", default_value = "1", value_name = "ID",
          value_parser = clap::value_parser!(u8).range(1..=99))]
    ids: Vec<u8>,
    /// I/O map of the slaves (TOML, one table per block: `[EA]` with `V1 = 0`,
    /// `[SD]` with `EN = "0.0"`, the file `twin serve --map` reads); blocks not
    /// named keep docs/protocols/meb.md's map. Remote clients of --listen
    /// still read and write in that default map.
    #[arg(long, value_name = "FILE", conflicts_with = "modbus_rtu")]
    map: Option<PathBuf>,
    /// Set point of the speed loop from the start, rpm (clients change it through VA 10).
    #[arg(long, default_value_t = 0.0, value_name = "RPM", value_parser = super::numbers::number)]
    set_point: f64,
    /// Hold VEL at this many DAC counts (0-4095) instead of closing the loop
    /// (clients close it through VD 10).
    #[arg(long, value_name = "VEL", value_parser = super::numbers::whole::<u16>)]
    open_loop: Option<u16>,
    /// Proportional gain, VEL counts per rpm.
    #[arg(long, default_value_t = 0.45, value_parser = super::numbers::number)]
    kp: f64,
    /// Integral gain, VEL counts per rpm per second.
    #[arg(long, default_value_t = 2.5, value_parser = super::numbers::number)]
    ki: f64,
    /// Which speed reading closes the loop.
    #[arg(long, value_enum, default_value_t = Source::Hall)]
    speed_source: Source,
    /// From one poll cycle to the next, ms.
    #[arg(long, default_value_t = 10.0, value_name = "MS", value_parser = super::numbers::number)]
    poll_ms: f64,
    /// Reply timeout, ms (docs/protocols/meb.md: 100).
    #[arg(long, default_value_t = 100.0, value_name = "MS", value_parser = super::numbers::number)]
    timeout_ms: f64,
    /// Attempts after a missing or bad reply.
    #[arg(long, default_value_t = 2, value_parser = super::numbers::whole::<u8>)]
    retries: u8,
    /// Also read the status words (ED 00, FA 00-01, FD 00) every N poll
    /// cycles, so clients can read them from the image (0: never).
    #[arg(long, default_value_t = 10, value_name = "N", value_parser = super::numbers::whole::<u32>)]
    status_poll: u32,
    /// Remote clients at once. A newcomer beyond them takes, with its first
    /// whole request, the place of the client quiet longest if that one has
    /// sent nothing but noise for --make-room-after, or of the one holding a
    /// partial frame longest if for over 0.1 s; if there is no such client, it
    /// is refused (closed at once).
    #[arg(long, default_value_t = 8, value_name = "N", value_parser = super::numbers::whole::<usize>)]
    max_clients: usize,
    /// How long a client must have been quiet for a newcomer beyond
    /// --max-clients to take its place (0: never).
    #[arg(long, default_value_t = 30.0, value_name = "SECONDS", value_parser = super::numbers::number)]
    make_room_after: f64,
    /// Close a remote client that has sent nothing but noise for this long (0: never;
    /// quiet connections stay open, as the MEB protocol page says).
    #[arg(long, default_value_t = 0.0, value_name = "SECONDS", value_parser = super::numbers::number)]
    idle_timeout: f64,
    /// Remote clients may read but not write (ER 01).
    #[arg(long)]
    read_only: bool,
    /// Close a client holding a partial frame this long, seconds.
    #[arg(long, default_value_t = 5.0, value_name = "SECONDS", value_parser = super::numbers::number)]
    partial_timeout: f64,
    /// Close a client sending more than this many frames per second (bursts
    /// of up to half as many again are allowed).
    #[arg(long, default_value_t = 200.0, value_name = "FRAMES", value_parser = super::numbers::number)]
    rate_limit: f64,
    /// Stop after this many seconds [default: run until interrupted].
    #[arg(long, value_name = "SECONDS", value_parser = super::numbers::above_zero)]
    duration: Option<f64>,
    #[command(flatten)]
    record: super::record_args::RecordArgs,
    #[command(flatten)]
    service: super::service_args::ServiceArgs,
    /// No frame monitor (status lines stay).
    #[arg(long)]
    quiet: bool,
    /// Seconds between status lines (0: none, and real time lost is then
    /// said only in the session's last lines).
    #[arg(long, default_value_t = 1.0, value_name = "SECONDS", value_parser = super::numbers::zero_or_more)]
    status_every: f64,
    /// Wait for a serial path that does not exist yet instead of failing.
    #[arg(long)]
    wait_for_ports: bool,
    /// Run the master's thread under the real-time FIFO scheduler at this
    /// priority, and the links' thread one below (1-99; needs root,
    /// CAP_SYS_NICE or an rtprio limit), so a busy machine cannot delay
    /// polls and replies.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u8).range(1..=99))]
    rt_priority: Option<u8>,
    /// Stream the session live to rerun, beside the recording: `--view`
    /// opens a viewer (or uses the one already running), `--view
    /// rerun+http://HOST:PORT/proxy` streams to a running viewer, `--view
    /// FILE.rrd` writes the stream to a file. Without a viewer the session
    /// goes on without the view.
    #[arg(long, value_name = "TARGET", num_args = 0..=1, default_missing_value = "spawn")]
    view: Option<String>,
    #[command(flatten)]
    web: super::web_args::WebArgs,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Source {
    /// RPM_M (EA 03): the motor's hall sensors.
    Hall,
    /// RPM_L (EA 04): the photoresistor.
    Light,
}

fn millis(name: &str, ms: f64) -> Result<SimDuration> {
    if !(ms.is_finite() && ms > 0.0 && ms <= 60_000.0) {
        bail!("--{name} {ms}: must be above 0 and at most 60000 ms");
    }
    Ok(SimDuration::from_secs_f64(ms / 1000.0))
}

/// The `--map` file, checked for what the loop needs besides its form.
fn map(args: &SuperviseArgs) -> Result<Option<nodes::firmware::MebMap>> {
    let Some(path) = &args.map else {
        return Ok(None);
    };
    let map = twin_realtime::serve::map::load(path)?;
    let source = speed_source(args);
    nodes::master::MebLayout::from_map(&map)
        .check(source.input_index(), source.name())
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(Some(map))
}

fn speed_source(args: &SuperviseArgs) -> SpeedSource {
    match args.speed_source {
        Source::Hall => SpeedSource::Hall,
        Source::Light => SpeedSource::Light,
    }
}

fn options(args: &SuperviseArgs) -> Result<SuperviseOptions> {
    // Either link will do, so clap is not told one is required: it would
    // name only the first.
    if args.meb.is_none() && args.modbus_rtu.is_none() {
        bail!(
            "no bus to supervise: give --meb LINK (a controller that speaks MEB) or \
             --modbus-rtu LINK (one that speaks Modbus RTU)"
        );
    }
    if !(args.set_point.is_finite() && (0.0..=20_000.0).contains(&args.set_point)) {
        bail!("--set-point {}: must be 0-20000 rpm", args.set_point);
    }
    if args.open_loop.is_some_and(|v| v > 4095) {
        bail!("--open-loop: VEL is a 12-bit DAC value, 0-4095");
    }
    if !(args.kp.is_finite() && args.ki.is_finite() && args.kp >= 0.0 && args.ki >= 0.0) {
        bail!("--kp and --ki must be non-negative numbers");
    }
    if let Some(d) = args.duration
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--duration {d}: must be a positive number of seconds");
    }
    if !(args.partial_timeout.is_finite() && args.partial_timeout > 0.0) {
        bail!("--partial-timeout must be a positive number of seconds");
    }
    if !(args.rate_limit.is_finite() && args.rate_limit >= 1.0) {
        bail!("--rate-limit must be at least 1 frame per second");
    }
    if args.max_clients == 0 {
        bail!("--max-clients must be at least 1");
    }
    let mut ids = args.ids.clone();
    ids.dedup();
    let server = ImageServerConfig {
        max_clients: args.max_clients,
        partial_timeout: SimDuration::from_secs_f64(args.partial_timeout),
        rate_per_second: args.rate_limit,
        rate_burst: (args.rate_limit * 1.5).max(10.0),
        read_only: args.read_only,
        // Longer than every attempt of a write on the line takes.
        max_forward_wait: SimDuration::from_secs_f64(
            (f64::from(args.retries) + 1.0) * args.timeout_ms / 1000.0 + 0.5,
        ),
        ..ImageServerConfig::default()
    };
    let view = args.view.as_deref().map(|target| {
        let slaves = ids.clone();
        super::live_view::opener(target, "twin supervise", Session::Supervise, move |_| {
            ViewLayout::of_supervise(&slaves)
        })
    });
    Ok(SuperviseOptions {
        session: SessionOptions {
            duration: args.duration,
            record: args.record.plan("supervise")?,
            monitor: !args.quiet,
            status_every: args.status_every.max(0.0),
            wait_for_ports: args.wait_for_ports,
            // No plant here: the module is on the other end of the bus.
            record_hz: 1.0,
            rt_priority: args.rt_priority,
            view,
            command_line: std::env::args().collect::<Vec<_>>().join(" "),
            allow: AllowList::new(args.service.allow.clone()),
            on_hangup: None,
        },
        bus: args
            .meb
            .clone()
            .or_else(|| args.modbus_rtu.clone())
            .unwrap_or_default(),
        protocol: if args.meb.is_some() {
            nodes::master::Protocol::Meb
        } else {
            nodes::master::Protocol::ModbusRtu
        },
        listen: if args.no_server {
            Vec::new()
        } else {
            args.listen.clone()
        },
        baud: args.baud,
        slaves: ids,
        set_point: args.set_point,
        open_loop: args.open_loop,
        kp: args.kp,
        ki: args.ki,
        speed_source: speed_source(args),
        poll_period: millis("poll-ms", args.poll_ms)?,
        reply_timeout: millis("timeout-ms", args.timeout_ms)?,
        retries: args.retries,
        status_poll: args.status_poll,
        meb_map: map(args)?,
        server,
        // Far above any frame rate allowed: only a flood of garbage hits it.
        rate_limit_bytes: Some((args.rate_limit * 1.5 * 410.0) as u64 + 4096),
        idle_timeout: super::timeout("--idle-timeout", args.idle_timeout)?,
        room_after_idle: super::timeout("--make-room-after", args.make_room_after)?,
    })
}

pub fn execute(args: &SuperviseArgs, matches: &ArgMatches) -> Result<()> {
    let command = super::service::command_of::<SuperviseArgs>("supervise");
    let file = super::service::load(args.service.config.as_deref(), &command, false)?;
    let merged;
    let args = match &file {
        Some(f) => {
            merged = super::service::reparse::<SuperviseArgs>(&command, f.words(None, matches))?;
            &merged
        }
        None => args,
    };
    let mut options = options(args)?;
    if args.service.check {
        supervise::check_links(&options)?;
        let listen: Vec<&str> = options.listen.iter().map(String::as_str).collect();
        println!(
            "supervises {} over {}{}{}; {}",
            options.bus,
            match options.protocol {
                nodes::master::Protocol::Meb => "MEB",
                nodes::master::Protocol::ModbusRtu => "Modbus RTU",
            },
            if listen.is_empty() {
                String::new()
            } else {
                format!("; serves MEB clients on {}", listen.join(", "))
            },
            if options.session.allow.shown().is_empty() {
                String::new()
            } else {
                format!(" from {}", options.session.allow.shown())
            },
            super::record_args::recorded(options.session.record.as_ref())
        );
        return Ok(());
    }
    if let (Some(f), Some(path)) = (file, &args.service.config) {
        options.session.on_hangup = Some(
            super::service::Reread::<SuperviseArgs> {
                path: path.clone(),
                command,
                command_line: matches.clone(),
                module: None,
                started: f,
                allow: options.session.allow.clone(),
                allow_of: |a| a.service.allow.clone(),
                plan_of: Box::new(|a| a.record.plan("supervise")),
            }
            .hook(),
        );
    }
    let panel = args.web.bind(
        twin_panel::PanelRole::Supervise,
        &mut options.session,
        "panel",
    )?;
    let panel_line = panel
        .as_ref()
        .map(|p| super::web_args::panel_line(p, args.web.token_file("panel").as_deref()));
    let earlier = options
        .session
        .record
        .as_ref()
        .and_then(|plan| plan.out.as_deref())
        .and_then(super::output::Earlier::at);
    let outcome = supervise::supervise_with(
        &options,
        |links| {
            let mut out = std::io::stdout().lock();
            let how = match options.open_loop {
                Some(vel) => format!("open loop, VEL {vel}"),
                None => format!(
                    "speed loop closed at {} rpm (kp {}, ki {})",
                    options.set_point, options.kp, options.ki
                ),
            };
            let _ = writeln!(
                out,
                "twin supervise: {how}, polling every {:.1} ms",
                options.poll_period.as_secs_f64() * 1e3
            );
            for l in links {
                let _ = writeln!(out, "  {} {} {}", l.protocol, l.address, l.role);
            }
            if let Some(line) = &panel_line {
                let _ = writeln!(out, "{line}");
            }
            if args.rt_priority.is_none() {
                let _ = writeln!(
                    out,
                    "{}",
                    twin_realtime::clock::without_priority(
                        "polls go out late and remote clients are answered late"
                    )
                );
            }
            let _ = writeln!(out, "ready");
            let _ = out.flush();
            twin_realtime::notify::ready(&format!("supervising {}", options.bus));
        },
        |engine| {
            if let Some(panel) = &panel
                && let Err(e) = panel.start(engine)
            {
                // With its cause (a thiserror type alone prints without).
                let e = anyhow::Error::from(e);
                eprintln!("--web: {e:#}; going on without the panel");
            }
        },
    )?;
    let session = &outcome.session;
    let l = session.lateness;
    println!(
        "twin supervise: stopped ({}) after {:.3} s",
        outcome.session.stopped_by, outcome.session.elapsed_s
    );
    for line in &outcome.status {
        println!("  {line}");
    }
    println!(
        "  tick lateness over {} ticks: p50 {:.0} µs, p99 {:.0} µs, max {:.0} µs",
        l.ticks, l.p50_us, l.p99_us, l.max_us
    );
    if let Some(line) = l.slip_line() {
        println!("  {line}");
    }
    let mut session_end = outcome.session;
    if args.view.is_none() {
        // The panel's feed is not a rerun view.
        session_end.view_samples = None;
    }
    super::print_session_end(&session_end, earlier.as_ref());
    Ok(())
}
