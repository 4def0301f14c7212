//! The client panel (`twin panel tcp://…`) in a real browser, an MEB-TCP
//! client of a real `twin serve` session: its gauges read the slave over
//! its own connection, its switches and VEL slider drive the module.

use crate::common;

use common::{chrome_capabilities, chromedriver, fresh_dir, http, serve};
use fantoccini::key::Key;
use fantoccini::{ClientBuilder, Locator};
use std::time::{Duration, Instant};
use twin_panel::AccessOptions;

#[test]
fn the_client_panel_shows_the_slave_and_its_clicks_drive_the_module() {
    let session = serve("127.0.0.1:0", AccessOptions::default(), 60.0);
    let panel = common::client_panel(&session.meb);
    let url = panel.running().url;
    let driver = chromedriver();
    let outputs = || {
        let (_, body) = http(&session.panel, "GET", "/api/state", None, true);
        let s: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
        s["state"]["devices"][0]["controller"]["outputs"].clone()
    };
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            let c = ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
                .capabilities(chrome_capabilities(&fresh_dir("client"), false))
                .connect(&driver.url)
                .await
                .expect("chromium starts under chromedriver");
            c.goto(&url).await.unwrap();
            assert_eq!(
                c.find(Locator::Css("#role"))
                    .await
                    .unwrap()
                    .text()
                    .await
                    .unwrap(),
                "client (twin panel)"
            );
            let start = Instant::now();
            loop {
                let v1 = c
                    .find(Locator::Css("#g-v1 .num"))
                    .await
                    .unwrap()
                    .text()
                    .await
                    .unwrap();
                let conn = c
                    .find(Locator::Css("#conn"))
                    .await
                    .unwrap()
                    .text()
                    .await
                    .unwrap();
                if v1.parse::<f64>().is_ok_and(|v| (30.0..50.0).contains(&v))
                    && conn.contains("MEB client of")
                {
                    break;
                }
                assert!(
                    start.elapsed() < Duration::from_secs(10),
                    "V1 shows `{v1}`, connection `{conn}`"
                );
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            // Enable, release the brake (it starts released: set it on and off), VEL up by keys.
            c.find(Locator::Css("#sw-EN"))
                .await
                .unwrap()
                .click()
                .await
                .unwrap();
            let vel = c.find(Locator::Css("#out-vel")).await.unwrap();
            vel.send_keys(&char::from(Key::PageUp).to_string())
                .await
                .unwrap();
            let start = Instant::now();
            loop {
                let o = outputs();
                if o["EN"]["on"] == true && o["VEL"]["counts"].as_u64().is_some_and(|v| v > 0) {
                    break;
                }
                assert!(
                    start.elapsed() < Duration::from_secs(5),
                    "the module's outputs: {o}"
                );
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            // The hall gauge answers.
            let start = Instant::now();
            loop {
                let hall = c
                    .find(Locator::Css("#g-hall .num"))
                    .await
                    .unwrap()
                    .text()
                    .await
                    .unwrap();
                if hall.parse::<f64>().is_ok_and(|h| h > 50.0) {
                    break;
                }
                assert!(
                    start.elapsed() < Duration::from_secs(10),
                    "hall rpm shows `{hall}`"
                );
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            let frames = c.find_all(Locator::Css("#frames tbody tr")).await.unwrap();
            assert!(!frames.is_empty(), "its own frames in the monitor");
            if std::env::var_os("TWIN_PANEL_SCREENSHOTS").is_some() {
                tokio::time::sleep(Duration::from_secs(3)).await;
                let png = c.screenshot().await.unwrap();
                let docs = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs");
                std::fs::write(docs.join("panel-client-laptop.png"), png).unwrap();
            }
            c.close().await.unwrap();
        });
}
