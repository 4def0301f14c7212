//! A page in a real browser: opened under chromedriver, read through
//! JavaScript, and waited on by polling (the machine is shared: no fixed
//! sleeps, generous limits).

use crate::common::{Driver, chrome_capabilities, fresh_dir};
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::Value;
use std::time::{Duration, Instant};

/// Chromium at `url`, its profile named `name`.
pub async fn open(driver: &Driver, name: &str, url: &str) -> Client {
    let c = ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(chrome_capabilities(&fresh_dir(name), false))
        .connect(&driver.url)
        .await
        .expect("chromium starts under chromedriver");
    c.goto(url).await.unwrap();
    c
}

/// The value of a JavaScript expression on the page.
pub async fn js(c: &Client, expression: &str) -> Value {
    c.execute(&format!("return {expression};"), vec![])
        .await
        .unwrap_or(Value::Null)
}

/// The text of the element `css` ("" while there is none). Read in one
/// script: the page redraws its rows 20 times a second, so an element found
/// by one call may be gone by the next.
pub async fn text(c: &Client, css: &str) -> String {
    let css = serde_json::to_string(css).unwrap();
    js(
        c,
        &format!("document.querySelector({css})?.textContent ?? ''"),
    )
    .await
    .as_str()
    .unwrap_or_default()
    .to_string()
}

pub async fn click(c: &Client, css: &str) {
    c.find(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no {css} on the page: {e}"))
        .click()
        .await
        .unwrap();
}

/// Polls `ok` every 100 ms until it holds, or fails with what it last saw.
pub async fn until(what: &str, limit: Duration, mut ok: impl AsyncFnMut() -> (bool, String)) {
    let start = Instant::now();
    loop {
        let (good, seen) = ok().await;
        if good {
            return;
        }
        assert!(
            start.elapsed() < limit,
            "timed out waiting for {what}: {seen}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// The frame monitor's rows: `[from → to, frame]`.
pub async fn frame_rows(c: &Client) -> Vec<(String, String)> {
    let rows = js(
        c,
        "[...document.querySelectorAll('#frames tbody tr')].map((r) => [r.cells[3].textContent, r.cells[4].textContent])",
    )
    .await;
    rows.as_array()
        .into_iter()
        .flatten()
        .filter_map(|r| {
            Some((
                r.get(0)?.as_str()?.to_string(),
                r.get(1)?.as_str()?.to_string(),
            ))
        })
        .collect()
}

pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}
