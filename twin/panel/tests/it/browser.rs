//! The panel in a real browser: Debian's chromium, driven over WebDriver
//! (chromedriver) by fantoccini, against a real `twin serve` session.

use crate::common;

use common::{ClientAddr, chrome_capabilities, chromedriver, fresh_dir, serve};
use fantoccini::{Client, ClientBuilder, Locator};
use protocols::meb::MebCmd;
use std::time::{Duration, Instant};
use twin_panel::AccessOptions;
use twin_realtime::client::MebClient;

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

async fn browser(driver: &common::Driver, name: &str, phone: bool) -> Client {
    let connector = hyper_util::client::legacy::connect::HttpConnector::new();
    ClientBuilder::new(connector)
        .capabilities(chrome_capabilities(&fresh_dir(name), phone))
        .connect(&driver.url)
        .await
        .expect("chromium starts under chromedriver")
}

/// Text of the first element matching `css`, or "".
async fn text(c: &Client, css: &str) -> String {
    match c.find(Locator::Css(css)).await {
        Ok(e) => e.text().await.unwrap_or_default(),
        Err(_) => String::new(),
    }
}

async fn eventually(
    c: &Client,
    what: &str,
    limit: Duration,
    check: impl Fn(&str) -> bool,
    css: &str,
) -> String {
    let start = Instant::now();
    loop {
        let t = text(c, css).await;
        if check(&t) {
            return t;
        }
        assert!(
            start.elapsed() < limit,
            "timed out waiting for {what}: `{css}` shows `{t}`"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Where screenshots go: `docs/` when TWIN_PANEL_SCREENSHOTS is set (to
/// refresh the manual's), else the temporary folder.
pub(crate) fn screenshot_path(name: &str) -> std::path::PathBuf {
    match std::env::var_os("TWIN_PANEL_SCREENSHOTS") {
        Some(_) => std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../docs")
            .join(name),
        None => std::env::temp_dir().join(name),
    }
}

/// V1 as the MEB link reads it: EA word 2, through the 10:1 divider of the
/// 12-bit, 5 V ADC (docs/protocols/meb.md).
fn meb_v1(meb: &str) -> f64 {
    let mut client = MebClient::connect(meb, Duration::from_secs(2)).expect("MEB connects");
    let words = client.read(1, MebCmd::EA, 0, 6).expect("EA reads");
    f64::from(words[2]) / 4095.0 * 5.0 * 10.0
}

/// Runs the wheel: EN on (SD0 bit 0 low), VEL half scale.
fn start_wheel(meb: &str) {
    let mut client = MebClient::connect(meb, Duration::from_secs(2)).expect("MEB connects");
    client
        .write(1, MebCmd::SA, 0, &[1200])
        .expect("VEL written");
    client
        .write(1, MebCmd::SD, 0, &[0x001E])
        .expect("EN written");
}

#[test]
fn the_panel_shows_the_bench_in_a_browser_and_its_monitor_shows_a_bad_check() {
    let session = serve("127.0.0.1:0", AccessOptions::default(), 60.0);
    start_wheel(&session.meb);
    let driver = chromedriver();
    runtime().block_on(async {
        let c = browser(&driver, "laptop", false).await;
        c.goto(&session.panel.url).await.unwrap();
        // The page loads and its V1 gauge shows the plant's V1 as the MEB link reads it.
        let shown = eventually(
            &c,
            "the V1 gauge",
            Duration::from_secs(10),
            |t| t.parse::<f64>().is_ok(),
            "#g-v1 .num",
        )
        .await;
        let shown: f64 = shown.parse().unwrap();
        let read = meb_v1(&session.meb);
        assert!(
            (shown - read).abs() <= 0.01 * read,
            "V1 gauge {shown} V, MEB reads {read} V"
        );
        // The wheel turns: the true-rpm gauge leaves zero.
        eventually(
            &c,
            "the wheel gauge",
            Duration::from_secs(15),
            |t| t.parse::<f64>().is_ok_and(|v| v > 100.0),
            "#g-wheel .num",
        )
        .await;

        // Bad check on the MEB link, switched on in the page: the monitor shows the bad frame.
        c.find(Locator::Css("#fault-bad-check-meb"))
            .await
            .expect("a bad-check switch for link meb")
            .click()
            .await
            .unwrap();
        eventually(
            &c,
            "the fault badge",
            Duration::from_secs(5),
            |t| t.contains("bad-check"),
            "#fault-badge",
        )
        .await;
        let mut meb = MebClient::connect(&session.meb, Duration::from_secs(2)).unwrap();
        let refused = meb.read(1, MebCmd::EA, 0, 6);
        assert!(refused.is_err(), "the MEB client sees the bad check");
        let bad = eventually(
            &c,
            "a bad frame in the monitor",
            Duration::from_secs(5),
            |t| !t.is_empty(),
            "#frames tr.bad td.dec",
        )
        .await;
        assert!(bad.contains('✗'), "{bad}");
        // The page's top for the picture: the click scrolled to the fault's row.
        c.execute("window.scrollTo(0, 0)", vec![]).await.unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let png = c.screenshot().await.unwrap();
        std::fs::write(screenshot_path("panel-laptop.png"), png).unwrap();
        c.find(Locator::Css("#fault-off-meb"))
            .await
            .unwrap()
            .click()
            .await
            .unwrap();
        eventually(
            &c,
            "the fault off",
            Duration::from_secs(5),
            |t| t.is_empty(),
            "#fault-badge",
        )
        .await;

        // 30 stream clients beside the browser: everyone stays served.
        let addr = session.panel.addr_for_clients();
        let streams: Vec<_> = (0..30)
            .map(|_| std::thread::spawn(move || common::stream_updates(addr, 3.0)))
            .collect();
        let before = text(&c, "#clock").await;
        tokio::time::sleep(Duration::from_secs(2)).await;
        let after = text(&c, "#clock").await;
        assert_ne!(before, after, "the page keeps updating beside 30 streams");
        let counts: Vec<usize> = streams.into_iter().map(|s| s.join().unwrap()).collect();
        assert!(counts.iter().all(|&n| n >= 20), "{counts:?}");
        c.close().await.unwrap();
    });
}

#[test]
fn at_phone_width_nothing_scrolls_sideways_and_the_gauges_show_numbers() {
    let session = serve("127.0.0.1:0", AccessOptions::default(), 60.0);
    start_wheel(&session.meb);
    let driver = chromedriver();
    runtime().block_on(async {
        let c = browser(&driver, "phone", true).await;
        c.goto(&session.panel.url).await.unwrap();
        for id in ["v1", "v2", "i", "soc", "hall", "light", "wheel"] {
            let css = format!("#g-{id} .num");
            eventually(&c, &css, Duration::from_secs(10), |t| t.parse::<f64>().is_ok(), &css).await;
        }
        // Let the trend and the monitor fill, then measure.
        tokio::time::sleep(Duration::from_secs(3)).await;
        let width = c
            .execute("return [window.innerWidth, document.documentElement.scrollWidth, document.body.scrollWidth];", vec![])
            .await
            .unwrap();
        let w: Vec<i64> = serde_json::from_value(width).unwrap();
        assert_eq!(w[0], 390, "the phone's viewport");
        assert!(w[1] <= 390 && w[2] <= 390, "the page scrolls sideways: {w:?}");
        c.close().await.unwrap();
    });
}
