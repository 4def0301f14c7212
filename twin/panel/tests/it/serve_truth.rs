//! The serve page says what is true: the fixed light detector's limit when
//! light rpm reads 0 at speed, the power-up outputs that light FR and CCW
//! while the wheel stands, a refused force said beside its control, and
//! the exception code chosen on the page.

use crate::common::{Session, chromedriver, http, serve_with};
use crate::page::{click, frame_rows, js, open, runtime, text, until};
use fantoccini::Locator;
use fantoccini::key::Key;
use nodes::firmware::sd;
use protocols::meb::MebCmd;
use serde_json::Value;
use std::time::Duration;
use twin_panel::AccessOptions;
use twin_realtime::client::MebClient;

const LIMIT: Duration = Duration::from_secs(30);

fn state(session: &Session) -> Value {
    let (_, body) = http(&session.panel, "GET", "/api/state", None, true);
    serde_json::from_str(&body).unwrap_or_default()
}

#[test]
fn the_serve_page_explains_light_power_up_refusals_and_exceptions() {
    // The fixed detector, whatever `twin serve`'s default.
    let serve = serve_with(
        "tcp://127.0.0.1:0",
        "127.0.0.1:0",
        AccessOptions::default(),
        120.0,
        false,
    );
    let driver = chromedriver();
    runtime().block_on(async {
        let c = open(&driver, "serve-truth", &serve.panel.url).await;

        // Power-up: FR on and CCW lit while the wheel stands, explained.
        until("the power-up note", LIMIT, async || {
            let note = text(&c, "#powerup-note").await;
            (
                note.contains("0x001F") && note.contains("reverse"),
                format!("`{note}`"),
            )
        })
        .await;
        let ccw = text(&c, "#flag-ccw").await;
        assert!(ccw.contains("CCW"), "the CCW lamp at power-up: `{ccw}`");

        // A master drives the wheel well past the fixed detector's limit.
        let mut master = MebClient::connect(&serve.meb, Duration::from_secs(2)).unwrap();
        let forward_enabled = sd::BRK | sd::PRO | sd::DES; // EN on (low), FR forward (low)
        master.write(1, MebCmd::SD, 0, &[forward_enabled]).unwrap();
        master.write(1, MebCmd::SA, 0, &[3000]).unwrap();
        until(
            "the light note at speed",
            Duration::from_secs(40),
            async || {
                let note = text(&c, "#light-note").await;
                let warn = js(
                    &c,
                    "document.getElementById('light-note').classList.contains('warn')",
                )
                .await;
                let light = text(&c, "#g-light .num").await;
                (
                    warn == true
                        && note.contains("sees the flag only up to")
                        && note.contains("reads 0"),
                    format!("light rpm {light}, note `{note}`"),
                )
            },
        )
        .await;
        let power_up = js(
            &c,
            "document.getElementById('powerup-note').classList.contains('hidden')",
        )
        .await;
        assert_eq!(
            power_up, true,
            "the power-up note stays once a master wrote SD0"
        );

        // 500 V forced: refused beside V1's control, with the range, in a live region.
        // Typed over as a person does (WebDriver's clear leaves the box,
        // and the page refills a box no one is in with the value in force).
        let value = c.find(Locator::Css("#value-v1")).await.unwrap();
        let type_over = async |text: &str| {
            value.click().await.unwrap();
            value.send_keys(&(Key::Control + "a")).await.unwrap();
            value.send_keys(&Key::Backspace).await.unwrap();
            value.send_keys(text).await.unwrap();
        };
        type_over("500").await;
        click(&c, "#force-v1").await;
        until("the refusal beside V1's control", LIMIT, async || {
            let said = text(&c, "#refusal-in-v1").await;
            (
                said.contains("500") && said.contains("0 to 100 V"),
                format!("`{said}`"),
            )
        })
        .await;
        let live = js(
            &c,
            "document.getElementById('refusal-in-v1').getAttribute('aria-live')",
        )
        .await;
        assert_eq!(live, "assertive", "refusals are an ARIA live region");
        assert_eq!(
            state(&serve)["state"]["devices"][0]["controller"]["forced"]["v1"],
            Value::Null
        );
        // A good force clears the refusal.
        type_over("30").await;
        click(&c, "#force-v1").await;
        until("the refusal cleared", LIMIT, async || {
            let said = text(&c, "#refusal-in-v1").await;
            let forced = state(&serve)["state"]["devices"][0]["controller"]["forced"]["v1"].clone();
            (
                said.is_empty() && forced == 30.0,
                format!("`{said}`, forced {forced}"),
            )
        })
        .await;

        // The exception code chosen on the page is the one in force.
        let (_, _) = http(
            &serve.panel,
            "POST",
            "/api/fault",
            Some(r#"{"fault":"exception","link":"meb","code":2}"#),
            true,
        );
        // The state is a snapshot made a few times a second: wait for it.
        let mut code_two = Value::Null;
        until("exception 02 set through the API", LIMIT, async || {
            code_two = state(&serve)["state"]["fault"]["fault"].clone();
            (!code_two.is_null(), format!("{code_two}"))
        })
        .await;
        let (_, _) = http(
            &serve.panel,
            "POST",
            "/api/fault",
            Some(r#"{"fault":"off"}"#),
            true,
        );
        c.find(Locator::Css("#fault-code-meb"))
            .await
            .unwrap()
            .select_by_value("2")
            .await
            .unwrap();
        click(&c, "#fault-exception-meb").await;
        until("exception 02 in force", LIMIT, async || {
            let fault = state(&serve)["state"]["fault"]["fault"].clone();
            (fault == code_two, format!("{fault}, wanted {code_two}"))
        })
        .await;
        c.close().await.unwrap();
    });
}

fn meb_frame(body: &str) -> Vec<u8> {
    let fcs = body.bytes().fold(0u8, |x, b| x ^ b);
    format!("{body}{fcs:02X}*\n").into_bytes()
}

/// Two clients ask at once, their replies held back 100 ms by a delay
/// fault so that both requests are in before either reply goes out: the
/// frame monitor shows each reply going to the client that asked (by the
/// connection it went out on, not the one heard last).
#[test]
fn the_serve_page_names_the_client_each_reply_goes_to() {
    use std::io::{BufRead, BufReader, Write};
    let serve = serve_with(
        "tcp://127.0.0.1:0",
        "127.0.0.1:0",
        AccessOptions::default(),
        60.0,
        false,
    );
    let (status, body) = http(
        &serve.panel,
        "POST",
        "/api/fault",
        Some(r#"{"fault": "delay", "delay_ms": 100}"#),
        true,
    );
    assert_eq!(status, 200, "{body}");
    let driver = chromedriver();
    runtime().block_on(async {
        let c = open(&driver, "serve-parties", &serve.panel.url).await;
        // The monitor shows what comes after the page opens.
        until("the stream", LIMIT, async || {
            let note = text(&c, "#powerup-note").await;
            (note.contains("0x001F"), format!("`{note}`"))
        })
        .await;
        let addr = crate::common::host_port(&serve.meb).to_string();
        let connect = || {
            let s = std::net::TcpStream::connect(&addr).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
            s
        };
        let (mut first, mut second) = (connect(), connect());
        // One word for the first, two for the second: their replies differ.
        first.write_all(&meb_frame("@01EA0001")).unwrap();
        second.write_all(&meb_frame("@01EA0002")).unwrap();
        let reply = |s: &std::net::TcpStream| {
            let mut line = String::new();
            BufReader::new(s).read_line(&mut line).unwrap();
            line.trim_end().to_string()
        };
        let (to_first, to_second) = (reply(&first), reply(&second));
        assert_ne!(to_first, to_second);
        until("both exchanges named", LIMIT, async || {
            let rows = frame_rows(&c).await;
            let sender = |body: &str| {
                let request = String::from_utf8(meb_frame(body)).unwrap_or_default();
                rows.iter()
                    .find(|(_, f)| f == request.trim_end())
                    .and_then(|(d, _)| d.strip_suffix(" → twin"))
                    .map(str::to_string)
            };
            let receiver = |text: &str| {
                rows.iter()
                    .find(|(_, f)| f == text)
                    .and_then(|(d, _)| d.strip_prefix("twin → "))
                    .map(str::to_string)
            };
            let pairs = [
                (sender("@01EA0001"), receiver(&to_first)),
                (sender("@01EA0002"), receiver(&to_second)),
            ];
            let ok = pairs
                .iter()
                .all(|(asked, answered)| asked.is_some() && asked == answered)
                && pairs[0].0 != pairs[1].0;
            (ok, format!("{pairs:?} in {rows:?}"))
        })
        .await;
        c.close().await.unwrap();
    });
}
