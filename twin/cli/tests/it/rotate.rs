//! A long `twin serve` session's recordings: rotated by time and on SIGHUP,
//! each file complete and named by its start time, every frame in exactly
//! one of them; old files pruned by the retention rules, and a nearly full
//! disk met by pruning and going on rather than stopping.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use crate::support;
use support::Proc;

fn folder(name: &str) -> PathBuf {
    support::folder("rotate", name)
}

fn signal(proc: &Proc, name: &str) {
    let pid = proc.child.id().to_string();
    assert!(
        Command::new("kill")
            .args([&format!("-{name}"), &pid])
            .status()
            .expect("kill runs")
            .success()
    );
}

/// Polls input registers 0-1 over Modbus TCP, one request in flight, each
/// with its own transaction id, until `until`; every reply checked. Returns
/// the ids sent.
fn poll_until(addr: &str, until: Instant) -> Vec<u16> {
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s.set_nodelay(true).unwrap();
    let mut sent = Vec::new();
    let mut tid: u16 = 1;
    while Instant::now() < until {
        let [hi, lo] = tid.to_be_bytes();
        s.write_all(&[hi, lo, 0, 0, 0, 6, 1, 4, 0, 0, 0, 2])
            .expect("send");
        let mut reply = [0u8; 13];
        s.read_exact(&mut reply).expect("a reply within 5 s");
        assert_eq!(&reply[..2], &[hi, lo], "the reply to request {tid}");
        assert_eq!(&reply[6..9], &[1, 4, 4], "a read of 2 registers");
        sent.push(tid);
        tid += 1;
        std::thread::sleep(Duration::from_millis(2));
    }
    sent
}

/// The session's files in `dir` (`serve-*.mcap`), in name order.
fn recordings(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("folder")
        .map(|e| e.expect("entry").path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("serve-"))
        })
        .collect();
    files.sort();
    files
}

/// What one file holds: Modbus TCP transaction ids by sender, its metadata
/// by name, and whether its summary counts the messages it holds.
struct FileContents {
    tids: BTreeMap<String, Vec<u16>>,
    metadata: BTreeMap<String, BTreeMap<String, String>>,
}

fn contents(path: &Path) -> FileContents {
    let bytes = std::fs::read(path).expect("recording");
    let mut tids: BTreeMap<String, Vec<u16>> = BTreeMap::new();
    let mut count = 0u64;
    for m in mcap::MessageStream::new(&bytes).expect("valid MCAP") {
        let m = m.expect("a whole message");
        count += 1;
        if m.channel.topic != "/link/modbus-tcp/frames" {
            continue;
        }
        let v: serde_json::Value =
            twin_recording::read::value_of(&m.channel, &m.data).expect("a message that reads");
        let hex = v["hex"].as_str().expect("hex");
        let tid = u16::from_str_radix(&hex[..4], 16).expect("tid");
        let from = v["from"].as_str().expect("from").to_string();
        tids.entry(if from == "twin" {
            from
        } else {
            "client".into()
        })
        .or_default()
        .push(tid);
    }
    let summary = mcap::Summary::read(&bytes)
        .expect("summary readable")
        .unwrap_or_else(|| panic!("{} has no summary: not finished", path.display()));
    let stats = summary.stats.expect("statistics");
    assert_eq!(stats.message_count, count, "{}", path.display());
    let mut metadata = BTreeMap::new();
    for index in &summary.metadata_indexes {
        let m = mcap::read::metadata(&bytes, index).expect("metadata");
        metadata.insert(m.name.clone(), m.metadata.clone());
    }
    FileContents { tids, metadata }
}

#[test]
fn every_frame_is_in_exactly_one_of_the_rotated_files() {
    let dir = folder("frames");
    let server = Proc::start(&[
        "serve",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--status-every",
        "0",
        "--record-dir",
        dir.to_str().unwrap(),
        "--rotate-every",
        "2s",
    ]);
    let addr = server.tcp_of("modbus-tcp");
    let start = Instant::now();
    let poller = std::thread::spawn(move || poll_until(&addr, start + Duration::from_millis(5500)));
    for at in [1200, 2700] {
        std::thread::sleep(
            (start + Duration::from_millis(at)).saturating_duration_since(Instant::now()),
        );
        signal(&server, "HUP");
    }
    let sent = poller.join().expect("poller");
    let printed = server.terminate();
    assert!(sent.len() > 500, "{} requests", sent.len());

    let files = recordings(&dir);
    // 5.5 s at one file per 2 s, and two SIGHUPs.
    assert!(files.len() >= 4, "{files:?}\n{printed}");
    assert_eq!(printed.matches("finished (SIGHUP)").count(), 2, "{printed}");
    assert!(
        printed.contains("finished (--rotate-every 2s)"),
        "{printed}"
    );
    let mut seen: BTreeMap<String, Vec<u16>> = BTreeMap::new();
    for (n, path) in files.iter().enumerate() {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        // serve-2026-12-03T07-35-44.mcap, or -2 … within one second.
        assert!(
            name.len() >= "serve-2026-12-03T07-35-44.mcap".len(),
            "{name}"
        );
        let c = contents(path);
        let run = &c.metadata["twin.run"];
        assert_eq!(run["kind"], "serve", "{name}");
        let last = n + 1 == files.len();
        if n > 0 {
            assert_eq!(run["part"], (n + 1).to_string(), "{name}");
            let previous = files[n - 1].file_name().unwrap().to_string_lossy();
            assert_eq!(run["previous"], previous, "{name}");
        }
        if last {
            assert!(c.metadata.contains_key("twin.realtime"), "{name}");
        } else {
            let part = &c.metadata["twin.part"];
            let next = files[n + 1].file_name().unwrap().to_string_lossy();
            assert_eq!(part["next"], next, "{name}");
            assert!(!c.metadata.contains_key("twin.realtime"), "{name}");
        }
        for (from, tids) in c.tids {
            seen.entry(from).or_default().extend(tids);
        }
    }
    // Each request and each reply once, in order, across the files.
    for from in ["client", "twin"] {
        assert_eq!(seen[from], sent, "frames from {from} across {files:?}");
    }
    assert!(
        printed.contains(&format!("(after {} earlier files)", files.len() - 1)),
        "{printed}"
    );
}

