//! Real Modbus masters we did not write — mbpoll (Debian) and pymodbus (PyPI)
//! — against `twin serve` over Modbus TCP and over Modbus RTU on a
//! pseudo-terminal: they read the input registers, write the speed set point
//! (VEL) and the enable coils, and see the wheel speed (RPM_M) follow two set
//! points. Addresses are docs/protocols/modbus-map.md's. These tests fail, rather than
//! skip, when mbpoll or pymodbus is missing (`.ci/run` installs them).

use crate::peers;

use peers::{PtyPair, Serve, run_timeout, scratch, script, wait_for};
use std::process::Command;
use std::time::Duration;

const V1: usize = 2;
const RPM_M: usize = 3;
const VEL_LOW: u16 = 1638; // 40 % of the DAC
const VEL_HIGH: u16 = 3276; // 80 %

/// How mbpoll reaches the slave: its options and the host or device last.
struct Mbpoll {
    options: Vec<String>,
    target: String,
}

impl Mbpoll {
    fn tcp(port: u16) -> Self {
        Mbpoll {
            options: ["-m", "tcp", "-p", &port.to_string()]
                .map(String::from)
                .to_vec(),
            target: "127.0.0.1".into(),
        }
    }

    fn rtu(device: &str) -> Self {
        // 8N1: mbpoll defaults to even parity.
        Mbpoll {
            options: ["-m", "rtu", "-b", "115200", "-P", "none"]
                .map(String::from)
                .to_vec(),
            target: device.into(),
        }
    }

    /// One mbpoll run, slave 1, 0-based addresses, one poll (`-1`).
    fn run(&self, args: &[&str], values: &[&str]) -> String {
        let out = run_timeout(
            Command::new("mbpoll")
                .args(&self.options)
                .args(["-a", "1", "-0", "-1", "-o", "3"])
                .args(args)
                .arg(&self.target)
                .args(values),
            Duration::from_secs(10),
        );
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "mbpoll {args:?} {values:?} failed\nstdout: {text}\nstderr: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        text
    }

    /// Values of `[i]: v` lines, in order.
    fn read(&self, table: &str, start: u16, count: u16) -> Vec<u16> {
        let text = self.run(
            &[
                "-t",
                table,
                "-r",
                &start.to_string(),
                "-c",
                &count.to_string(),
            ],
            &[],
        );
        let values: Vec<u16> = text
            .lines()
            .filter(|l| l.starts_with('['))
            .map(|l| {
                l.split(':')
                    .nth(1)
                    .unwrap()
                    .trim()
                    .parse()
                    .unwrap_or_else(|e| panic!("{l}: {e}"))
            })
            .collect();
        assert_eq!(
            values.len(),
            usize::from(count),
            "mbpoll read {count}: {text}"
        );
        values
    }

    fn write(&self, table: &str, start: u16, values: &[&str]) {
        let text = self.run(&["-t", table, "-r", &start.to_string()], values);
        assert!(
            text.contains(&format!("Written {} references", values.len())),
            "{text}"
        );
    }

    fn rpm(&self) -> u16 {
        self.read("3", RPM_M as u16, 1)[0]
    }
}

/// Waits until two readings a second apart agree within 2 % (and the wheel
/// turns), for at most 20 s; returns the last reading.
fn settle(mut rpm: impl FnMut() -> u16) -> u16 {
    let mut last = rpm();
    wait_for(Duration::from_secs(20), Duration::from_secs(1), || {
        let now = rpm();
        let settled = now > 200 && now.abs_diff(last) as f64 <= 0.02 * now as f64;
        last = now;
        settled.then_some(now)
    })
    .unwrap_or(last)
}

/// Waits until the wheel passes `target` rpm, for at most 20 s; returns the
/// last reading.
fn rise_past(target: f64, mut rpm: impl FnMut() -> u16) -> u16 {
    let mut last = 0;
    wait_for(Duration::from_secs(20), Duration::from_millis(200), || {
        last = rpm();
        (f64::from(last) > target).then_some(last)
    })
    .unwrap_or(last)
}

fn drive_with_mbpoll(mb: &Mbpoll) {
    let inputs = mb.read("3", 0, 10);
    assert!(
        inputs[V1] > 0 && inputs[V1] < 4096,
        "V1 is an ADC count of a charged battery: {inputs:?}"
    );
    assert_eq!(
        inputs[RPM_M], 0,
        "the wheel stands still before enabling: {inputs:?}"
    );
    let coils = mb.read("0", 0, 1);
    assert_eq!(coils, [1], "EN reads 1 (disabled) at power-up");

    mb.write("4", 0, &[&VEL_LOW.to_string()]);
    assert_eq!(mb.read("4", 0, 1), [VEL_LOW], "VEL reads back");
    // EN = 0 enables, BRK = 1 releases the brake (coils hold the pin level).
    mb.write("0", 0, &["0", "1"]);
    assert_eq!(mb.read("0", 0, 2), [0, 1]);

    let low = settle(|| mb.rpm());
    assert!(low > 200, "the wheel turns at VEL {VEL_LOW}: {low} rpm");
    mb.write("4", 0, &[&VEL_HIGH.to_string()]);
    let high = rise_past(1.4 * f64::from(low), || mb.rpm());
    assert!(
        high as f64 > 1.4 * low as f64,
        "doubling VEL speeds the wheel up: {low} -> {high} rpm"
    );
}

