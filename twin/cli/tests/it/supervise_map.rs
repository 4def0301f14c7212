//! `twin supervise --map`: a slave whose I/O map is not the MEB page's, as
//! the M3CVME tool lets one configure it, supervised over a `twin vsp` pair.
//! The wheel's speed is read from the slave itself (a TCP link of its own,
//! at the map's address), so what the supervisor believes proves nothing.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::supervise::{Raw, client, frame, pair_paths, reply_words, s, server_tcp};
use crate::support::{self, Proc};

fn moved_map() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/examples/meb-map-moved.toml")
}

/// A `twin serve --map` slave on one end of a vsp pair and on TCP; the
/// other end of the pair for the supervisor.
fn mapped_slave(name: &str) -> (Proc, Proc, PathBuf, Raw) {
    let (a, b) = pair_paths(name);
    let vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let map = moved_map();
    let serve = Proc::start(&[
        "serve",
        "--meb",
        s(&b),
        "--meb",
        "tcp://127.0.0.1:0",
        "--map",
        s(&map),
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ]);
    let slave = Raw::connect(&server_tcp(&serve));
    (vsp, serve, a, slave)
}

/// RPM_M as the slave answers it: EA 00 in the moved map.
fn slave_rpm(slave: &mut Raw) -> u16 {
    slave.send(&frame("@01EA0001"));
    reply_words(&slave.frames(1)[0])[0]
}

/// Waits until the slave's wheel stays within 3 % of `target` for five
/// readings in a row; the readings on failure.
fn settles_at(slave: &mut Raw, target: f64, within: Duration) -> Result<(), Vec<u16>> {
    let deadline = Instant::now() + within;
    let (mut seen, mut settled) = (Vec::new(), 0);
    while Instant::now() < deadline {
        let rpm = slave_rpm(slave);
        seen.push(rpm);
        settled = if (f64::from(rpm) - target).abs() <= 0.03 * target {
            settled + 1
        } else {
            0
        };
        if settled == 5 {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    Err(seen)
}

fn supervise(bus: &Path, extra: &[&str]) -> Proc {
    let mut args = vec![
        "supervise",
        "--meb",
        s(bus),
        "--listen",
        "tcp://127.0.0.1:0",
        "--set-point",
        "1500",
        "--quiet",
        "--no-record",
        "--status-every",
        "0",
    ];
    args.extend_from_slice(extra);
    Proc::start(&args)
}

#[test]
fn supervise_with_the_slaves_map_closes_the_loop_and_its_clients_keep_the_default_map() {
    let (_vsp, _serve, bus, mut slave) = mapped_slave("map-loop");
    let map = moved_map();
    let supervisor = supervise(&bus, &["--map", s(&map)]);
    if let Err(seen) = settles_at(&mut slave, 1500.0, Duration::from_secs(25)) {
        panic!("the mapped slave's wheel did not reach 1500 rpm: {seen:?}");
    }
    // The supervisor's own clients read the MEB page's map: RPM_M at EA 03.
    let url = format!("tcp://{}", server_tcp(&supervisor));
    let image = client(&[&url, "read", "EA", "3", "1"]);
    let text = String::from_utf8_lossy(&image.stdout);
    let rpm: f64 = text
        .lines()
        .find(|l| l.starts_with("EA 03"))
        .and_then(|l| l.split('=').nth(1)?.split_whitespace().next()?.parse().ok())
        .unwrap_or_else(|| panic!("no EA 03 in {text:?}"));
    assert!((rpm - 1500.0).abs() < 150.0, "{text}");
    // The status words the map moves: SOC (FA 03 on the slave) read into
    // the image's FA 00, which a full battery holds well above zero.
    let soc = client(&[&url, "read", "FA", "0", "1"]);
    let soc_text = String::from_utf8_lossy(&soc.stdout);
    assert!(soc.status.success(), "{soc_text}");
    assert!(!soc_text.contains("FA 00 =     0"), "{soc_text}");
    // A client's brake in the default map (SD 00 bit 1 low) reaches the
    // slave at SD 01, and the wheel stops.
    let brake = client(&[&url, "write", "SD", "0", "0x000C"]);
    assert!(
        brake.status.success(),
        "{}",
        String::from_utf8_lossy(&brake.stderr)
    );
    let deadline = Instant::now() + Duration::from_secs(20);
    while slave_rpm(&mut slave) >= 100 {
        assert!(
            Instant::now() < deadline,
            "the brake never reached the slave"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn supervise_without_the_slaves_map_never_reaches_the_set_point() {
    let (_vsp, _serve, bus, mut slave) = mapped_slave("map-none");
    let _supervisor = supervise(&bus, &[]);
    // The default map's EA 03 is V1 here, and SA 00 and SD 00 are empty:
    // the wheel never moves.
    let result = settles_at(&mut slave, 1500.0, Duration::from_secs(8));
    let seen = result.expect_err("the wheel reached the set point without the map");
    assert!(seen.iter().all(|&rpm| rpm < 100), "{seen:?}");
}

#[test]
fn a_map_without_the_speed_the_loop_measures_is_refused_naming_the_file() {
    let path = support::scratch("supervise-map", "no-rpm.toml");
    std::fs::write(&path, "[EA]\nV1 = 0\nV2 = 1\n").unwrap();
    let out = support::twin(&[
        "supervise",
        "--meb",
        "tcp://127.0.0.1:9",
        "--map",
        s(&path),
        "--no-record",
        "--check",
    ]);
    assert_eq!(out.status.code(), Some(1));
    let text = support::text(&out);
    assert!(
        text.contains(&format!(
            "{}: the I/O map places no RPM_M, which the supervisor measures the speed with",
            path.display()
        )),
        "{text}"
    );
    std::fs::write(&path, "[EA]\nV1 = 0\nRPM_M = 0\n").unwrap();
    let out = support::twin(&["supervise", "--meb", "tcp://127.0.0.1:9", "--map", s(&path)]);
    let text = support::text(&out);
    assert!(
        text.contains(&format!("{}:2: [EA]", path.display())),
        "{text}"
    );
}
