//! The class's index: one page for the teacher of a class served from one
//! `twin serve` (a configuration file's `[[module]]` tables), listing every
//! module with the state of its links, how long ago its last request came,
//! its errors, the recording it writes and a link to its panel.
//!
//! It always needs the teacher's own token, whatever its address: it
//! links to every student's panel with that panel's token, so a student's
//! token, or none, must not open it. It reads what each module's panel
//! (or, for a module without one, an [unserved](crate::Panel::unserved)
//! feed) last published: the index never asks an engine anything itself.

use axum::Router;
use axum::extract::{Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde_json::{Value, json};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use twin_realtime::rotate::RecordPlan;

use crate::access::{Access, AccessOptions, TokenError};
use crate::http::{escape, token_of};
use crate::{Limits, Panel, Running};

/// Why the class's index cannot be served.
#[derive(Debug, thiserror::Error)]
pub enum IndexError {
    #[error("the class's index on {addr}")]
    Token {
        addr: SocketAddr,
        #[source]
        source: TokenError,
    },
    #[error("the class's index: cannot listen on {addr}")]
    Listen {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot start the class's index's thread")]
    Thread(#[source] std::io::Error),
}

/// One module of the class, as the index shows it.
#[derive(Debug, Clone)]
pub struct ClassModule {
    /// The class file's `name`.
    pub name: String,
    /// Its panel, or its unserved feed: the state the index shows.
    pub panel: Panel,
    /// Where it records (`None`: it does not).
    pub record: Option<RecordPlan>,
}

/// The index, bound and waiting for the class's modules to start.
#[derive(Debug)]
pub struct ClassIndex {
    access: Arc<Access>,
    listener: std::net::TcpListener,
    addr: SocketAddr,
    limits: Limits,
}

/// What the index's handlers share.
#[derive(Clone)]
struct IndexState {
    access: Arc<Access>,
    modules: Arc<Vec<ClassModule>>,
    /// The cookie that keeps the teacher's token, one per port as the
    /// panels' are.
    cookie: Arc<str>,
}

/// How often the page reloads itself, seconds.
const REFRESH_S: u32 = 2;

impl ClassIndex {
    /// Binds `addr` and reads the teacher's token from `token_file` (a new
    /// one written there, readable by its owner only, if it is missing).
    pub fn bind(addr: SocketAddr, token_file: &Path) -> Result<Self, IndexError> {
        let access = Access::new(
            &AccessOptions {
                token_file: Some(token_file.to_path_buf()),
                read_only: true,
            },
            &addr,
        )
        .map_err(|source| IndexError::Token { addr, source })?;
        let listen = |source| IndexError::Listen { addr, source };
        let listener = std::net::TcpListener::bind(addr).map_err(listen)?;
        listener.set_nonblocking(true).map_err(listen)?;
        let addr = listener.local_addr().map_err(listen)?;
        Ok(Self {
            access: Arc::new(access),
            listener,
            addr,
            limits: Limits::from_env(),
        })
    }

    /// The address bound and the URL to open, with the teacher's token.
    pub fn running(&self) -> Running {
        let host = match self.addr {
            SocketAddr::V4(a) if a.ip().is_unspecified() => format!("127.0.0.1:{}", a.port()),
            SocketAddr::V6(a) if a.ip().is_unspecified() => format!("[::1]:{}", a.port()),
            a => a.to_string(),
        };
        Running {
            addr: self.addr,
            url: format!("http://{host}/?token={}", self.access.token().unwrap_or("")),
            read_only: true,
        }
    }

    /// Serves the index of `modules` on a thread of its own, at the
    /// panels' lower priority.
    pub fn start(self, modules: Vec<ClassModule>) -> Result<(), IndexError> {
        let state = IndexState {
            access: self.access,
            modules: Arc::new(modules),
            cookie: format!("twin_class_token_{}", self.addr.port()).into(),
        };
        let (listener, limits) = (self.listener, self.limits);
        std::thread::Builder::new()
            .name("twin-class-index".into())
            .spawn(move || {
                let _ = rustix::process::setpriority_process(None, 10);
                let runtime = match tokio::runtime::Builder::new_current_thread()
                    .enable_io()
                    .enable_time()
                    .build()
                {
                    Ok(rt) => rt,
                    Err(e) => {
                        eprintln!("the class's index: cannot start its runtime: {e}");
                        return;
                    }
                };
                runtime.block_on(async move {
                    let listener = match tokio::net::TcpListener::from_std(listener) {
                        Ok(l) => l,
                        Err(e) => {
                            eprintln!("the class's index: cannot serve: {e}");
                            return;
                        }
                    };
                    let say: crate::server::Say =
                        Arc::new(|line| eprintln!("the class's index: {line}"));
                    crate::server::run(listener, router(state, limits), limits, say).await;
                });
            })
            .map_err(IndexError::Thread)?;
        Ok(())
    }
}

fn router(state: IndexState, limits: Limits) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/api/class", get(api))
        .fallback(|| async {
            crate::http::error(
                404,
                json!({ "error": "no such page: the class's index is at / and its state at /api/class" }),
            )
        })
        .layer(middleware::from_fn_with_state(state.clone(), guard))
        .layer(middleware::from_fn_with_state(
            limits,
            crate::server::bounded_body,
        ))
        .with_state(state)
}

/// What a browser without the teacher's token is shown.
const NEEDS_TOKEN_HTML: &str = "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">\
<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
<title>token needed: the class's index — EV lab twin</title></head>\
<body style=\"font-family:sans-serif;max-width:40em;margin:2em auto\">\
<h1>The class's index needs the teacher's token</h1>\
<p>Open the address twin printed beside the modules' panels when it started \
(<code>index: …/?token=…</code>), or add <code>?token=</code> and the token in \
the index's token file. A student's panel token does not open it.</p></body></html>";

/// Only the teacher's token opens the index; a student's is refused like none.
async fn guard(State(state): State<IndexState>, request: Request, next: Next) -> Response {
    let token = token_of(&request, &state.cookie);
    if request.method() != axum::http::Method::GET {
        return crate::http::error(
            405,
            json!({ "error": "the class's index only shows: open a module's panel to change anything" }),
        );
    }
    if state.access.check(token.as_deref()).is_ok() {
        let mut response = next.run(request).await;
        // A reload of `/` without the query keeps working through the cookie.
        if let Some(t) = token
            && let Ok(v) = HeaderValue::from_str(&format!(
                "{}={t}; Path=/; HttpOnly; SameSite=Strict",
                state.cookie
            ))
        {
            response.headers_mut().insert(header::SET_COOKIE, v);
        }
        return response;
    }
    let browser = request
        .headers()
        .get(header::ACCEPT)
        .and_then(|a| a.to_str().ok())
        .is_some_and(|a| a.contains("text/html"));
    if browser {
        return (
            StatusCode::UNAUTHORIZED,
            [(
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/html; charset=utf-8"),
            )],
            NEEDS_TOKEN_HTML,
        )
            .into_response();
    }
    crate::http::error(
        401,
        json!({ "error": "the class's index needs the teacher's token: open the index: URL twin printed (…/?token=…), or send Authorization: Bearer TOKEN" }),
    )
}

/// The host a browser reached the index by, without its port: the
/// modules' panels are on the same machine, on ports of their own.
fn host_of(request_host: Option<&str>) -> String {
    let host = request_host.unwrap_or("127.0.0.1");
    match host.rsplit_once(':') {
        // `[::1]:8100`, `lab:8100`; a bare IPv6 address has no brackets.
        Some((h, port)) if port.chars().all(|c| c.is_ascii_digit()) && !h.ends_with(':') => {
            h.to_string()
        }
        _ => host.to_string(),
    }
}

/// The link to a module's panel, on the host the teacher used, with the
/// panel's token.
fn panel_link(panel: &Panel, host: &str) -> Option<String> {
    if !panel.served() {
        return None;
    }
    let addr = panel.running().addr;
    let host = if addr.ip().is_unspecified() {
        host.to_string()
    } else {
        match addr {
            SocketAddr::V6(a) => format!("[{}]", a.ip()),
            SocketAddr::V4(a) => a.ip().to_string(),
        }
    };
    let token = panel
        .token()
        .map(|t| format!("?token={t}"))
        .unwrap_or_default();
    Some(format!("http://{host}:{}/{token}", addr.port()))
}

/// The file a module records to now: the newest of its session's name in
/// its folder (a new one at every rotation), or the one `--out` named.
fn recording_now(plan: &RecordPlan) -> Option<PathBuf> {
    let start = format!("{}-", plan.prefix);
    let newest = std::fs::read_dir(&plan.dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| e.file_name().into_string().ok())
        .filter(|n| n.starts_with(&start) && n.ends_with(".mcap"))
        .max();
    match (newest, &plan.out) {
        (Some(name), _) => Some(plan.dir.join(name)),
        (None, Some(out)) => Some(out.clone()),
        (None, None) => None,
    }
}

/// A link's lamp and its word, by the panel's own rule (`panel.js`,
/// `linkLamp`): red with errors in the last 5 s and no good frame for a
/// second, amber with errors among good frames or a link quiet for a
/// second, grey before any frame.
fn lamp(stats: &Value) -> (&'static str, String) {
    let age = stats["last_frame_age_s"].as_f64();
    let good = stats["last_good_age_s"].as_f64();
    let recent = stats["errors_recent"].as_u64().unwrap_or(0);
    let Some(age) = age else {
        return ("off", "no frames yet".into());
    };
    if recent > 0 && good.is_none_or(|g| g > 1.0) {
        let since = good.map_or_else(|| "yet".to_string(), |g| format!("for {g:.1} s"));
        return ("bad", format!("{recent} errors, no good frame {since}"));
    }
    if recent > 0 {
        return ("warn", format!("{recent} errors in the last 5 s"));
    }
    if age >= 1.0 {
        return ("warn", format!("quiet for {age:.1} s"));
    }
    ("on", "ok".into())
}

/// How bad a lamp is, to show a module by its worst link.
fn rank(lamp: &str) -> u8 {
    match lamp {
        "bad" => 3,
        "warn" => 2,
        "on" => 1,
        _ => 0,
    }
}

/// One module as `/api/class` gives it.
fn module_json(m: &ClassModule, host: &str) -> Value {
    let latest: Value = serde_json::from_str(&m.panel.hub().latest()).unwrap_or_default();
    let mut links = Vec::new();
    let (mut errors, mut last) = (0u64, None::<f64>);
    let mut worst = ("off", "no frames yet".to_string());
    if let Some(stats) = latest["links"].as_object() {
        for (name, s) in stats {
            let (state, said) = lamp(s);
            errors += s["errors"].as_u64().unwrap_or(0);
            if let Some(age) = s["last_in_age_s"].as_f64() {
                last = Some(last.map_or(age, |l: f64| l.min(age)));
            }
            if rank(state) > rank(worst.0) {
                worst = (state, format!("{name}: {said}"));
            }
            links.push(json!({
                "name": name,
                "state": state,
                "said": said,
                "clients": s["clients"],
                "errors": s["errors"],
                "last_request_age_s": s["last_in_age_s"],
            }));
        }
    }
    json!({
        "name": m.name,
        "role": m.panel.role(),
        "running": latest.get("t").is_some(),
        "state": worst.0,
        "said": worst.1,
        "links": links,
        "errors": errors,
        "last_request_age_s": last,
        "recording": m.record.as_ref().and_then(recording_now).map(|p| p.display().to_string()),
        "panel": panel_link(&m.panel, host),
    })
}

fn class_json(state: &IndexState, request_host: Option<&str>) -> Value {
    let host = host_of(request_host);
    json!({
        "modules": state.modules.iter().map(|m| module_json(m, &host)).collect::<Vec<_>>(),
    })
}

fn request_host(request: &Request) -> Option<String> {
    request
        .headers()
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .map(str::to_string)
}

async fn api(State(state): State<IndexState>, request: Request) -> Response {
    axum::Json(class_json(&state, request_host(&request).as_deref())).into_response()
}

/// The index as a page that reloads itself: a table a teacher reads from
/// across the room, and that works without a script.
async fn page(State(state): State<IndexState>, request: Request) -> Response {
    let class = class_json(&state, request_host(&request).as_deref());
    let mut rows = String::new();
    for m in class["modules"].as_array().into_iter().flatten() {
        let name = escape(m["name"].as_str().unwrap_or_default());
        let clients: u64 = m["links"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|l| l["clients"].as_u64())
            .sum();
        let last = m["last_request_age_s"]
            .as_f64()
            .map_or_else(|| "none yet".to_string(), ago);
        let recording = m["recording"]
            .as_str()
            .map_or_else(|| "not recorded".to_string(), escape);
        let panel = match m["panel"].as_str() {
            Some(url) => format!(
                "<a class=\"panel-link\" href=\"{}\">{name}'s panel</a>",
                escape(url)
            ),
            None => "no panel (no <code>web</code> in its table)".into(),
        };
        let state_word = if m["running"] == true {
            escape(m["said"].as_str().unwrap_or_default())
        } else {
            "starting".into()
        };
        rows.push_str(&format!(
            "<tr id=\"module-{name}\"><th scope=\"row\" class=\"name\">{name}</th>\
             <td class=\"state\" data-state=\"{lamp}\"><span class=\"lamp {lamp}\"></span> {state_word}</td>\
             <td class=\"clients\">{clients}</td><td class=\"last\">{last}</td>\
             <td class=\"errors\">{errors}</td><td class=\"recording\">{recording}</td>\
             <td class=\"panel\">{panel}</td></tr>",
            lamp = m["state"].as_str().unwrap_or("off"),
            errors = m["errors"].as_u64().unwrap_or(0),
        ));
    }
    let count = class["modules"].as_array().map_or(0, Vec::len);
    let html = format!(
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">\
<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
<meta http-equiv=\"refresh\" content=\"{REFRESH_S}\">\
<title>the class's index ({count} modules) — EV lab twin</title>\
<link rel=\"icon\" href=\"data:,\">\
<style>{INDEX_CSS}</style></head><body>\
<h1>The class <span class=\"note\">{count} modules, one twin serve</span></h1>\
<p class=\"note\">Each module's links: the worst lamp of its links and why; how long ago \
a client's last request came on any of them; its errors (frames that failed their check) since it \
started; the recording it writes now. The page reloads every {REFRESH_S} s.</p>\
<div class=\"scroll\"><table id=\"modules\"><thead><tr><th>module</th><th>links</th>\
<th>clients</th><th>last request</th><th>errors</th><th>recording</th><th>panel</th></tr></thead>\
<tbody>{rows}</tbody></table></div></body></html>"
    );
    (
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/html; charset=utf-8"),
            ),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        ],
        html,
    )
        .into_response()
}

