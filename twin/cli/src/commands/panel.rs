//! `twin panel`: the remote client panel in a browser (the M3CVME tool's TCP client).

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::time::Duration;
use twin_panel::remote::{Remote, RemoteOptions};
use twin_panel::{AccessOptions, Panel, PanelOptions, PanelRole};
use twin_realtime::io::spec::{LinkSpec, LinkSpecError};

/// A panel in a browser for an MEB slave over TCP, as the M3CVME tool's TCP client.
///
/// The panel is itself an MEB-TCP client of URL: a supervisor (`twin supervise
/// --listen`), `twin serve --meb tcp://…`, or a student's own server. It polls
/// the slave's inputs (EA), hall code (ED), SOC and ERRS (FA) and status (FD)
/// every --poll-ms and shows them on gauges; VEL and the switches (EN, BRK,
/// PRO, DES, FR, CHG) are set from the page; the frame monitor shows every
/// frame of its connection. A connection that drops is shown on the page and
/// made again every second. --map places the signals where the slave has them
/// (the file `twin serve --map` reads).
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  twin supervise --meb /tmp/ttyV0 --listen tcp://127.0.0.1:5701 &\n  twin panel tcp://127.0.0.1:5701 --web 127.0.0.1:8080\n  twin panel tcp://192.168.1.20:5700 --id 3 --map lab-map.toml --web 0.0.0.0:8080"
)]
pub struct PanelArgs {
    /// The slave or supervisor: tcp://HOST:PORT.
    url: String,
    /// Slave id to address.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=99))]
    id: u8,
    /// I/O map of the slave (TOML, one table per block: `[EA]` with `V1 = 0`,
    /// `[SD]` with `EN = "0.0"`); blocks not named keep docs/protocols/meb.md's map.
    #[arg(long, value_name = "FILE")]
    map: Option<PathBuf>,
    /// Serve the panel to browsers at ADDR (0.0.0.0:8080 for phones on the
    /// lab's network; any address but a loopback one needs a token, shown in
    /// the URL at start on a terminal and otherwise kept in a file only:
    /// --web-token-file, or panel.token here).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:8080")]
    web: std::net::SocketAddr,
    /// Keep the panel's token in FILE (made if missing), so its URL stays
    /// the same across restarts; a loopback panel then needs it too.
    #[arg(long, value_name = "FILE")]
    web_token_file: Option<PathBuf>,
    /// A panel that shows and changes nothing (a projector, a class watching).
    #[arg(long)]
    web_read_only: bool,
    /// From one poll of the slave to the next, ms.
    #[arg(long, default_value_t = 50, value_name = "MS", value_parser = super::numbers::whole::<u64>)]
    poll_ms: u64,
    /// How long to wait for the connection and for each reply, ms.
    #[arg(long, default_value_t = 500, value_name = "MS", value_parser = super::numbers::whole::<u64>)]
    timeout_ms: u64,
    /// Stop after this many seconds [default: run until interrupted].
    #[arg(long, value_name = "SECONDS", value_parser = super::numbers::above_zero)]
    duration: Option<f64>,
}

pub fn execute(args: &PanelArgs) -> Result<()> {
    let spec = LinkSpec::parse_without_options(&args.url, "the panel's address takes no options");
    match spec {
        Ok(spec) if spec.is_tcp() => {}
        // A TCP address with a fault of its own: the links' words for it.
        Err(e @ (LinkSpecError::BadTcp { .. } | LinkSpecError::NotTaken { .. })) => {
            return Err(e.into());
        }
        _ => bail!(
            "`{}` is not tcp://HOST:PORT: the panel talks MEB over TCP to a supervisor \
             (twin supervise --listen) or a slave (twin serve --meb tcp://…)",
            args.url
        ),
    }
    if !(1..=60_000).contains(&args.poll_ms) || !(1..=60_000).contains(&args.timeout_ms) {
        bail!("--poll-ms and --timeout-ms must be 1-60000 ms");
    }
    let map = match &args.map {
        Some(path) => twin_realtime::serve::map::load(path)?,
        None => Default::default(),
    };
    let map_said = match &args.map {
        Some(path) => format!("I/O map {}", path.display()),
        None => "default I/O map".into(),
    };
    // The panel's share of connections comes from the limit it starts with.
    if let Some(Err(e)) = twin_realtime::fd_limit::raise_once() {
        eprintln!("warning: {e}");
    }
    let token_file = super::web_args::token_file(args.web, args.web_token_file.as_ref(), "panel");
    let panel = Panel::bind(PanelOptions {
        role: PanelRole::Client,
        addr: args.web,
        access: AccessOptions {
            token_file: token_file.clone(),
            read_only: args.web_read_only,
        },
        rate_hz: 20.0,
    })?;
    let remote = Remote::start(
        RemoteOptions {
            url: args.url.clone(),
            id: args.id,
            map,
            poll: Duration::from_millis(args.poll_ms),
            timeout: Duration::from_millis(args.timeout_ms),
        },
        panel.hub(),
    )?;
    panel.start_remote(remote.clone())?;
    println!(
        "twin panel: MEB client of {}, slave {:02}, {map_said}",
        args.url, args.id
    );
    println!(
        "{}",
        super::web_args::panel_line(&panel, token_file.as_deref())
    );
    println!("ready");
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let stopped = runtime.block_on(watch(&remote, &args.url, args.duration))?;
    println!("twin panel: stopped ({stopped})");
    Ok(())
}

/// Says on the console too when the connection drops and comes back, until
/// SIGINT, SIGTERM or the end of `duration`; returns which.
async fn watch(remote: &Remote, url: &str, duration: Option<f64>) -> Result<&'static str> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = signal(SignalKind::terminate())?;
    let mut int = signal(SignalKind::interrupt())?;
    let end = tokio::time::sleep(Duration::from_secs_f64(duration.unwrap_or(1e9)));
    tokio::pin!(end);
    let mut tick = tokio::time::interval(Duration::from_millis(200));
    let mut connected = true;
    loop {
        tokio::select! {
            _ = term.recv() => return Ok("SIGTERM"),
            _ = int.recv() => return Ok("SIGINT"),
            _ = &mut end => return Ok("--duration"),
            _ = tick.tick() => {}
        }
        let state = remote.state();
        if state.connected != connected {
            connected = state.connected;
            if connected {
                println!("connected again to {url}");
            } else {
                println!(
                    "disconnected: {}; retrying every second",
                    state.error.as_deref().unwrap_or("the connection closed")
                );
            }
        }
    }
}
