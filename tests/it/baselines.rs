//! Every embedded scenario against its baseline recording in
//! `recordings/baselines/`: a change to the physics or a protocol fails here
//! with the signal and the time where the run departs. If the change is
//! meant, re-record: `cargo run --release -p twin -- baseline --record`.

use std::path::Path;
use twin_recording::compare;
use twin_sim::baseline;

#[test]
fn every_embedded_scenario_matches_its_baseline() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../recordings/baselines");
    let scratch = std::env::temp_dir().join(format!("e2e-baselines-{}", std::process::id()));
    std::fs::create_dir_all(&scratch).expect("temp dir");
    let mut failures = Vec::new();
    for name in baseline::names() {
        let c = baseline::check(&dir, name, &scratch.join(format!("{name}.mcap")), |_| {})
            .unwrap_or_else(|e| panic!("{name}: {e:#}"));
        assert!(!c.rows.is_empty(), "{name}: no signals compared");
        if !c.passed() {
            let first = c
                .failures()
                .filter_map(|r| Some((r.first_beyond_s?, r.signal.clone())))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            failures.push(format!(
                "{name}: first departure {first:?}{}\n{}",
                c.span_mismatch.as_deref().unwrap_or(""),
                compare::table(&c, false)
            ));
        }
    }
    let _ = std::fs::remove_dir_all(&scratch);
    assert!(
        failures.is_empty(),
        "runs depart from their baselines (re-record with `twin baseline --record` if meant):\n{}",
        failures.join("\n")
    );
}

#[test]
fn baselines_stay_small() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../recordings/baselines");
    let total: u64 = baseline::names()
        .iter()
        .map(|n| std::fs::metadata(baseline::path(&dir, n)).map_or(0, |m| m.len()))
        .sum();
    assert!(
        total < 1_000_000,
        "baselines take {total} bytes: cut them down in baselines.toml"
    );
}
