//! Long runs on the virtual clock show how far they have got on a terminal
//! (stderr a pseudo-terminal here, as in a user's shell) and print nothing of
//! it when stderr is piped or redirected, as in a script or a log.

use crate::support;
use std::io::Read;
use std::os::fd::OwnedFd;
use std::path::PathBuf;
use std::process::{Command, Output, Stdio};

fn scratch(name: &str) -> PathBuf {
    support::scratch("progress-cli", name)
}

/// Runs `twin ARGS` with stderr on a fresh pseudo-terminal (100 columns,
/// TERM=xterm) and stdout piped: what the terminal showed and the output.
fn on_a_terminal(args: &[&str]) -> (String, Output) {
    use rustix::fs::{Mode, OFlags};
    use rustix::pty::{OpenptFlags, grantpt, openpt, ptsname, unlockpt};
    use rustix::termios::{Winsize, tcsetwinsize};
    let master = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY).expect("posix_openpt");
    grantpt(&master).expect("grantpt");
    unlockpt(&master).expect("unlockpt");
    let name = ptsname(&master, Vec::new()).expect("ptsname");
    let size = Winsize {
        ws_row: 24,
        ws_col: 100,
        ws_xpixel: 0,
        ws_ypixel: 0,
    };
    tcsetwinsize(&master, size).expect("window size");
    let terminal: OwnedFd = rustix::fs::open(
        name.as_c_str(),
        OFlags::RDWR | OFlags::NOCTTY,
        Mode::empty(),
    )
    .expect("the terminal opens");
    // The terminal is read while the run goes on, so it never fills.
    let mut screen = std::fs::File::from(master);
    let reader = std::thread::spawn(move || {
        let mut shown = Vec::new();
        let mut buf = [0u8; 4096];
        // Once the last holder of the terminal side is gone, read fails (EIO).
        while let Ok(n) = screen.read(&mut buf) {
            if n == 0 {
                break;
            }
            shown.extend_from_slice(&buf[..n]);
        }
        String::from_utf8_lossy(&shown).into_owned()
    });
    let output = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(args)
        .env("TERM", "xterm")
        .stdin(Stdio::null())
        .stderr(Stdio::from(terminal))
        .output()
        .expect("twin runs");
    let shown = reader.join().expect("terminal read");
    (shown, output)
}

fn piped(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(args)
        .env("TERM", "xterm")
        .output()
        .expect("twin runs")
}

/// No progress line, no carriage return, no cursor movement.
fn assert_quiet(what: &str, stderr: &[u8]) {
    let err = String::from_utf8_lossy(stderr);
    assert!(
        !err.contains('\r') && !err.contains('\u{1b}') && !err.contains("simulated"),
        "{what} printed progress on a piped stderr: {err:?}"
    );
}

#[test]
fn a_long_run_shows_simulated_time_on_a_terminal() {
    let out = scratch("tty.mcap");
    let (shown, o) = on_a_terminal(&["run", "--duration", "20", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "twin run failed; terminal: {shown}");
    assert!(
        shown.contains("ev-meb [") && shown.contains(" of 20.0 s simulated"),
        "no progress line on the terminal: {shown:?}"
    );
    // The results still go to stdout, and the line is taken off at the end.
    let summary = String::from_utf8_lossy(&o.stdout);
    assert!(summary.contains("twin run: scenario ev-meb"), "{summary}");
    assert!(
        !summary.contains("simulated, "),
        "progress on stdout: {summary}"
    );
    assert!(
        shown.ends_with("\u{1b}[2K") || shown.ends_with('\r'),
        "the line stays: {shown:?}"
    );
}

#[test]
fn a_long_run_piped_prints_no_progress() {
    let out = scratch("piped.mcap");
    let o = piped(&["run", "--duration", "20", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_quiet("twin run", &o.stderr);
    let summary = String::from_utf8_lossy(&o.stdout);
    assert!(summary.contains("twin run: scenario ev-meb"), "{summary}");
}

#[test]
fn recording_a_baseline_shows_which_scenario_is_running() {
    let dir = scratch("baselines");
    // `--record` writes into a set of baselines; it does not start one.
    std::fs::create_dir_all(&dir).unwrap();
    let args = [
        "baseline",
        "--record",
        "ev-meb",
        "--dir",
        dir.to_str().unwrap(),
    ];
    let (shown, o) = on_a_terminal(&args);
    assert!(o.status.success(), "terminal: {shown}");
    assert!(
        shown.contains("ev-meb (1 of 1) ["),
        "no progress line: {shown:?}"
    );
    let o = piped(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_quiet("twin baseline --record", &o.stderr);
}

#[test]
fn bench_shows_each_run_it_times() {
    let args = [
        "bench",
        "--scenario",
        "ev-meb",
        "--seconds",
        "5",
        "--repeat",
        "2",
    ];
    let (shown, o) = on_a_terminal(&args);
    assert!(o.status.success(), "terminal: {shown}");
    // The unrecorded and recorded runs take turns.
    let mut last = 0;
    for run in [
        "ev-meb, not recorded, run 1 of 2",
        "ev-meb, recorded, run 1 of 2",
        "ev-meb, not recorded, run 2 of 2",
        "ev-meb, recorded, run 2 of 2",
    ] {
        let at = shown
            .find(run)
            .unwrap_or_else(|| panic!("no `{run}` on the terminal: {shown:?}"));
        assert!(at >= last, "`{run}` came too early: {shown:?}");
        last = at;
    }
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(table.contains("ev-meb"), "{table}");
    assert!(
        table.contains("pair by pair (2 pairs), the median: "),
        "{table}"
    );
    let o = piped(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_quiet("twin bench", &o.stderr);
}

/// Users profile the bench with valgrind (callgrind counts instructions,
/// which this noisy machine's clocks cannot): it must run there too. It
/// once died at its first CPU-time reading, in rustix's own reading of the
/// process's auxiliary vector, which valgrind's loader lays out otherwise.
#[test]
fn bench_runs_under_valgrind() {
    let twin = env!("CARGO_BIN_EXE_twin");
    let o = Command::new("valgrind")
        .args(["--tool=none", "--error-exitcode=99", twin])
        .args(["bench", "--scenario", "ev-meb", "--seconds", "0.2"])
        .args(["--repeat", "1"])
        .output()
        .expect("valgrind runs (bash .ci/install installs it)");
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{table}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(table.contains("ev-meb               mcap"), "{table}");
}

#[test]
fn the_parallel_experiment_shows_each_variant() {
    let dir = scratch("parallel");
    let args = [
        "experiment",
        "parallel",
        "--duration",
        "1",
        "--out-dir",
        dir.to_str().unwrap(),
    ];
    let (shown, o) = on_a_terminal(&args);
    assert!(o.status.success(), "terminal: {shown}");
    for variant in ["parallel-pwm-broadcast [", "parallel-rtu-1m ["] {
        assert!(
            shown.contains(variant),
            "no `{variant}` on the terminal: {shown:?}"
        );
    }
    let o = piped(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_quiet("twin experiment parallel", &o.stderr);
}
