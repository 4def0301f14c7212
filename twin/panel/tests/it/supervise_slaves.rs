//! The supervise page with two slaves on one line (`--id 1 --id 2`): both
//! shown, and the loop controls act on the slave chosen, and on it only,
//! as each module's own wheel shows.

use crate::common::{self, chromedriver, http, serve_id, supervise_ids};
use crate::meb_bus::meb_bus;
use crate::page::{self, js, text, until};
use fantoccini::Locator;
use serde_json::Value;
use std::time::Duration;

fn state(session: &common::Session) -> Value {
    let (_, body) = http(&session.panel, "GET", "/api/state", None, true);
    serde_json::from_str(&body).unwrap_or_default()
}

/// The set point the supervisor holds for slave `id`.
fn set_point(sup: &common::Session, id: u64) -> f64 {
    state(sup)["state"]["devices"][0]["loops"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|l| l["id"].as_u64() == Some(id))
        .and_then(|l| l["set_point_rpm"].as_f64())
        .unwrap_or(f64::NAN)
}

/// The module's true wheel, on its own side of the line.
fn wheel(serve: &common::Session) -> f64 {
    state(serve)["state"]["modules"][0]["wheel_rpm"]
        .as_f64()
        .unwrap_or(f64::NAN)
        .abs()
}

#[test]
fn the_supervise_page_shows_both_slaves_and_a_set_point_for_slave_2_moves_only_its_loop() {
    let one = serve_id(1, "tcp://127.0.0.1:0", "127.0.0.1:0", 120.0);
    let two = serve_id(2, "tcp://127.0.0.1:0", "127.0.0.1:0", 120.0);
    let bus = meb_bus(&[(1, &one.meb), (2, &two.meb)]);
    let sup = supervise_ids(&bus, "127.0.0.1:0", 120.0, &[1, 2]);
    let driver = chromedriver();
    page::runtime().block_on(async {
        let c = page::open(&driver, "supervise-slaves", &sup.panel.url).await;
        until("both slaves' lamps lit", Duration::from_secs(20), async || {
            let lamps = js(
                &c,
                "['slave-1', 'slave-2'].map((id) => document.getElementById(id)?.dataset.state ?? 'none')",
            )
            .await;
            (lamps == serde_json::json!(["on", "on"]), lamps.to_string())
        })
        .await;
        let choices = js(
            &c,
            "[...document.querySelectorAll('#loop-slave option')].map((o) => o.textContent)",
        )
        .await;
        assert_eq!(choices, serde_json::json!(["slave 01", "slave 02"]));

        // Slave 02 chosen in the list, its set point moved on the slider.
        c.find(Locator::Css("#loop-slave"))
            .await
            .unwrap()
            .select_by_value("2")
            .await
            .unwrap();
        until("the loop card naming slave 02", Duration::from_secs(5), async || {
            let heading = text(&c, "#loop-card h2").await;
            (heading.contains("slave 02"), heading)
        })
        .await;
        js(
            &c,
            "(() => { const s = document.getElementById('set-point'); s.value = 1200; \
             s.dispatchEvent(new Event('input')); s.dispatchEvent(new Event('change')); return 1; })()",
        )
        .await;
        until("slave 02's set point", Duration::from_secs(5), async || {
            let (sp1, sp2) = (set_point(&sup, 1), set_point(&sup, 2));
            (sp2 == 1200.0, format!("slave 01 {sp1}, slave 02 {sp2}"))
        })
        .await;
        assert_eq!(set_point(&sup, 1), 0.0, "slave 01's set point moved too");

        // Each module's own wheel: slave 02's turns at the set point, slave
        // 01's stays still; the page's wheel gauge is slave 02's loop's.
        until("slave 02's wheel at 1200 rpm", Duration::from_secs(30), async || {
            let (w1, w2) = (wheel(&one), wheel(&two));
            let gauge: f64 = text(&c, "#g-wheel .num").await.parse().unwrap_or(f64::NAN);
            (
                (w2 - 1200.0).abs() <= 40.0 && (gauge - 1200.0).abs() <= 40.0 && w1 < 20.0,
                format!("wheel 01 {w1}, wheel 02 {w2}, gauge {gauge}"),
            )
        })
        .await;

        // Slave 01 chosen by its lamp: the gauge and the slider are its own.
        page::click(&c, "#loop-slaves .out-row[data-id='1']").await;
        until("slave 01's loop on the page", Duration::from_secs(5), async || {
            let gauge: f64 = text(&c, "#g-wheel .num").await.parse().unwrap_or(f64::NAN);
            let slider = js(&c, "+document.getElementById('set-point').value").await;
            (
                gauge < 20.0 && slider == serde_json::json!(0),
                format!("gauge {gauge}, slider {slider}"),
            )
        })
        .await;
        assert!(wheel(&one) < 20.0 && (wheel(&two) - 1200.0).abs() <= 40.0);
        c.close().await.unwrap();
    });

    // A slave the supervisor does not poll is named in a 404.
    let (status, body) = http(
        &sup.panel,
        "POST",
        "/api/loop",
        Some(r#"{"slave": 3, "set_point_rpm": 100}"#),
        true,
    );
    assert_eq!(status, 404, "{body}");
    assert!(body.contains("no slave 3"), "{body}");
}