#[test]
fn mbpoll_drives_the_wheel_over_modbus_tcp() {
    let serve = Serve::start(&["--quiet", "--modbus", "tcp://127.0.0.1:0"]);
    drive_with_mbpoll(&Mbpoll::tcp(serve.port("modbus-tcp")));
}

#[test]
fn mbpoll_drives_the_wheel_over_rtu_on_a_pty() {
    let dir = scratch("mbpoll-rtu");
    let pair = PtyPair::new(&dir);
    let serve = Serve::start(&["--quiet", "--modbus-rtu", pair.a.to_str().unwrap()]);
    assert_eq!(serve.link("modbus-rtu").address, pair.a.to_str().unwrap());
    drive_with_mbpoll(&Mbpoll::rtu(pair.b.to_str().unwrap()));
}

fn drive_with_pymodbus(args: &[&str]) {
    let out = run_timeout(
        Command::new("python3")
            .arg(script("pymodbus_master.py"))
            .args(args),
        Duration::from_secs(90),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "pymodbus master failed: {stderr}");
    let seen: serde_json::Value =
        serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {stderr}"));
    let inputs: Vec<u64> = serde_json::from_value(seen["inputs"].clone()).unwrap();
    assert_eq!(inputs.len(), 10);
    assert!(inputs[V1] > 0 && inputs[V1] < 4096, "{seen}");
    assert_eq!(inputs[RPM_M], 0, "{seen}");
    assert_eq!(
        seen["coils_before"][0], true,
        "EN disabled at power-up: {seen}"
    );
    assert_eq!(seen["vel_readback"], VEL_LOW, "{seen}");
    assert_eq!(
        seen["coils_after"],
        serde_json::json!([false, true]),
        "{seen}"
    );
    let low = seen["rpm_low"].as_f64().unwrap();
    let high = seen["rpm_high"].as_f64().unwrap();
    assert!(low > 200.0, "the wheel turns at VEL {VEL_LOW}: {seen}");
    assert!(high > 1.4 * low, "doubling VEL speeds the wheel up: {seen}");
}

#[test]
fn pymodbus_drives_the_wheel_over_modbus_tcp() {
    let serve = Serve::start(&["--quiet", "--modbus", "tcp://127.0.0.1:0"]);
    let port = serve.port("modbus-tcp").to_string();
    drive_with_pymodbus(&["tcp", "127.0.0.1", &port]);
}

#[test]
fn pymodbus_drives_the_wheel_over_rtu_on_a_pty() {
    let dir = scratch("pymodbus-rtu");
    let pair = PtyPair::new(&dir);
    let _serve = Serve::start(&["--quiet", "--modbus-rtu", pair.a.to_str().unwrap()]);
    drive_with_pymodbus(&["rtu", pair.b.to_str().unwrap()]);
}

/// Every frame of four pymodbus masters polling back to back is recorded,
/// however fast they poll: as many frames on `/link/modbus-tcp/frames` as
/// requests and replies, and the server says so when it stops.
#[test]
fn every_frame_of_pymodbus_masters_polling_back_to_back_is_recorded() {
    let dir = scratch("pymodbus-flood");
    let out = dir.join("flood.mcap");
    let mut serve = Serve::start(&[
        "--quiet",
        "--turnaround-ms",
        "0",
        "--status-every",
        "0",
        "--rate-limit",
        "0",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--out",
        out.to_str().unwrap(),
    ]);
    let port = serve.port("modbus-tcp").to_string();
    let flood = run_timeout(
        Command::new("python3")
            .arg(script("pymodbus_flood.py"))
            .args(["127.0.0.1", &port, "4", "3"]),
        Duration::from_secs(60),
    );
    let stderr = String::from_utf8_lossy(&flood.stderr);
    assert!(flood.status.success(), "pymodbus masters failed: {stderr}");
    let seen: serde_json::Value =
        serde_json::from_slice(&flood.stdout).unwrap_or_else(|e| panic!("{e}: {stderr}"));
    let answered = seen["answered"].as_u64().unwrap();
    assert!(answered > 100, "the masters were answered: {seen}");
    assert_eq!(
        seen["sent"], seen["answered"],
        "every request answered: {seen} {stderr}"
    );
    assert_eq!(seen["errors"], 0, "no Modbus exception: {seen}");
    serve.terminate();
    let line = serve.expect_line("frames recorded on the links", Duration::from_secs(5));
    assert_eq!(
        line.trim(),
        format!(
            "{} frames recorded on the links (requests and replies)",
            2 * answered
        ),
        "{seen}"
    );
    let bytes = std::fs::read(&out).expect("recording written");
    let frames = mcap::MessageStream::new(&bytes)
        .expect("valid MCAP")
        .map(|m| m.expect("message"))
        .filter(|m| m.channel.topic == "/link/modbus-tcp/frames")
        .count() as u64;
    assert_eq!(frames, 2 * answered, "{seen}");
    let _ = std::fs::remove_dir_all(&dir);
}
