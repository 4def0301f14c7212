//! `twin calibrate` from the command line: every kind of bad log or
//! calibration file refused with the file, the line and what is wrong; a
//! search cut short says so; the fitted parameter file goes to `--params`
//! of a closed-loop run; the EV module calibrated from a supervisor's
//! recording (one the twin made with parameters it is not told), and
//! parameters that make one inertia reported as not told apart.

use std::path::{Path, PathBuf};

use crate::support::{Proc, scratch, text, twin};

/// The shipped log and scenario, for jobs in a scratch folder.
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

const HEADER: &str = "time_s,motor_value,sensor_value\n";

/// A scratch folder with `csv` as `log.csv` and a job file whose step and
/// fit are `step` and `fit` (TOML), and whose motor column is in `unit`.
fn job(name: &str, csv: &str, step: &str, unit: &str, fit: &str) -> PathBuf {
    let dir = scratch("calibrate", name);
    std::fs::create_dir_all(&dir).expect("scratch");
    std::fs::write(dir.join("log.csv"), csv).expect("csv");
    let scenario = repo().join("recordings/calibration/controller-network-step-scenario.toml");
    let text = format!(
        "log = \"log.csv\"\nscenario = \"{}\"\n\n[step]\n{step}\n\n\
         [[signal]]\ncolumn = \"motor_value\"\nunit = \"{unit}\"\ntwin = \"motor-rpm-read\"\n\n\
         [[fit]]\n{fit}\n",
        scenario.display()
    );
    let file = dir.join("job.toml");
    std::fs::write(&file, text).expect("job");
    file
}

const STEP: &str = "at_s = 1.0\nfrom = 0.0\nto = 10000.0";
const FIT: &str = "path = \"motor.torque_constant\"\nmin = 0.005\nmax = 0.03\nstart = 0.0114";

/// A plausible log: 0 before the step, 9500 rpm after it, to `end` s.
fn log(end: f64) -> String {
    let mut csv = String::from(HEADER);
    let mut t = 0.0;
    while t <= end {
        let v = if t < 1.05 { 0.0 } else { 9500.0 };
        csv.push_str(&format!("{t:.3},{v},\n"));
        t += 0.01;
    }
    csv
}

