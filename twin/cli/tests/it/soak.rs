//! The soak script (`tests/soak.py`) for 30 seconds, as CI runs it: an
//! MEB-TCP, a Modbus TCP and a pty Modbus RTU master poll `twin serve` at
//! 100 Hz each, every reply checked. The hour-long run is by hand (see the
//! script); its figures are in docs/measurements.md.

use std::path::Path;
use std::process::Command;

#[test]
fn thirty_seconds_of_three_masters_lose_no_reply() {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/soak.py");
    let o = Command::new("python3")
        .arg(&script)
        .args(["--twin", env!("CARGO_BIN_EXE_twin")])
        .args(["--seconds", "30", "--json"])
        .output()
        .expect("python3 runs");
    let stdout = String::from_utf8_lossy(&o.stdout);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    let figures: serde_json::Value =
        serde_json::from_str(stdout.lines().last().expect("a JSON line")).expect("JSON");
    for name in ["meb-tcp", "modbus-tcp", "modbus-rtu-pty"] {
        let m = &figures["masters"][name];
        assert_eq!(m["lost"], 0, "{name}: {m}");
        assert_eq!(m["wrong"], 0, "{name}: {m}");
        // Late replies (over 2 s) are in `m`, not failed: on a loaded
        // machine the kernel has held pty bytes that long.
        // 3000 asked; a loaded machine paces the masters more slowly, but
        // one request in flight at a time still makes many.
        assert!(m["answered"].as_u64().unwrap() >= 1000, "{name}: {m}");
        assert_eq!(m["answered"], m["sent"], "{name}: {m}");
    }
    assert_eq!(
        figures["server_exit"], 0,
        "SIGTERM ends the session cleanly"
    );
    let threads = &figures["threads"];
    assert_eq!(
        threads["first"], threads["last"],
        "no thread left behind: {threads}"
    );
    // The plant ticked all along: 30 000 ticks at 1 kHz, fewer where a tick
    // overran and the next was skipped (a loaded machine skips hundreds), but
    // never a stalled plant.
    let tick = &figures["tick_lateness_total"];
    assert!(
        tick["ticks"].as_u64().unwrap() > 15_000,
        "the plant ticked: {tick}"
    );
    assert!(figures["recording_bytes"].as_u64().unwrap() > 0);
}
