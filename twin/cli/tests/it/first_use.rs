//! What a new user meets first, run from a folder outside the repository as
//! the manual's commands are: every kind of recording replays or is refused
//! in words, baselines are found from anywhere and never made up, compare
//! says first when two recordings come from different runs, runs say what
//! they replace, real-time sessions never write over the last one, `twin
//! step` leaves its figures, `twin export` one time column.
//!
//! What the commands that end on their own print there (replays, compares,
//! baselines, what a run replaced) is checked whole by the cases
//! `tests/cmd/first-use-*.trycmd`; here are the checks of files, and of the
//! sessions that need a second process or are named by the clock.

use crate::support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use support::{Proc, text};

/// `twin ARGS` run in `dir`.
fn twin_in(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .output()
        .expect("twin runs")
}

/// `twin ARGS` in `dir`, which must succeed; what it printed.
fn ok_in(dir: &Path, args: &[&str]) -> String {
    let o = twin_in(dir, args);
    assert!(o.status.success(), "twin {}: {}", args.join(" "), text(&o));
    text(&o)
}

/// A fresh folder outside the repository.
fn folder(name: &str) -> PathBuf {
    support::folder("first-use", name)
}

/// The files in `dir` whose names start with `prefix`.
fn files_starting(dir: &Path, prefix: &str) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .expect("folder")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(prefix))
        .collect();
    names.sort();
    names
}

/// A step recording made before the step's settings were stored: its
/// messages and a `twin.run` without them.
#[test]
fn an_earlier_step_recording_is_refused_in_words() {
    let dir = folder("old-step");
    ok_in(
        &dir,
        &["step", "--open-loop", "--duration", "1", "--at", "0.5"],
    );
    let recording = twin_recording::Recording::read(&dir.join("step.mcap")).expect("readable");
    let mut run = recording.metadata["twin.run"].clone();
    run.retain(|k, _| k != "experiment" && !k.starts_with("step_"));
    let bytes = std::fs::read(dir.join("step.mcap")).expect("recording");
    let old = dir.join("old.mcap");
    let mut rec = twin_recording::record::Recorder::create(&old).expect("create");
    rec.write_metadata("twin.run", run).expect("metadata");
    for m in mcap::MessageStream::new(&bytes).expect("valid MCAP") {
        let m = m.expect("message");
        let v: serde_json::Value =
            twin_recording::read::value_of(&m.channel, &m.data).expect("a message that reads");
        if !rec.has_channel(&m.channel.topic) {
            rec.add_channel(&m.channel.topic, &v).expect("channel");
        }
        rec.write(&m.channel.topic, m.log_time as f64 * 1e-9, &v)
            .expect("write");
    }
    rec.finish().expect("finish");
    let o = twin_in(&dir, &["replay", "old.mcap"]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("a step response recorded by an earlier twin") && !err.contains("absent"),
        "{err}"
    );
}

#[test]
fn a_real_time_session_is_refused_in_words_and_named_by_its_start_time() {
    let dir = folder("serve");
    let serve = [
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--duration",
        "0.5",
        "--quiet",
    ];
    let first = ok_in(&dir, &serve);
    let second = ok_in(&dir, &serve);
    let sessions = files_starting(&dir, "serve-");
    assert_eq!(sessions.len(), 2, "{sessions:?}\n{first}\n{second}");
    let named: Vec<&str> = [&first, &second]
        .iter()
        .map(|printed| {
            assert!(!printed.contains("replaced"), "{printed}");
            printed
                .lines()
                .find_map(|l| l.strip_prefix("recording: "))
                .unwrap_or_else(|| panic!("no recording named: {printed}"))
        })
        .collect();
    assert_ne!(named[0], named[1]);
    for name in named {
        assert!(
            sessions.iter().any(|s| s == name),
            "{name} not in {sessions:?}"
        );
        assert!(
            name.ends_with(".mcap") && name.len() >= "serve-2026-12-03T07-35-44.mcap".len(),
            "{name}"
        );
    }
    let o = twin_in(&dir, &["replay", &sessions[0]]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("is a `twin serve` session")
            && err.contains("cannot be run again")
            && err.contains("--frames-to"),
        "{err}"
    );
    assert!(!err.contains("unknown run kind"), "{err}");
    // Told where, a session replaces the file and says what it held.
    ok_in(
        &dir,
        &[
            "serve",
            "--meb",
            "tcp://127.0.0.1:0",
            "--duration",
            "0.5",
            "--quiet",
            "--out",
            "mine.mcap",
        ],
    );
    let again = ok_in(
        &dir,
        &[
            "serve",
            "--meb",
            "tcp://127.0.0.1:0",
            "--duration",
            "0.5",
            "--quiet",
            "--out",
            "mine.mcap",
        ],
    );
    assert!(
        again.contains(
            "recording: mine.mcap (replaced the one there before: a `twin serve` session, seed 1)"
        ),
        "{again}"
    );
}

