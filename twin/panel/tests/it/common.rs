//! A real `twin serve` session (the real-time engine, a real MEB TCP link)
//! with its panel, for the panel's tests; requests to it; chromedriver.

use std::net::TcpStream;
use std::os::unix::process::CommandExt;
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

/// The `HOST:PORT` of a link given as `tcp://HOST:PORT`.
pub fn host_port(link: &str) -> &str {
    link.strip_prefix("tcp://")
        .unwrap_or_else(|| panic!("`{link}` is not a TCP link"))
}

pub struct Session {
    pub engine: Sender<Inbound>,
    /// `tcp://127.0.0.1:PORT` of the MEB link.
    pub meb: String,
    pub panel: Running,
    /// The panel itself (a class's index reads its feed).
    pub feed: Panel,
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
    serve_on("tcp://127.0.0.1:0", web, access, seconds)
}

/// `twin serve --meb LINK --adaptive-light --web WEB` for at most `seconds`.
pub fn serve_on(link: &str, web: &str, access: AccessOptions, seconds: f64) -> Session {
    serve_with(link, web, access, seconds, true)
}

/// `twin serve --meb LINK --web WEB`, with the adaptive light detector or
/// the fixed one, for at most `seconds`.
pub fn serve_with(
    link: &str,
    web: &str,
    access: AccessOptions,
    seconds: f64,
    light_adaptive: bool,
) -> Session {
    serve_module(link, web, access, seconds, light_adaptive, None)
}

/// `twin serve --meb LINK --web WEB` as a class's module `name` runs it
/// (its panel names it), or as a session of its own (`None`).
pub fn serve_module(
    link: &str,
    web: &str,
    access: AccessOptions,
    seconds: f64,
    light_adaptive: bool,
    name: Option<&str>,
) -> Session {
    serve_slave(link, web, access, seconds, light_adaptive, name, 1)
}

/// `twin serve --meb LINK --web WEB --id ID` for at most `seconds`.
pub fn serve_id(id: u8, link: &str, web: &str, seconds: f64) -> Session {
    serve_slave(link, web, AccessOptions::default(), seconds, true, None, id)
}

fn serve_slave(
    link: &str,
    web: &str,
    access: AccessOptions,
    seconds: f64,
    light_adaptive: bool,
    name: Option<&str>,
    id: u8,
) -> Session {
    let panel = Panel::bind(PanelOptions {
        role: PanelRole::Serve,
        addr: web.parse().unwrap(),
        access,
        rate_hz: 20.0,
    })
    .expect("the panel binds");
    let panel = match name {
        Some(name) => panel.named(name),
        None => panel,
    };
    let running = panel.running();
    let feeds = panel.clone();
    let feed = panel.clone();
    let options = ServeOptions {
        session: session_options(Some(ViewOpener::new(move |_| Some(feeds.view()))), seconds),
        links: vec![(ServeProtocol::Meb, link.into())],
        defaults: LinkDefaults::default(),
        id,
        meb_map: None,
        params: PlantParams::preset("vemodule").unwrap(),
        seed: 1,
        max_clients: Some(8),
        partial_timeout: None,
        rate_limit: None,
        idle_timeout: None,
        room_after_idle: None,
        read_only: false,
        light_adaptive,
        firmware: Vec::new(),
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
        feed,
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

/// One request to the panel; `with_token` sends the panel's token when it
/// has one. The status and the body, a refusal's too.
pub fn http(
    panel: &Running,
    method: &str,
    path: &str,
    body: Option<&str>,
    with_token: bool,
) -> (u16, String) {
    let mut request = ureq::http::Request::builder()
        .method(method)
        .uri(format!("http://{}{path}", panel.addr_for_clients()));
    if with_token && let Some(token) = token_of(panel) {
        request = request.header("Authorization", format!("Bearer {token}"));
    }
    let answer = match body {
        Some(body) => agent().run(
            request
                .header("Content-Type", "application/json")
                .body(body)
                .unwrap(),
        ),
        None => agent().run(request.body(()).unwrap()),
    };
    let answer = answer.unwrap_or_else(|e| panic!("{method} {path}: {e}"));
    let status = answer.status().as_u16();
    (
        status,
        answer.into_body().read_to_string().unwrap_or_default(),
    )
}

/// The tests' HTTP client: a refusal is an answer, not an error; nothing
/// waits longer than a loaded machine could need.
pub fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(30)))
        .build()
        .into()
}

/// Reads the panel's stream at `addr` for `seconds`: the updates it got.
pub fn stream_updates(addr: std::net::SocketAddr, seconds: f64) -> usize {
    use std::io::BufRead;
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .timeout_global(Some(Duration::from_secs_f64(seconds)))
        .build()
        .into();
    let Ok(stream) = agent
        .get(format!("http://{addr}/api/stream"))
        .header("Accept", "text/event-stream")
        .call()
    else {
        return 0;
    };
    let mut events = std::io::BufReader::new(stream.into_body().into_reader());
    let end = Instant::now() + Duration::from_secs_f64(seconds);
    let (mut updates, mut line) = (0, String::new());
    while Instant::now() < end {
        line.clear();
        match events.read_line(&mut line) {
            // The stream's time is up (ureq's timeout), or the panel closed it.
            Ok(0) | Err(_) => break,
            Ok(_) if line.starts_with("event: update") => updates += 1,
            Ok(_) => {}
        }
    }
    updates
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
        // Chromium is chromedriver's child, in its process group: a test
        // that failed before closing its browser would leave it running.
        let _ = std::process::Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", self.child.id())])
            .status();
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
        // A group of its own, ended whole with the driver (see `Drop`).
        .process_group(0)
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
    chrome_at(profile, phone.then_some((390, 844)))
}

