//! The HTTP side: the page, the JSON API (`docs/panel-api.md`), the stream
//! and the producer that feeds it. Everything here runs on the panel's own
//! thread and runtime.

use axum::Router;
use axum::body::Bytes;
use axum::extract::{Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum_extra::extract::cookie::CookieJar;
use futures_util::Stream;
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::convert::Infallible;
use std::sync::atomic::Ordering;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::broadcast::error::RecvError;

use crate::access::{Access, Refused};
use crate::commands::{self, EngineCommand, Rejected};
use crate::hub::Hub;
use crate::monitor::Monitor;
use crate::remote::Remote;
use crate::snapshot::{self, EngineSnapshot};
use crate::{PanelRole, assets, outputs};
use twin_realtime::Inbound;

/// What the panel fronts: a session's engine, or (`twin panel`) its own
/// MEB-TCP connection to a slave.
#[derive(Clone, Debug)]
pub enum Backend {
    Engine(Arc<Mutex<Sender<Inbound>>>),
    Remote(Arc<Remote>),
}

/// What every handler shares.
#[derive(Clone, Debug)]
pub struct AppState {
    pub hub: Arc<Hub>,
    pub access: Arc<Access>,
    pub backend: Backend,
    pub role: PanelRole,
    pub rate_hz: f64,
    /// The switches the panel had a supervisor write.
    pub written: outputs::Written,
    /// The I/O map's places (`twin serve --map`), for the labels.
    pub layout: Option<Arc<crate::remote::layout::Layout>>,
    /// What the server allows a client.
    pub limits: crate::server::Limits,
    /// The page as this panel serves it, and its cookie.
    pub page: Arc<Page>,
}

/// What makes one panel's page its own: the module and role it names, and
/// the cookie that keeps its token.
#[derive(Debug)]
pub struct Page {
    /// `index.html` with the module and role in its title and heading.
    pub html: String,
    /// What a browser without the token is shown.
    pub needs_token: String,
    /// The cookie's name: one per panel port, because a browser keeps
    /// cookies per host, not per port, so two students' panels on one
    /// server (a class) would otherwise overwrite each other's token.
    pub cookie: String,
    pub module: Option<String>,
}

impl Page {
    pub fn new(role: PanelRole, module: Option<&str>, port: u16) -> Self {
        let role_text = role.described();
        let (title, heading) = match module {
            Some(m) => {
                let m = escape(m);
                (
                    format!("{m} · {role_text} — EV lab twin"),
                    format!("<span id=\"module\">{m}</span> <span id=\"role\">{role_text}</span>"),
                )
            }
            None => (
                format!("{role_text} — EV lab twin"),
                format!("EV lab twin <span id=\"role\">{role_text}</span>"),
            ),
        };
        let html = assets::INDEX_HTML
            .replace(
                "<title>EV lab twin — panel</title>",
                &format!("<title>{title}</title>"),
            )
            .replace(
                "<h1>EV lab twin <span id=\"role\">panel</span></h1>",
                &format!("<h1>{heading}</h1>"),
            );
        let whose = module.map_or_else(
            || "This panel".to_string(),
            |m| format!("The panel of {}", escape(m)),
        );
        let needs_token = NEEDS_TOKEN_HTML
            .replace("{title}", &title)
            .replace("{whose}", &whose);
        Page {
            html,
            needs_token,
            cookie: format!("twin_panel_token_{port}"),
            module: module.map(str::to_string),
        }
    }
}

/// Text for HTML: a module's name is letters, digits, `-` and `_`, but the
/// page does not rely on it.
pub(crate) fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Serves until the session ends (the engine stops taking commands).
pub async fn serve(listener: std::net::TcpListener, state: AppState) {
    let listener = match tokio::net::TcpListener::from_std(listener) {
        Ok(l) => l,
        Err(e) => {
            eprintln!("--web: cannot serve the panel: {e}");
            return;
        }
    };
    let producer = match &state.backend {
        Backend::Engine(engine) => tokio::spawn(produce(state.clone(), engine.clone())),
        Backend::Remote(remote) => tokio::spawn(produce_remote(state.clone(), remote.clone())),
    };
    let limits = state.limits;
    let say: crate::server::Say = Arc::new(|line| eprintln!("--web: {line}"));
    tokio::select! {
        () = crate::server::run(listener, router(state), limits, say) => {}
        _ = producer => {}
    }
}

pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(|State(s): State<AppState>| async move { own_page(&s.page.html) }))
        .route("/panel.css", get(|| async { page(assets::PANEL_CSS, "text/css; charset=utf-8") }))
        .route("/panel.js", get(|| async { page(assets::PANEL_JS, "text/javascript; charset=utf-8") }))
        .route("/api/info", get(info))
        .route("/api/state", get(latest))
        .route("/api/trend", get(trend))
        .route("/api/plant", get(plant))
        .route("/api/stream", get(stream))
        .route("/api/force", post(|s, h, b| command(s, h, b, commands::force)))
        .route("/api/release", post(|s, h, b| command(s, h, b, commands::release)))
        .route("/api/fault", post(|s, h, b| command(s, h, b, commands::fault)))
        .route("/api/loop", post(|s, h, b| command(s, h, b, commands::supervise_loop)))
        .route("/api/slave", post(|s, h, b| command(s, h, b, commands::slave)))
        .route("/api/step", post(step))
        .route("/api/outputs", post(set_outputs))
        .fallback(|| async { error(404, json!({ "error": "no such page: the panel is at / and its API under /api/ (docs/panel-api.md)" })) })
        .layer(middleware::from_fn_with_state(state.clone(), guard))
        // Outside the guard: an oversized or endless body is refused before
        // anything else is looked at.
        .layer(middleware::from_fn_with_state(
            state.limits,
            crate::server::bounded_body,
        ))
        .with_state(state)
}

