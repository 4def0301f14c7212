//! The build profiles, as the manual's "Getting started" promises them: `cargo
//! install` (the release profile) makes a small binary with no debug info,
//! and the `profiling` and `bench` profiles keep the line tables that perf
//! needs to name lines and inlined calls.

use std::path::Path;
use toml::Value;

fn profile(name: &str) -> toml::Table {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../Cargo.toml");
    let text = std::fs::read_to_string(&root).expect("the workspace's Cargo.toml");
    let manifest: toml::Table = toml::from_str(&text).expect("Cargo.toml parses");
    manifest["profile"][name]
        .as_table()
        .unwrap_or_else(|| panic!("no [profile.{name}] in Cargo.toml"))
        .clone()
}

#[test]
fn the_installed_binary_has_no_debug_info() {
    let release = profile("release");
    let debug = release.get("debug");
    assert!(
        matches!(debug, Some(Value::Boolean(false)) | Some(Value::Integer(0))),
        "[profile.release] debug must be false (line tables for every dependency make the binary ten times larger), got {debug:?}"
    );
    let strip = release.get("strip");
    assert!(
        matches!(strip, Some(Value::String(s)) if s == "debuginfo" || s == "symbols")
            || matches!(strip, Some(Value::Boolean(true))),
        "[profile.release] strip must take the standard library's debug info out too, got {strip:?}"
    );
}

#[test]
fn profiling_and_bench_builds_keep_line_tables() {
    for name in ["profiling", "bench"] {
        let p = profile(name);
        assert_eq!(
            p.get("debug").and_then(Value::as_str),
            Some("line-tables-only"),
            "[profile.{name}] debug"
        );
        // Both inherit release's strip unless they say otherwise.
        assert_eq!(
            p.get("strip").and_then(Value::as_str),
            Some("none"),
            "[profile.{name}] strip"
        );
    }
    let profiling = profile("profiling");
    assert_eq!(
        profiling.get("inherits").and_then(Value::as_str),
        Some("release"),
        "the profiling build must be the release build's code"
    );
}
