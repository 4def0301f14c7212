//! `twin experiment parallel` as a user runs it: four recordings written,
//! one table row each, read back from them.

use std::process::Command;

#[test]
fn runs_the_four_links_and_prints_one_row_each() {
    let dir = std::env::temp_dir().join(format!("twin-parallel-cli-{}", std::process::id()));
    let output = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["experiment", "parallel", "--duration", "1", "--out-dir"])
        .arg(&dir)
        .output()
        .expect("twin runs");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let out = String::from_utf8(output.stdout).expect("utf-8");
    assert!(out.contains("latency mean / max"), "{out}");
    for name in [
        "parallel-pwm-broadcast",
        "parallel-pwm-designated",
        "parallel-rtu-115200",
        "parallel-rtu-1m",
    ] {
        let row = out
            .lines()
            .find(|l| l.trim_start().starts_with(name))
            .unwrap_or_else(|| panic!("no row for {name}:\n{out}"));
        let cycle_ms: f64 = row
            .split_whitespace()
            .nth(1)
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("cycle in {row}"));
        // PWM keeps the 1 ms update; Modbus cannot.
        if name.contains("pwm") {
            assert!((cycle_ms - 1.0).abs() < 0.01, "{row}");
        } else {
            assert!(cycle_ms > 3.9, "{row}");
        }
        let recording = dir.join(format!("{name}.mcap"));
        assert!(std::fs::metadata(&recording).expect("recording").len() > 10_000);
    }
}

#[test]
fn a_bad_duration_is_refused() {
    let output = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["experiment", "parallel", "--duration=-1"])
        .output()
        .expect("twin runs");
    assert!(!output.status.success());
    let err = String::from_utf8_lossy(&output.stderr);
    assert!(err.contains("must be above 0, got -1"), "{err}");
}
