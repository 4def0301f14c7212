//! `--web` and its options, shared by `twin serve` and `twin supervise`:
//! the lab's panel in a browser, served by the session itself.

use anyhow::Result;
use clap::Args;
use std::io::IsTerminal;
use std::net::SocketAddr;
use std::path::PathBuf;
use twin_panel::{AccessOptions, Panel, PanelOptions, PanelRole, Running, view::Tee};
use twin_realtime::session::SessionOptions;
use twin_realtime::sink::ViewOpener;

#[derive(Debug, Args)]
pub struct WebArgs {
    /// Serve the panel (gauges, controls, trend, frame monitor) to browsers
    /// at ADDR, e.g. 127.0.0.1:8080 or 0.0.0.0:8080 for phones on the lab's
    /// network; any address but a loopback one needs a token, shown in the
    /// URL at start on a terminal and otherwise kept in a file only
    /// (--web-token-file, or panel.token here; a class's module: NAME.token).
    #[arg(long, value_name = "ADDR")]
    pub web: Option<SocketAddr>,
    /// Keep the panel's token in FILE (made if missing), so its URL stays
    /// the same across restarts; a loopback panel then needs it too.
    #[arg(long, value_name = "FILE", requires = "web")]
    pub web_token_file: Option<PathBuf>,
    /// A panel that shows and changes nothing (a projector, a class watching).
    #[arg(long, requires = "web")]
    pub web_read_only: bool,
}

impl WebArgs {
    /// The file the panel's token is kept in (see [`token_file`]); `name`
    /// names the panel (`panel`, a class's module).
    pub fn token_file(&self, name: &str) -> Option<PathBuf> {
        token_file(self.web?, self.web_token_file.as_ref(), name)
    }

    /// What `--check` says of the panel, if one is asked for.
    pub fn described(&self, name: &str) -> Option<String> {
        let addr = self.web?;
        let token = match self.token_file(name) {
            Some(file) => format!("its token in {}", file.display()),
            None => "no token (this machine only)".into(),
        };
        let read_only = if self.web_read_only {
            ", read-only"
        } else {
            ""
        };
        Some(format!("a panel on {addr} ({token}{read_only})"))
    }

    /// Binds the panel, if asked for, and makes the session feed it; `name`
    /// names its token file when it needs one of its own.
    pub fn bind(
        &self,
        role: PanelRole,
        session: &mut SessionOptions,
        name: &str,
    ) -> Result<Option<Panel>> {
        let Some(addr) = self.web else {
            return Ok(None);
        };
        let panel = Panel::bind(PanelOptions {
            role,
            addr,
            access: AccessOptions {
                token_file: self.token_file(name),
                read_only: self.web_read_only,
            },
            rate_hz: 20.0,
        })?;
        feed(&panel, session);
        Ok(Some(panel))
    }
}

/// Makes the session feed `panel` its frames and events, beside a rerun
/// view if it has one.
pub fn feed(panel: &Panel, session: &mut SessionOptions) {
    let rerun = session.view.take();
    let feeds = panel.clone();
    session.view = Some(ViewOpener::new(move |modules| {
        let view = feeds.view();
        Some(match rerun.as_ref().and_then(|r| r.open(modules)) {
            Some(rerun) => Box::new(Tee(rerun, view)),
            None => view,
        })
    }));
}

/// Where a panel's token is kept: `given` (--web-token-file), or, for a
/// panel that needs a token (any address but a loopback one) while standard
/// output is no terminal, `NAME.token` here: the token is printed only to a
/// terminal, never to a service's journal, which keeps what it is given.
pub fn token_file(addr: SocketAddr, given: Option<&PathBuf>, name: &str) -> Option<PathBuf> {
    given.cloned().or_else(|| {
        (!addr.ip().is_loopback() && !std::io::stdout().is_terminal())
            .then(|| PathBuf::from(format!("{name}.token")))
    })
}

/// The line printed before `ready`: where to open the panel. Its token is
/// in the URL only on a terminal; otherwise the line says which file holds it.
pub fn panel_line(panel: &Panel, token_file: Option<&std::path::Path>) -> String {
    let running = panel.running();
    let url = url_shown(&running, token_file);
    format!(
        "panel: {}{}",
        url,
        if running.read_only {
            " (read-only)"
        } else {
            ""
        }
    )
}

/// The URL to open as printed: with its token only on a terminal, and
/// otherwise with the file that holds the token.
pub fn url_shown(running: &Running, token_file: Option<&std::path::Path>) -> String {
    match (running.url.split_once("?token="), token_file) {
        (Some((bare, _)), Some(file)) if !std::io::stdout().is_terminal() => format!(
            "{bare} (add ?token= and the token in {}; it is shown only on a terminal)",
            file.display()
        ),
        _ => running.url.clone(),
    }
}
