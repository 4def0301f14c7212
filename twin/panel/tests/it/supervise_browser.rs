//! The supervise page in a real browser, over a real bus: `twin supervise
//! --web` polling `twin serve` through a `twin vsp` pair. The set point is
//! dragged with the mouse, the switches are clicked in manual mode, and the
//! plant on the other end of the bus answers.

use crate::common;

use common::{chrome_capabilities, chromedriver, fresh_dir, http, serve_on, supervise, vsp};
use fantoccini::actions::{InputSource, MOUSE_BUTTON_LEFT, MouseActions, PointerAction};
use fantoccini::key::Key;
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::Value;
use std::time::{Duration, Instant};
use twin_panel::AccessOptions;

fn state(session: &common::Session) -> Value {
    let (_, body) = http(&session.panel, "GET", "/api/state", None, true);
    serde_json::from_str(&body).unwrap_or_default()
}

/// The plant's true wheel, on the serve side of the bus.
fn true_wheel(serve: &common::Session) -> f64 {
    state(serve)["state"]["modules"][0]["wheel_rpm"]
        .as_f64()
        .unwrap_or(0.0)
        .abs()
}

async fn number(c: &Client, css: &str) -> f64 {
    match c.find(Locator::Css(css)).await {
        Ok(e) => e
            .text()
            .await
            .unwrap_or_default()
            .parse()
            .unwrap_or(f64::NAN),
        Err(_) => f64::NAN,
    }
}

async fn slider_value(c: &Client) -> f64 {
    c.execute(
        "return +document.getElementById('set-point').value;",
        vec![],
    )
    .await
    .unwrap()
    .as_f64()
    .unwrap()
}

/// Drags the set-point slider's thumb to where `rpm` is, with the mouse.
async fn drag_set_point(c: &Client, rpm: f64) -> f64 {
    let slider = c.find(Locator::Css("#set-point")).await.unwrap();
    let (_, _, width, _) = slider.rectangle().await.unwrap();
    // Press where the thumb is, then move to the value's place: the
    // thumb's centre runs from half a thumb in to half a thumb from the end.
    let thumb = 16.0;
    let place = |v: f64| (v / 3000.0 - 0.5) * (width - thumb);
    let from = slider_value(c).await;
    let actions = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element: slider.clone(),
            duration: None,
            x: place(from),
            y: 0.0,
        })
        .then(PointerAction::Down {
            button: MOUSE_BUTTON_LEFT,
        })
        .then(PointerAction::MoveBy {
            duration: Some(Duration::from_millis(400)),
            x: place(rpm) - place(from),
            y: 0.0,
        })
        .then(PointerAction::Up {
            button: MOUSE_BUTTON_LEFT,
        });
    c.perform_actions(actions).await.unwrap();
    let dragged = slider_value(c).await;
    // The last few steps by the arrow keys, as a student would.
    let mut v = dragged;
    while (v - rpm).abs() >= 5.0 {
        let key = if v < rpm { Key::Right } else { Key::Left };
        slider
            .send_keys(&char::from(key).to_string())
            .await
            .unwrap();
        v = slider_value(c).await;
    }
    dragged
}

