//! `twin serve`: the simulated controller, in real time on real links.

use anyhow::{Context, Result, bail};
use clap::{ArgMatches, Args};
use nodes::firmware::LightDetectorConfig;
use plant::PlantParams;
use protocols::time::SimDuration;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::PathBuf;
use twin_realtime::allow::AllowList;
use twin_realtime::io::LinkDefaults;
use twin_realtime::serve::{self, ServeOptions, ServeProtocol, console};
use twin_realtime::session::SessionOptions;
use twin_view::{Session, ViewLayout};

mod class;

/// Run the EV module in real time and serve its controller on real links.
///
/// LINK is `tcp://HOST:PORT` (port 0: any free port, printed) or a serial
/// device or pseudo-terminal path, with options after `?`:
/// `/tmp/ttyV1?baud=9600&parity=E&stop=2&turnaround_ms=1&pace=1`.
/// Give any number of links; all serve the same module. After every link is
/// open it prints one line per link (protocol, address, slave id) and `ready`.
/// While it runs: a frame monitor, a status line each second, and commands on
/// stdin (`help`). Started in the background of a terminal (`twin serve … &`)
/// it reads no commands, so the terminal never stops it ("Stopped (tty
/// input)"), until `fg` brings it to the foreground. It stops on SIGINT/SIGTERM, `stop`, or after --duration,
/// and finishes its MCAP recording; SIGHUP starts a new recording file.
///
/// As a service: --config FILE holds the options (a `[[module]]` table per
/// module serves a class from one process), --check checks it, and under
/// systemd (Type=notify) it reports when it is ready.
#[derive(Debug, Args)]
#[command(
    mut_arg("out", super::record_args::named("serve")),
    after_help = "Examples:\n  twin serve --meb tcp://127.0.0.1:5700\n  twin serve --meb /tmp/ttyV1 --baud 115200\n  twin serve --modbus tcp://127.0.0.1:5020 --meb tcp://127.0.0.1:5700\n  twin serve --modbus-rtu /tmp/ttyV1?parity=E\n  twin serve --modbus8 /tmp/ttyV1    (Controller_network: motor 01, light sensor 02)"
)]
pub struct ServeArgs {
    /// MEB slave on LINK (serial, pty or TCP).
    #[arg(long, value_name = "LINK")]
    meb: Vec<String>,
    /// Modbus TCP server on LINK (tcp://HOST:PORT); unit ids ID, 0 and 255.
    #[arg(long, value_name = "LINK")]
    modbus: Vec<String>,
    /// Modbus RTU slave on LINK (serial or pty).
    #[arg(long, value_name = "LINK")]
    modbus_rtu: Vec<String>,
    /// Modbus ASCII slave on LINK (serial or pty).
    #[arg(long, value_name = "LINK")]
    modbus_ascii: Vec<String>,
    /// The Controller_network project's nodes on LINK: motor node 01 and light
    /// sensor 02 on the geared bench, 8-byte Modbus.
    #[arg(long, value_name = "LINK")]
    modbus8: Vec<String>,
    /// Default baud rate of serial links (and of --pace on TCP).
    #[arg(long, default_value_t = 115_200, value_parser = super::numbers::whole::<u32>)]
    baud: u32,
    /// Reply turnaround in ms [default: 1 on serial links, 0 on TCP].
    #[arg(long, value_name = "MS", value_parser = super::numbers::zero_or_more)]
    turnaround_ms: Option<f64>,
    /// Hold every reply for its wire time at the link's baud, so a master on
    /// a pty sees real bus timing.
    #[arg(long)]
    pace: bool,
    /// A controller board as a compiled Arduino sketch (ELF or Intel HEX for
    /// the ATmega328P at 16 MHz), run in simavr in real time and answering
    /// on its own UART (`twin-avr serve` only: it links simavr, GPL). FILE
    /// alone is the EV module's controller (its MEB links); `motor=FILE`
    /// and `light=FILE` are the Controller_network Nanos (the --modbus8 link).
    /// Give it once per board.
    #[arg(long, value_name = "[BOARD=]FILE")]
    firmware: Vec<String>,
    /// A sketch's wiring map, `[BOARD=]MAP`: a shipped one (ev-controller,
    /// motor-nano, light-nano) or a TOML file [default: the board's shipped map].
    #[arg(long, value_name = "[BOARD=]MAP", requires = "firmware")]
    wiring: Vec<String>,
    /// Slave id of the EV module's controller (MEB slave number, Modbus unit id).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8)
          .range(i64::from(*serve::SLAVE_IDS.start())..=i64::from(*serve::SLAVE_IDS.end())))]
    id: u8,
    /// I/O map of the MEB links (TOML, one table per block: `[EA]` with
    /// `V1 = 0`, `[SD]` with `EN = "0.0"`); blocks not named keep docs/protocols/meb.md's map.
    #[arg(long, value_name = "FILE")]
    map: Option<PathBuf>,
    /// Plant parameter file (TOML) whose fields override the vemodule preset.
    #[arg(long, value_name = "FILE")]
    params: Option<PathBuf>,
    /// Seed of the plant's noise.
    #[arg(long, default_value_t = 1, value_parser = super::numbers::whole::<u64>)]
    seed: u64,
    /// Stop after this many seconds [default: run until interrupted].
    #[arg(long, value_name = "SECONDS", value_parser = super::numbers::above_zero)]
    duration: Option<f64>,
    #[command(flatten)]
    pub(super) record: super::record_args::RecordArgs,
    #[command(flatten)]
    pub(super) service: super::service_args::ServiceArgs,
    /// Plant state messages recorded per second.
    #[arg(long, default_value_t = 200.0, value_name = "HZ", value_parser = super::numbers::above_zero)]
    record_hz: f64,
    /// No frame monitor (status lines stay).
    #[arg(long)]
    quiet: bool,
    /// Seconds between status lines (0: none, and real time lost is then
    /// said only in the session's last lines).
    #[arg(long, default_value_t = 1.0, value_name = "SECONDS", value_parser = super::numbers::zero_or_more)]
    status_every: f64,
    /// TCP clients per link (each has a thread of its own; 0: no limit). A
    /// newcomer beyond it takes, with its first whole request, the place of
    /// the client quiet longest if that one has sent nothing but noise for
    /// --make-room-after, or of the one holding a partial frame longest if
    /// for over 0.1 s; if there is no such client, it is refused (closed at
    /// once).
    #[arg(long, default_value_t = 8, value_name = "N", value_parser = super::numbers::whole::<usize>)]
    max_clients: usize,
    /// How long a client must have been quiet for a newcomer beyond
    /// --max-clients to take its place (0: never).
    #[arg(long, default_value_t = 30.0, value_name = "SECONDS", value_parser = super::numbers::number)]
    make_room_after: f64,
    /// Close a TCP connection that has sent nothing but noise for this long (0: never;
    /// quiet connections stay open, as the MEB protocol page says).
    #[arg(long, default_value_t = 0.0, value_name = "SECONDS", value_parser = super::numbers::number)]
    idle_timeout: f64,
    /// Close a TCP connection holding a partial frame this long (0: never).
    #[arg(long, default_value_t = 5.0, value_name = "SECONDS", value_parser = super::numbers::number)]
    partial_timeout: f64,
    /// Close a TCP connection that sends more than this many bytes in one
    /// second (0: no limit).
    #[arg(long, default_value_t = 1_000_000, value_name = "BYTES", value_parser = super::numbers::whole::<u64>)]
    rate_limit: u64,
    /// Remote clients may read but not write (MEB ER 01, Modbus exception 01).
    #[arg(long)]
    read_only: bool,
    /// The EV controller's light detector at start: `adaptive` (`LDR_ADAPT`
    /// set, as the default scenario of `twin run` has it) follows the wheel up
    /// to about 1800 rpm; `fixed`, the firmware's threshold at power-up, loses
    /// the flag above about 260 rpm. A master can switch it either way by
    /// writing VD0 (LDR_ADAPT).
    #[arg(long, value_enum, value_name = "DETECTOR", default_value_t = LightDetector::Adaptive)]
    light_detector: LightDetector,
    /// The adaptive light detector: the default now (--light-detector).
    #[arg(long, hide = true, conflicts_with = "light_detector")]
    adaptive_light: bool,
    /// Run the plant thread under the real-time FIFO scheduler at this
    /// priority, and the links' thread one below (1-99; needs root,
    /// CAP_SYS_NICE or an rtprio limit), so a busy machine cannot delay
    /// ticks and replies.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u8).range(1..=99))]
    rt_priority: Option<u8>,
    /// Wait for serial paths that do not exist yet (a pty another program
    /// will create) instead of failing.
    #[arg(long)]
    wait_for_ports: bool,
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

