//! The frame monitor's scope in a real browser: `twin supervise --web`
//! polling `twin serve` over a `twin vsp` pair at 57600 baud. The frames the
//! scope draws are read back from its SVG paths, bit by bit (start bit,
//! eight data bits least significant first, stop bit), and must be the
//! frames the monitor lists, at the link's baud, each side on its trace.

use crate::browser::screenshot_path;
use crate::common::{chromedriver, serve_on, supervise, vsp};
use crate::page::{click, js, open, runtime, until};
use serde_json::Value;
use std::time::Duration;
use twin_panel::AccessOptions;

const BAUD: u32 = 57_600;

/// The scope's frames and the monitor's rows, read in one script.
const READ: &str = "(() => {
  const svg = document.getElementById('scope');
  const paths = [...svg.querySelectorAll('path.bits')].map((p) => ({
    d: p.getAttribute('d'), cls: p.getAttribute('class'), t: +p.dataset.t,
    x0: +p.dataset.x0, bit: +p.dataset.bit, high: +p.dataset.high, low: +p.dataset.low,
    chars: +p.dataset.chars, per_char: +p.dataset.bitsPerChar }));
  const rows = [...document.querySelectorAll('#frames tbody tr')].map((r) =>
    [r.cells[0].textContent, r.cells[2].textContent, r.cells[3].textContent, r.cells[4].textContent]);
  return { link: svg.dataset.link, baud: +svg.dataset.baud, paths, rows,
    note: document.getElementById('scope-note').textContent };
})()";

/// The line's level along a path of `M x y`, `H x` and `V y` commands:
/// the horizontal runs, `(from, to, y)`.
fn runs(d: &str) -> Vec<(f64, f64, f64)> {
    let mut out = Vec::new();
    let (mut x, mut y) = (f64::NAN, f64::NAN);
    let mut rest = d.trim();
    while let Some(command) = rest.chars().next() {
        let body = &rest[1..];
        let end = body
            .find(|c: char| c.is_ascii_alphabetic())
            .unwrap_or(body.len());
        let args: Vec<f64> = body[..end]
            .split_whitespace()
            .map(|v| v.parse().expect("a number in the path"))
            .collect();
        match command {
            'M' => (x, y) = (args[0], args[1]),
            'H' => {
                out.push((x, args[0], y));
                x = args[0];
            }
            'V' => y = args[0],
            other => panic!("unexpected command {other} in {d}"),
        }
        rest = &body[end..];
    }
    out
}

/// The bytes a frame's path draws: each character sampled at its bits'
/// middles, its start bit low and its stop bit high.
fn decode(p: &Value) -> Vec<u8> {
    let n = |k: &str| p[k].as_f64().unwrap_or(f64::NAN);
    let (x0, bit, high, low) = (n("x0"), n("bit"), n("high"), n("low"));
    let runs = runs(p["d"].as_str().unwrap());
    let level = |k: f64| -> bool {
        let x = x0 + (k + 0.5) * bit;
        let (_, _, y) = runs
            .iter()
            .find(|(a, b, _)| *a <= x && x < *b)
            .unwrap_or_else(|| panic!("no line at x {x} in {p}"));
        assert!(*y == high || *y == low, "a level between the two: {p}");
        *y == high
    };
    let per_char = n("per_char");
    assert_eq!(per_char, 10.0, "8N1: {p}");
    (0..n("chars") as usize)
        .map(|c| {
            let first = c as f64 * per_char;
            assert!(!level(first), "character {c}: its start bit is high: {p}");
            assert!(
                level(first + 9.0),
                "character {c}: its stop bit is low: {p}"
            );
            (0..8).fold(0u8, |byte, i| {
                byte | (u8::from(level(first + 1.0 + f64::from(i))) << i)
            })
        })
        .collect()
}