#[test]
fn old_recordings_go_by_the_retention_rules_and_others_stay() {
    let dir = folder("keep");
    // Files the session must never touch: another name, another kind.
    let foreign = [
        "serve-notes.mcap",
        "supervise-2020-01-01T00-00-00.mcap",
        "serve-2020-01-01T00-00-00.txt",
    ];
    for name in foreign {
        std::fs::write(dir.join(name), b"not ours").unwrap();
    }
    // An old recording of this session's name, past --keep-age.
    let old = dir.join("serve-2020-01-01T00-00-00.mcap");
    std::fs::write(&old, b"old").unwrap();
    let file = std::fs::File::options().write(true).open(&old).unwrap();
    file.set_modified(std::time::SystemTime::UNIX_EPOCH + Duration::from_secs(1_577_836_800))
        .unwrap();
    drop(file);
    let server = Proc::start(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--status-every",
        "0",
        "--record-dir",
        dir.to_str().unwrap(),
        "--rotate-every",
        "1",
        "--keep-files",
        "2",
        "--keep-age",
        "30d",
    ]);
    let start = Instant::now();
    while Instant::now() < start + Duration::from_secs(10)
        && server.output().matches(" finished (").count() < 4
    {
        std::thread::sleep(Duration::from_millis(50));
    }
    let printed = server.terminate();
    assert!(printed.matches(" finished (").count() >= 4, "{printed}");
    let files = recordings(&dir);
    let ours: Vec<&PathBuf> = files
        .iter()
        .filter(|p| {
            p.extension().is_some_and(|e| e == "mcap") && *p != &dir.join("serve-notes.mcap")
        })
        .collect();
    assert_eq!(ours.len(), 2, "--keep-files 2: {files:?}\n{printed}");
    assert!(!old.exists(), "{printed}");
    assert!(
        printed.contains("serve-2020-01-01T00-00-00.mcap") && printed.contains("--keep-"),
        "the old one's deletion is said: {printed}"
    );
    assert!(printed.contains("(0.0 MB; --keep-files 2)"), "{printed}");
    for name in foreign {
        assert!(dir.join(name).exists(), "{name} was deleted");
    }
    for path in ours {
        contents(path);
    }
}

/// The free space of the disk holding `dir`, in MB (MiB).
fn free_mb(dir: &Path) -> u64 {
    let stat = rustix::fs::statvfs(dir).expect("statvfs");
    stat.f_bavail * stat.f_frsize / (1024 * 1024)
}

#[test]
fn a_nearly_full_disk_prunes_the_oldest_and_recording_goes_on() {
    let dir = folder("disk");
    // An old recording taking real blocks (not a sparse file), whose
    // deletion gives the disk room again.
    let old = dir.join("serve-2020-01-01T00-00-00.mcap");
    let file = std::fs::File::create(&old).unwrap();
    rustix::fs::fallocate(&file, rustix::fs::FallocateFlags::empty(), 0, 256 << 20)
        .expect("256 MB for the old recording");
    drop(file);
    // The floor just above what is free now: the first check stops the
    // recording; deleting the old one gives back 256 MB, more than the
    // floor plus the 64 MB a recording needs to go on.
    let floor = free_mb(&dir) + 16;
    let child = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args([
            "serve",
            "--meb",
            "tcp://127.0.0.1:0",
            "--quiet",
            "--status-every",
            "0",
            "--record-dir",
            dir.to_str().unwrap(),
            "--keep-size",
            "100G",
            "--duration",
            "2",
        ])
        .env("TWIN_MIN_FREE_DISK_MB", floor.to_string())
        .output()
        .expect("twin runs");
    let printed = String::from_utf8_lossy(&child.stdout).into_owned();
    assert!(child.status.success(), "{printed}");
    assert!(!old.exists(), "{printed}");
    assert!(
        printed.contains("serve-2020-01-01T00-00-00.mcap (268.4 MB; the disk was nearly full)"),
        "{printed}"
    );
    assert!(printed.contains("recording: going on in "), "{printed}");
    assert!(!printed.contains("recording stopped"), "{printed}");
    let files = recordings(&dir);
    assert_eq!(files.len(), 2, "the stopped file and the next: {files:?}");
    for path in &files {
        contents(path);
    }
}
