//! `twin check server`: the twin's own supervisor (`twin supervise`) passes
//! every check, and a student's supervisor written outside the twin (a
//! Python program on a pseudo-terminal and TCP) passes when correct, each
//! planted bug found alone; and a class of them from a roster. The bus is
//! a `twin vsp` pair: the supervisor on one end, the check's slave on the
//! other.

use crate::supervise::{pair_paths, s, server_tcp};
use crate::support::{Proc, scratch, text, twin};
use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use super::failed;

/// The student's supervisor on `bus`, with `bugs` planted.
struct StudentServer {
    child: Child,
    link: String,
}

impl Drop for StudentServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn student_server(name: &str, bus: &Path, bugs: &[&str]) -> StudentServer {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/meb_student_server.py");
    let port_file = scratch("check-server", &format!("{name}.port"));
    let _ = std::fs::remove_file(&port_file);
    let mut command = Command::new("python3");
    command.arg(script).arg(bus).arg(&port_file);
    for bug in bugs {
        command.args(["--bug", bug]);
    }
    let mut child = command.spawn().expect("python3 runs");
    let deadline = Instant::now() + Duration::from_secs(10);
    let port = loop {
        if let Ok(port) = std::fs::read_to_string(&port_file) {
            break port;
        }
        if let Ok(Some(status)) = child.try_wait() {
            panic!("the student's supervisor stopped: {status}");
        }
        assert!(
            Instant::now() < deadline,
            "the student's supervisor never listened"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    StudentServer {
        child,
        link: format!("tcp://127.0.0.1:{}", port.trim()),
    }
}

/// `twin check server LINK --bus BUS MORE…`, reads given 1 s (writes 10 s):
/// a loaded test machine may answer late, and the logic is what is checked.
/// Not recorded unless MORE says where.
fn check_server(link: &str, bus: &Path, more: &[&str]) -> std::process::Output {
    let mut args = vec![
        "check",
        "server",
        link,
        "--bus",
        s(bus),
        "--timeout-ms",
        "1000",
    ];
    args.extend_from_slice(more);
    if !more
        .iter()
        .any(|a| a.starts_with("--record") || *a == "--no-record")
    {
        args.push("--no-record");
    }
    twin(&args)
}

#[test]
fn the_twins_own_supervisor_passes_every_server_check() {
    let (a, b) = pair_paths("check-supervise");
    let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let supervise = Proc::start(&[
        "supervise",
        "--meb",
        s(&a),
        "--listen",
        "tcp://127.0.0.1:0",
        "--no-record",
        "--quiet",
        "--status-every",
        "0",
        "--duration",
        "120",
    ]);
    let link = format!("tcp://{}", server_tcp(&supervise));
    let started = Instant::now();
    let out = check_server(&link, &b, &[]);
    let wall = started.elapsed();
    let shown = text(&out);
    assert!(out.status.success(), "{shown}");
    assert!(
        shown.contains("score: 20 of 20 points (15 of 15 checks passed)"),
        "{shown}"
    );
    assert!(!shown.contains("FAIL"), "{shown}");
    // The figure for the measurements, not a bound.
    eprintln!(
        "twin check server against twin supervise: {:.2} s",
        wall.as_secs_f64()
    );
    supervise.terminate();
}

#[test]
fn a_correct_student_server_passes_and_each_planted_bug_is_found_alone() {
    let json = scratch("check-server", "run.json");
    let cases: [(&str, &[&str]); 3] = [
        ("correct", &[]),
        (
            "one-client-at-a-time",
            &["two clients connected at once are both served"],
        ),
        (
            "write-wrong-block",
            &["a client's VEL write (SA 00) goes on the bus as SA 00 and is acknowledged"],
        ),
    ];
    for (name, expected) in cases {
        let (a, b) = pair_paths(&format!("check-{name}"));
        let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
        let bugs: &[&str] = if name == "correct" { &[] } else { &[name] };
        let server = student_server(name, &a, bugs);
        let out = check_server(&server.link, &b, &["--json", json.to_str().unwrap()]);
        let shown = text(&out);
        assert_eq!(failed(&json), expected, "{name}: {shown}");
        assert_eq!(out.status.success(), expected.is_empty(), "{name}: {shown}");
        if name == "write-wrong-block" {
            assert!(
                shown.contains("the write went on the bus as VA 00 (`@01VA000104D2"),
                "{shown}"
            );
            // The evidence holds both sides: the client's request and
            // what the supervisor put on the bus.
            assert!(
                shown.contains(" s  sent      client    @01SA000104D2"),
                "{shown}"
            );
            assert!(
                shown.contains(" s  received  bus       @01VA000104D2"),
                "{shown}"
            );
            // The book's report is this one.
            let page = std::fs::read_to_string(
                Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/check.md"),
            )
            .unwrap();
            let start = page
                .find("```text\nMEB server suite, ")
                .expect("the report on the page")
                + 8;
            let book = &page[start..start + page[start..].find("\n```").unwrap()];
            assert_eq!(super::comparable(&shown), super::comparable(book));
        }
        if name == "one-client-at-a-time" {
            assert!(
                shown.contains("client 2: no reply within 1000 ms"),
                "{shown}"
            );
        }
    }
}

#[test]
fn a_server_that_is_not_listening_is_reported_with_every_check_failed() {
    let (a, b) = pair_paths("check-nobody");
    let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let junit = scratch("check-server", "nobody.junit.xml");
    let out = check_server(
        "tcp://127.0.0.1:9",
        &b,
        &["--junit", junit.to_str().unwrap()],
    );
    let shown = text(&out);
    assert!(!out.status.success(), "{shown}");
    assert!(
        shown.contains(
            "could not be checked: cannot connect to tcp://127.0.0.1:9: connection refused"
        ),
        "{shown}"
    );
    let read = super::junit_read(&junit);
    assert_eq!(read["name"], "MEB server");
    assert_eq!(
        (read["tests"].as_u64(), read["errors"].as_u64()),
        (Some(15), Some(15))
    );
    // And the link must be TCP: a serial path is the bus, said so.
    let out = twin(&["check", "server", s(&a), "--bus", s(&b)]);
    assert!(
        text(&out).contains("the server is reached over TCP: give tcp://HOST:PORT"),
        "{}",
        text(&out)
    );
}

/// A port on this machine that nobody listens on (bound, then let go).
fn free_port() -> u16 {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.local_addr().unwrap().port()
}

#[test]
fn a_class_of_servers_gets_its_scores_from_a_roster() {
    let dir = crate::support::folder("check-server", "class3");
    let (a1, b1) = pair_paths("check-class-anna");
    let (a2, b2) = pair_paths("check-class-ben");
    let (_, b3) = pair_paths("check-class-carl");
    let _vsp1 = Proc::start(&["vsp", s(&a1), s(&b1)]);
    let _vsp2 = Proc::start(&["vsp", s(&a2), s(&b2)]);
    let anna = student_server("class-anna", &a1, &[]);
    let ben = student_server("class-ben", &a2, &["write-wrong-block"]);
    // Carl's supervisor is not running: his bus is a pseudo-terminal of
    // its own (the check opens it) and nobody listens on his port.
    let (a3, _) = pair_paths("check-class-carl");
    let _vsp3 = Proc::start(&["vsp", s(&a3), s(&b3)]);
    let nobody = format!("tcp://127.0.0.1:{}", free_port());
    let roster = dir.join("class.csv");
    std::fs::write(
        &roster,
        format!(
            "student,link,bus\nAnna Berg,{},{}\nBen Okafor,{},{}\nChloé Martin,{nobody},{}\n",
            anna.link,
            s(&b1),
            ben.link,
            s(&b2),
            s(&b3)
        ),
    )
    .unwrap();
    // Run in the class's folder: the reports go to the default one.
    let out_dir = dir.join("check-meb-server-reports");
    let out = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args([
            "check",
            "server",
            "--roster",
            s(&roster),
            "--timeout-ms",
            "1000",
        ])
        .current_dir(&dir)
        .output()
        .unwrap();
    let shown = text(&out);
    assert_eq!(out.status.code(), Some(1), "{shown}");
    super::held_to_the_book("check::server's a_class_of_servers", &shown);
    assert!(
        shown.starts_with("MEB server suite: 3 students, 3 at once\n"),
        "{shown}"
    );
    let scores = std::fs::read_to_string(out_dir.join("scores.csv")).unwrap();
    let rows: Vec<&str> = scores.lines().collect();
    assert_eq!(
        rows[..3],
        [
            "student,score,points,checks_passed,checks,first_failure,not_applicable",
            "Anna Berg,20,20,15,15,,0",
            "Ben Okafor,18,20,14,15,a client's VEL write (SA 00) goes on the bus as SA 00 and is acknowledged,0",
        ],
        "{shown}"
    );
    assert!(
        rows[3].starts_with(&format!(
            "Chloé Martin,0,20,0,15,cannot connect to {nobody}: connection refused"
        )),
        "{scores}"
    );
    assert_eq!(rows.len(), 4, "{scores}");
    for stem in ["Anna_Berg", "Ben_Okafor", "Chloé_Martin"] {
        for ext in ["txt", "json", "html", "junit.xml", "mcap"] {
            assert!(
                out_dir.join(format!("{stem}.{ext}")).is_file(),
                "{stem}.{ext}"
            );
        }
    }
    let ben_txt = std::fs::read_to_string(out_dir.join("Ben_Okafor.txt")).unwrap();
    assert!(
        ben_txt.contains(" s  received  bus       @01VA000104D2"),
        "{ben_txt}"
    );

    // A roster whose student has no bus, and no --bus for all: refused
    // with the line, before anything is opened.
    std::fs::write(&roster, format!("student,link\nAnna Berg,{}\n", anna.link)).unwrap();
    let out = twin(&["check", "server", "--roster", s(&roster)]);
    assert!(
        text(&out).contains("class.csv, line 2: `Anna Berg` has no bus: give each student's in a `bus` column, or one for all with --bus"),
        "{}",
        text(&out)
    );
}

#[test]
fn a_server_check_records_both_links_with_every_frame_its_report_cites() {
    let dir = crate::support::folder("check-server", "recorded");
    let (mcap, json) = (dir.join("run.mcap"), dir.join("run.json"));
    let (a, b) = pair_paths("check-recorded");
    let _vsp = Proc::start(&["vsp", s(&a), s(&b)]);
    let server = student_server("recorded", &a, &["write-wrong-block"]);
    let out = check_server(
        &server.link,
        &b,
        &["--record", s(&mcap), "--json", s(&json)],
    );
    let shown = text(&out);
    assert_eq!(out.status.code(), Some(1), "{shown}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let recorded = super::recorded::read(&mcap);
    assert_eq!(recorded["run"]["role"], "server");
    assert_eq!(recorded["check"]["score"], "18");
    let frames = recorded["frames"].as_array().unwrap();
    let on = |topic: &str| frames.iter().filter(|f| f["topic"] == topic).count();
    let (server_frames, bus_frames) = (on("/link/server/frames"), on("/link/bus/frames"));
    assert_eq!(server_frames + bus_frames, frames.len(), "two links only");
    // Every poll of the supervisor is there, where the report cites a few.
    let cited_on_bus = report["checks"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|c| c["frames"].as_array().unwrap())
        .filter(|f| f["text"].as_str().unwrap().starts_with("bus "))
        .count();
    assert!(
        bus_frames > cited_on_bus + 20,
        "{bus_frames} on the bus, {cited_on_bus} cited"
    );
    // The checks' frames add up to every frame recorded, and every frame
    // the report cites is recorded, on its link, from its sender, at its time.
    let cited = super::recorded::cited_frames_recorded(&report, &recorded, |side, sent| {
        let (topic, from) = match (side, sent) {
            ("bus", true) => ("/link/bus/frames", "slave 01"),
            ("bus", false) => ("/link/bus/frames", "supervisor"),
            (client, true) => ("/link/server/frames", client),
            (_, false) => ("/link/server/frames", "supervisor"),
        };
        (topic, from.to_string())
    });
    assert!(cited > 40, "{cited}");
    // The disputed write as the bus carried it, decoded as MEB.
    let write = frames
        .iter()
        .find(|r| r["topic"] == "/link/bus/frames" && r["text"] == "@01VA000104D225*\n")
        .unwrap_or_else(|| panic!("the write on the bus: {shown}"));
    assert_eq!(
        (&write["protocol"], &write["cmd"]),
        (&"meb".into(), &"VA".into())
    );

    // The twin's own readers: the bus as a logic analyzer sees it, the
    // frames as CSV, and the view.
    let vcd = dir.join("bus.vcd");
    let out = twin(&["scope", s(&mcap), "--link", "bus", "--vcd", s(&vcd)]);
    assert!(out.status.success(), "{}", text(&out));
    let wave = std::fs::read_to_string(&vcd).unwrap();
    assert!(
        wave.contains("supervisor"),
        "{}",
        &wave[..wave.len().min(2000)]
    );
    let csv = dir.join("csv");
    let out = twin(&["export", s(&mcap), "--csv", s(&csv)]);
    assert!(out.status.success(), "{}", text(&out));
    for file in ["link_bus_frames.csv", "link_server_frames.csv"] {
        assert!(csv.join(file).is_file(), "{file}");
    }
    let rrd = dir.join("run.rrd");
    let out = twin(&["view", s(&mcap), "--save", s(&rrd)]);
    assert!(out.status.success(), "{}", text(&out));
}
