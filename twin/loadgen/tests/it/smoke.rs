//! The load generator against the servers it ships with: its Modbus TCP and
//! RTU requests, built by hand, must be answered by tokio-modbus (a server we
//! did not write) and pass its own reply checks, and the echo must come back
//! byte for byte. Only that every reply was right is asserted: speed is for
//! `serve-bench` itself, not for a test.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

#[test]
fn every_reply_of_the_reference_servers_passes_the_checks() {
    let out = Command::new(env!("CARGO_BIN_EXE_serve-bench"))
        .args([
            "--no-twin",
            "--requests",
            "300",
            "--seconds",
            "0.3",
            "--clients",
            "2",
        ])
        .output()
        .expect("serve-bench runs");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rows: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("  echo") || l.starts_with("  tokio-modbus"))
        .collect();
    // Latency: echo tcp + pty, tokio-modbus tcp + pty; rate: echo, the
    // echo on tokio, tokio-modbus.
    assert_eq!(rows.len(), 7, "{text}");
    for row in rows {
        let bad: u64 = row.split_whitespace().last().unwrap().parse().unwrap();
        assert_eq!(bad, 0, "wrong replies: {row}");
        assert!(!row.contains(" 0/s"), "no replies at all: {row}");
    }
}

/// `serve-bench load` against a server started apart (the echo here), as a
/// user loads their own server; and a clear error where there is none.
#[test]
fn load_checks_every_reply_of_a_server_given_by_address() {
    let mut echo = Command::new(env!("CARGO_BIN_EXE_serve-bench"))
        .arg("echo-tokio")
        .stdout(Stdio::piped())
        .spawn()
        .expect("the echo starts");
    let mut lines = BufReader::new(echo.stdout.take().unwrap()).lines();
    let address = lines
        .next()
        .and_then(|l| l.ok())
        .and_then(|l| l.split_whitespace().nth(1).map(str::to_string))
        .expect("the echo prints its address");
    let load = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_serve-bench"))
            .arg("load")
            .args(args)
            .output()
            .expect("serve-bench runs")
    };
    let out = load(&["--echo", &address, "--seconds", "0.3", "--clients", "2"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert!(
        text.contains("from 2 clients") && text.ends_with("0 bad replies\n"),
        "{text}"
    );
    let answered: u64 = text
        .split_whitespace()
        .nth(1)
        .and_then(|n| n.parse().ok())
        .unwrap_or(0);
    assert!(answered > 0, "{text}");
    // The echo's replies are no Modbus replies: every one is counted bad.
    let out = load(&[&address, "--seconds", "0.2", "--clients", "1"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(!text.contains(" 0 bad replies"), "{text}");
    let _ = echo.kill();
    let _ = echo.wait();

    let out = load(&["tcp://127.0.0.1:1", "--seconds", "0.2"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("connecting to 127.0.0.1:1"), "{err}");
}