#[test]
fn a_supervise_session_is_refused_in_words_too() {
    let dir = folder("supervise");
    let slave = Proc::start(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--no-record",
    ]);
    let link = format!("tcp://{}", slave.tcp_of("meb"));
    let printed = ok_in(
        &dir,
        &[
            "supervise",
            "--meb",
            &link,
            "--no-server",
            "--duration",
            "0.5",
            "--quiet",
        ],
    );
    let sessions = files_starting(&dir, "supervise-");
    assert_eq!(sessions.len(), 1, "{sessions:?}: {printed}");
    assert!(
        printed.contains(&format!("recording: {}", sessions[0])),
        "{printed}"
    );
    let o = twin_in(&dir, &["replay", &sessions[0]]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("is a `twin supervise` session") && err.contains("--frames-to LINK"),
        "{err}"
    );
}

/// Recording never starts a new set of baselines by mistake: no folder is
/// made. What `twin baseline` prints, from anywhere, with the repository's
/// baselines or a folder that lacks one, is `tests/cmd/first-use-baselines.trycmd`.
#[test]
fn recording_a_baseline_never_makes_its_folder() {
    let dir = folder("baselines");
    let o = twin_in(
        &dir,
        &[
            "baseline",
            "--record",
            "ev-meb",
            "--dir",
            "recordings/baselines",
        ],
    );
    assert!(!o.status.success(), "{}", text(&o));
    assert!(!dir.join("recordings").exists(), "a folder was created");
}

/// What it prints, and the second time what it replaced:
/// `tests/cmd/first-use-step-here.trycmd`.
#[test]
fn step_without_out_leaves_its_figures_here() {
    let dir = folder("step-here");
    ok_in(
        &dir,
        &["step", "--open-loop", "--duration", "2", "--at", "0.5"],
    );
    for file in ["step.json", "step.png", "step.mcap"] {
        assert!(dir.join(file).is_file(), "no {file}");
    }
}

/// What it prints, and the second time what it replaced:
/// `tests/cmd/first-use-sweep-here.trycmd`.
#[test]
fn sweep_without_out_leaves_its_figures_here() {
    let dir = folder("sweep-here");
    ok_in(
        &dir,
        &[
            "sweep",
            "--detector",
            "fixed",
            "--points",
            "2",
            "--rpm",
            "100",
            "200",
            "--settle",
            "0.5",
            "--measure",
            "0.5",
        ],
    );
    for file in ["sweep.json", "sweep.png"] {
        assert!(dir.join(file).is_file(), "no {file}");
    }
}

#[test]
fn export_writes_one_time_column() {
    let dir = folder("export");
    ok_in(&dir, &["run", "--duration", "0.5"]);
    ok_in(&dir, &["export", "ev-meb.mcap", "--csv", "csv"]);
    let sensors = std::fs::read_to_string(dir.join("csv/plant_ev1_sensors.csv")).expect("csv");
    let header: Vec<&str> = sensors.lines().next().expect("header").split(',').collect();
    assert_eq!(
        header.iter().filter(|c| c.contains("time_s")).count(),
        1,
        "{header:?}"
    );
    assert_eq!(header[0], "time_s");
    let row: Vec<&str> = sensors.lines().nth(2).expect("a row").split(',').collect();
    assert_eq!(row.len(), header.len());
    // What it prints, and the second time what it replaced:
    // tests/cmd/first-use-export.trycmd.
}
