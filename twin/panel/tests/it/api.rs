//! The panel's API on a real `twin serve` session: access rules, commands
//! and their refusals, many stream clients at once.

use crate::common;

use common::{ClientAddr, http, serve, wait_for};
use std::io::Write;
use std::time::{Duration, Instant};
use twin_panel::AccessOptions;

fn state(session: &common::Session) -> serde_json::Value {
    let (_, body) = http(&session.panel, "GET", "/api/state", None, true);
    serde_json::from_str(&body).expect("the state is JSON")
}

fn forced_v1(session: &common::Session) -> serde_json::Value {
    state(session)["state"]["devices"][0]["controller"]["forced"]["v1"].clone()
}

#[test]
fn a_panel_off_the_loopback_needs_its_token_and_refuses_without_changing_anything() {
    let session = serve("0.0.0.0:0", AccessOptions::default(), 30.0);
    let token = common::token_of(&session.panel).expect("a token in the URL printed");
    assert!(
        session.panel.url.contains("/?token="),
        "{}",
        session.panel.url
    );
    assert!(token.len() >= 32);
    for path in ["/", "/api/state", "/api/info", "/api/stream", "/panel.js"] {
        let (status, body) = http(&session.panel, "GET", path, None, false);
        assert_eq!(status, 401, "{path} without the token: {body}");
        assert!(body.contains("token"), "{body}");
    }
    let (status, _) = http(
        &session.panel,
        "POST",
        "/api/force",
        Some(r#"{"input":"v1","value":12}"#),
        false,
    );
    assert_eq!(status, 401);
    let (status, _) = http(
        &session.panel,
        "GET",
        &format!("/?token={}x", token),
        None,
        false,
    );
    assert_eq!(status, 401, "a wrong token");
    std::thread::sleep(Duration::from_millis(200));
    assert!(
        forced_v1(&session).is_null(),
        "a refused command changed nothing"
    );
    let (status, page) = http(
        &session.panel,
        "GET",
        &format!("/?token={token}"),
        None,
        false,
    );
    assert_eq!(status, 200);
    assert!(page.contains("panel.js"));
    let (status, _) = http(
        &session.panel,
        "POST",
        "/api/force",
        Some(r#"{"input":"v1","value":12}"#),
        true,
    );
    assert_eq!(status, 200);
    wait_for(Duration::from_secs(3), "v1 forced", || {
        forced_v1(&session) == 12.0
    });
}

#[test]
fn bad_commands_get_a_4xx_naming_the_field_and_change_nothing() {
    let session = serve("127.0.0.1:0", AccessOptions::default(), 30.0);
    for (body, status, field) in [
        (r#"{"input":"v1","value":1e9}"#, 422, Some("value")),
        (r#"{"input":"vel","value":1}"#, 422, Some("input")),
        (r#"{"input":"v1"}"#, 422, Some("value")),
        (r#"{"input":"v1","value":"high"}"#, 422, Some("value")),
        (r#"{"input":"v1","value":3,"extra":1}"#, 422, Some("extra")),
        ("{not json", 400, None),
        ("[1,2]", 400, None),
    ] {
        let (got, answer) = http(&session.panel, "POST", "/api/force", Some(body), true);
        assert_eq!(got, status, "{body}: {answer}");
        let answer: serde_json::Value = serde_json::from_str(&answer).expect("a JSON refusal");
        let message = answer["error"].as_str().unwrap_or_default();
        match field {
            Some(f) => {
                assert_eq!(answer["field"], f, "{body}: {answer}");
                assert!(message.starts_with(f), "{message}");
            }
            None => assert!(!message.is_empty()),
        }
    }
    let (got, answer) = http(
        &session.panel,
        "POST",
        "/api/fault",
        Some(r#"{"fault":"bad-check","link":"rs485"}"#),
        true,
    );
    assert_eq!(got, 404, "{answer}");
    assert!(
        answer.contains("no link `rs485`") && answer.contains("meb"),
        "{answer}"
    );
    let (got, answer) = http(
        &session.panel,
        "POST",
        "/api/fault",
        Some(r#"{"fault":"smoke"}"#),
        true,
    );
    assert_eq!(got, 422, "{answer}");
    let (got, _) = http(
        &session.panel,
        "POST",
        "/api/loop",
        Some(r#"{"set_point_rpm":1000}"#),
        true,
    );
    assert_eq!(got, 409, "a set point on a session with no supervisor");
    std::thread::sleep(Duration::from_millis(200));
    let now = state(&session);
    assert!(
        now["state"]["fault"].is_null(),
        "no fault switched on: {}",
        now["state"]["fault"]
    );
    assert!(forced_v1(&session).is_null());
}

#[test]
fn a_read_only_panel_shows_and_changes_nothing() {
    let session = serve(
        "127.0.0.1:0",
        AccessOptions {
            token_file: None,
            read_only: true,
        },
        30.0,
    );
    let (status, info) = http(&session.panel, "GET", "/api/info", None, true);
    assert_eq!(status, 200);
    assert!(info.contains("\"read_only\":true"), "{info}");
    let (status, body) = http(
        &session.panel,
        "POST",
        "/api/fault",
        Some(r#"{"fault":"no-reply"}"#),
        true,
    );
    assert_eq!(status, 403, "{body}");
    assert!(state(&session)["state"]["fault"].is_null());
}

#[test]
fn thirty_stream_clients_are_all_served() {
    let session = serve("127.0.0.1:0", AccessOptions::default(), 30.0);
    let addr = session.panel.addr_for_clients();
    let clients: Vec<_> = (0..30)
        .map(|_| std::thread::spawn(move || common::stream_updates(addr, 3.0)))
        .collect();
    wait_for(Duration::from_secs(5), "30 stream clients counted", || {
        state(&session)["stream_clients"].as_u64() == Some(30)
    });
    let counts: Vec<usize> = clients.into_iter().map(|c| c.join().unwrap()).collect();
    // 20 updates a second for 3 s; every client got a steady share of them.
    for (i, n) in counts.iter().enumerate() {
        assert!(
            *n >= 20,
            "client {i} got only {n} updates in 3 s: {counts:?}"
        );
    }
    wait_for(Duration::from_secs(5), "the clients counted out", || {
        state(&session)["stream_clients"].as_u64() == Some(0)
    });
}

/// Session times in the API are whole microseconds (`1.522848`), never a
/// float's last digits (`1.5228476739999999`): in the state, its frames
/// and the trend.
#[test]
fn session_times_are_whole_microseconds() {
    let session = serve("127.0.0.1:0", AccessOptions::default(), 30.0);
    let decimals = |v: &serde_json::Value| {
        let text = v.to_string();
        text.split_once('.').map_or(0, |(_, d)| d.len())
    };
    let mut checked = 0;
    let deadline = Instant::now() + Duration::from_secs(10);
    while checked < 20 && Instant::now() < deadline {
        let s = state(&session);
        if s["t"].as_f64().is_some_and(|t| t > 0.0) {
            assert!(decimals(&s["t"]) <= 6, "state t {}", s["t"]);
            checked += 1;
        }
        std::thread::sleep(Duration::from_millis(60));
    }
    assert!(checked >= 20, "the state carries its time");
    let (_, body) = http(&session.panel, "GET", "/api/trend", None, true);
    let trend: serde_json::Value = serde_json::from_str(&body).expect("the trend is JSON");
    let rows = trend["rows"].as_array().expect("rows");
    assert!(!rows.is_empty(), "{body}");
    for row in rows {
        assert!(decimals(&row[0]) <= 6, "trend t {}", row[0]);
    }
}

/// A person who opens the panel in a browser without its token reads a page
/// that says what to do, not raw JSON; a program still gets JSON.
#[test]
fn a_browser_without_the_token_gets_a_page_in_words() {
    let session = serve("0.0.0.0:0", AccessOptions::default(), 30.0);
    let url = |path: &str| format!("http://{}{path}", session.panel.addr_for_clients());
    let page = common::agent()
        .get(url("/"))
        .header("Accept", "text/html,application/xhtml+xml")
        .call()
        .unwrap();
    assert_eq!(page.status(), 401);
    let kind = header(&page, "content-type");
    assert!(kind.contains("text/html"), "{kind}");
    let page = page.into_body().read_to_string().unwrap();
    assert!(
        page.contains("<h1>This panel needs its token</h1>"),
        "{page}"
    );
    assert!(!page.contains("{\"error\""), "{page}");
    let (status, body) = http(&session.panel, "GET", "/api/state", None, false);
    assert_eq!(status, 401);
    assert!(
        body.starts_with("{\"error\""),
        "a program gets JSON: {body}"
    );
    // The token from the URL is kept in the panel's own cookie, named after
    // its port, and a reload without the query is let in by that cookie only.
    let token = common::token_of(&session.panel).unwrap();
    let cookie = format!(
        "twin_panel_token_{}",
        session.panel.addr_for_clients().port()
    );
    let first = common::agent()
        .get(url(&format!("/api/info?token={token}")))
        .call()
        .unwrap();
    assert_eq!(first.status(), 200);
    let set = header(&first, "set-cookie").to_ascii_lowercase();
    assert!(
        set.starts_with(&format!("{cookie}={token}; path=/; httponly")),
        "{set}"
    );
    for (name, status) in [(cookie.as_str(), 200), ("twin_panel_token", 401)] {
        let again = common::agent()
            .get(url("/api/info"))
            .header("Cookie", format!("{name}={token}"))
            .call()
            .unwrap();
        assert_eq!(again.status(), status, "cookie {name}");
    }
}

/// `/api/info` asked with `query` after `?` and the given headers: its status.
fn info_status(session: &common::Session, query: &str, headers: &[(&str, String)]) -> u16 {
    let addr = session.panel.addr_for_clients();
    let mut request = common::agent().get(format!("http://{addr}/api/info?{query}"));
    for (name, value) in headers {
        request = request.header(*name, value);
    }
    request.call().unwrap().status().as_u16()
}

/// A token in the query may come percent-encoded (as a link in a mail or a
/// page may carry it): it opens the panel decoded. And where a request
/// carries it more than one way, the query wins over the header, the
/// header over the cookie, wrong or right.
#[test]
fn a_percent_encoded_token_in_the_query_opens_the_panel() {
    let session = serve("0.0.0.0:0", AccessOptions::default(), 30.0);
    let token = common::token_of(&session.panel).unwrap();
    let encoded: String = token.bytes().map(|b| format!("%{b:02X}")).collect();
    assert_eq!(info_status(&session, &format!("token={encoded}"), &[]), 200);
    // Among other parameters, and the cookie it sets holds it decoded.
    let addr = session.panel.addr_for_clients();
    let answer = common::agent()
        .get(format!("http://{addr}/api/info?x=1&token={encoded}&y=%20"))
        .call()
        .unwrap();
    assert_eq!(answer.status(), 200);
    let set = header(&answer, "set-cookie");
    assert!(set.contains(&format!("={token};")), "{set}");
    assert_eq!(
        info_status(&session, &format!("token={encoded}%30"), &[]),
        401,
        "one character more, encoded, is another token"
    );
    let cookie = format!("twin_panel_token_{}={token}", addr.port());
    let bearer = |t: &str| ("Authorization", format!("Bearer {t}"));
    for (query, headers, status, why) in [
        (
            format!("token={token}"),
            vec![bearer("wrong")],
            200,
            "the query wins over the header",
        ),
        (
            "token=wrong".into(),
            vec![bearer(&token)],
            401,
            "the query wins, wrong too",
        ),
        (
            String::new(),
            vec![bearer(&token), ("Cookie", "x=1".into())],
            200,
            "the header alone",
        ),
        (
            String::new(),
            vec![bearer("wrong"), ("Cookie", cookie.clone())],
            401,
            "the header wins over the cookie",
        ),
        (
            String::new(),
            vec![("Cookie", cookie.clone())],
            200,
            "the cookie alone",
        ),
    ] {
        assert_eq!(info_status(&session, &query, &headers), status, "{why}");
    }
}

/// A browser sends every cookie of the host in one header: a class's
/// panels on one server each find their own among the others' and a
/// stranger's, in any order; another panel's cookie is never taken.
#[test]
fn two_cookies_in_one_header_each_panel_takes_its_own() {
    let session = serve("0.0.0.0:0", AccessOptions::default(), 30.0);
    let token = common::token_of(&session.panel).unwrap();
    let port = session.panel.addr_for_clients().port();
    let other = port.wrapping_add(1);
    let cookie = |header: String| vec![("Cookie", header)];
    for (header, status) in [
        (
            format!("twin_panel_token_{other}=wrong; twin_panel_token_{port}={token}"),
            200,
        ),
        (
            format!("twin_panel_token_{port}={token}; twin_panel_token_{other}=wrong"),
            200,
        ),
        (format!("theme=dark;twin_panel_token_{port}={token}"), 200),
        // The right token under another panel's name, or a longer name.
        (
            format!("twin_panel_token_{other}={token}; twin_panel_token_{port}0={token}"),
            401,
        ),
    ] {
        assert_eq!(
            info_status(&session, "", &cookie(header.clone())),
            status,
            "{header}"
        );
    }
}

/// A header of `answer`, as text (empty when it has none).
fn header(answer: &ureq::http::Response<ureq::Body>, name: &str) -> String {
    answer
        .headers()
        .get(name)
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default()
        .to_string()
}

/// One MEB exchange on `link` (`tcp://HOST:PORT`): read EA 0..6 from slave
/// 1; every byte that comes within a second of the request.
fn meb_exchange(link: &str) -> Vec<u8> {
    use std::io::Read;
    let addr = common::host_port(link);
    let mut s = std::net::TcpStream::connect(addr).expect("connects");
    s.set_nodelay(true).unwrap();
    let mut request = [0u8; 32];
    let n = protocols::meb::MebRepr {
        id: 1,
        cmd: protocols::meb::MebCmd::EA,
        addr: 0,
        cnt: 6,
        data: protocols::meb::MebWords::new(),
    }
    .emit(&mut request)
    .unwrap();
    s.write_all(&request[..n]).unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 256];
    let deadline = Instant::now() + Duration::from_secs(3);
    // 13 bytes and 4 per word, and whatever junk came with them.
    while got.len() < 37 + 2 && Instant::now() < deadline {
        s.set_read_timeout(Some(Duration::from_secs(1))).unwrap();
        match s.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => got.extend_from_slice(&buf[..n]),
        }
    }
    got
}

#[test]
fn the_new_fault_kinds_switch_on_from_the_api_and_reach_a_client() {
    use protocols::meb::MebRepr;
    let session = serve("127.0.0.1:0", AccessOptions::default(), 60.0);
    let post = |body: &str| http(&session.panel, "POST", "/api/fault", Some(body), true);
    // The state is published a period after the command: waited for.
    let shows = |text: &str| {
        wait_for(Duration::from_secs(10), text, || {
            state(&session)["state"]["fault"]["fault"] == text
        })
    };

    let (got, answer) = post(r#"{"fault":"wrong-id","id":7,"link":"meb"}"#);
    assert_eq!(got, 200, "{answer}");
    shows("wrong-id (replies as id 7)");
    let reply = meb_exchange(&session.meb);
    let repr = MebRepr::parse(&reply).unwrap_or_else(|e| panic!("{e}: {reply:02x?}"));
    assert_eq!(repr.id, 7, "a well-formed reply from slave 7");

    let (got, answer) = post(r#"{"fault":"junk","junk_hex":"00ff","junk_place":"before"}"#);
    assert_eq!(got, 200, "{answer}");
    shows("junk 00 ff before each reply");
    let reply = meb_exchange(&session.meb);
    assert_eq!(reply[..2], [0x00, 0xff], "{reply:02x?}");
    assert_eq!(MebRepr::parse(&reply[2..]).unwrap().id, 1);

    let (got, answer) = post(r#"{"fault":"split","gap_ms":20}"#);
    assert_eq!(got, 200, "{answer}");
    shows("split (replies in two writes, 20.0 ms apart)");
    let reply = meb_exchange(&session.meb);
    assert_eq!(
        MebRepr::parse(&reply).unwrap().id,
        1,
        "whole once both came"
    );

    for (body, field) in [
        (r#"{"fault":"split"}"#, "gap_ms"),
        (r#"{"fault":"junk","junk_hex":"0g"}"#, "junk_hex"),
        (
            r#"{"fault":"junk","junk_hex":"00","junk_count":2}"#,
            "junk_hex",
        ),
        (
            r#"{"fault":"junk","junk_count":2,"junk_place":"inside"}"#,
            "junk_place",
        ),
        (r#"{"fault":"wrong-id","id":400}"#, "id"),
    ] {
        let (got, answer) = post(body);
        assert_eq!(got, 422, "{body}: {answer}");
        let answer: serde_json::Value = serde_json::from_str(&answer).unwrap();
        assert_eq!(answer["field"], field, "{body}: {answer}");
    }
    let (got, _) = post(r#"{"fault":"off"}"#);
    assert_eq!(got, 200);
    wait_for(Duration::from_secs(10), "the fault off", || {
        state(&session)["state"]["fault"].is_null()
    });
}
