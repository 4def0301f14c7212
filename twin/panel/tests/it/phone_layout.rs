//! The page on a phone (390x844 CSS px) for each role: the frame monitor's
//! text gets a whole line, the links table's errors and the scope's frames
//! are on the screen, and nothing scrolls sideways.

use crate::browser::screenshot_path;
use crate::common::{
    self, chrome_at, chromedriver, client_panel, fresh_dir, serve, serve_on, supervise, vsp,
};
use crate::page::{js, runtime, until};
use fantoccini::{Client, ClientBuilder};
use protocols::meb::MebCmd;
use serde_json::Value;
use std::time::Duration;
use twin_panel::AccessOptions;
use twin_realtime::client::MebClient;

const PHONE: (u32, u32) = (390, 844);

/// What the test measures, in one script: the viewport, the page's width,
/// the first frame's text cell and the first link's errors cell.
const MEASURE: &str = "(() => {
  const text = document.querySelector('#frames tbody td.text');
  const errors = document.querySelector('#links tbody tr')?.cells[6];
  const box = (e) => e ? e.getBoundingClientRect() : null;
  const t = box(text), e = box(errors);
  return { inner: window.innerWidth, scroll: document.documentElement.scrollWidth,
    text: t && t.width, errors_left: e && e.left, errors_right: e && e.right,
    errors_label: errors ? getComputedStyle(errors, '::before').content : null,
    links_scroll: (() => { const s = document.querySelector('#links-card .scroll');
      return s.scrollWidth - s.clientWidth; })(),
    scope_right: box(document.getElementById('scope')).right,
    scope_frames: document.querySelectorAll('#scope path.bits').length };
})()";

async fn phone(driver: &common::Driver, name: &str, url: &str) -> Client {
    let c = ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(chrome_at(&fresh_dir(name), Some(PHONE)))
        .connect(&driver.url)
        .await
        .expect("chromium starts under chromedriver");
    c.goto(url).await.unwrap();
    c
}

/// Waits for frames and a link on the page, then checks the layout.
async fn readable_on_a_phone(c: &Client, role: &str) {
    let mut seen = Value::Null;
    until(
        &format!("the {role} page's frames and links"),
        Duration::from_secs(20),
        async || {
            seen = js(c, MEASURE).await;
            (
                seen["text"].is_number()
                    && seen["errors_right"].is_number()
                    && seen["scope_frames"].as_u64() > Some(0),
                seen.to_string(),
            )
        },
    )
    .await;
    let n = |k: &str| seen[k].as_f64().unwrap_or(f64::NAN);
    assert_eq!(
        n("inner"),
        f64::from(PHONE.0),
        "{role}: the phone's viewport: {seen}"
    );
    assert!(
        n("scroll") <= f64::from(PHONE.0),
        "{role}: the page scrolls sideways: {seen}"
    );
    assert!(
        n("text") >= 300.0,
        "{role}: the frame's text is squeezed: {seen}"
    );
    assert!(
        n("errors_left") >= 0.0 && n("errors_right") <= f64::from(PHONE.0),
        "{role}: the errors column is off the screen: {seen}"
    );
    assert!(
        n("links_scroll") <= 0.0,
        "{role}: the links table scrolls sideways: {seen}"
    );
    assert_eq!(seen["errors_label"], "\"errors \"", "{role}: {seen}");
    // The scope draws its frames (two on a phone) within the screen.
    assert!(
        n("scope_right") <= f64::from(PHONE.0) && n("scope_frames") <= 2.0,
        "{role}: the scope: {seen}"
    );
}

#[test]
fn on_a_phone_every_page_shows_whole_frames_and_the_links_errors() {
    let driver = chromedriver();
    // twin serve, with a client reading so that frames flow.
    let served = serve("127.0.0.1:0", AccessOptions::default(), 90.0);
    let meb = served.meb.clone();
    std::thread::spawn(move || {
        let Ok(mut client) = MebClient::connect(&meb, Duration::from_secs(2)) else {
            return;
        };
        while client.read(1, MebCmd::EA, 0, 6).is_ok() {
            std::thread::sleep(Duration::from_millis(100));
        }
    });
    // twin supervise over a vsp pair to another twin serve.
    let [a, b] = vsp("phone");
    let _slave = serve_on(
        b.to_str().unwrap(),
        "127.0.0.1:0",
        AccessOptions::default(),
        90.0,
    );
    let supervised = supervise(a.to_str().unwrap(), "127.0.0.1:0", 90.0);
    // twin panel, an MEB client of the first.
    let panel = client_panel(&served.meb);
    let client_url = panel.running().url;
    runtime().block_on(async {
        for (role, url) in [
            ("serve", served.panel.url.clone()),
            ("supervise", supervised.panel.url.clone()),
            ("client", client_url.clone()),
        ] {
            let c = phone(&driver, &format!("phone-{role}"), &url).await;
            readable_on_a_phone(&c, role).await;
            if std::env::var_os("TWIN_PANEL_SCREENSHOTS").is_some() {
                // The page as it opens: the manual shows each role's.
                js(&c, "window.scrollTo(0, 0)").await;
                let png = c.screenshot().await.unwrap();
                std::fs::write(screenshot_path(&format!("panel-{role}-phone.png")), png).unwrap();
            }
            if role == "supervise" && std::env::var_os("TWIN_PANEL_SCREENSHOTS").is_some() {
                js(&c, "document.getElementById('links-card').scrollIntoView()").await;
                let png = c.screenshot().await.unwrap();
                std::fs::write(screenshot_path("panel-phone-monitor.png"), png).unwrap();
            }
            c.close().await.unwrap();
        }
    });
}