fn page(body: &'static str, kind: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static(kind)),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        ],
        body,
    )
        .into_response()
}

/// The page of this panel (its module and role in it).
fn own_page(html: &str) -> Response {
    (
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/html; charset=utf-8"),
            ),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        ],
        html.to_string(),
    )
        .into_response()
}

pub(crate) fn error(status: u16, body: Value) -> Response {
    let status = StatusCode::from_u16(status).unwrap_or(StatusCode::BAD_REQUEST);
    (status, axum::Json(body)).into_response()
}

/// The one query parameter the guard reads (the handlers read their own).
#[derive(serde::Deserialize)]
struct TokenQuery {
    token: Option<String>,
}

/// The token a request carries: `?token=` (percent-encoding decoded), else
/// `Authorization: Bearer`, else the cookie named `cookie` (the panel's own:
/// another port's panel's cookie, sent to the same host, is not it).
pub(crate) fn token_of(request: &Request, cookie: &str) -> Option<String> {
    // A query that does not read (`token` given twice) carries no token.
    let from_query = Query::<TokenQuery>::try_from_uri(request.uri())
        .ok()
        .and_then(|Query(q)| q.token);
    let headers = request.headers();
    let from_header = || {
        headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(|t| t.trim().to_string())
    };
    let from_cookie = || {
        CookieJar::from_headers(headers)
            .get(cookie)
            .map(|c| c.value().to_string())
    };
    from_query.or_else(from_header).or_else(from_cookie)
}

/// What a browser shows when the panel is opened without its token
/// (`{title}` and `{whose}` name the panel).
const NEEDS_TOKEN_HTML: &str = "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">\
<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
<title>token needed: {title}</title></head><body style=\"font-family:sans-serif;max-width:40em;margin:2em auto\">\
<h1>{whose} needs its token</h1>\
<p>Open the address twin printed when it started: it ends in <code>/?token=…</code>. \
The browser then keeps the token for this panel alone, so other panels of the \
same server stay open beside it.</p>\
<p>A program sends it as <code>Authorization: Bearer TOKEN</code>.</p></body></html>";

