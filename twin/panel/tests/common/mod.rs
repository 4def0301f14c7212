//! A real `twin serve` session (the real-time engine, a real MEB TCP link)
//! with its panel, for the panel's tests; a small HTTP client; chromedriver.

#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::TcpStream;
use std::sync::mpsc::{Sender, channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use plant::PlantParams;
use twin_panel::{AccessOptions, Panel, PanelOptions, PanelRole, Running};
use twin_realtime::Inbound;
use twin_realtime::io::LinkDefaults;
use twin_realtime::serve::{self, ServeOptions, ServeProtocol};
use twin_realtime::session::SessionOptions;
use twin_realtime::sink::ViewOpener;

pub struct Session {
    pub engine: Sender<Inbound>,
    /// `tcp://127.0.0.1:PORT` of the MEB link.
    pub meb: String,
    pub panel: Running,
    thread: Option<JoinHandle<()>>,
}

impl Drop for Session {
    fn drop(&mut self) {
        let _ = self.engine.send(Inbound::Stop("test over".into()));
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

pub fn session_options(view: Option<ViewOpener>, seconds: f64) -> SessionOptions {
    SessionOptions {
        duration: Some(seconds),
        record: None,
        monitor: false,
        status_every: 0.0,
        wait_for_ports: false,
        record_hz: 50.0,
        rt_priority: None,
        view,
        command_line: "twin serve (panel test)".into(),
        allow: Default::default(),
        on_hangup: None,
    }
}

/// `twin serve --meb tcp://127.0.0.1:0 --web WEB` for at most `seconds`.
pub fn serve(web: &str, access: AccessOptions, seconds: f64) -> Session {
    let panel = Panel::bind(PanelOptions {
        role: PanelRole::Serve,
        addr: web.parse().unwrap(),
        access,
        rate_hz: 20.0,
    })
    .expect("the panel binds");
    let running = panel.running();
    let feeds = panel.clone();
    let options = ServeOptions {
        session: session_options(Some(ViewOpener::new(move |_| Some(feeds.view()))), seconds),
        links: vec![(ServeProtocol::Meb, "tcp://127.0.0.1:0".into())],
        defaults: LinkDefaults::default(),
        id: 1,
        meb_map: None,
        params: PlantParams::preset("vemodule").unwrap(),
        seed: 1,
        max_clients: Some(8),
        partial_timeout: None,
        rate_limit: None,
        idle_timeout: None,
        room_after_idle: None,
        read_only: false,
        light_adaptive: true,
        firmware: None,
    };
    let (ready_tx, ready_rx) = channel();
    let (engine_tx, engine_rx) = channel();
    let thread = std::thread::spawn(move || {
        let ready_tx2 = ready_tx.clone();
        let result = serve::serve(
            &options,
            move |links| {
                let _ = ready_tx.send(Some(links[0].address.clone()));
            },
            move |engine| {
                panel.start(engine.clone()).expect("the panel starts");
                let _ = engine_tx.send(engine);
            },
        );
        if let Err(e) = result {
            eprintln!("serve failed: {e:#}");
            let _ = ready_tx2.send(None);
        }
    });
    let meb = ready_rx
        .recv_timeout(Duration::from_secs(20))
        .expect("the session starts")
        .expect("the session opens its link");
    let engine = engine_rx
        .recv_timeout(Duration::from_secs(20))
        .expect("the engine runs");
    let session = Session {
        engine,
        meb,
        panel: running,
        thread: Some(thread),
    };
    wait_for(Duration::from_secs(10), "the panel's first update", || {
        let (status, body) = http(&session.panel, "GET", "/api/state", None, true);
        status == 200 && body.contains("\"state\"")
    });
    session
}

/// Polls `ok` every 50 ms until it holds, or fails naming `what`.
pub fn wait_for(limit: Duration, what: &str, mut ok: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ok() {
        assert!(start.elapsed() < limit, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// One HTTP/1.1 request; `with_token` sends the panel's token when it has one.
pub fn http(
    panel: &Running,
    method: &str,
    path: &str,
    body: Option<&str>,
    with_token: bool,
) -> (u16, String) {
    let mut stream = TcpStream::connect(panel.addr_for_clients()).expect("connects to the panel");
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let auth = match (with_token, token_of(panel)) {
        (true, Some(t)) => format!("Authorization: Bearer {t}\r\n"),
        _ => String::new(),
    };
    let body = body.unwrap_or("");
    let request = format!(
        "{method} {path} HTTP/1.1\r\nHost: panel\r\n{auth}Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(request.as_bytes()).unwrap();
    let mut response = String::new();
    let _ = stream.read_to_string(&mut response);
    let status = response
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (status, body)
}

pub fn token_of(panel: &Running) -> Option<String> {
    panel.url.split_once("token=").map(|(_, t)| t.to_string())
}

/// Extension: where a client on this machine reaches the panel.
pub trait ClientAddr {
    fn addr_for_clients(&self) -> std::net::SocketAddr;
}

impl ClientAddr for Running {
    fn addr_for_clients(&self) -> std::net::SocketAddr {
        let mut a = self.addr;
        if a.ip().is_unspecified() {
            a.set_ip(std::net::Ipv4Addr::LOCALHOST.into());
        }
        a
    }
}

/// chromedriver on a free port of 127.0.0.1, ended with the value.
pub struct Driver {
    child: std::process::Child,
    pub url: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub fn chromedriver() -> Driver {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let child = std::process::Command::new("chromedriver")
        .arg(format!("--port={port}"))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("chromedriver runs (Debian's chromium-driver, installed by .ci/install)");
    let driver = Driver {
        child,
        url: format!("http://127.0.0.1:{port}"),
    };
    wait_for(Duration::from_secs(20), "chromedriver to listen", || {
        TcpStream::connect(("127.0.0.1", port)).is_ok()
    });
    driver
}

/// Chromium's options for this machine: headless, as root, no network.
pub fn chrome_capabilities(
    profile: &std::path::Path,
    phone: bool,
) -> serde_json::Map<String, serde_json::Value> {
    let mut args = vec![
        "--headless".to_string(),
        "--no-sandbox".into(),
        "--disable-gpu".into(),
        "--disable-quic".into(),
        "--no-first-run".into(),
        "--disable-background-networking".into(),
        "--disable-component-update".into(),
        "--disable-sync".into(),
        "--disable-dev-shm-usage".into(),
        format!("--user-data-dir={}", profile.display()),
    ];
    let mut options = serde_json::json!({});
    if phone {
        options["mobileEmulation"] = serde_json::json!({
            "deviceMetrics": { "width": 360, "height": 740, "pixelRatio": 2.0, "touch": true }
        });
    } else {
        args.push("--window-size=1280,1700".into());
    }
    options["args"] = serde_json::json!(args);
    if std::path::Path::new("/usr/bin/chromium").exists() {
        options["binary"] = "/usr/bin/chromium".into();
    }
    let mut caps = serde_json::Map::new();
    caps.insert("browserName".into(), "chrome".into());
    caps.insert("goog:chromeOptions".into(), options);
    caps
}

/// A fresh profile folder under the system's temporary folder.
pub fn fresh_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("twin-panel-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}
