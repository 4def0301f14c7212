//! `twin experiment pwmcap` runs and prints the paper's figures beside the model's.

use std::process::Command;

fn run(args: &[&str]) -> String {
    let output = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["experiment", "pwmcap"])
        .args(args)
        .output()
        .expect("twin runs");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout).expect("utf-8 output")
}

#[test]
fn prints_table2_reliability_and_cable_length() {
    let out = run(&["--cable-limit-m", "200"]);
    for expected in [
        "Table 2",
        "64.000 µs",
        "92.000 µs",
        "13.653 µs",
        "14.320 µs",
        "4.69×",
        "6.42×",
        "accuracy",
        "precision",
        "recall",
        "sent 1 read 1 = TP",
        "calibrated",
        "paper (1, 5, 20 Ω rows)",
        "Longest cable without a bit error",
    ] {
        assert!(out.contains(expected), "missing {expected:?} in:\n{out}");
    }
    // One initial and one calibrated row for each of the three impedances:
    // "+R Ω", "τ ticks", mode, then four figures.
    let mode_rows = |mode: &str| {
        out.lines()
            .filter(|l| {
                let tokens: Vec<&str> = l.split_whitespace().collect();
                tokens.get(2) == Some(&mode)
                    && tokens.len() == 11
                    && tokens[3]
                        .parse::<f64>()
                        .is_ok_and(|a| (0.0..=1.0).contains(&a))
            })
            .count()
    };
    assert_eq!(mode_rows("initial"), 3, "{out}");
    assert_eq!(mode_rows("calibrated"), 3, "{out}");
}

#[test]
fn output_is_determined_by_the_seed() {
    let args = ["--cable-limit-m", "0", "--seed", "11"];
    assert_eq!(run(&args), run(&args));
    assert_ne!(run(&args), run(&["--cable-limit-m", "0", "--seed", "12"]));
}

#[test]
fn bad_options_fail_cleanly() {
    let output = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["experiment", "pwmcap", "--signals", "0"])
        .output()
        .expect("twin runs");
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("--signals"));
}

#[test]
fn the_cable_can_be_a_distributed_line() {
    let lumped = run(&["--cable-limit-m", "0", "--signals", "20"]);
    let elmore = run(&[
        "--cable-limit-m",
        "0",
        "--signals",
        "20",
        "--cable-model",
        "elmore",
    ]);
    assert!(elmore.contains("distributed RC line"), "{elmore}");
    assert!(!lumped.contains("distributed RC line"), "{lumped}");
    // The 20 Ω row's time constant: 138.0 ticks lumped, 136.5 distributed.
    assert!(lumped.contains("138.0"), "{lumped}");
    assert!(elmore.contains("136.5"), "{elmore}");
}