/// Every request passes here: without the token, 401 and nothing changes;
/// on a read-only panel, commands get 403.
async fn guard(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let token = token_of(&request, &state.page.cookie);
    let is_command = request.method() == axum::http::Method::POST;
    // A person opening the page in a browser gets a page, not JSON.
    let browser = !is_command
        && request
            .headers()
            .get(header::ACCEPT)
            .and_then(|a| a.to_str().ok())
            .is_some_and(|a| a.contains("text/html"));
    let checked = if is_command {
        state.access.check_command(token.as_deref())
    } else {
        state.access.check(token.as_deref())
    };
    match checked {
        Ok(()) => {
            let mut response = next.run(request).await;
            // The page's own fetches carry the token; a reload of `/` without
            // the query keeps working through the cookie.
            if let (Some(t), true) = (token, state.access.token().is_some())
                && let Ok(v) = HeaderValue::from_str(&format!(
                    "{}={t}; Path=/; HttpOnly; SameSite=Strict",
                    state.page.cookie
                ))
            {
                response.headers_mut().insert(header::SET_COOKIE, v);
            }
            response
        }
        Err(Refused::Token) if browser => (
            StatusCode::UNAUTHORIZED,
            [(
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/html; charset=utf-8"),
            )],
            state.page.needs_token.clone(),
        )
            .into_response(),
        Err(Refused::Token) => error(
            401,
            json!({ "error": "this panel needs its token: open the URL twin printed when it started (…/?token=…), or send Authorization: Bearer TOKEN" }),
        ),
        Err(Refused::ReadOnly) => error(
            403,
            json!({ "error": "this panel is read-only (--web-read-only): it shows, it changes nothing" }),
        ),
    }
}

async fn info(State(state): State<AppState>) -> Response {
    axum::Json(json!({
        "role": state.role,
        "module": state.page.module,
        "read_only": state.access.read_only(),
        "rate_hz": state.rate_hz,
        "version": env!("CARGO_PKG_VERSION"),
        "stream_clients": state.hub.clients.load(Ordering::Relaxed),
        // What each input takes, for the serve page's sliders and switches.
        "inputs": (state.role == PanelRole::Serve).then(commands::inputs_json),
    }))
    .into_response()
}

async fn latest(State(state): State<AppState>) -> Response {
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        )],
        state.hub.latest().to_string(),
    )
        .into_response()
}

/// The plant's parameters, per module: what a check of a slave on this
/// bench (`twin check slave --bench`) derives its expected speeds and
/// counts from. A GET (read-only panels answer it), run on the engine
/// because the parameters live with each module's plant.
async fn plant(State(state): State<AppState>) -> Response {
    let Backend::Engine(engine) = &state.backend else {
        return error(
            409,
            json!({ "error": "twin panel has no plant: it is a remote client of a slave" }),
        );
    };
    let read: EngineCommand = Box::new(|e| {
        let modules: Vec<Value> = e
            .modules
            .iter()
            .map(|m| json!({ "name": m.name, "params": m.plant.params() }))
            .collect();
        Ok(json!({ "modules": modules }))
    });
    match commands::run_on_engine(engine, read).await {
        Ok(answer) => axum::Json(answer).into_response(),
        Err(e) => error(e.status, e.to_json()),
    }
}

async fn trend(
    State(state): State<AppState>,
    Query(q): Query<BTreeMap<String, String>>,
) -> Response {
    let seconds = q
        .get("seconds")
        .and_then(|s| s.parse::<f64>().ok())
        .filter(|s| s.is_finite() && *s > 0.0)
        .unwrap_or(30.0)
        .min(30.0);
    axum::Json(state.hub.trend(seconds)).into_response()
}

async fn command(
    State(state): State<AppState>,
    _headers: HeaderMap,
    body: Bytes,
    parse: fn(&serde_json::Map<String, Value>) -> Result<EngineCommand, Rejected>,
) -> Response {
    let result = match (
        commands::object(&body).and_then(|map| parse(&map)),
        &state.backend,
    ) {
        (Ok(command), Backend::Engine(engine)) => commands::run_on_engine(engine, command).await,
        (Ok(_), Backend::Remote(_)) => Err(client_only()),
        (Err(e), _) => Err(e),
    };
    match result {
        Ok(answer) => axum::Json(answer).into_response(),
        Err(e) => error(e.status, e.to_json()),
    }
}

async fn step(State(state): State<AppState>, body: Bytes) -> Response {
    let result = match (commands::object(&body), &state.backend) {
        (Ok(map), Backend::Engine(engine)) => crate::step::step(&state.hub, engine, &map).await,
        (Ok(_), Backend::Remote(_)) => Err(client_only()),
        (Err(e), _) => Err(e),
    };
    match result {
        Ok(answer) => axum::Json(answer).into_response(),
        Err(e) => error(e.status, e.to_json()),
    }
}

