//! A small MEB master written in Python from docs/protocols/meb.md alone
//! (`peers/meb_master.py`) against `twin serve`, over TCP and over a
//! pseudo-terminal: it reads the inputs, gets the error replies the spec
//! prescribes, sees bad frames ignored and counted, pipelines requests, writes
//! VEL and the outputs and watches RPM_M follow.

use crate::peers;

use peers::{PtyPair, Serve, run_timeout, scratch, script};
use serde_json::{Value, json};
use std::process::Command;
use std::time::Duration;

fn run_master(args: &[&str]) -> Value {
    let out = run_timeout(
        Command::new("python3")
            .arg(script("meb_master.py"))
            .args(args),
        Duration::from_secs(90),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "MEB master failed: {stderr}");
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {stderr}"))
}

fn check(seen: &Value) {
    let ea: Vec<u64> = serde_json::from_value(seen["ea"].clone()).unwrap();
    assert_eq!(ea.len(), 6, "{seen}");
    assert!(ea[2] > 0 && ea[2] < 4096, "V1 is an ADC count: {seen}");
    assert_eq!(ea[3], 0, "RPM_M is 0 before enabling: {seen}");
    assert_eq!(seen["er_range"], json!([2]), "EA 0 99 is error 02: {seen}");
    assert_eq!(seen["er_command"], json!([1]), "QQ is error 01: {seen}");
    assert_eq!(
        seen["bad_fcs_reply"],
        Value::Null,
        "a bad FCS is ignored: {seen}"
    );
    assert_eq!(
        seen["after_garbage"], "EA",
        "garbage before @ is dropped: {seen}"
    );
    assert_eq!(
        seen["extra_reply"],
        Value::Null,
        "one reply per frame: {seen}"
    );
    let (before, after) = (
        seen["errs_before"].as_u64().unwrap(),
        seen["errs_after"].as_u64().unwrap(),
    );
    assert!(after > before, "ERRS counts the dropped frames: {seen}");
    assert_eq!(seen["pipelined"], json!(["EA", "FA", "ED"]), "{seen}");
    let low = seen["rpm_low"].as_f64().unwrap();
    let high = seen["rpm_high"].as_f64().unwrap();
    assert!(low > 200.0, "the wheel turns at 40 % VEL: {seen}");
    assert!(high > 1.4 * low, "doubling VEL speeds the wheel up: {seen}");
    let status = seen["status"].as_u64().unwrap();
    assert_eq!(status & 0b11, 0, "no trip: {seen}");
}

#[test]
fn python_meb_master_over_tcp() {
    let serve = Serve::start(&["--quiet", "--meb", "tcp://127.0.0.1:0"]);
    let port = serve.port("meb").to_string();
    check(&run_master(&["tcp", "127.0.0.1", &port]));
}

#[test]
fn python_meb_master_over_a_pty() {
    let dir = scratch("meb-pty");
    let pair = PtyPair::new(&dir);
    let _serve = Serve::start(&["--quiet", "--meb", pair.a.to_str().unwrap()]);
    check(&run_master(&["serial", pair.b.to_str().unwrap()]));
}
