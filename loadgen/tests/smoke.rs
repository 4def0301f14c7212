//! The load generator against the servers it ships with: its Modbus TCP and
//! RTU requests, built by hand, must be answered by tokio-modbus (a server we
//! did not write) and pass its own reply checks, and the echo must come back
//! byte for byte. Only that every reply was right is asserted: speed is for
//! `serve-bench` itself, not for a test.

use std::process::Command;

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
    // Latency: echo tcp + pty, tokio-modbus tcp + pty; rate: echo, tokio-modbus.
    assert_eq!(rows.len(), 6, "{text}");
    for row in rows {
        let bad: u64 = row.split_whitespace().last().unwrap().parse().unwrap();
        assert_eq!(bad, 0, "wrong replies: {row}");
        assert!(!row.contains(" 0/s"), "no replies at all: {row}");
    }
}