/// What a client panel answers the commands of a session's panel.
fn client_only() -> Rejected {
    Rejected {
        status: 409,
        field: None,
        message: "this panel is an MEB client of a remote slave: it sets outputs (POST /api/outputs), it cannot force, fault or step".into(),
    }
}

async fn set_outputs(State(state): State<AppState>, body: Bytes) -> Response {
    let parsed = commands::object(&body).and_then(|map| outputs::parse(&map));
    let result = match (parsed, &state.backend) {
        (Err(e), _) => Err(e),
        (Ok((_, request)), Backend::Remote(remote)) => remote.write(request).await,
        (Ok((slave, request)), Backend::Engine(engine)) if state.role == PanelRole::Supervise => {
            outputs::supervise(engine, &state.written, slave, request).await
        }
        (Ok(_), Backend::Engine(_)) => Err(Rejected {
            status: 409,
            field: None,
            message: "on twin serve the master sets the outputs; force an input instead (POST /api/force)".into(),
        }),
    };
    match result {
        Ok(answer) => axum::Json(answer).into_response(),
        Err(e) => error(e.status, e.to_json()),
    }
}

/// Counts a stream client while it is connected.
struct Connected(Arc<Hub>);

impl Drop for Connected {
    fn drop(&mut self) {
        self.0.clients.fetch_sub(1, Ordering::Relaxed);
    }
}

async fn stream(
    State(state): State<AppState>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let hub = state.hub.clone();
    hub.clients.fetch_add(1, Ordering::Relaxed);
    let first = Some(hub.latest());
    let rx = hub.subscribe();
    let events = futures_util::stream::unfold(
        (rx, Connected(hub), first),
        |(mut rx, connected, first)| async move {
            if let Some(message) = first {
                let event = Event::default().event("update").data(&*message);
                return Some((Ok(event), (rx, connected, None)));
            }
            let event = match rx.recv().await {
                Ok(message) => Event::default().event("update").data(&*message),
                // A client too slow for the stream is told what it missed.
                Err(RecvError::Lagged(n)) => Event::default().event("lagged").data(n.to_string()),
                Err(RecvError::Closed) => return None,
            };
            Some((Ok(event), (rx, connected, None)))
        },
    );
    Sse::new(events).keep_alive(KeepAlive::default())
}

/// Every stream period: the engine's state, the frames and events since the
/// last message, one message for every client.
async fn produce(state: AppState, engine: Arc<Mutex<Sender<Inbound>>>) {
    let mut interval = tokio::time::interval(Duration::from_secs_f64(1.0 / state.rate_hz));
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut monitor = Monitor::new(state.role);
    loop {
        interval.tick().await;
        let snap = match read_snapshot(&engine).await {
            Ok(s) => s,
            Err(Gone) => return,
        };
        let Some(snap) = snap else { continue };
        for l in &snap.links {
            monitor
                .protocols
                .entry(l.name.clone())
                .or_insert(l.protocol);
        }
        let (frames, events, lateness) = monitor.take(&state.hub);
        let (dropped, total) = state.hub.frame_counts();
        let link_stats = monitor.links(
            snap.links.iter().map(|l| (l.name.as_str(), l.clients)),
            snap.t,
        );
        let mut shown = snap.to_json();
        if let Some(devices) = shown["devices"].as_array_mut() {
            for (d, device) in devices.iter_mut().zip(&snap.devices) {
                // The map in force now (the page may have changed it),
                // else the one the session started with.
                let now = device
                    .address
                    .as_ref()
                    .map(|a| a.meb_map.as_ref().map(crate::remote::layout::Layout::new));
                let layout = match now {
                    Some(map) => map.map(Arc::new),
                    None => state.layout.clone(),
                };
                if let (Some(layout), Some(c)) = (layout, d.get_mut("controller")) {
                    crate::remote::layout::label(c, &layout);
                }
            }
        }
        let mut message = json!({
            "t": crate::seconds(snap.t),
            "role": state.role,
            "state": shown,
            "links": link_stats,
            "frames": frames,
            "events": events,
            "skipped_frames": dropped + monitor.cut,
            "frames_total": total,
            "lateness": lateness.map(|(p99, max)| json!({ "p99_us": p99, "max_us": max })),
            "stream_clients": state.hub.clients.load(Ordering::Relaxed),
        });
        if state.role == PanelRole::Supervise {
            let ids = snap
                .devices
                .iter()
                .flat_map(|d| d.loops.iter().map(|l| l.id));
            message["switches"] = outputs::written_json(&state.written, ids);
        }
        state.hub.publish(message.to_string(), snap.trend());
    }
}

