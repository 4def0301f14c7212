//! A class in one browser, as its teacher and two students meet it: two
//! modules served side by side, each panel behind its own token, both open
//! in one Chromium, and the class's index behind the teacher's token.
//!
//! A browser keeps cookies per host, not per port: with one cookie name
//! for every panel, logging in to the second module's panel replaced the
//! first's token and its bookmark (the URL without `?token=`) got 401.

use crate::browser::screenshot_path;
use crate::common::{self, ClientAddr, chromedriver, http, serve_module};
use crate::page::{js, open, text, until};
use fantoccini::Client;
use protocols::meb::MebCmd;
use std::time::Duration;
use twin_panel::{AccessOptions, ClassIndex, ClassModule};
use twin_realtime::client::MebClient;

/// The panel's address without its token: a student's bookmark.
fn bare(url: &str) -> String {
    url.split_once('?').map_or(url, |(u, _)| u).to_string()
}

/// Waits until the page shows V1 from its stream, proof that its token
/// was taken (a refused page has no gauges).
async fn loads_its_data(c: &Client, who: &str) {
    until(
        &format!("{who}'s V1 gauge"),
        Duration::from_secs(15),
        async || {
            let v1 = text(c, "#g-v1 .num").await;
            let heading = text(c, "h1").await;
            (
                v1.parse::<f64>().is_ok_and(|v| v > 20.0),
                format!("V1 `{v1}`, heading `{heading}`"),
            )
        },
    )
    .await;
}

/// The page names its module and its role, in its title and its heading.
async fn names(c: &Client, module: &str) {
    let title = js(c, "document.title").await;
    let title = title.as_str().unwrap_or_default();
    assert!(
        title.starts_with(module) && title.contains("module (twin serve)"),
        "the title names {module} and its role: `{title}`"
    );
    assert_eq!(text(c, "h1 #module").await, module);
    assert_eq!(text(c, "h1 #role").await, "module (twin serve)");
}

#[test]
fn two_students_panels_stay_open_side_by_side_and_the_teachers_index_links_both() {
    let dir = common::fresh_dir("class-tokens");
    let module = |name: &str| {
        serve_module(
            "tcp://127.0.0.1:0",
            "127.0.0.1:0",
            AccessOptions {
                token_file: Some(dir.join(format!("{name}.token"))),
                read_only: false,
            },
            90.0,
            true,
            Some(name),
        )
    };
    let (one, two) = (module("student01"), module("student02"));
    assert_ne!(one.panel.url, two.panel.url);
    let index = ClassIndex::bind("127.0.0.1:0".parse().unwrap(), &dir.join("teacher.token"))
        .expect("the index binds");
    let index_url = index.running().url;
    index
        .start(
            [("student01", &one), ("student02", &two)]
                .into_iter()
                .map(|(name, s)| ClassModule {
                    name: name.into(),
                    panel: s.feed.clone(),
                    record: None,
                })
                .collect(),
        )
        .expect("the index starts");
    // Over HTTP first: a bare panel request is refused, so the browser's
    // cookie is what opens the bookmarks below.
    for s in [&one, &two] {
        let (status, _) = http(&s.panel, "GET", "/api/state", None, false);
        assert_eq!(status, 401, "{} needs its token", s.panel.url);
    }
    let driver = chromedriver();
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            let c = open(&driver, "class", &one.panel.url).await;
            loads_its_data(&c, "student01").await;
            names(&c, "student01").await;
            let first = c.window().await.unwrap();
            // The second student's panel, in a tab of the same browser.
            let tab = c.new_window(true).await.unwrap();
            c.switch_to_window(tab.handle).await.unwrap();
            c.goto(&two.panel.url).await.unwrap();
            loads_its_data(&c, "student02").await;
            names(&c, "student02").await;
            // Both bookmarks, opened without the token after the second
            // student logged in: each panel's own cookie holds.
            c.goto(&bare(&two.panel.url)).await.unwrap();
            loads_its_data(&c, "student02 (bookmark)").await;
            c.switch_to_window(first).await.unwrap();
            c.goto(&bare(&one.panel.url)).await.unwrap();
            loads_its_data(&c, "student01 (bookmark, after student02 logged in)").await;
            names(&c, "student01").await;
            let cookies: Vec<String> = c
                .get_all_cookies()
                .await
                .unwrap()
                .iter()
                .map(|k| k.name().to_string())
                .collect();
            for s in [&one, &two] {
                let own = format!("twin_panel_token_{}", s.panel.addr_for_clients().port());
                assert!(cookies.contains(&own), "{own} among {cookies:?}");
            }
            // The index without the teacher's token, and with a student's.
            c.goto(&bare(&index_url)).await.unwrap();
            let refused = text(&c, "h1").await;
            assert!(refused.contains("teacher's token"), "{refused}");
            let student = common::token_of(&one.panel).unwrap();
            c.goto(&format!("{}?token={student}", bare(&index_url)))
                .await
                .unwrap();
            let refused = text(&c, "h1").await;
            assert!(refused.contains("teacher's token"), "{refused}");
            // A request on student01's link: the index says how long ago.
            let mut meb =
                MebClient::connect(&one.meb, Duration::from_secs(2)).expect("MEB connects");
            meb.read(1, MebCmd::EA, 0, 6).expect("EA reads");
            // With it: both modules, each with a link that opens its panel.
            c.goto(&index_url).await.unwrap();
            until(
                "student01's last request on the index",
                Duration::from_secs(15),
                async || {
                    let last = text(&c, "#module-student01 .last").await;
                    let none = text(&c, "#module-student02 .last").await;
                    (
                        last.ends_with(" ago") && none == "none yet",
                        format!("`{last}`, `{none}`"),
                    )
                },
            )
            .await;
            let png = c.screenshot().await.unwrap();
            std::fs::write(screenshot_path("class-index-laptop.png"), png).unwrap();
            let rows = js(
                &c,
                "[...document.querySelectorAll('#modules tbody tr')].map(r => r.id)",
            )
            .await;
            assert_eq!(
                rows,
                serde_json::json!(["module-student01", "module-student02"]),
                "the index lists the class in its order"
            );
            // The page reloads itself every 2 s: the link is read, then
            // followed, so a reload between finding and clicking it cannot
            // leave the test holding a stale element.
            let link = js(
                &c,
                "document.querySelector('#module-student02 a.panel-link')?.href ?? ''",
            )
            .await;
            let link = link.as_str().unwrap_or_default().to_string();
            assert!(
                link.starts_with(&bare(&two.panel.url)),
                "student02's link `{link}` is its panel, {}",
                two.panel.url
            );
            c.goto(&link).await.unwrap();
            loads_its_data(&c, "student02, from the index").await;
            names(&c, "student02").await;
            c.close().await.unwrap();
        });
    let _ = std::fs::remove_dir_all(&dir);
}