/// How the EV controller's light detector starts (`light_detector` in a
/// scenario's `ev-controller` node).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LightDetector {
    Fixed,
    Adaptive,
}

impl ServeArgs {
    fn light_adaptive(&self) -> bool {
        self.adaptive_light || self.light_detector == LightDetector::Adaptive
    }
}

/// The session `args` describe; `module` names a class's module, whose
/// recordings go in a folder of its own name.
pub(super) fn options(args: &ServeArgs, module: Option<&str>) -> Result<ServeOptions> {
    let mut links = Vec::new();
    for (protocol, list) in [
        (ServeProtocol::Meb, &args.meb),
        (ServeProtocol::ModbusTcp, &args.modbus),
        (ServeProtocol::ModbusRtu, &args.modbus_rtu),
        (ServeProtocol::ModbusAscii, &args.modbus_ascii),
        (ServeProtocol::Modbus8, &args.modbus8),
    ] {
        links.extend(list.iter().map(|l| (protocol, l.clone())));
    }
    let base = LinkDefaults::default();
    let defaults = match args.turnaround_ms {
        Some(ms) if !(0.0..=10_000.0).contains(&ms) => {
            bail!("--turnaround-ms {ms}: must be 0-10000")
        }
        Some(ms) => LinkDefaults {
            baud: args.baud,
            serial_turnaround: SimDuration::from_secs_f64(ms / 1000.0),
            tcp_turnaround: SimDuration::from_secs_f64(ms / 1000.0),
            pace: args.pace,
        },
        None => LinkDefaults {
            baud: args.baud,
            pace: args.pace,
            ..base
        },
    };
    let preset = PlantParams::preset("vemodule").unwrap_or_default();
    let params = match &args.params {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("cannot read {}", path.display()))?;
            PlantParams::from_toml(&text, path, &preset)?
        }
        None => preset,
    };
    if let Some(d) = args.duration
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--duration {d}: must be a positive number of seconds");
    }
    let params_for_view = params.clone();
    Ok(ServeOptions {
        session: SessionOptions {
            duration: args.duration,
            record: plan(args, module)?,
            monitor: !args.quiet,
            status_every: args.status_every,
            wait_for_ports: args.wait_for_ports,
            record_hz: args.record_hz,
            rt_priority: args.rt_priority,
            view: args.view.as_deref().map(|target| {
                let params = params_for_view.clone();
                let light_adaptive = args.light_adaptive();
                super::live_view::opener(target, "twin serve", Session::Serve, move |modules| {
                    let has = |name: &str| modules.iter().any(|m| m == name);
                    ViewLayout::of_serve(&params, has("ev1"), has("bench"), light_adaptive)
                })
            }),
            // The program's own path stays out of the recording, as in `twin run`.
            command_line: std::iter::once("twin".to_string())
                .chain(std::env::args().skip(1))
                .chain(module.map(|m| format!("(module {m})")))
                .collect::<Vec<_>>()
                .join(" "),
            allow: AllowList::new(args.service.allow.clone()),
            on_hangup: None,
        },
        links,
        defaults,
        id: args.id,
        meb_map: args.map.as_deref().map(serve::map::load).transpose()?,
        params,
        seed: args.seed,
        max_clients: (args.max_clients > 0).then_some(args.max_clients),
        partial_timeout: super::timeout("--partial-timeout", args.partial_timeout)?,
        rate_limit: (args.rate_limit > 0).then_some(args.rate_limit),
        idle_timeout: super::timeout("--idle-timeout", args.idle_timeout)?,
        room_after_idle: super::timeout("--make-room-after", args.make_room_after)?,
        read_only: args.read_only,
        light_adaptive: args.light_adaptive(),
        firmware: firmware_nodes(&args.firmware, &args.wiring)?,
    })
}

