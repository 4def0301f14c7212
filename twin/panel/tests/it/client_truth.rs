//! The client panel (`twin panel tcp://…`) after its slave goes away and
//! comes back: the gauges say they are the last values read while it is
//! gone, and the outputs this panel wrote before are not shown as the
//! module's after the reconnect (the module restarted with its power-up
//! outputs). Its frames are named like every panel's.

use crate::common::{Session, chromedriver, client_panel, http, serve_on};
use crate::page::{click, frame_rows, js, open, runtime, text, until};
use std::time::Duration;
use twin_panel::AccessOptions;

const LIMIT: Duration = Duration::from_secs(30);

fn outputs(session: &Session) -> serde_json::Value {
    let (_, body) = http(&session.panel, "GET", "/api/state", None, true);
    let s: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
    s["state"]["devices"][0]["controller"]["outputs"].clone()
}

#[test]
fn the_client_panel_forgets_its_writes_across_a_reconnect_and_says_when_it_is_stale() {
    let first = serve_on(
        "tcp://127.0.0.1:0",
        "127.0.0.1:0",
        AccessOptions::default(),
        120.0,
    );
    let url = first.meb.clone();
    let panel = client_panel(&url);
    let page_url = panel.running().url;
    let driver = chromedriver();
    runtime().block_on(async {
        let c = open(&driver, "client-truth", &page_url).await;
        until("the first reads", LIMIT, async || {
            let conn = text(&c, "#conn").await;
            (conn.contains("MEB client of"), format!("`{conn}`"))
        })
        .await;
        // Its frames: the panel's requests to slave 01 and the replies.
        until("the frames named", LIMIT, async || {
            let rows = frame_rows(&c).await;
            let sent = rows.iter().any(|(d, f)| d == "twin → slave 01" && f.starts_with("@01"));
            let got = rows.iter().any(|(d, _)| d == "slave 01 → twin");
            (sent && got, format!("{:?}", rows.iter().take(4).collect::<Vec<_>>()))
        })
        .await;
        // The inverter enabled from the page, then the slave goes away.
        click(&c, "#sw-EN").await;
        until("EN written", LIMIT, async || {
            let o = outputs(&first);
            (o["EN"]["on"] == true, format!("{o}"))
        })
        .await;
        until("EN shown on", LIMIT, async || {
            let on = js(&c, "document.getElementById('sw-EN').checked").await;
            (on == true, format!("{on}"))
        })
        .await;
        drop(first);
        until("the gauges said stale", LIMIT, async || {
            let note = text(&c, "#stale-note").await;
            let stale = js(&c, "document.getElementById('gauges').classList.contains('stale')").await;
            (stale == true && note.contains("last read"), format!("{stale} `{note}`"))
        })
        .await;

        // A fresh module on the same address: power-up outputs, EN off.
        let second = serve_on(&url, "127.0.0.1:0", AccessOptions::default(), 60.0);
        assert_eq!(outputs(&second)["EN"]["on"], false);
        until("the reconnect, with nothing claimed of the outputs", LIMIT, async || {
            let conn = text(&c, "#conn").await;
            let en = js(&c, "[document.getElementById('sw-EN').checked, document.getElementById('sw-EN').indeterminate]").await;
            let rows = text(&c, "#outputs").await;
            let stale = js(&c, "document.getElementById('gauges').classList.contains('stale')").await;
            (
                conn.contains("MEB client of") && en == serde_json::json!([false, true])
                    && rows.contains("not written since connecting") && stale == false,
                format!("`{conn}`, EN (checked, unknown) {en}, stale {stale}, outputs `{rows}`"),
            )
        })
        .await;
        c.close().await.unwrap();
        drop(second);
    });
}

/// A VEL slider dragged sends writes back to back; the panel still reads
/// the module's inputs and status between them, as often as it polls.
#[test]
fn the_client_panel_keeps_reading_while_vel_is_written_back_to_back() {
    let module = serve_on(
        "tcp://127.0.0.1:0",
        "127.0.0.1:0",
        AccessOptions::default(),
        60.0,
    );
    let panel = client_panel(&module.meb);
    let running = panel.running();
    let connection = || {
        let (_, body) = http(&running, "GET", "/api/state", None, true);
        let s: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
        s["state"]["connection"].clone()
    };
    crate::common::wait_for(LIMIT, "the first reads", || {
        connection()["last_reply_age_s"].is_number()
    });
    // A dragged slider's writes overlap (the page does not wait for one
    // to be acknowledged before it sends the next): four writers at once.
    let started = std::time::Instant::now();
    let writers: Vec<_> = (0..4u32)
        .map(|w| {
            let running = running.clone();
            std::thread::spawn(move || {
                let mut writes = 0u32;
                while started.elapsed() < Duration::from_millis(1500) {
                    let body = format!("{{\"vel\": {}}}", 100 + w * 500 + writes % 400);
                    let (status, answer) =
                        http(&running, "POST", "/api/outputs", Some(&body), true);
                    assert_eq!(status, 200, "{answer}");
                    writes += 1;
                }
                writes
            })
        })
        .collect();
    let mut oldest = 0.0f64;
    while started.elapsed() < Duration::from_millis(1500) {
        let age = connection()["last_reply_age_s"]
            .as_f64()
            .unwrap_or(f64::INFINITY);
        oldest = oldest.max(age);
        std::thread::sleep(Duration::from_millis(20));
    }
    let writes: u32 = writers.into_iter().map(|w| w.join().unwrap()).sum();
    eprintln!("{writes} writes; the inputs read at most {oldest:.3} s before");
    assert!(
        writes >= 30,
        "only {writes} writes in 1.5 s: not back to back"
    );
    // A poll every 50 ms, each four exchanges on a loopback: a read is
    // never older than a few polls, however busy the writes keep it.
    assert!(
        oldest < 0.4,
        "the inputs went unread for {oldest:.3} s while {writes} writes went through"
    );
}
