//! `--web` and its options, shared by `twin serve` and `twin supervise`:
//! the lab's panel in a browser, served by the session itself.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;
use twin_panel::{AccessOptions, Panel, PanelOptions, PanelRole, view::Tee};
use twin_realtime::session::SessionOptions;
use twin_realtime::sink::ViewOpener;

#[derive(Debug, Args)]
pub struct WebArgs {
    /// Serve the panel (gauges, controls, trend, frame monitor) to browsers
    /// at ADDR, e.g. 127.0.0.1:8080 or 0.0.0.0:8080 for phones on the lab's
    /// network; any address but a loopback one needs the token printed in
    /// the URL at start.
    #[arg(long, value_name = "ADDR")]
    pub web: Option<std::net::SocketAddr>,
    /// Keep the panel's token in FILE (made if missing), so its URL stays
    /// the same across restarts; a loopback panel then needs it too.
    #[arg(long, value_name = "FILE", requires = "web")]
    pub web_token_file: Option<PathBuf>,
    /// A panel that shows and changes nothing (a projector, a class watching).
    #[arg(long, requires = "web")]
    pub web_read_only: bool,
}

impl WebArgs {
    /// Binds the panel, if asked for, and makes the session feed it.
    pub fn bind(&self, role: PanelRole, session: &mut SessionOptions) -> Result<Option<Panel>> {
        let Some(addr) = self.web else {
            return Ok(None);
        };
        let panel = Panel::bind(PanelOptions {
            role,
            addr,
            access: AccessOptions {
                token_file: self.web_token_file.clone(),
                read_only: self.web_read_only,
            },
            rate_hz: 20.0,
        })?;
        let rerun = session.view.take();
        let feeds = panel.clone();
        session.view = Some(ViewOpener::new(move |modules| {
            let view = feeds.view();
            Some(match rerun.as_ref().and_then(|r| r.open(modules)) {
                Some(rerun) => Box::new(Tee(rerun, view)),
                None => view,
            })
        }));
        Ok(Some(panel))
    }
}

/// The line printed before `ready`: where to open the panel.
pub fn panel_line(panel: &Panel) -> String {
    let running = panel.running();
    format!(
        "panel: {}{}",
        running.url,
        if running.read_only {
            " (read-only)"
        } else {
            ""
        }
    )
}
