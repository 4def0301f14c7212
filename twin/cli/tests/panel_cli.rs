//! `--web` as a user runs it: the real binary prints the panel's URL (with
//! its token off the loopback), refuses requests without it, and on `twin
//! supervise` the panel's set point and step button drive the real loop
//! against `twin serve` over a `twin vsp` pair. (The page itself is tested
//! in a real browser in twin/panel/tests/browser.rs.)

#![allow(
    clippy::disallowed_methods,
    reason = "the test drives real processes, ports and sockets in real time"
)]

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

mod support;
use support::Proc;

/// The URL printed on the `panel:` line.
fn panel_url(proc: &Proc) -> String {
    let out = proc.output();
    let line = out
        .lines()
        .find_map(|l| l.strip_prefix("panel: "))
        .unwrap_or_else(|| panic!("no panel line printed: {out}"));
    line.split_whitespace().next().unwrap().to_string()
}

/// HOST:PORT and token of a panel URL.
fn parts(url: &str) -> (String, Option<String>) {
    let rest = url.strip_prefix("http://").expect("an http URL");
    let (host, path) = rest.split_once('/').unwrap();
    (
        host.to_string(),
        path.split_once("token=").map(|(_, t)| t.to_string()),
    )
}

fn http(host: &str, method: &str, path: &str, token: Option<&str>, body: &str) -> (u16, String) {
    let mut s = TcpStream::connect(host).expect("the panel answers");
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let auth = token
        .map(|t| format!("Authorization: Bearer {t}\r\n"))
        .unwrap_or_default();
    let request = format!(
        "{method} {path} HTTP/1.1\r\nHost: panel\r\n{auth}Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(request.as_bytes()).unwrap();
    let mut response = String::new();
    let _ = s.read_to_string(&mut response);
    let status = response
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (status, body)
}

#[test]
fn serve_off_the_loopback_prints_a_token_url_and_refuses_requests_without_it() {
    let dir = std::env::temp_dir().join(format!("twin-{}-panel-token", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let token_file = dir.join("token");
    let mut tokens = Vec::new();
    for _ in 0..2 {
        let serve = Proc::start(&[
            "serve",
            "--meb",
            "tcp://127.0.0.1:0",
            "--web",
            "0.0.0.0:0",
            "--web-token-file",
            token_file.to_str().unwrap(),
            "--quiet",
            "--no-record",
            "--status-every",
            "0",
        ]);
        let url = panel_url(&serve);
        let (host, token) = parts(&url);
        let token = token.unwrap_or_else(|| panic!("no token in {url}"));
        let (status, body) = http(&host, "GET", "/api/state", None, "");
        assert_eq!(status, 401, "{body}");
        let (status, _) = http(&host, "POST", "/api/fault", None, r#"{"fault":"no-reply"}"#);
        assert_eq!(status, 401);
        let (status, body) = http(&host, "GET", "/api/state", Some(&token), "");
        assert_eq!(status, 200, "{body}");
        assert!(
            body.contains("\"fault\":null"),
            "the refused fault changed nothing"
        );
        tokens.push(token);
        serve.terminate();
    }
    assert_eq!(
        tokens[0], tokens[1],
        "--web-token-file keeps the token across restarts"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The first loop of the supervisor's state.
fn first_loop(host: &str) -> serde_json::Value {
    let (_, body) = http(host, "GET", "/api/state", None, "");
    let state: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
    state["state"]["devices"][0]["loops"][0].clone()
}

#[test]
fn supervise_panel_moves_the_set_point_and_steps_the_loop() {
    let base = std::env::temp_dir().join(format!("twin-{}-panel", std::process::id()));
    let (a, b) = (base.with_extension("V0"), base.with_extension("V1"));
    let _vsp = Proc::start(&["vsp", a.to_str().unwrap(), b.to_str().unwrap()]);
    let _serve = Proc::start(&[
        "serve",
        "--meb",
        b.to_str().unwrap(),
        "--adaptive-light",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let supervise = Proc::start(&[
        "supervise",
        "--meb",
        a.to_str().unwrap(),
        "--no-server",
        "--web",
        "127.0.0.1:0",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let (host, token) = parts(&panel_url(&supervise));
    assert!(token.is_none(), "a loopback panel needs no token");
    let (status, body) = http(
        &host,
        "POST",
        "/api/loop",
        None,
        r#"{"set_point_rpm":2000}"#,
    );
    assert_eq!(status, 200, "{body}");
    // The wheel settles within 3 % of 2000 rpm, and stays there for a second.
    let start = Instant::now();
    let mut inside_since: Option<Instant> = None;
    loop {
        let l = first_loop(&host);
        let rpm = l["measured_rpm"].as_f64().unwrap_or(0.0);
        if (rpm - 2000.0).abs() <= 60.0 {
            let since = *inside_since.get_or_insert_with(Instant::now);
            if since.elapsed() > Duration::from_secs(1) {
                break;
            }
        } else {
            inside_since = None;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "the wheel did not settle at 2000 rpm: {l}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // A bad value is refused by name and changes nothing.
    let (status, body) = http(&host, "POST", "/api/loop", None, r#"{"set_point_rpm":-5}"#);
    assert_eq!(status, 422, "{body}");
    assert!(body.contains("set_point_rpm"), "{body}");
    assert_eq!(first_loop(&host)["set_point_rpm"], 2000.0);
    // The step button: 2000 -> 1200 rpm, figures as `twin step` gives them.
    let (status, body) = http(
        &host,
        "POST",
        "/api/step",
        None,
        r#"{"to_rpm":1200,"seconds":5}"#,
    );
    assert_eq!(status, 200, "{body}");
    let step: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(step["from_rpm"], 2000.0);
    let hall = &step["signals"]["hall rpm"]["metrics"];
    let final_rpm = hall["final_value"].as_f64().unwrap_or(0.0);
    assert!(
        (final_rpm - 1200.0).abs() < 36.0,
        "hall settles at 1200 rpm: {step}"
    );
    assert!(
        hall["settling_time_s"]
            .as_f64()
            .is_some_and(|s| s > 0.0 && s < 5.0),
        "{step}"
    );
    assert!(
        hall["overshoot_pct"]
            .as_f64()
            .is_some_and(|o| (0.0..100.0).contains(&o)),
        "{step}"
    );
    supervise.terminate();
}

#[test]
fn each_module_of_a_class_has_its_own_panel_and_token() {
    let dir = std::env::temp_dir().join(format!("twin-{}-panel-class", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let mut config = format!(
        "quiet = true\nstatus-every = 0\nrecord-dir = \"{}\"\n",
        dir.display()
    );
    for n in 1..=2 {
        config.push_str(&format!(
            "\n[[module]]\nname = \"student{n:02}\"\nmeb = [\"tcp://127.0.0.1:0\"]\nweb = \"127.0.0.1:0\"\nweb-token-file = \"{}\"\n",
            dir.join(format!("student{n:02}.token")).display()
        ));
    }
    let path = dir.join("class.toml");
    std::fs::write(&path, config).unwrap();
    let server = Proc::start(&["serve", "--config", path.to_str().unwrap()]);
    // `  panel: URL NAME`, one per module, before `ready`.
    let panels: Vec<(String, String)> = server
        .links()
        .into_iter()
        .filter(|l| l.first().map(String::as_str) == Some("panel:"))
        .map(|l| (l[2].clone(), l[1].clone()))
        .collect();
    assert_eq!(panels.len(), 2, "{}", server.output());
    let (host1, token1) = parts(&panels[0].1);
    let (host2, token2) = parts(&panels[1].1);
    let (token1, token2) = (token1.unwrap(), token2.unwrap());
    assert_ne!(host1, host2, "two panels, two ports");
    assert_ne!(token1, token2, "each module its own token");
    for (name, host, own, other) in [
        (&panels[0].0, &host1, &token1, &token2),
        (&panels[1].0, &host2, &token2, &token1),
    ] {
        let saved = std::fs::read_to_string(dir.join(format!("{name}.token"))).unwrap();
        assert_eq!(saved.trim(), own.as_str(), "{name}'s token file");
        let (status, body) = http(host, "GET", "/api/state", Some(own), "");
        assert_eq!(status, 200, "{name}: {body}");
        let (status, _) = http(host, "GET", "/api/state", Some(other), "");
        assert_eq!(
            status, 401,
            "{name}'s panel refuses the other module's token"
        );
    }
    server.terminate();
    let _ = std::fs::remove_dir_all(&dir);
}
