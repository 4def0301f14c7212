//! The supervise page says what is true, over a real bus (`twin supervise
//! --web` polling `twin serve` through a `twin vsp` pair): who sent each
//! frame, the loop's controls as the supervisor holds them, lamps that
//! follow the recent state, the status word's lamps, and a step refused
//! while the loop is off.

use crate::common::{Session, chromedriver, http, serve_on, supervise, vsp};
use crate::page::{click, frame_rows, js, open, runtime, text, until};
use fantoccini::Locator;
use serde_json::Value;
use std::time::Duration;
use twin_panel::AccessOptions;

const LIMIT: Duration = Duration::from_secs(30);

fn state(session: &Session) -> Value {
    let (_, body) = http(&session.panel, "GET", "/api/state", None, true);
    serde_json::from_str(&body).unwrap_or_default()
}

fn the_loop(sup: &Session) -> Value {
    state(sup)["state"]["devices"][0]["loops"][0].clone()
}

fn true_wheel(serve: &Session) -> f64 {
    state(serve)["state"]["modules"][0]["wheel_rpm"]
        .as_f64()
        .unwrap_or(0.0)
        .abs()
}

fn post(session: &Session, path: &str, body: &str) {
    let (status, answer) = http(&session.panel, "POST", path, Some(body), true);
    assert_eq!(status, 200, "{path} {body}: {answer}");
}

