//! `twin step` and `twin sweep` from the command line: the files of `--out
//! DIR`. Their tables and refusals, as printed, are the cases
//! `tests/cmd/step-*.trycmd`.

use std::path::PathBuf;
use std::process::{Command, Output};

fn twin(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(args)
        .output()
        .expect("twin runs")
}

fn ok(args: &[&str]) -> String {
    let o = twin(args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8(o.stdout).expect("utf-8 output")
}

fn scratch(name: &str) -> PathBuf {
    let dir = crate::support::scratch("step", name);
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn is_png(path: &PathBuf) -> bool {
    let bytes = std::fs::read(path).unwrap_or_default();
    bytes.len() > 1000 && bytes.starts_with(b"\x89PNG\r\n\x1a\n")
}

#[test]
fn open_loop_step_writes_figures_plot_and_recording() {
    let dir = scratch("open");
    let d = dir.to_str().expect("utf-8 path");
    // Its table: tests/cmd/step-open-loop.trycmd.
    ok(&["step", "--open-loop", "--out", d]);
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("step.json")).expect("step.json"))
            .expect("valid JSON");
    assert_eq!(json["mode"], "open-loop");
    let signals = json["signals"].as_array().expect("signals");
    assert_eq!(signals.len(), 3);
    for s in signals {
        assert!(
            s["metrics"]["rise_time_s"]
                .as_f64()
                .is_some_and(|r| r > 0.0),
            "{s}"
        );
    }
    // Both sensors lag the true speed, the light sensor more.
    let lag = |i: usize| signals[i]["delay_s"].as_f64().expect("delay");
    assert!(0.0 < lag(1) && lag(1) < lag(2), "{json}");
    assert!(is_png(&dir.join("step.png")));
    // The recording opens in the Python `mcap` reader, with a sample of the
    // step channel every 2 ms of the 6 s and the run's metadata.
    let script = r#"
import json, sys
from mcap.reader import make_reader
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f)
    summary = reader.get_summary()
    counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
    meta = {m.name: m.metadata for m in reader.iter_metadata()}
print(json.dumps({"counts": counts, "vel_before": meta["twin.run"]["vel_before_fraction"]}))
"#;
    let o = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(dir.join("step.mcap"))
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "the Python `mcap` package must read it (pip install mcap): {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("JSON");
    assert_eq!(v["counts"]["/experiment/step"], 3000);
    assert_eq!(v["vel_before"], "0.025");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_default_scenarios_light_sensor_is_measured_at_its_own_speeds() {
    // ev-meb's controller runs the adaptive detector: the step names it,
    // with its limit (tests/cmd/step-open-loop.trycmd), and at 1000 → 1500
    // rpm the light sensor has figures.
    let dir = scratch("adaptive");
    let d = dir.to_str().expect("utf-8 path");
    let out = ok(&["step", "--from", "1000", "--to", "1500", "--out", d]);
    let light = out
        .lines()
        .find(|l| l.trim_start().starts_with("light sensor"))
        .unwrap_or_else(|| panic!("no light sensor row in:\n{out}"));
    let last = light.split_whitespace().collect::<Vec<_>>();
    let final_rpm: f64 = last[3].parse().expect("its final rpm");
    assert!((final_rpm - 1500.0).abs() < 40.0, "{out}");
}

#[test]
fn sweep_writes_its_figures_plot_and_runs() {
    let dir = scratch("sweep");
    let d = dir.to_str().expect("utf-8 path");
    // Where the light sensor fails, as it prints it: tests/cmd/step-open-loop.trycmd.
    ok(&[
        "sweep",
        "--detector",
        "fixed",
        "--rpm",
        "150",
        "350",
        "--points",
        "5",
        "--settle",
        "2",
        "--measure",
        "2",
        "--out",
        d,
    ]);
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("sweep.json")).expect("sweep.json"))
            .expect("valid JSON");
    assert_eq!(json[0]["points"].as_array().map(Vec::len), Some(5));
    assert!(is_png(&dir.join("sweep.png")));
    let runs = std::fs::read_dir(dir.join("runs/fixed"))
        .expect("runs")
        .count();
    assert_eq!(runs, 5);
    let _ = std::fs::remove_dir_all(&dir);
}

// What cannot run is refused with the reason: tests/cmd/step-refusals.trycmd.

#[test]
fn a_missing_font_says_what_to_install_and_keeps_the_figures() {
    let dir = scratch("font");
    std::fs::create_dir_all(&dir).expect("scratch folder");
    let not_a_font = dir.join("not-a-font.ttf");
    std::fs::write(&not_a_font, b"plain text").expect("file");
    let out = dir.join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(["step", "--open-loop", "--out", out.to_str().expect("utf-8")])
        .env("TWIN_FONT", &not_a_font)
        .output()
        .expect("twin runs");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("not a TrueType font"), "{err}");
    // The run and its figures are not lost with the plot.
    assert!(out.join("step.json").exists() && out.join("step.mcap").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_open_loop_light_detector_defaults_as_twin_serve_and_ev_meb_have_it() {
    // `twin serve`'s default, read from its help (the real-time module).
    let serve = ok(&["serve", "--help"]);
    let at = serve
        .find("--light-detector")
        .expect("serve has --light-detector");
    assert!(
        serve[at..].contains("[default: adaptive]"),
        "twin serve's default light detector changed: {}",
        &serve[at..at + 600]
    );
    // `twin step --open-loop`'s, from its report: the same, and `fixed`
    // when asked.
    let dir = scratch("detector");
    let d = dir.to_str().expect("utf-8 path");
    let default = ok(&[
        "step",
        "--open-loop",
        "--duration",
        "1",
        "--at",
        "0.5",
        "--out",
        d,
    ]);
    assert!(
        default.contains("light detector: EV controller, adaptive"),
        "{default}"
    );
    let fixed = ok(&[
        "step",
        "--open-loop",
        "--duration",
        "1",
        "--at",
        "0.5",
        "--light-detector",
        "fixed",
        "--out",
        d,
    ]);
    assert!(
        fixed.contains("light detector: EV controller, fixed"),
        "{fixed}"
    );
    // The Controller_network light Nano has no adaptive detector: asked for
    // one, the step says so instead of running the fixed one silently.
    let o = twin(&[
        "step",
        "--open-loop",
        "--preset",
        "controller-network",
        "--light-detector",
        "adaptive",
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("has its fixed threshold only"), "{err}");
}