/// The boards `--firmware` can replace: (name on the command line, device
/// name in the session, its module, its shipped wiring map).
const BOARDS: [(&str, &str, &str, &str); 3] = [
    ("ev1", "ev1", "ev1", "ev-controller"),
    ("motor", "motor", "bench", "motor-nano"),
    ("light", "sensor", "bench", "light-nano"),
];

/// Splits `[BOARD=]VALUE` into the board (`ev1` when not named) and the value.
fn board_and(text: &str, option: &str) -> Result<(&'static str, String)> {
    let (board, value) = match text.split_once('=') {
        Some((b, v)) if !b.contains('/') && !b.contains('.') => (b, v),
        _ => ("ev1", text),
    };
    let Some(&(name, ..)) = BOARDS.iter().find(|(n, ..)| *n == board) else {
        bail!(
            "{option} {text}: no board `{board}`; name ev1 (the EV controller, also FILE alone), motor or light"
        );
    };
    Ok((name, value.to_string()))
}

/// The firmware nodes `--firmware` and `--wiring` describe.
fn firmware_nodes(
    firmware: &[String],
    wiring: &[String],
) -> Result<Vec<twin_sim::scenario::NodeSpec>> {
    if !firmware.is_empty() && !twin_sim::external::available() {
        bail!(
            "--firmware runs a compiled AVR sketch: use `twin-avr serve`, the build of \
             the twin that links simavr (GPL)"
        );
    }
    let mut maps = BTreeMap::new();
    for text in wiring {
        let (board, map) = board_and(text, "--wiring")?;
        if maps.insert(board, map).is_some() {
            bail!("--wiring {text}: board {board} has a map already");
        }
    }
    let mut nodes = Vec::new();
    for text in firmware {
        let (board, elf) = board_and(text, "--firmware")?;
        let &(_, name, module, shipped) = BOARDS
            .iter()
            .find(|(n, ..)| *n == board)
            .unwrap_or(&BOARDS[0]);
        if nodes
            .iter()
            .any(|n: &twin_sim::scenario::NodeSpec| n.name() == name)
        {
            bail!("--firmware {text}: board {board} has a sketch already");
        }
        nodes.push(twin_sim::scenario::NodeSpec::Firmware {
            name: name.into(),
            bus: "link".into(),
            module: module.into(),
            elf,
            wiring: maps.remove(board).unwrap_or_else(|| shipped.into()),
            mcu: "atmega328p".into(),
            clock_hz: 16_000_000,
            // The sketch starts with the session; its master, after `ready`.
            boot_ms: 0.0,
        });
    }
    if let Some(board) = maps.keys().next() {
        bail!("--wiring: board {board} has no --firmware");
    }
    Ok(nodes)
}

