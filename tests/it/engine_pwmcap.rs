//! The PWM-capture paper's link in the engine: three parallel EV modules, the
//! master's VEL sent to two slaves, recorded to MCAP and read back.

use std::path::{Path, PathBuf};

use serde_json::Value;
use twin_lab::parallel::{ParallelFigures, analyse};
use twin_sim::scenario::{EMBEDDED, Scenario};

fn embedded(name: &str) -> &'static str {
    EMBEDDED
        .iter()
        .find(|(n, _, _)| *n == name)
        .map(|(_, _, text)| *text)
        .expect("embedded scenario")
}

/// An embedded scenario with some lines replaced and a shorter duration.
fn variant(name: &str, duration_s: f64, replace: &[(&str, &str)]) -> Scenario {
    let mut text =
        embedded(name).replace("duration_s = 6.0", &format!("duration_s = {duration_s:?}"));
    for (from, to) in replace {
        assert!(text.contains(from), "{name} has no `{from}`");
        text = text.replace(from, to);
    }
    Scenario::parse(&text, name).expect("scenario parses")
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("e2e-pwmcap-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir.join(name)
}

fn run(scenario: &Scenario, file: &str) -> (PathBuf, ParallelFigures) {
    let out = scratch(file);
    twin_sim::virtual_run::run(scenario, &out, |_| {}).expect("run completes");
    let figures = analyse(scenario, &out).expect("recording reads back");
    (out, figures)
}

fn messages(path: &Path, topic: &str) -> Vec<Value> {
    let bytes = std::fs::read(path).expect("recording");
    mcap::MessageStream::new(&bytes)
        .expect("valid MCAP")
        .map(|m| m.expect("message"))
        .filter(|m| m.channel.topic == topic)
        .map(|m| twin_recording::read::value_of(&m.channel, &m.data).expect("a message that reads"))
        .collect()
}

fn events(path: &Path, kind: &str) -> usize {
    messages(path, "/events")
        .iter()
        .filter(|e| e["kind"] == kind)
        .count()
}

#[test]
fn a_clean_short_line_delivers_every_value_sent() {
    for name in ["parallel-pwm-broadcast", "parallel-pwm-designated"] {
        let scenario = variant(name, 1.0, &[("cable_m = 10.0", "cable_m = 1.0")]);
        let (out, figures) = run(&scenario, &format!("{name}-clean.mcap"));
        let frames = messages(&out, "/bus/pwm/frames");
        assert!(frames.len() >= 1000, "{name}: {} frames", frames.len());
        for frame in &frames {
            let sent = &frame["decoded"]["values"];
            let receptions = frame["decoded"]["receptions"]
                .as_array()
                .expect("receptions");
            assert!(!receptions.is_empty(), "{frame}");
            for r in receptions {
                assert_eq!(&r["values"], sent, "{name}: {frame}");
                assert_eq!(r["lost"], 0, "{frame}");
                assert_eq!(r["wrong"], 0, "{frame}");
            }
        }
        // Every slave took every reference, and nothing else.
        assert_eq!(figures.wrong_values, 0, "{name}: {figures:?}");
        assert_eq!(figures.skipped, 0, "{name}: {figures:?}");
        assert!(figures.latencies > 100, "{figures:?}");
        for kind in ["timeout", "bad_check", "retry", "dropped"] {
            assert_eq!(events(&out, kind), 0, "{name}: {kind} events");
        }
        // A broadcast frame is never answered; a designated one always is.
        let answers = frames.iter().filter(|f| f["from"] != "master").count();
        if name.ends_with("broadcast") {
            assert_eq!(answers, 0);
        } else {
            // The last frame may still be waiting for its answer at the end.
            let to_slaves = frames.len() - answers;
            assert!(
                answers <= to_slaves && answers + 1 >= to_slaves,
                "{answers} answers to {to_slaves} designated frames"
            );
        }
    }
}

#[test]
fn noise_on_a_long_line_gives_errors_that_the_master_retransmits() {
    let scenario = variant(
        "parallel-pwm-designated",
        2.0,
        &[
            ("cable_m = 10.0", "cable_m = 50.0"),
            ("noise_mv = 0.5", "noise_mv = 5.0"),
        ],
    );
    let (out, figures) = run(&scenario, "noisy.mcap");
    let frames = messages(&out, "/bus/pwm/frames");
    let wrong: u64 = frames
        .iter()
        .flat_map(|f| {
            f["decoded"]["receptions"]
                .as_array()
                .cloned()
                .unwrap_or_default()
        })
        .map(|r| r["wrong"].as_u64().unwrap_or(0) + r["lost"].as_u64().unwrap_or(0))
        .sum();
    assert!(wrong > 20, "values wrong or lost in the recording: {wrong}");
    let (bad, timeouts, retries) = (
        events(&out, "bad_check"),
        events(&out, "timeout"),
        events(&out, "retry"),
    );
    assert!(
        bad > 10 && timeouts > 0 && retries > 10,
        "{bad} {timeouts} {retries}"
    );
    // Every retry is a frame sent again: more frames to the slaves than cycles × 2.
    let loops = messages(&out, "/master/master/loop");
    let last = loops.last().expect("master loop recorded");
    let requests: u64 = last["slaves"]
        .as_array()
        .expect("slaves")
        .iter()
        .map(|s| s["requests"].as_u64().unwrap_or(0))
        .sum();
    let cycles = last["cycles"].as_u64().unwrap_or(0);
    assert!(
        requests > 2 * cycles,
        "{requests} requests in {cycles} cycles"
    );
    // No check in the frame: some wrong references reach a slave's actuator.
    assert!(figures.wrong_values > 0, "{figures:?}");
    // The loop still runs: the master's wheel reaches its set point.
    let sensors = messages(&out, "/plant/master/sensors");
    let rpm = sensors.last().expect("sensors")["wheel_rpm"]
        .as_f64()
        .unwrap_or(0.0);
    assert!((rpm - 1500.0).abs() < 60.0, "master wheel {rpm} rpm");
}

#[test]
fn parallel_wheels_track_the_master_and_pwm_beats_modbus() {
    let pwm = variant("parallel-pwm-broadcast", 4.0, &[]);
    let rtu = variant("parallel-rtu-115200", 4.0, &[]);
    let (out, p) = run(&pwm, "track-pwm.mcap");
    let (_, r) = run(&rtu, "track-rtu.mcap");
    // The slaves follow the master within a few rpm on the PWM link …
    assert!(p.track_max_rpm < 2.0, "{p:?}");
    // … and every wheel reaches the set point.
    for module in ["master", "slave2", "slave3"] {
        let sensors = messages(&out, &format!("/plant/{module}/sensors"));
        let rpm = sensors.last().expect("sensors")["wheel_rpm"]
            .as_f64()
            .unwrap_or(0.0);
        assert!((rpm - 2500.0).abs() < 50.0, "{module}: {rpm} rpm");
    }
    // One 10 kHz loop tick is all the PWM link adds; Modbus at 115200 baud
    // takes milliseconds, skips updates and tracks worse.
    assert!(p.latency_max_s <= 100.5e-6, "{p:?}");
    assert!(r.latency_mean_s > 1e-3, "{r:?}");
    assert!(r.skipped > r.master_changes / 3, "{r:?}");
    assert!(r.track_max_rpm > 5.0 * p.track_max_rpm, "{r:?} vs {p:?}");
    // A Modbus cycle is, per slave: the 8-byte FC 06 request and its 8-byte
    // echo at 10 bits per byte, the slave's 0.1 ms turnaround, and the
    // 1.75 ms line silence the master keeps before the next request.
    let exchange = 2.0 * 8.0 * 10.0 / 115_200.0 + 0.1e-3 + 1.75e-3;
    let cycle = 2.0 * exchange;
    assert!(
        (r.cycle_s - cycle).abs() < 0.01 * cycle,
        "{} vs {cycle}",
        r.cycle_s
    );
    assert!((p.cycle_s - 1e-3).abs() < 1e-6, "PWM: one cycle per update");
}

#[test]
fn the_same_seed_gives_the_same_recording() {
    let scenario = variant(
        "parallel-pwm-designated",
        0.5,
        &[("noise_mv = 0.5", "noise_mv = 5.0")],
    );
    let (a, _) = run(&scenario, "same-a.mcap");
    let (b, _) = run(&scenario, "same-b.mcap");
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    let mut other = scenario.clone();
    other.seed += 1;
    let (c, _) = run(&other, "same-c.mcap");
    assert_ne!(std::fs::read(&a).unwrap(), std::fs::read(&c).unwrap());
}

#[test]
fn scenario_errors_name_the_line() {
    let text = embedded("parallel-pwm-broadcast");
    let cases: [(&str, &str, &str); 6] = [
        (
            "slaves = [2, 3]",
            "slaves = [2, 16]",
            "`slaves` of node `master` holds 16: ids on this link are 1 to 15",
        ),
        (
            "clock_hz = 150000000",
            "clock_hz = 7",
            "`clock_hz` 7 does not divide 72 GHz",
        ),
        ("cable_m = 10.0", "cable_m = -3.0", "`cable_m` must be"),
        (
            "medium = \"pwmcap\"",
            "medium = \"serial\"",
            "`medium` of bus `pwm` is serial",
        ),
        (
            "cable_m = 10.0",
            "cable_ohms = 10.0",
            "unknown field `cable_ohms`",
        ),
        (
            "id = 3",
            "id = 16",
            "`id` 16 of node `slave3`: a PWM slave id is 1 to 15",
        ),
    ];
    for (from, to, message) in cases {
        let broken = text.replacen(from, to, 1);
        let line = broken
            .lines()
            .position(|l| l.contains(to))
            .map(|n| n + 1)
            .expect("changed line");
        let error = Scenario::parse(&broken, "p.toml")
            .expect_err(to)
            .to_string();
        assert!(error.contains(message), "{to}: {error}");
        let place: usize = error
            .strip_prefix("p.toml:")
            .and_then(|rest| rest.split(':').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{to}: no line in {error}"));
        // The line named is the changed one, or for a node the `bus` line of
        // that node (a serial node on a PWM link), a few lines below it.
        assert_eq!(place, line, "{to}: {error}");
    }
    // A fault on a PWM node: refused at the fault's `node` line.
    let faulty = format!(
        "{text}\n[[fault]]\nnode = \"slave2\"\nkind = \"drop-reply\"\nfrom_s = 1.0\nuntil_s = 2.0\n"
    );
    let error = Scenario::parse(&faulty, "f.toml")
        .expect_err("fault on pwm")
        .to_string();
    let node_line = faulty
        .lines()
        .position(|l| l.starts_with("node = "))
        .unwrap()
        + 1;
    assert!(
        error.starts_with(&format!(
            "f.toml:{node_line}: `node` fault on `slave2`: faults apply to serial nodes"
        )),
        "{error}"
    );
    // A serial protocol on a PWM-capture link: the master's `bus` line.
    let rtu = embedded("parallel-rtu-115200")
        .replace("baud = 115200", "baud = 115200\nmedium = \"pwmcap\"");
    let error = Scenario::parse(&rtu, "r.toml")
        .expect_err("modbus on pwm")
        .to_string();
    let master_bus = rtu
        .lines()
        .enumerate()
        .skip_while(|(_, l)| !l.contains("kind = \"parallel-master\""))
        .find(|(_, l)| l.starts_with("bus ="))
        .map(|(n, _)| n + 1)
        .expect("master's bus line");
    assert!(
        error.starts_with(&format!(
            "r.toml:{master_bus}: `bus` `rs485` of node `master` is a PWM-capture link"
        )),
        "{error}"
    );
}

#[test]
fn half_duplex_answers_wait_for_the_enable_full_duplex_answers_at_once() {
    for duplex in ["half", "full"] {
        let scenario = variant(
            "parallel-pwm-designated",
            0.3,
            &[
                ("cable_m = 10.0", "cable_m = 1.0"),
                ("duplex = \"half\"", &format!("duplex = \"{duplex}\"")),
                // Slaves answer the instant the fourth pulse is captured.
                ("turnaround_ms = 0.01", "turnaround_ms = 0.0"),
            ],
        );
        let (out, _) = run(&scenario, &format!("duplex-{duplex}.mcap"));
        let frames = messages(&out, "/bus/pwm/frames");
        let mut answers = 0;
        for pair in frames.windows(2) {
            let (request, answer) = (&pair[0], &pair[1]);
            if request["from"] != "master" || answer["from"] == "master" {
                continue;
            }
            answers += 1;
            let (end, start) = (
                request["end_s"].as_f64().unwrap(),
                answer["start_s"].as_f64().unwrap(),
            );
            if duplex == "half" {
                // The master holds the enable to the end of its last symbol period.
                assert!(start >= end - 1e-12, "answer at {start} before {end}");
            } else {
                // The slave answers on its own pair once it has the fourth pulse,
                // before the master's last symbol period is over.
                assert!(
                    start < end,
                    "full duplex answer at {start}, request ends {end}"
                );
            }
            // Never more than the last symbol's OFF time apart (one period, 8.16 µs).
            assert!((start - end).abs() < 8.2e-6, "{start} vs {end}");
        }
        assert!(answers > 400, "{duplex}: {answers} answers");
    }
}

#[test]
fn a_slow_line_needs_the_start_width_calibrated_at_initialisation() {
    let slow = |calibrate: bool| {
        variant(
            "parallel-pwm-designated",
            1.5,
            &[(
                "noise_mv = 0.5",
                &format!(
                    "noise_mv = 0.5\nadded_series_ohm = 1.0\nadded_shunt_nf = 20.0\ncalibrate = {calibrate}"
                ),
            )],
        )
    };
    // The paper's start-bit overflow: τ ≈ 80 ticks shrinks the 200-tick start
    // so much that no status symbol decodes, and no slave ever runs.
    let (out, figures) = run(&slow(false), "slow.mcap");
    assert_eq!(figures.latencies, 0, "{figures:?}");
    let last_rpm = |out: &Path, module: &str| {
        messages(out, &format!("/plant/{module}/sensors"))
            .last()
            .expect("sensors")["wheel_rpm"]
            .as_f64()
            .unwrap_or(f64::NAN)
    };
    assert_eq!(last_rpm(&out, "slave2"), 0.0);
    assert!(last_rpm(&out, "master") > 1400.0);
    // Calibrated: the slaves follow the master again.
    let (out, figures) = run(&slow(true), "slow-calibrated.mcap");
    assert!(figures.latencies > 1000, "{figures:?}");
    assert!(figures.track_max_rpm < 5.0, "{figures:?}");
    let bytes = std::fs::read(&out).expect("recording");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("has one");
    let metadata = summary
        .metadata_indexes
        .iter()
        .find(|m| m.name == "twin.run")
        .expect("twin.run metadata");
    let record = mcap::read::metadata(&bytes, metadata).expect("metadata reads");
    let found = &record.metadata["pwm_calibration"];
    assert!(found.starts_with("bus pwm: start "), "{found}");
}
