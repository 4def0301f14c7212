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
fn table2_has_an_initial_and_a_calibrated_row_per_impedance() {
    // The whole table, as it prints it: tests/cmd/experiment-pwmcap.trycmd.
    let out = run(&["--cable-limit-m", "200"]);
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

// Bad options fail cleanly, and the cable can be a distributed RC line:
// tests/cmd/experiment-pwmcap.trycmd.