/// The recording plan of `args`; a class's module records in a folder of its name.
pub(super) fn plan(
    args: &ServeArgs,
    module: Option<&str>,
) -> Result<Option<twin_realtime::rotate::RecordPlan>> {
    let mut plan = args.record.plan("serve")?;
    if let (Some(plan), Some(name)) = (plan.as_mut(), module)
        && plan.out.is_none()
    {
        plan.dir = plan.dir.join(name);
    }
    Ok(plan)
}

pub fn execute(args: &ServeArgs, matches: &ArgMatches) -> Result<()> {
    let command = super::service::command_of::<ServeArgs>("serve");
    let file = super::service::load(args.service.config.as_deref(), &command, true)?;
    let merged;
    let args = match &file {
        Some(f) if !f.modules.is_empty() => {
            return class::execute(f, &command, matches, args.service.check);
        }
        Some(f) => {
            merged = super::service::reparse::<ServeArgs>(&command, f.words(None, matches))?;
            &merged
        }
        None => args,
    };
    let mut options = options(args, None)?;
    if args.service.check {
        serve::check_links(&options)?;
        let panel = args.web.described("panel");
        println!(
            "{}{}",
            described(&options),
            panel.map(|p| format!("; {p}")).unwrap_or_default()
        );
        return Ok(());
    }
    if let (Some(f), Some(path)) = (file, &args.service.config) {
        options.session.on_hangup = Some(
            super::service::Reread::<ServeArgs> {
                path: path.clone(),
                command,
                command_line: matches.clone(),
                module: None,
                started: f,
                allow: options.session.allow.clone(),
                allow_of: |a| a.service.allow.clone(),
                plan_of: Box::new(|a| plan(a, None)),
            }
            .hook(),
        );
    }
    serve_one(args, &options)
}

/// What `--check` says a configuration would serve.
pub(super) fn described(options: &ServeOptions) -> String {
    let links: Vec<String> = options
        .links
        .iter()
        .map(|(p, l)| format!("{} {l}", p.name()))
        .collect();
    let mut text = format!("serves {}", links.join(", "));
    if !options.session.allow.shown().is_empty() {
        text.push_str(&format!(" to {}", options.session.allow.shown()));
    }
    text.push_str(&format!(
        "; {}",
        super::record_args::recorded(options.session.record.as_ref())
    ));
    text
}