/// `0.4 s ago`, `12 s ago`, `3 min ago`.
fn ago(seconds: f64) -> String {
    if seconds < 10.0 {
        format!("{seconds:.1} s ago")
    } else if seconds < 120.0 {
        format!("{seconds:.0} s ago")
    } else {
        format!("{:.0} min ago", seconds / 60.0)
    }
}

/// The index's few styles: the panel's lamps and a table that scrolls on a
/// phone rather than the page.
const INDEX_CSS: &str = "body{font-family:system-ui,sans-serif;margin:1em;color:#222}\
h1{font-size:1.2rem}.note{color:#666;font-weight:normal;font-size:.9rem}\
.scroll{overflow-x:auto}table{border-collapse:collapse}th,td{padding:.3em .6em;\
border-bottom:1px solid #ddd;text-align:left;vertical-align:top}\
.lamp{display:inline-block;width:.8em;height:.8em;border-radius:50%;background:#bbb}\
.lamp.on{background:#2a2}.lamp.warn{background:#e90}.lamp.bad{background:#d22}";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_teachers_host_is_kept_and_its_port_dropped() {
        assert_eq!(host_of(Some("lab:8100")), "lab");
        assert_eq!(host_of(Some("10.0.3.1:8100")), "10.0.3.1");
        assert_eq!(host_of(Some("[::1]:8100")), "[::1]");
        assert_eq!(host_of(Some("lab")), "lab");
        assert_eq!(host_of(None), "127.0.0.1");
    }

    #[test]
    fn a_module_shows_its_worst_link() {
        let ok = json!({"last_frame_age_s": 0.2, "last_good_age_s": 0.2, "errors_recent": 0});
        let failing = json!({"last_frame_age_s": 0.1, "last_good_age_s": 3.0, "errors_recent": 7});
        assert_eq!(lamp(&ok).0, "on");
        assert_eq!(lamp(&failing).0, "bad");
        assert!(rank(lamp(&failing).0) > rank(lamp(&ok).0));
        assert_eq!(lamp(&json!({})).0, "off");
    }
}
