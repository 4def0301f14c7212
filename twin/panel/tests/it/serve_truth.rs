//! The serve page says what is true: the fixed light detector's limit when
//! light rpm reads 0 at speed, the power-up outputs that light FR and CCW
//! while the wheel stands, a refused force said beside its control, and
//! the exception code chosen on the page.

use crate::common::{Session, chromedriver, http, serve_with};
use crate::page::{click, js, open, runtime, text, until};
use fantoccini::Locator;
use fantoccini::key::Key;
use nodes::firmware::sd;
use nodes::proto::meb::MebCmd;
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