fn serve_one(args: &ServeArgs, options: &ServeOptions) -> Result<()> {
    let mut options = options.clone();
    let panel = args
        .web
        .bind(twin_panel::PanelRole::Serve, &mut options.session, "panel")?
        .map(|p| match &options.meb_map {
            Some(map) => p.with_map(map),
            None => p,
        });
    let panel_line = panel
        .as_ref()
        .map(|p| super::web_args::panel_line(p, args.web.token_file("panel").as_deref()));
    let earlier = options
        .session
        .record
        .as_ref()
        .and_then(|plan| plan.out.as_deref())
        .and_then(super::output::Earlier::at);
    let light = light_detector_line(&options);
    let outcome = serve::serve(
        &options,
        |links| {
            let mut out = std::io::stdout().lock();
            let _ = writeln!(
                out,
                "twin serve: {} link(s); {}",
                links.len(),
                if console::stdin_is_ours(&std::io::stdin()) {
                    "type `help` for commands"
                } else {
                    "in the background: `fg` for its commands"
                }
            );
            for l in links {
                let _ = writeln!(out, "  {} {} {}", l.protocol, l.address, l.ids);
            }
            for line in &light {
                let _ = writeln!(out, "{line}");
            }
            if let Some(line) = &panel_line {
                let _ = writeln!(out, "{line}");
            }
            if args.rt_priority.is_none() {
                let _ = writeln!(out, "{}", without_priority());
            }
            let _ = writeln!(out, "ready");
            let _ = out.flush();
            let served: Vec<String> = links
                .iter()
                .map(|l| format!("{} {}", l.protocol, l.address))
                .collect();
            twin_realtime::notify::ready(&format!("serving {}", served.join(", ")));
        },
        |engine| {
            if let Some(panel) = &panel
                && let Err(e) = panel.start(engine.clone())
            {
                // With its cause (a thiserror type alone prints without).
                let e = anyhow::Error::from(e);
                eprintln!("--web: {e:#}; going on without the panel");
            }
            console::spawn_stdin(engine);
        },
    )?;
    let l = outcome.lateness;
    println!(
        "twin serve: stopped ({}) after {:.3} s",
        outcome.stopped_by, outcome.elapsed_s
    );
    println!(
        "  tick lateness over {} ticks: p50 {:.0} µs, p99 {:.0} µs, p99.9 {:.0} µs, max {:.0} µs; {} overruns",
        l.ticks, l.p50_us, l.p99_us, l.p999_us, l.max_us, l.overruns
    );
    if let Some(line) = l.slip_line() {
        println!("  {line}");
    }
    if l.p99_us > 250.0 {
        match args.rt_priority {
            // How to grant it was said at the start.
            None => println!(
                "  (ticks ran late: the machine was busy, and the plant thread ran at normal priority)"
            ),
            Some(_) => {
                println!("  (ticks ran late even at real-time priority: the machine was busy)")
            }
        }
    }
    let mut outcome = outcome;
    if args.view.is_none() {
        // The panel's feed is not a rerun view.
        outcome.view_samples = None;
    }
    super::print_session_end(&outcome, earlier.as_ref());
    Ok(())
}

/// What `twin serve` says once when started without `--rt-priority`: the
/// plant's 1 ms tick is what samples the encoders, so a late tick loses
/// edges, not just time.
pub(super) fn without_priority() -> String {
    twin_realtime::clock::without_priority(
        "ticks run late and replies come late, and a stall longer than the twin catches up holds its clock back (real time lost)",
    )
}

/// What the EV controller's light detector can see, when an EV link is
/// served: the first thing a master reading RPM_L needs to know. A board
/// run as a sketch is named instead: its light detector is its own.
fn light_detector_line(options: &ServeOptions) -> Vec<String> {
    let mut lines: Vec<String> = options
        .firmware
        .iter()
        .filter_map(|spec| match spec {
            twin_sim::scenario::NodeSpec::Firmware {
                name, elf, wiring, ..
            } => Some(format!(
                "{name}: the sketch {elf} (wiring {wiring}) in simavr, in place of the twin's own node"
            )),
            _ => None,
        })
        .collect();
    let ev_sketch = options.firmware.iter().any(|spec| spec.name() == "ev1");
    if ev_sketch
        || options
            .links
            .iter()
            .all(|(p, _)| *p == ServeProtocol::Modbus8)
    {
        return lines;
    }
    let light = &options.params.light;
    let mut detector = LightDetectorConfig::for_sensor(light);
    detector.adaptive = options.light_adaptive;
    lines.push(format!(
        "ev1 light detector: {}; it sees the flag up to {:.0} rpm{}",
        detector.describe(light),
        detector.max_rpm(light),
        if options.light_adaptive {
            ""
        } else {
            " (--light-detector adaptive, or VD0 LDR_ADAPT from a master, for the adaptive one)"
        }
    ));
    lines
}