/// Waits until `ok` holds for a whole second.
async fn settles(what: &str, limit: Duration, mut ok: impl AsyncFnMut() -> (bool, String)) {
    let start = Instant::now();
    let mut inside: Option<Instant> = None;
    loop {
        let (good, shown) = ok().await;
        if good {
            if inside.get_or_insert_with(Instant::now).elapsed() > Duration::from_secs(1) {
                return;
            }
        } else {
            inside = None;
        }
        assert!(start.elapsed() < limit, "{what} did not settle: {shown}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[test]
fn dragging_the_set_point_turns_the_wheel_and_the_switches_reach_the_module() {
    let [a, b] = vsp("supervise-browser");
    let serve = serve_on(
        b.to_str().unwrap(),
        "127.0.0.1:0",
        AccessOptions::default(),
        90.0,
    );
    let sup = supervise(a.to_str().unwrap(), "127.0.0.1:0", 90.0);
    let driver = chromedriver();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(async {
        let c = ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
            .capabilities(chrome_capabilities(&fresh_dir("supervise"), false))
            .connect(&driver.url)
            .await
            .expect("chromium starts under chromedriver");
        c.goto(&sup.panel.url).await.unwrap();
        c.wait()
            .for_element(Locator::Css("#loop-slaves .lamp:not(.bad)"))
            .await
            .unwrap();

        // The set point dragged to 2000 rpm: the wheel gauge (the loop's
        // measurement) and the plant's true wheel settle within 3 %.
        let dragged = drag_set_point(&c, 2000.0).await;
        eprintln!("the drag left the slider at {dragged} rpm");
        assert!((dragged - 2000.0).abs() <= 150.0, "the drag moved the slider to {dragged}");
        settles("the wheel at 2000 rpm", Duration::from_secs(25), async || {
            let gauge = number(&c, "#g-wheel .num").await;
            let wheel = true_wheel(&serve);
            let sp = state(&sup)["state"]["devices"][0]["loops"][0]["set_point_rpm"].clone();
            (
                sp == 2000.0 && (gauge - 2000.0).abs() <= 60.0 && (wheel - 2000.0).abs() <= 60.0,
                format!("set point {sp}, gauge {gauge}, true wheel {wheel}"),
            )
        })
        .await;
        // The laptop's view: gauges and the trend above the fold.
        let trend_top = c
            .execute("return document.getElementById('trend').getBoundingClientRect().bottom <= window.innerHeight;", vec![])
            .await
            .unwrap();
        assert_eq!(trend_top, Value::Bool(true), "the trend is above the fold at 1366x768");
        if std::env::var_os("TWIN_PANEL_SCREENSHOTS").is_some() {
            let png = c.screenshot().await.unwrap();
            let docs = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs");
            std::fs::write(docs.join("panel-supervise-laptop.png"), png).unwrap();
        }

        // At a speed the photoresistor follows (the adaptive detector), the
        // light-rpm gauge tracks the wheel gauge.
        drag_set_point(&c, 1200.0).await;
        settles("the light rpm with the wheel at 1200 rpm", Duration::from_secs(25), async || {
            let wheel = number(&c, "#g-wheel .num").await;
            let light = number(&c, "#g-light .num").await;
            (
                (wheel - 1200.0).abs() <= 36.0 && (light - wheel).abs() <= 0.05 * wheel,
                format!("wheel {wheel}, light {light}"),
            )
        })
        .await;

        // The switches: refused while the loop is closed, and nothing changes.
        let (status, body) = http(&sup.panel, "POST", "/api/outputs", Some(r#"{"BRK":true}"#), true);
        assert_eq!(status, 409, "{body}");
        assert!(body.contains("manual"), "{body}");
        let (status, body) = http(&sup.panel, "POST", "/api/outputs", Some(r#"{"BRAKE":true}"#), true);
        assert_eq!(status, 422, "{body}");
        assert!(body.contains("BRAKE"), "{body}");
        let outputs = |s: &common::Session| state(s)["state"]["devices"][0]["controller"]["outputs"].clone();
        assert_eq!(outputs(&serve)["BRK"]["on"], false);
        // Loop off (manual VEL), then the brake on and the module disabled, by clicks.
        assert!(c.find(Locator::Css("#sw-BRK")).await.unwrap().prop("disabled").await.unwrap() == Some("true".into()));
        c.find(Locator::Css("#loop-on")).await.unwrap().click().await.unwrap();
        c.wait()
            .for_element(Locator::Css("#sw-BRK:not([disabled])"))
            .await
            .unwrap();
        c.find(Locator::Css("#sw-BRK")).await.unwrap().click().await.unwrap();
        c.find(Locator::Css("#sw-EN")).await.unwrap().click().await.unwrap();
        let start = Instant::now();
        loop {
            let o = outputs(&serve);
            if o["BRK"]["on"] == true && o["EN"]["on"] == false {
                assert_eq!(o["BRK"]["pin"], 0, "the brake is active low: {o}");
                break;
            }
            assert!(start.elapsed() < Duration::from_secs(5), "the controller's outputs: {o}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        // The page shows the switches as written.
        tokio::time::sleep(Duration::from_millis(300)).await;
        let checked = |id: &'static str| {
            let c = &c;
            async move { c.find(Locator::Css(id)).await.unwrap().prop("checked").await.unwrap() }
        };
        assert_eq!(checked("#sw-BRK").await.as_deref(), Some("true"));
        assert_eq!(checked("#sw-EN").await.as_deref(), Some("false"));
        // The brake holds the wheel.
        settles("the braked wheel", Duration::from_secs(20), async || {
            let w = true_wheel(&serve);
            (w < 50.0, format!("true wheel {w}"))
        })
        .await;
        c.close().await.unwrap();
    });
}