/// [`chrome_capabilities`] on a phone of `(width, height)` CSS px, or a laptop.
pub fn chrome_at(
    profile: &std::path::Path,
    phone: Option<(u32, u32)>,
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
    if let Some((width, height)) = phone {
        options["mobileEmulation"] = serde_json::json!({
            "deviceMetrics": { "width": width, "height": height, "pixelRatio": 2.0, "touch": true }
        });
    } else {
        // A laptop: the trend must show above the fold.
        args.push("--window-size=1366,768".into());
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

/// A fresh profile folder under the system's temporary folder. Those an
/// earlier run left (its process gone; a browser profile is tens of MB) are
/// removed first.
pub fn fresh_dir(name: &str) -> std::path::PathBuf {
    let tmp = std::env::temp_dir();
    let prefix = format!("twin-panel-{name}-");
    for e in std::fs::read_dir(&tmp).into_iter().flatten().flatten() {
        let file_name = e.file_name();
        let pid = file_name
            .to_str()
            .and_then(|n| n.strip_prefix(&prefix))
            .and_then(|rest| rest.parse::<u32>().ok());
        if let Some(pid) = pid
            && !std::path::Path::new(&format!("/proc/{pid}")).exists()
        {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
    let dir = tmp.join(format!("{prefix}{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// `twin vsp A B`: a crossed pseudo-terminal pair, copied by a thread of
/// its own for as long as the test runs.
pub fn vsp(name: &str) -> [std::path::PathBuf; 2] {
    let base = std::env::temp_dir().join(format!("twin-panel-{name}-{}", std::process::id()));
    let ends = [base.with_extension("V0"), base.with_extension("V1")];
    let links = ends.clone();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        runtime.block_on(async move {
            let mut pair = twin_realtime::vsp::Pair::open(
                [&links[0], &links[1]],
                twin_realtime::vsp::PairOptions::default(),
            )
            .expect("the pty pair opens");
            let _ = pair.run(None, |_| {}, |_| {}).await;
        });
    });
    wait_for(Duration::from_secs(10), "the pty pair", || {
        ends.iter().all(|e| e.exists())
    });
    ends
}

/// `twin supervise --meb BUS --no-server --web WEB` (a PI loop on slave 01,
/// polled every 10 ms, status words every 10 cycles) for at most `seconds`.
pub fn supervise(bus: &str, web: &str, seconds: f64) -> Session {
    supervise_ids(bus, web, seconds, &[1])
}

/// [`supervise`] polling the slaves `ids` (`--id` repeated), each with its loop.
pub fn supervise_ids(bus: &str, web: &str, seconds: f64, ids: &[u8]) -> Session {
    use nodes::master::image_server::ImageServerConfig;
    use protocols::time::SimDuration;
    use twin_realtime::supervise::{SuperviseOptions, supervise_with};
    let panel = Panel::bind(PanelOptions {
        role: PanelRole::Supervise,
        addr: web.parse().unwrap(),
        access: AccessOptions::default(),
        rate_hz: 20.0,
    })
    .expect("the panel binds");
    let running = panel.running();
    let feeds = panel.clone();
    let feed = panel.clone();
    let options = SuperviseOptions {
        session: session_options(Some(ViewOpener::new(move |_| Some(feeds.view()))), seconds),
        bus: bus.into(),
        protocol: nodes::master::Protocol::Meb,
        listen: Vec::new(),
        baud: 115_200,
        slaves: ids.to_vec(),
        set_point: 0.0,
        open_loop: None,
        kp: 0.45,
        ki: 2.5,
        speed_source: nodes::master::SpeedSource::Hall,
        poll_period: SimDuration::from_millis(10),
        reply_timeout: SimDuration::from_millis(100),
        retries: 2,
        status_poll: 10,
        meb_map: None,
        server: ImageServerConfig::default(),
        rate_limit_bytes: None,
        idle_timeout: None,
        room_after_idle: None,
    };
    let (engine_tx, engine_rx) = channel();
    let thread = std::thread::spawn(move || {
        let result = supervise_with(
            &options,
            |_| {},
            move |engine| {
                panel.start(engine.clone()).expect("the panel starts");
                let _ = engine_tx.send(engine);
            },
        );
        if let Err(e) = result {
            eprintln!("supervise failed: {e:#}");
        }
    });
    let engine = engine_rx
        .recv_timeout(Duration::from_secs(20))
        .expect("the supervisor runs");
    let session = Session {
        engine,
        meb: bus.into(),
        panel: running,
        feed,
        thread: Some(thread),
    };
    wait_for(
        Duration::from_secs(10),
        "the supervise panel's first update",
        || {
            let (status, body) = http(&session.panel, "GET", "/api/state", None, true);
            status == 200 && body.contains("\"loops\"")
        },
    );
    session
}

/// `twin panel` in this process: the client panel of slave 01 at `url`
/// (`tcp://…`), polling every 50 ms, its page served on a free port.
pub fn client_panel(url: &str) -> Panel {
    use twin_panel::remote::{Remote, RemoteOptions};
    let panel = Panel::bind(PanelOptions {
        role: PanelRole::Client,
        addr: "127.0.0.1:0".parse().unwrap(),
        access: AccessOptions::default(),
        rate_hz: 20.0,
    })
    .unwrap();
    let remote = Remote::start(
        RemoteOptions {
            url: url.to_string(),
            id: 1,
            map: Default::default(),
            poll: Duration::from_millis(50),
            timeout: Duration::from_millis(500),
        },
        panel.hub(),
    )
    .unwrap();
    panel.start_remote(remote).unwrap();
    panel
}
