//! The serve page as the M3CVME tool's simulator: every input set with a
//! graphic element (a slider for each analog input, a select for the hall
//! code, switches for the flag and the driver fault), and the device
//! number and I/O map chosen on the page. Each is checked where a master
//! sees it: a real MEB client on the module's link.

use crate::common::{Session, chromedriver, http, serve};
use crate::page::{click, open, runtime, text, until};
use fantoccini::key::Key;
use fantoccini::{Client, Locator};
use nodes::firmware::status;
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

/// `CNT` words of block `cmd` from `ADDR`, read by slave `id` on a new
/// connection (`None`: no answer within `wait`).
fn read(meb: &str, id: u8, cmd: MebCmd, addr: u8, cnt: u8, wait: Duration) -> Option<Vec<u16>> {
    MebClient::connect(meb, wait)
        .ok()?
        .read(id, cmd, addr, cnt)
        .ok()
}

const SHORT: Duration = Duration::from_millis(700);

async fn type_into(c: &Client, css: &str, text: &str) {
    let e = c
        .find(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no {css} on the page: {e}"));
    // As a person does it: into the box, everything selected, typed over
    // (WebDriver's clear leaves the box, and the page refills a box no
    // one is in).
    e.click().await.unwrap();
    e.send_keys(&(Key::Control + "a")).await.unwrap();
    e.send_keys(&Key::Backspace).await.unwrap();
    e.send_keys(text).await.unwrap();
}

#[test]
fn digital_inputs_and_a_slider_set_on_the_page_reach_a_client() {
    let serve = serve("127.0.0.1:0", AccessOptions::default(), 120.0);
    let meb = serve.meb.clone();
    let sensing = plant::PlantParams::preset("vemodule").unwrap().sensing;
    let driver = chromedriver();
    runtime().block_on(async {
        let c = open(&driver, "sim-inputs", &serve.panel.url).await;
        until("the input controls", LIMIT, async || {
            let n = crate::page::js(&c, "document.querySelectorAll('.input-row').length").await;
            (n == 9, format!("{n} rows"))
        })
        .await;

        // The hall code from its select: ED0 bits 0-2, as a master reads them.
        c.find(Locator::Css("#value-hall"))
            .await
            .unwrap()
            .select_by_value("5")
            .await
            .unwrap();
        until("ED0 hall code 5 read by a client", LIMIT, async || {
            let ed0 = read(&meb, 1, MebCmd::ED, 0, 1, SHORT);
            (
                ed0.as_ref().is_some_and(|w| w[0] & 0b111 == 0b101),
                format!("ED0 {ed0:?}"),
            )
        })
        .await;

        // The flag switched into the beam: ED0 bit 3 (dark), and held
        // there, even by the adaptive detector that forgets a still flag.
        click(&c, "#value-flag").await;
        until("ED0 bit 3 read by a client", LIMIT, async || {
            let ed0 = read(&meb, 1, MebCmd::ED, 0, 1, SHORT);
            (
                ed0.as_ref()
                    .is_some_and(|w| w[0] & 0b1000 != 0 && w[0] & 0b111 == 0b101),
                format!("ED0 {ed0:?}"),
            )
        })
        .await;
        tokio::time::sleep(Duration::from_secs(2)).await;
        let ed0 = read(&meb, 1, MebCmd::ED, 0, 1, Duration::from_secs(2)).unwrap();
        assert_ne!(ed0[0] & 0b1000, 0, "the flag still reads dark: {ed0:?}");
        assert_eq!(
            state(&serve)["state"]["devices"][0]["controller"]["forced"]["flag"],
            true
        );

        // The driver fault switched on: the controller trips, FD0 says
        // over-current, as the firmware latches a driver's fault.
        click(&c, "#value-driver_fault").await;
        until(
            "the over-current flag read by a client",
            LIMIT,
            async || {
                let fd0 = read(&meb, 1, MebCmd::FD, 0, 1, SHORT);
                (
                    fd0.as_ref()
                        .is_some_and(|w| w[0] & status::OVER_CURRENT != 0),
                    format!("FD0 {fd0:?}"),
                )
            },
        )
        .await;

        // Released: the hall code is the motor's own again (the wheel
        // stands; whatever code it rests on, the page says "plant").
        click(&c, "#release-flag").await;
        until("the flag released", LIMIT, async || {
            let f = state(&serve)["state"]["devices"][0]["controller"]["forced"]["flag"].clone();
            let now = text(&c, "#in-flag .now").await;
            (
                f.is_null() && now.starts_with("plant"),
                format!("{f}, `{now}`"),
            )
        })
        .await;

        // V1's slider moved by the keyboard: to its low end, then five
        // steps of 0.1 V up. A client reads V1's word for 0.5 V.
        let slider = c.find(Locator::Css("#slider-v1")).await.unwrap();
        slider.send_keys(&Key::Home).await.unwrap();
        for _ in 0..5 {
            slider.send_keys(&Key::Up).await.unwrap();
        }
        let want = sensing.counts(0.5 / sensing.battery_divider);
        until("V1 at 0.5 V read by a client", LIMIT, async || {
            let ea = read(&meb, 1, MebCmd::EA, 0, 6, SHORT);
            let forced = state(&serve)["state"]["devices"][0]["controller"]["forced"]["v1"].clone();
            (
                ea.as_ref().is_some_and(|w| w[2] == want),
                format!("EA {ea:?}, want V1 {want}; forced {forced}"),
            )
        })
        .await;
        until("the page saying what is set", LIMIT, async || {
            let shown = text(&c, "#in-v1 .now").await;
            (shown == "set: 0.50", format!("`{shown}`"))
        })
        .await;
        let unit = text(&c, "#in-v1 .unit").await;
        assert_eq!(unit, "V (0 to 100)", "unit and range beside the slider");
        c.execute(
            "document.getElementById('force-card').scrollIntoView()",
            vec![],
        )
        .await
        .unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let png = c.screenshot().await.unwrap();
        std::fs::write(
            crate::browser::screenshot_path("panel-serve-inputs.png"),
            png,
        )
        .unwrap();
        c.close().await.unwrap();
    });
}

#[test]
fn the_id_and_map_chosen_on_the_page_are_where_a_client_finds_the_module() {
    let serve = serve("127.0.0.1:0", AccessOptions::default(), 120.0);
    let meb = serve.meb.clone();
    let sensing = plant::PlantParams::preset("vemodule").unwrap().sensing;
    let driver = chromedriver();
    runtime().block_on(async {
        let c = open(&driver, "sim-slave", &serve.panel.url).await;
        until("the slave card", LIMIT, async || {
            let now = text(&c, "#slave-now").await;
            (now.contains("slave 01"), format!("`{now}`"))
        })
        .await;
        // A client connected before the change, and answered at 01.
        let mut before = MebClient::connect(&meb, SHORT).unwrap();
        assert!(before.read(1, MebCmd::EA, 0, 1).is_ok());

        // A bad id is refused beside the box, with its range; nothing changes.
        type_into(&c, "#slave-id", "120").await;
        click(&c, "#slave-id-set").await;
        until("the refusal beside the id", LIMIT, async || {
            let said = text(&c, "#refusal-slave-id").await;
            (
                said.contains("120") && said.contains("1 to 99"),
                format!("`{said}`"),
            )
        })
        .await;
        assert!(read(&meb, 1, MebCmd::EA, 0, 1, SHORT).is_some());

        // Id 07: a new client reaches it there, and not at 01; the client
        // connected before is answered at 07 too.
        type_into(&c, "#slave-id", "7").await;
        click(&c, "#slave-id-set").await;
        until("slave 07 answering a new client", LIMIT, async || {
            let got = read(&meb, 7, MebCmd::EA, 0, 1, SHORT);
            (got.is_some(), format!("{got:?}"))
        })
        .await;
        assert!(
            read(&meb, 1, MebCmd::EA, 0, 1, SHORT).is_none(),
            "the old id gets no answer"
        );
        assert!(before.read(7, MebCmd::EA, 0, 1).is_ok());
        assert!(before.read(1, MebCmd::EA, 0, 1).is_err());
        let said = text(&c, "#refusal-slave-id").await;
        assert!(said.is_empty(), "a good id clears the refusal: `{said}`");
        until("the page says 07", LIMIT, async || {
            let now = text(&c, "#slave-now").await;
            (now.contains("slave 07"), format!("`{now}`"))
        })
        .await;

        // A map with two signals at one place: refused beside the box, by
        // the checks of --map, naming its line.
        type_into(&c, "#slave-map", "[EA]\nV1 = 0\nV2 = 0\n").await;
        click(&c, "#slave-map-set").await;
        until("the refusal beside the map", LIMIT, async || {
            let said = text(&c, "#refusal-slave-map").await;
            (
                said.contains("line 3") && said.contains("would share EA 0 with `V1`"),
                format!("`{said}`"),
            )
        })
        .await;

        // V1 moved to EA 00: with V1 forced, a client reads it there.
        let (status, answer) = http(
            &serve.panel,
            "POST",
            "/api/force",
            Some(r#"{"input":"v1","value":30}"#),
            true,
        );
        assert_eq!(status, 200, "{answer}");
        type_into(&c, "#slave-map", "[EA]\nV1 = 0\nV2 = 2\n").await;
        click(&c, "#slave-map-set").await;
        let want = sensing.counts(30.0 / sensing.battery_divider);
        until("V1 at EA 00", LIMIT, async || {
            let ea = read(&meb, 7, MebCmd::EA, 0, 1, SHORT);
            (
                ea.as_ref().is_some_and(|w| w[0] == want),
                format!("EA 00 {ea:?}, want {want}"),
            )
        })
        .await;
        until("the gauge saying where V1 is", LIMIT, async || {
            let label = text(&c, "#g-v1 .raw").await;
            (label.contains("(EA 00)"), format!("`{label}`"))
        })
        .await;
        // Back to the default map: V1 at EA 02 again.
        click(&c, "#slave-map-default").await;
        until("V1 back at EA 02", LIMIT, async || {
            let ea = read(&meb, 7, MebCmd::EA, 0, 3, SHORT);
            (
                ea.as_ref().is_some_and(|w| w[2] == want && w[0] != want),
                format!("EA {ea:?}, want V1 {want} at 02"),
            )
        })
        .await;
        c.close().await.unwrap();
    });
}

#[test]
fn the_slave_command_checks_as_the_command_line_does() {
    let session = serve("127.0.0.1:0", AccessOptions::default(), 30.0);
    for (body, field, says) in [
        (r#"{"id":0}"#, Some("id"), "1 to 99"),
        (r#"{"id":100}"#, Some("id"), "1 to 99"),
        (r#"{"id":2.5}"#, Some("id"), "whole number"),
        (r#"{"id":"two"}"#, Some("id"), "must be a number"),
        (r#"{"map":"[EA]\nWHEEL = 4\n"}"#, Some("map"), "line 2"),
        (r#"{"map":"V1 = 0"}"#, Some("map"), "one table per block"),
        (r#"{"map":3}"#, Some("map"), "must be a string"),
        (r#"{"slave":3}"#, Some("slave"), "unknown field"),
        ("{}", None, "nothing to change"),
    ] {
        let (got, answer) = http(&session.panel, "POST", "/api/slave", Some(body), true);
        let answer: Value = serde_json::from_str(&answer).expect("a JSON refusal");
        let message = answer["error"].as_str().unwrap_or_default();
        assert!(got == 422 || got == 400, "{body}: {got} {answer}");
        assert_eq!(answer["field"].as_str(), field, "{body}: {answer}");
        assert!(message.contains(says), "{body}: {message}");
    }
    for (body, says) in [
        (r#"{"input":"hall","value":8}"#, "0 to 7"),
        (r#"{"input":"flag","value":2}"#, "on or off"),
        (
            r#"{"input":"v1","value":500}"#,
            "500 V is out of range: V1 takes 0 to 100 V",
        ),
    ] {
        let (got, answer) = http(&session.panel, "POST", "/api/force", Some(body), true);
        assert_eq!(got, 422, "{body}: {answer}");
        assert!(answer.contains(says), "{body}: {answer}");
    }
    let (got, answer) = http(
        &session.panel,
        "POST",
        "/api/force",
        Some(r#"{"input":"flag","value":true}"#),
        true,
    );
    assert_eq!(got, 200, "{answer}");
    crate::common::wait_for(Duration::from_secs(5), "the flag forced", || {
        state(&session)["state"]["devices"][0]["controller"]["forced"]["flag"] == true
    });
    let now = state(&session);
    let device = &now["state"]["devices"][0];
    assert_eq!(device["slave"]["id"], 1, "nothing refused changed the id");
    assert_eq!(device["slave"]["map_is_default"], true);
    assert_eq!(device["controller"]["forced"]["flag"], true);
    let (_, info) = http(&session.panel, "GET", "/api/info", None, true);
    let info: Value = serde_json::from_str(&info).unwrap();
    let names: Vec<&str> = info["inputs"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|i| i["name"].as_str())
        .collect();
    assert_eq!(
        names,
        [
            "v1",
            "v2",
            "i",
            "rpm_m",
            "rpm_l",
            "ldr",
            "hall",
            "flag",
            "driver_fault"
        ]
    );
}