fn refused(job: &Path) -> String {
    let o = twin(&["calibrate", job.to_str().expect("utf-8 path")]);
    assert!(!o.status.success(), "accepted: {}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!err.contains("panicked"), "{err}");
    err
}

#[test]
fn bad_logs_and_files_are_refused_with_where_and_why() {
    let good = log(3.0);
    let cases: Vec<(&str, PathBuf, &[&str])> = vec![
        (
            "constant",
            job(
                "constant",
                &good,
                "at_s = 1.0\nfrom = 10000.0\nto = 10000.0",
                "rpm",
                FIT,
            ),
            &["job.toml:", "a constant command excites nothing"],
        ),
        (
            "short",
            job("short", &log(1.1), STEP, "rpm", FIT),
            &["log.csv", "too short to identify"],
        ),
        (
            "nan",
            job(
                "nan",
                &good.replacen(",9500,", ",NaN,", 1),
                STEP,
                "rpm",
                FIT,
            ),
            &["log.csv:", "column `motor_value`: `NaN`"],
        ),
        (
            "empty",
            job("empty", &good.replacen(",9500,", ",,", 1), STEP, "rpm", FIT),
            &[
                "log.csv:",
                "column `motor_value` is empty",
                "empty = \"skip\"",
            ],
        ),
        (
            "backwards",
            job("backwards", &format!("{good}0.5,9500,\n"), STEP, "rpm", FIT),
            &["log.csv:", "time goes backwards"],
        ),
        (
            "column",
            job(
                "column",
                &good.replace("motor_value", "rpm"),
                STEP,
                "rpm",
                FIT,
            ),
            &[
                "log.csv",
                "no column `motor_value`",
                "columns: time_s, rpm, sensor_value",
            ],
        ),
        (
            "unit",
            job("unit", &good, STEP, "V", FIT),
            &["job.toml:", "unit `V` is not a speed"],
        ),
        (
            "magnitude",
            job("magnitude", &good, STEP, "rad/s", FIT),
            &["log.csv", "is the unit right?"],
        ),
        (
            "bounds",
            job(
                "bounds",
                &good,
                STEP,
                "rpm",
                "path = \"motor.torque_constant\"\nmin = 0.005\nmax = 0.03\nstart = 0.05",
            ),
            &[
                "job.toml:",
                "the start 0.05 is outside its bounds [0.005, 0.03]",
            ],
        ),
        (
            "path",
            job(
                "path",
                &good,
                STEP,
                "rpm",
                "path = \"motor.torque\"\nmin = 0.005\nmax = 0.03\nstart = 0.01",
            ),
            &["job.toml:", "`motor.torque` is no parameter of the plant"],
        ),
    ];
    for (name, file, expected) in cases {
        let err = refused(&file);
        for e in expected {
            assert!(err.contains(e), "{name}: `{e}` not in: {err}");
        }
    }
}

#[test]
fn a_search_cut_short_says_so_and_its_parameters_drive_a_closed_loop_run() {
    let file = job("short-search", &log(3.0), STEP, "rpm", FIT);
    let out = file.parent().expect("folder").join("out");
    let o = twin(&[
        "calibrate",
        file.to_str().expect("utf-8"),
        "--max-iterations",
        "2",
        "--out",
        out.to_str().expect("utf-8"),
    ]);
    let printed = text(&o);
    assert!(o.status.success(), "{printed}");
    assert!(printed.contains("before converging"), "{printed}");
    let params = out.join("calibrated-params.toml");
    let fitted = std::fs::read_to_string(&params).expect("params written");
    assert!(fitted.contains("torque_constant = "), "{fitted}");
    // The file drives a closed-loop run of the embedded scenario: the motor
    // runs at the speed its fitted motor constant allows.
    let run = twin(&[
        "run",
        "controller-network",
        "--duration",
        "2",
        "--params",
        params.to_str().expect("utf-8"),
        "--out",
        out.join("run.mcap").to_str().expect("utf-8"),
    ]);
    assert!(run.status.success(), "{}", text(&run));
}

#[test]
fn params_change_every_module_of_a_closed_loop_run() {
    let dir = scratch("calibrate", "closed-loop-params");
    std::fs::create_dir_all(&dir).expect("scratch");
    // Half the preset's gearbox: the master still holds the motor at
    // 10000 rpm, so the wheel turns twice as fast (about 200 rpm, not 100).
    let params = dir.join("half-gearbox.toml");
    std::fs::write(&params, "[gearbox]\nratio = 50.0\n").expect("params");
    let wheel = |extra: &[&str]| -> f64 {
        let mut args = vec!["run", "controller-network", "--duration", "3"];
        args.extend_from_slice(extra);
        let out = dir.join("run.mcap");
        args.extend_from_slice(&["--out", out.to_str().expect("utf-8")]);
        let o = twin(&args);
        let printed = text(&o);
        assert!(o.status.success(), "{printed}");
        let at = printed.find("wheel ").expect("a wheel speed") + "wheel ".len();
        printed[at..]
            .split_whitespace()
            .next()
            .and_then(|v| v.parse().ok())
            .expect("a number")
    };
    let preset = wheel(&[]);
    let fast = wheel(&["--params", params.to_str().expect("utf-8")]);
    assert!((90.0..110.0).contains(&preset), "{preset}");
    assert!((180.0..220.0).contains(&fast), "{fast}");
    // A mistake in the file is named with its line, as for an open-loop run.
    std::fs::write(&params, "[gearbox]\nratio = \"fifty\"\n").expect("params");
    let o = twin(&[
        "run",
        "controller-network",
        "--params",
        params.to_str().expect("utf-8"),
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("half-gearbox.toml:2"), "{err}");
}

/// The stand-in for a supervisor's recording of a real EV module, made by
/// the twin with parameters the calibration is not told, in `dir`.
fn stand_in_recording(dir: &Path) -> PathBuf {
    std::fs::create_dir_all(dir).expect("scratch");
    let shipped = repo().join("recordings/calibration");
    let mcap = dir.join("ev1-step.mcap");
    let o = twin(&[
        "run",
        shipped
            .join("ev-module-stand-in.toml")
            .to_str()
            .expect("utf-8"),
        "--params",
        shipped
            .join("ev-module-stand-in-params.toml")
            .to_str()
            .expect("utf-8"),
        "--out",
        mcap.to_str().expect("utf-8"),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    mcap
}

#[test]
fn the_ev_module_is_calibrated_from_a_supervisors_recording() {
    let dir = scratch("calibrate", "ev-module");
    let mcap = stand_in_recording(&dir);
    let out = dir.join("out");
    let job = repo().join("recordings/calibration/ev-module-step.toml");
    let o = twin(&[
        "calibrate",
        job.to_str().expect("utf-8"),
        "--log",
        mcap.to_str().expect("utf-8"),
        "--out",
        out.to_str().expect("utf-8"),
    ]);
    let printed = text(&o);
    assert!(o.status.success(), "{printed}");
    // The step is found in the recorded set point: 1000 -> 1500 rpm.
    assert!(
        printed.contains("passes (bench / twin): 1250 at"),
        "{printed}"
    );
    let figures: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("calibrate.json")).expect("figures"),
    )
    .expect("json");
    // Without noise, each value within 3 % of the stand-in's.
    let truth = std::fs::read_to_string(
        repo().join("recordings/calibration/ev-module-stand-in-params.toml"),
    )
    .expect("stand-in params");
    let truth: toml::Table = truth.parse().expect("toml");
    for p in figures["parameters"].as_array().expect("parameters") {
        let path = p["path"].as_str().expect("path");
        let (table, key) = path.split_once('.').expect("dotted");
        let want = truth[table][key].as_float().expect("a number");
        let got = p["value"].as_f64().expect("value");
        assert!(
            (got - want).abs() <= 0.03 * want,
            "{path}: fitted {got}, the stand-in has {want}\n{printed}"
        );
    }
    for f in figures["fit"].as_array().expect("fit") {
        let pct = f["fit_averaged_pct"].as_f64().expect("FIT %");
        assert!(pct > 99.0, "{f}");
    }
}

#[test]
fn parameters_that_make_one_inertia_are_reported_as_not_told_apart() {
    let dir = scratch("calibrate", "ev-module-apart");
    let mcap = stand_in_recording(&dir);
    // The wheel's mass and radius reach the speed only through its inertia
    // (½ m r²): a recording of the loop cannot tell them apart.
    let job = dir.join("apart.toml");
    std::fs::write(
        &job,
        "scenario = \"ev-meb\"\n\
         set_point = \"/master/supervisor/loop.loops.0.set_point_rpm\"\n\n\
         [[signal]]\ncolumn = \"/master/supervisor/loop.loops.0.measured_rpm\"\n\
         unit = \"rpm\"\ntwin = \"supervisor-rpm\"\n\n\
         [[fit]]\npath = \"wheel.mass_kg\"\nmin = 0.1\nmax = 2.0\nstart = 0.5\n\n\
         [[fit]]\npath = \"wheel.radius_m\"\nmin = 0.05\nmax = 0.2\nstart = 0.1\n",
    )
    .expect("job");
    let o = twin(&[
        "calibrate",
        job.to_str().expect("utf-8"),
        "--log",
        mcap.to_str().expect("utf-8"),
        "--max-iterations",
        "8",
        "--out",
        dir.join("out").to_str().expect("utf-8"),
    ]);
    let printed = text(&o);
    assert!(o.status.success(), "{printed}");
    assert!(
        printed.contains("cannot tell apart: wheel.mass_kg and wheel.radius_m"),
        "{printed}"
    );
    assert!(printed.contains("weigh it"), "{printed}");
}

#[test]
fn a_recording_that_does_not_fit_the_job_is_refused_with_why() {
    let dir = scratch("calibrate", "ev-module-bad");
    let mcap = stand_in_recording(&dir);
    let write = |name: &str, body: &str| -> PathBuf {
        let file = dir.join(name);
        std::fs::write(&file, body).expect("job");
        file
    };
    let signal = "[[signal]]\ncolumn = \"/master/supervisor/loop.loops.0.measured_rpm\"\n\
                  unit = \"rpm\"\ntwin = \"supervisor-rpm\"\n";
    let fit = "[[fit]]\npath = \"wheel.mass_kg\"\nmin = 0.1\nmax = 2.0\nstart = 0.5\n";
    let set_point = "set_point = \"/master/supervisor/loop.loops.0.set_point_rpm\"\n";
    let cases: Vec<(PathBuf, &[&str])> = vec![
        // A signal the recording does not have: its loop's signals listed.
        (
            write(
                "no-signal.toml",
                &format!(
                    "scenario = \"ev-meb\"\n{set_point}\n[[signal]]\n\
                     column = \"/master/supervisor/loop.loops.0.measured\"\n\
                     unit = \"rpm\"\ntwin = \"supervisor-rpm\"\n\n{fit}"
                ),
            ),
            &[
                "ev1-step.mcap: no signal `/master/supervisor/loop.loops.0.measured`",
                "loops.0.measured_rpm",
            ],
        ),
        // No step and no set point: nothing says when the command changed.
        (
            write(
                "no-step.toml",
                &format!("scenario = \"ev-meb\"\n\n{signal}\n{fit}"),
            ),
            &["no `[step]` and no `set_point`"],
        ),
        // A set point that never changes.
        (
            write(
                "constant.toml",
                &format!(
                    "scenario = \"ev-meb\"\nset_point = \"/master/supervisor/loop.loops.0.slave\"\n\n\
                     {signal}\n{fit}"
                ),
            ),
            &["constant.toml:2:", "never changes", "nothing to identify"],
        ),
        // Empty cells are a CSV file's.
        (
            write(
                "empty.toml",
                &format!("scenario = \"ev-meb\"\n{set_point}\n{signal}empty = \"skip\"\n\n{fit}"),
            ),
            &["empty.toml:", "a recording has no empty cells"],
        ),
        // VEL in rpm: a unit the signal cannot have.
        (
            write(
                "vel-unit.toml",
                &format!(
                    "scenario = \"ev-meb\"\n{set_point}\n[[signal]]\n\
                     column = \"/master/supervisor/loop.loops.0.output\"\n\
                     unit = \"rpm\"\ntwin = \"supervisor-vel\"\n\n{fit}"
                ),
            ),
            &["vel-unit.toml:", "unit `rpm`", "counts, V"],
        ),
    ];
    for (job, expected) in cases {
        let o = twin(&[
            "calibrate",
            job.to_str().expect("utf-8"),
            "--log",
            mcap.to_str().expect("utf-8"),
        ]);
        assert!(
            !o.status.success(),
            "accepted {}: {}",
            job.display(),
            text(&o)
        );
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(!err.contains("panicked"), "{err}");
        for e in expected {
            assert!(err.contains(e), "{}: no `{e}` in: {err}", job.display());
        }
    }
    // Both a log and a recording in the file: one of them, please.
    let both = write(
        "both.toml",
        &format!(
            "log = \"a.csv\"\nrecording = \"b.mcap\"\nscenario = \"ev-meb\"\n{set_point}\n{signal}\n{fit}"
        ),
    );
    let err = refused(&both);
    assert!(err.contains("both `log` and `recording`"), "{err}");
    // A file that is no recording.
    let o = twin(&[
        "calibrate",
        both.to_str().expect("utf-8"),
        "--log",
        both.with_extension("mcap").to_str().expect("utf-8"),
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(err.contains("cannot read the recording"), "{err}");
}

#[test]
fn a_real_time_supervise_session_is_a_log_to_calibrate_from() {
    // `twin serve` stands in for the module over a `twin vsp` pair, as a
    // real module on an adapter would be; `twin supervise` records the
    // session, and a client steps the set point as a student would.
    let _cores = crate::support::cores_to_myself();
    let dir = scratch("calibrate", "supervise-session");
    std::fs::create_dir_all(&dir).expect("scratch");
    let (a, b) = (dir.join("ttyV0"), dir.join("ttyV1"));
    let _vsp = Proc::start(&[
        "vsp",
        a.to_str().expect("utf-8"),
        b.to_str().expect("utf-8"),
    ]);
    let _serve = Proc::start(&[
        "serve",
        "--meb",
        b.to_str().expect("utf-8"),
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let mcap = dir.join("ev1-step.mcap");
    let supervise = Proc::start(&[
        "supervise",
        "--meb",
        a.to_str().expect("utf-8"),
        "--listen",
        "tcp://127.0.0.1:0",
        "--set-point",
        "1000",
        "--duration",
        "5",
        "--out",
        mcap.to_str().expect("utf-8"),
        "--quiet",
        "--status-every",
        "0",
    ]);
    // Its server's line, not the bus's `master` line.
    let server = supervise
        .links()
        .into_iter()
        .find(|f| f.iter().any(|w| w.starts_with("tcp://")) && !f.iter().any(|w| w == "master"))
        .and_then(|f| f.into_iter().find(|w| w.starts_with("tcp://")))
        .unwrap_or_else(|| panic!("no server printed: {}", supervise.output()));
    std::thread::sleep(std::time::Duration::from_millis(2500));
    let o = twin(&["client", &server, "write", "VA", "10", "1500"]);
    assert!(o.status.success(), "{}", text(&o));
    supervise.wait();
    let job = repo().join("recordings/calibration/ev-module-step.toml");
    let o = twin(&[
        "calibrate",
        job.to_str().expect("utf-8"),
        "--log",
        mcap.to_str().expect("utf-8"),
        "--max-iterations",
        "2",
        "--out",
        dir.join("out").to_str().expect("utf-8"),
    ]);
    let printed = text(&o);
    assert!(o.status.success(), "{printed}");
    // The step the client made is found in the recording (1000 -> 1500),
    // and every poll cycle the session recorded is a row of the fit (as
    // `twin export` counts them: about 500 in 5 s on a quiet machine, 149
    // beside two builds, when the supervisor lost cycles).
    assert!(
        printed.contains("passes (bench / twin): 1250 at"),
        "{printed}"
    );
    let figures: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("out/calibrate.json")).expect("figures"),
    )
    .expect("json");
    let speed = &figures["fit_at_start"][0];
    assert_eq!(
        speed["column"], "/master/supervisor/loop.loops.0.measured_rpm",
        "{speed}"
    );
    let rows = speed["rows"].as_u64().expect("rows");
    let csv = dir.join("csv");
    let o = twin(&[
        "export",
        "--csv",
        csv.to_str().expect("utf-8"),
        mcap.to_str().expect("utf-8"),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let exported = std::fs::read_to_string(csv.join("master_supervisor_loop.csv"))
        .expect("the loop's CSV")
        .lines()
        .count() as u64
        - 1;
    assert!(
        rows > 0 && rows == exported,
        "{rows} rows of {exported}: {printed}"
    );
    // How closely the preset twin follows the session is not held here: it
    // is real time, and a machine busy enough to stall `twin serve` makes
    // the module's readings jump (an overshoot of 136 % was seen beside a
    // release build); on a quiet machine the fit at the start is 99 %.
}