/// A module's feed with no page (`Panel::unserved`): the producer alone,
/// until the session ends.
pub async fn feed(state: AppState) {
    if let Backend::Engine(engine) = state.backend.clone() {
        produce(state, engine).await;
    }
}

/// The client panel's producer: its connection's state instead of an engine's.
async fn produce_remote(state: AppState, remote: Arc<Remote>) {
    let mut interval = tokio::time::interval(Duration::from_secs_f64(1.0 / state.rate_hz));
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut monitor = Monitor::new(state.role);
    loop {
        interval.tick().await;
        let (snapshot, trend) = crate::remote::message_state(&remote);
        let t = remote.now();
        let (frames, events, _) = monitor.take(&state.hub);
        let (dropped, total) = state.hub.frame_counts();
        let connected = usize::from(snapshot["connection"]["connected"] == true);
        let link_stats = monitor.links(std::iter::once((crate::remote::LINK, connected)), t);
        let message = json!({
            "t": crate::seconds(t),
            "role": state.role,
            "state": snapshot,
            "links": link_stats,
            "frames": frames,
            "events": events,
            "skipped_frames": dropped + monitor.cut,
            "frames_total": total,
            "lateness": null,
            "stream_clients": state.hub.clients.load(Ordering::Relaxed),
        });
        state.hub.publish(message.to_string(), trend);
    }
}

/// The session has ended.
struct Gone;

/// Reads the engine; `Ok(None)` if it did not answer this time.
async fn read_snapshot(engine: &Mutex<Sender<Inbound>>) -> Result<Option<EngineSnapshot>, Gone> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    let sent = engine
        .lock()
        .map_err(|_| Gone)?
        .send(Inbound::Command(Box::new(move |e| {
            let _ = tx.send(snapshot::read(e));
        })));
    if sent.is_err() {
        return Err(Gone);
    }
    match tokio::time::timeout(Duration::from_millis(500), rx).await {
        Ok(Ok(s)) => Ok(Some(s)),
        Ok(Err(_)) => Err(Gone),
        Err(_) => Ok(None),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_page_names_its_module_and_role() {
        let p = Page::new(PanelRole::Supervise, Some("student07"), 8107);
        assert!(
            p.html
                .contains("<title>student07 · supervisor (twin supervise) — EV lab twin</title>"),
            "the title is replaced in index.html"
        );
        assert!(p.html.contains(
            "<h1><span id=\"module\">student07</span> <span id=\"role\">supervisor (twin supervise)</span></h1>"
        ));
        assert!(
            p.needs_token
                .contains("The panel of student07 needs its token")
        );
        let alone = Page::new(PanelRole::Client, None, 8080);
        assert!(
            alone
                .html
                .contains("<title>client (twin panel) — EV lab twin</title>")
        );
        assert!(
            alone
                .html
                .contains("<h1>EV lab twin <span id=\"role\">client (twin panel)</span></h1>")
        );
    }

    #[test]
    fn a_panel_reads_its_own_cookie_only() {
        let p = Page::new(PanelRole::Serve, Some("student02"), 8102);
        assert_eq!(p.cookie, "twin_panel_token_8102");
        let request = |cookie: &str| {
            Request::builder()
                .uri("/api/state")
                .header(header::COOKIE, cookie)
                .body(axum::body::Body::empty())
                .unwrap()
        };
        let both = request("twin_panel_token_8101=one; twin_panel_token_8102=two");
        assert_eq!(token_of(&both, &p.cookie).as_deref(), Some("two"));
        assert_eq!(
            token_of(&both, "twin_panel_token_8101").as_deref(),
            Some("one")
        );
        // A name that only starts like the panel's is another panel's.
        let longer = request("twin_panel_token_81020=three");
        assert_eq!(token_of(&longer, &p.cookie), None);
        // The one name every panel shared before is no panel's now.
        let shared = request("twin_panel_token=four");
        assert_eq!(token_of(&shared, &p.cookie), None);
    }
}
