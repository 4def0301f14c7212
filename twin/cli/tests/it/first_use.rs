//! What a new user meets first, run from a folder outside the repository as
//! the README's commands are: every kind of recording replays or is refused
//! in words, baselines are found from anywhere and never made up, compare
//! says first when two recordings come from different runs, runs say what
//! they replace, real-time sessions never write over the last one, `twin
//! step` leaves its figures, `twin export` one time column.

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
    let dir = std::env::temp_dir().join(format!("twin-first-use-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
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

#[test]
fn a_step_recording_replays_byte_for_byte_closed_and_open_loop() {
    let dir = folder("step-replay");
    ok_in(
        &dir,
        &["step", "--duration", "2", "--at", "0.5", "--out", "closed"],
    );
    let o = ok_in(&dir, &["replay", "closed/step.mcap"]);
    assert!(
        o.contains("step response, scenario ev-meb, set point 100 → 200 rpm at 0.5 s")
            && o.contains("byte-identical"),
        "{o}"
    );
    ok_in(
        &dir,
        &[
            "step",
            "--open-loop",
            "--duration",
            "2",
            "--at",
            "0.5",
            "--adaptive-light",
            "--out",
            "open",
        ],
    );
    let o = ok_in(&dir, &["replay", "open/step.mcap"]);
    assert!(
        o.contains("VEL 2.5 → 4.5 % at 0.5 s") && o.contains("byte-identical"),
        "{o}"
    );
    // A change to the bench is named where the replay departs.
    let o = twin_in(
        &dir,
        &[
            "replay",
            "open/step.mcap",
            "--set",
            "vel_fraction=0.05",
            "--out",
            "faster.mcap",
        ],
    );
    assert!(
        !o.status.success() && text(&o).contains("DEPARTS at"),
        "{}",
        text(&o)
    );
    // The step itself changes too: its set point after the step.
    let o = twin_in(
        &dir,
        &[
            "replay",
            "closed/step.mcap",
            "--set",
            "step.to=300",
            "--out",
            "to-300.mcap",
        ],
    );
    assert!(
        text(&o).contains("changed: step.to=300")
            && text(&o).contains(
                "DEPARTS at 0.500000 s on /experiment/step.set_point: recorded 200.0, replayed 300.0"
            ),
        "{}",
        text(&o)
    );
    let o = twin_in(
        &dir,
        &["replay", "closed/step.mcap", "--set", "step.size=3"],
    );
    assert!(
        !o.status.success()
            && text(&o)
                .contains("the step has `step.from`, `step.to` and `step.at_s`, not `step.size`"),
        "{}",
        text(&o)
    );
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
fn the_runs_of_a_sweep_replay() {
    let dir = folder("sweep-replay");
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
            "--out",
            "sweep",
        ],
    );
    let runs = dir.join("sweep/runs/fixed");
    let first = files_starting(&runs, "sweep-")
        .into_iter()
        .next()
        .expect("a run recorded");
    let o = ok_in(
        &dir,
        &["replay", s(&runs.join(first)), "--out", "again.mcap"],
    );
    assert!(o.contains("byte-identical"), "{o}");
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

#[test]
fn a_run_says_what_it_replaced() {
    let dir = folder("replaced");
    let first = ok_in(&dir, &["run", "--duration", "2"]);
    assert!(
        first.lines().any(|l| l == "recording: ev-meb.mcap"),
        "{first}"
    );
    let second = ok_in(&dir, &["run", "--duration", "1"]);
    assert!(
        second.contains(
            "recording: ev-meb.mcap (replaced the one there before: a scenario run of ev-meb, seed 1, 2 s)"
        ),
        "{second}"
    );
    let open = ok_in(&dir, &["run", "--open-loop", "--duration", "0.5"]);
    assert!(
        open.lines().any(|l| l == "recording: twin-run.mcap"),
        "{open}"
    );
    let open = ok_in(
        &dir,
        &["run", "--open-loop", "--duration", "0.5", "--seed", "2"],
    );
    assert!(
        open.contains("(replaced the one there before: an open-loop run on the vemodule preset, seed 1, 0.5 s)"),
        "{open}"
    );
}

#[test]
fn baselines_are_the_repositorys_wherever_twin_runs() {
    let dir = folder("baselines");
    let o = ok_in(&dir, &["baseline", "controller-network"]);
    let repository = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../recordings/baselines")
        .canonicalize()
        .expect("the repository's baselines");
    assert!(
        o.contains(&format!("the baselines in {}", repository.display())),
        "{o}"
    );
    assert!(
        o.lines().any(|l| l
            .split_whitespace()
            .take(2)
            .eq(["controller-network", "pass"])),
        "{o}"
    );
    // Recording never starts a new set of baselines by mistake.
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
    assert!(!o.status.success());
    assert!(text(&o).contains("create the folder first"), "{}", text(&o));
    assert!(!dir.join("recordings").exists(), "a folder was created");
    // A folder that lacks a baseline says it is missing, not that it passes.
    std::fs::create_dir(dir.join("mine")).expect("folder");
    let o = twin_in(&dir, &["baseline", "controller-network", "--dir", "mine"]);
    assert!(!o.status.success());
    let t = text(&o);
    assert!(
        t.contains("controller-network       MISSING")
            && t.contains("have no baseline in mine (controller-network)")
            && t.contains("twin baseline --record controller-network --dir mine")
            && !t.contains(" pass "),
        "{t}"
    );
    let o = twin_in(&dir, &["baseline", "--dir", "no-such-folder"]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("no folder no-such-folder"),
        "{}",
        text(&o)
    );
}

#[test]
fn compare_says_first_that_recordings_come_from_different_runs() {
    let dir = folder("compare");
    ok_in(&dir, &["run", "ev-meb", "--duration", "1"]);
    ok_in(&dir, &["run", "controller-network", "--duration", "1"]);
    let o = twin_in(&dir, &["compare", "controller-network.mcap", "ev-meb.mcap"]);
    assert!(!o.status.success());
    let out = String::from_utf8_lossy(&o.stdout);
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(
        lines[1], "  the recordings come from different runs:",
        "{out}"
    );
    assert!(
        out.contains("    run       a scenario run of controller-network, seed 1, 1 s")
            && out.contains("    baseline  a scenario run of ev-meb, seed 1, 1 s"),
        "{out}"
    );
    assert!(
        !out.contains("missing"),
        "no table of missing signals: {out}"
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("different runs")
            && err.contains("scenario (controller-network, baseline ev-meb)"),
        "{err}"
    );
    let forced = twin_in(
        &dir,
        &[
            "compare",
            "controller-network.mcap",
            "ev-meb.mcap",
            "--force",
        ],
    );
    assert!(
        String::from_utf8_lossy(&forced.stdout).contains("missing"),
        "{}",
        text(&forced)
    );
    // The same scenario with another seed and length: said first, then compared.
    ok_in(
        &dir,
        &[
            "run",
            "ev-meb",
            "--duration",
            "0.8",
            "--seed",
            "2",
            "--out",
            "seed2.mcap",
        ],
    );
    let o = twin_in(&dir, &["compare", "seed2.mcap", "ev-meb.mcap"]);
    let out = String::from_utf8_lossy(&o.stdout);
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(
        lines[1], "  the run's settings differ from the baseline's:",
        "{out}"
    );
    assert!(
        lines[2].trim_start().starts_with("seed") && lines[2].ends_with("run 2, baseline 1"),
        "{out}"
    );
    assert!(
        lines[3].trim_start().starts_with("duration_s")
            && lines[3].ends_with("run 0.8, baseline 1.0"),
        "{out}"
    );
    assert!(out.contains("signals"), "then compared: {out}");
}

#[test]
fn step_without_out_leaves_its_figures_here() {
    let dir = folder("step-here");
    let o = ok_in(
        &dir,
        &["step", "--open-loop", "--duration", "2", "--at", "0.5"],
    );
    for (line, file) in [
        ("figures:", "step.json"),
        ("plot:", "step.png"),
        ("recording:", "step.mcap"),
    ] {
        assert!(o.lines().any(|l| l == format!("{line} {file}")), "{o}");
        assert!(dir.join(file).is_file(), "no {file}: {o}");
    }
    let again = ok_in(
        &dir,
        &["step", "--open-loop", "--duration", "2", "--at", "0.5"],
    );
    assert!(
        again.contains("plot: step.png (replaced the one there before)"),
        "{again}"
    );
}

#[test]
fn sweep_without_out_leaves_its_figures_here() {
    let dir = folder("sweep-here");
    let sweep = [
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
    ];
    let o = ok_in(&dir, &sweep);
    for (line, file) in [("figures:", "sweep.json"), ("plot:", "sweep.png")] {
        assert!(o.lines().any(|l| l == format!("{line} {file}")), "{o}");
        assert!(dir.join(file).is_file(), "no {file}: {o}");
    }
    assert!(!o.contains("recordings:"), "{o}");
    let again = ok_in(&dir, &sweep);
    assert!(
        again.contains("figures: sweep.json (replaced the one there before)"),
        "{again}"
    );
}

#[test]
fn the_parallel_experiment_says_it_replaced_its_recordings_and_they_replay() {
    let dir = folder("parallel");
    let parallel = [
        "experiment",
        "parallel",
        "--duration",
        "0.3",
        "--out-dir",
        "p",
    ];
    let first = ok_in(&dir, &parallel);
    assert!(first.lines().any(|l| l == "recordings: p"), "{first}");
    let again = ok_in(&dir, &parallel);
    assert!(
        again
            .lines()
            .any(|l| l == "recordings: p (replaced the 4 there before)"),
        "{again}"
    );
    let o = ok_in(&dir, &["replay", "p/parallel-rtu-1m.mcap"]);
    assert!(o.contains("byte-identical"), "{o}");
}

#[test]
fn export_writes_one_time_column() {
    let dir = folder("export");
    ok_in(&dir, &["run", "--duration", "0.5"]);
    let o = ok_in(&dir, &["export", "ev-meb.mcap", "--csv", "csv"]);
    assert!(!o.contains("replaced"), "{o}");
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
    let o = ok_in(&dir, &["export", "ev-meb.mcap", "--csv", "csv"]);
    assert!(
        o.contains("plant_ev1_sensors.csv (replaced the one there before)"),
        "{o}"
    );
}