#[test]
fn the_supervise_page_shows_what_the_supervisor_and_the_bus_hold() {
    let [a, b] = vsp("supervise-truth");
    let serve = serve_on(
        b.to_str().unwrap(),
        "127.0.0.1:0",
        AccessOptions::default(),
        150.0,
    );
    let sup = supervise(a.to_str().unwrap(), "127.0.0.1:0", 150.0);
    let driver = chromedriver();
    runtime().block_on(async {
        let c = open(&driver, "supervise-truth", &sup.panel.url).await;
        post(&sup, "/api/loop", r#"{"set_point_rpm": 2000}"#);
        until(
            "the wheel near 2000 rpm",
            Duration::from_secs(40),
            async || {
                let w = true_wheel(&serve);
                (w > 1500.0, format!("true wheel {w}"))
            },
        )
        .await;

        // The frame monitor: the supervisor's requests go from the twin to
        // slave 01, the replies come back from it; no "client" on a bus
        // where the twin is the master.
        until(
            "the bus's frames, each with its sender",
            LIMIT,
            async || {
                let rows = frame_rows(&c).await;
                let request = rows
                    .iter()
                    .any(|(dir, f)| dir == "twin → slave 01" && f.starts_with("@01EA"));
                let reply = rows.iter().any(|(dir, _)| dir == "slave 01 → twin");
                let client = rows.iter().any(|(dir, _)| dir.contains("client"));
                (
                    request && reply && !client,
                    format!("{:?}", rows.iter().take(6).collect::<Vec<_>>()),
                )
            },
        )
        .await;
        // The same words on the serve end of the bus: there the twin is the slave.
        let serve_page = open(&driver, "supervise-truth-serve", &serve.panel.url).await;
        until("the serve panel's frames", LIMIT, async || {
            let rows = frame_rows(&serve_page).await;
            let request = rows.iter().any(|(dir, f)| {
                dir.starts_with("client ") && dir.ends_with(" → twin") && f.starts_with("@01EA")
            });
            let reply = rows
                .iter()
                .any(|(dir, _)| dir.starts_with("twin → client "));
            (
                request && reply,
                format!("{:?}", rows.iter().take(6).collect::<Vec<_>>()),
            )
        })
        .await;
        serve_page.close().await.unwrap();

        // Gains changed elsewhere show in the boxes.
        post(&sup, "/api/loop", r#"{"kp": 0.6}"#);
        until("Kp 0.6 in its box", LIMIT, async || {
            let kp = js(&c, "document.getElementById('kp').value").await;
            (kp == "0.6", format!("the box shows {kp}"))
        })
        .await;
        // The loop opened by another master at the VEL it had (as a
        // client's VD 10 0 does): the box follows.
        let held = the_loop(&sup)["vel_written"]
            .as_u64()
            .expect("a VEL written");
        post(
            &sup,
            "/api/loop",
            &format!(r#"{{"mode": "manual", "vel": {held}}}"#),
        );
        until("loop on unticked", LIMIT, async || {
            let on = js(&c, "document.getElementById('loop-on').checked").await;
            let mode = text(&c, "#loop-mode").await;
            (
                on == false && mode.contains("manual"),
                format!("ticked {on}, `{mode}`"),
            )
        })
        .await;
        // Ticked, then unticked by the user: the loop closes, then opens
        // holding the VEL the slave has; the wheel keeps turning.
        click(&c, "#loop-on").await;
        until("the loop closed", LIMIT, async || {
            let mode = the_loop(&sup)["mode"].clone();
            (mode == "loop", format!("mode {mode}"))
        })
        .await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        click(&c, "#loop-on").await;
        until("the loop open at the slave's VEL", LIMIT, async || {
            let l = the_loop(&sup);
            let manual = l["mode"]["manual"].as_u64();
            (
                manual.is_some_and(|v| v > 100),
                format!("mode {}", l["mode"]),
            )
        })
        .await;
        tokio::time::sleep(Duration::from_secs(2)).await;
        let w = true_wheel(&serve);
        assert!(w > 1000.0, "unticking the loop stopped the wheel: {w} rpm");

        // An empty gain box is refused beside the control; nothing changes.
        let kp = c.find(Locator::Css("#kp")).await.unwrap();
        kp.clear().await.unwrap();
        kp.send_keys(" ").await.unwrap();
        click(&c, "#gains").await;
        until("the refusal beside the gains", LIMIT, async || {
            let said = text(&c, "#refusal-loop").await;
            (
                said.contains("Kp") && said.contains("number"),
                format!("`{said}`"),
            )
        })
        .await;
        assert_eq!(the_loop(&sup)["kp"], 0.6, "an empty box changed Kp");

        // The status word's lamps, with words: direction, then the brake.
        until("the direction lamp", LIMIT, async || {
            let dir = text(&c, "#flag-ccw").await;
            (
                dir.contains("CW"),
                format!("`{dir}`, status words {}", the_loop(&sup)["status"]),
            )
        })
        .await;
        // A busy machine may lose the write on the pty pair: the answer
        // says so (502), and the page's user would click again.
        let mut tries = 0;
        loop {
            let (status, answer) = http(
                &sup.panel,
                "POST",
                "/api/outputs",
                Some(r#"{"BRK": true}"#),
                true,
            );
            tries += 1;
            if status == 200 {
                break;
            }
            assert!(status == 502 && tries < 4, "{status} {answer}");
        }
        until("the brake lamp lit", LIMIT, async || {
            let on = js(&c, "document.getElementById('flag-brake')?.dataset.on").await;
            let words = text(&c, "#flag-brake").await;
            (on == "1" && words.contains("on"), format!("{on} `{words}`"))
        })
        .await;
        let legend = text(&c, "#legend-wheel").await;
        assert!(
            legend.contains("loop's measurement"),
            "the trend's legend: {legend}"
        );
        // A step while the loop is off is refused, saying so.
        click(&c, "#step").await;
        until("the step refused", LIMIT, async || {
            let said = text(&c, "#refusal-loop").await;
            (said.contains("loop is off"), format!("`{said}`"))
        })
        .await;

        // Replies with a bad check: the bus's lamp turns red with words,
        // the slave's too; the fault off, both recover.
        post(&serve, "/api/fault", r#"{"fault": "bad-check"}"#);
        until("red lamps", LIMIT, async || {
            let link = js(&c, "document.getElementById('lamp-bus')?.dataset.state").await;
            let words = text(&c, "#lamp-bus").await;
            let slave = js(&c, "document.getElementById('slave-1')?.dataset.state").await;
            (
                link == "bad" && words.contains("errors") && slave == "bad",
                format!("bus {link} `{words}`, slave {slave}"),
            )
        })
        .await;
        post(&serve, "/api/fault", r#"{"fault": "off"}"#);
        until("green lamps again", LIMIT, async || {
            let link = js(&c, "document.getElementById('lamp-bus')?.dataset.state").await;
            let slave = js(&c, "document.getElementById('slave-1')?.dataset.state").await;
            let words = text(&c, "#slave-1").await;
            (
                link == "on" && slave == "on" && words.contains("replying"),
                format!(
                    "bus {link}, slave {slave} `{words}` {}",
                    the_loop(&sup)["counters"]
                ),
            )
        })
        .await;
        c.close().await.unwrap();
    });
}