#[test]
fn the_scope_draws_the_bits_of_the_frames_the_monitor_lists() {
    let driver = chromedriver();
    let [a, b] = vsp("scope");
    let line = |end: &std::path::Path| format!("{}?baud={BAUD}", end.display());
    let _slave = serve_on(&line(&b), "127.0.0.1:0", AccessOptions::default(), 90.0);
    let supervised = supervise(&line(&a), "127.0.0.1:0", 90.0);
    runtime().block_on(async {
        let c = open(&driver, "scope", &supervised.panel.url).await;
        // Requests and replies on the bus, both drawn.
        until("the scope's traces", Duration::from_secs(20), async || {
            let seen = js(&c, READ).await;
            let paths = seen["paths"].as_array().map_or(0, Vec::len);
            (paths >= 4, seen.to_string())
        })
        .await;
        // Frozen, the monitor and the scope show the same frames.
        click(&c, "#pause").await;
        let seen = js(&c, READ).await;
        assert_eq!(seen["link"], "bus", "{seen}");
        assert_eq!(seen["baud"].as_f64(), Some(f64::from(BAUD)), "{seen}");
        assert!(
            seen["note"].as_str().unwrap().contains("57600 baud 8N1"),
            "{seen}"
        );
        let rows = seen["rows"].as_array().unwrap();
        let mut paths = seen["paths"].as_array().unwrap().clone();
        assert_eq!(paths.len(), 4, "four frames on a laptop: {seen}");
        paths.sort_by(|p, q| {
            p["t"]
                .as_f64()
                .unwrap()
                .total_cmp(&q["t"].as_f64().unwrap())
        });
        // The monitor lists the newest first: its first four rows are the scope's.
        for (p, row) in paths.iter().rev().zip(rows) {
            let row: Vec<&str> = row
                .as_array()
                .unwrap()
                .iter()
                .map(|c| c.as_str().unwrap())
                .collect();
            // The monitor shows t to 0.1 ms.
            let listed: f64 = row[0].parse().unwrap();
            assert!(
                (listed - p["t"].as_f64().unwrap()).abs() <= 0.000_051,
                "{p} {row:?}"
            );
            assert_eq!(row[1], "bus");
            // MEB's text, and its line end, which the monitor does not show.
            let bytes = decode(p);
            let text = String::from_utf8(bytes).expect("MEB is text");
            assert_eq!(text.trim_end(), row[3], "{p}");
            assert!(text.ends_with('\n'), "the line end is drawn too: {text:?}");
            let (upper, lower) = (18.0, 82.0);
            if row[2].starts_with("twin →") {
                assert!(p["cls"].as_str().unwrap().contains("out"), "{p}");
                assert_eq!(p["high"].as_f64(), Some(upper), "{p}");
            } else {
                assert!(p["cls"].as_str().unwrap().contains("in"), "{p}");
                assert_eq!(p["high"].as_f64(), Some(lower), "{p}");
            }
        }
        // Left to right in time on each line, one frame at a time: a frame
        // recorded as starting before the last on its side had ended (a pty
        // carries no line timing, so a request and its reply may share a
        // time stamp) is drawn after it, never over it.
        let placed: Vec<_> = paths
            .iter()
            .map(|p| (&p["t"], &p["x0"], &p["cls"]))
            .collect();
        for side in ["in", "out"] {
            let mut ends = f64::NEG_INFINITY;
            for p in paths
                .iter()
                .filter(|p| p["cls"].as_str().unwrap().split(' ').any(|c| c == side))
            {
                let x0 = p["x0"].as_f64().unwrap();
                assert!(x0 >= ends - 0.01, "{side}: {placed:?}");
                let bits = p["chars"].as_f64().unwrap() * p["per_char"].as_f64().unwrap();
                ends = x0 + bits * p["bit"].as_f64().unwrap();
            }
        }
        // Coordinates are drawn to 0.01 px and a bit's width given to 0.0001 px.
        for p in &paths {
            let last = runs(p["d"].as_str().unwrap()).last().unwrap().1;
            let drawn = (last - p["x0"].as_f64().unwrap()) / p["bit"].as_f64().unwrap();
            let chars = p["chars"].as_f64().unwrap();
            assert!(
                (drawn - chars * 10.0).abs() < 0.1,
                "{drawn} bits for {chars} chars: {p}"
            );
        }
        if std::env::var_os("TWIN_PANEL_SCREENSHOTS").is_some() {
            js(
                &c,
                "document.getElementById('scope').scrollIntoView({block: 'center'})",
            )
            .await;
            let png = c.screenshot().await.unwrap();
            std::fs::write(screenshot_path("panel-scope.png"), png).unwrap();
        }
        c.close().await.unwrap();
    });
}
