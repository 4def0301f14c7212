//! `twin check client`: a session with a client following the checklist,
//! driven without a person: the twin's own `twin client` (every item seen,
//! the display left "not judged"), and a student's client written outside
//! the twin (a Python program), correct and with VEL written to the wrong
//! block, found by name; and a class's sessions from a roster.

use crate::supervise::client;
use crate::supervise::s;
use crate::support::{Proc, scratch, text};
use std::path::Path;
use std::process::{Command, Stdio};

use super::failed;

/// `twin check client` listening on a free port, stdin held open (its end
/// would end the session), not recorded unless `more` says where, with
/// `more` options.
fn session(more: &[&str]) -> (Proc, String) {
    let mut args = vec!["check", "client", "--listen", "tcp://127.0.0.1:0"];
    args.extend_from_slice(more);
    if !more.iter().any(|a| a.starts_with("--record")) {
        args.push("--no-record");
    }
    let proc = Proc::spawn(&args, Stdio::piped());
    let addr = proc.tcp_of("meb");
    (proc, addr)
}

/// The session's lines, the port and the run's time taken out.
fn without_port(shown: &str) -> Vec<String> {
    shown
        .lines()
        .map(|line| match line.split_once("tcp://127.0.0.1:") {
            Some((head, rest)) => {
                let tail = rest.trim_start_matches(|c: char| c.is_ascii_digit());
                format!("{head}tcp://…{tail}")
            }
            None => match line.split_once(" in ") {
                Some((head, _)) if line.starts_with("score:") => head.to_string(),
                _ => line.to_string(),
            },
        })
        .collect()
}

/// Waits for the session to end by itself (every item seen): whether it
/// exited 0, and what it printed.
fn ended(mut proc: Proc) -> (bool, String) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    loop {
        if let Some(status) = proc.child.try_wait().expect("wait") {
            // Let the reader thread take the last lines.
            std::thread::sleep(std::time::Duration::from_millis(200));
            return (status.success(), proc.output());
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the session did not end: {}",
            proc.output()
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

fn student_client(addr: &str, bugs: &[&str]) -> std::process::Output {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/meb_student_client.py");
    let mut command = Command::new("python3");
    command.arg(script).arg(addr);
    for bug in bugs {
        command.args(["--bug", bug]);
    }
    command.output().expect("python3 runs")
}

#[test]
fn the_twins_own_client_follows_the_checklist_and_passes() {
    let json = scratch("check-client", "own.json");
    let junit = scratch("check-client", "own.junit.xml");
    let (proc, addr) = session(&[
        "--json",
        json.to_str().unwrap(),
        "--junit",
        junit.to_str().unwrap(),
        "--duration",
        "120",
    ]);
    let url = format!("tcp://{addr}");
    assert!(client(&[&url, "read", "EA", "0", "6"]).status.success());
    assert!(client(&[&url, "write", "SA", "0", "2048"]).status.success());
    assert!(
        client(&[&url, "write", "SD", "0", "0x001E"])
            .status
            .success()
    );
    // Until the twin plays each fault: an error reply, then a hang-up.
    let mut saw = Vec::new();
    for _ in 0..200 {
        let out = client(&[&url, "read", "EA", "0", "6"]);
        if !out.status.success() {
            saw.push(text(&out));
            if saw.len() == 2 {
                break;
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    assert_eq!(saw.len(), 2, "{saw:?}");
    assert!(saw[0].contains("04"), "the error 04: {}", saw[0]);
    assert!(client(&[&url, "read", "EA", "0", "6"]).status.success());
    let (success, printed) = ended(proc);
    assert!(success, "{printed}");
    assert!(printed.contains("  2. seen"), "{printed}");
    assert_eq!(failed(&json), Vec::<String>::new());
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let results: Vec<&str> = run["checks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["result"].as_str().unwrap())
        .collect();
    assert_eq!(
        results,
        ["pass", "pass", "pass", "pass", "pass", "not judged", "pass"]
    );
    let read = super::junit_read(&junit);
    assert_eq!(
        (read["tests"].as_u64(), read["failures"].as_u64()),
        (Some(7), Some(0))
    );
}

#[test]
fn a_student_client_passes_and_a_vel_written_to_the_wrong_block_is_found() {
    for (name, bugs, expected) in [
        ("correct", &[][..], &[][..]),
        (
            "writes-wrong-block",
            &["writes-wrong-block"][..],
            &["set VEL to half of full scale (SA 00, about 2048)"][..],
        ),
    ] {
        let json = scratch("check-client", &format!("{name}.json"));
        // The buggy one recorded (the correct one's lines are the book's).
        let mcap = scratch("check-client", &format!("{name}.mcap"));
        let record = format!("--record={}", mcap.display());
        let mut more = vec!["--json", json.to_str().unwrap(), "--duration", "120"];
        if name == "writes-wrong-block" {
            more.push(&record);
        }
        let (proc, addr) = session(&more);
        let out = student_client(&addr, bugs);
        assert!(out.status.success(), "{name}: {}", text(&out));
        let shown = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(shown.contains("error 0004 from the server"), "{shown}");
        assert!(shown.contains("the server hung up"), "{shown}");
        let (success, printed) = ended(proc);
        assert_eq!(failed(&json), expected, "{name}: {printed}");
        assert_eq!(success, expected.is_empty(), "{printed}");
        if name == "correct" {
            // The book's session is this one.
            let page = std::fs::read_to_string(
                Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/check.md"),
            )
            .unwrap();
            let start = page
                .find("```text\ntwin check client: slave")
                .expect("the session on the page")
                + 8;
            let book = &page[start..start + page[start..].find("\n```").unwrap()];
            assert_eq!(without_port(&printed), without_port(book));
        }
        if name == "writes-wrong-block" {
            assert!(
                printed.contains("VEL went to VA 00, not SA 00 (`@01VA00010800"),
                "{printed}"
            );
            every_cited_frame_is_recorded(&json, &mcap);
        }
    }
}

#[test]
fn a_class_of_clients_gets_its_scores_from_a_roster() {
    let dir = crate::support::folder("check-client", "class3");
    let ports: Vec<u16> = (0..3)
        .map(|_| {
            let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            listener.local_addr().unwrap().port()
        })
        .collect();
    let roster = dir.join("class.toml");
    let mut toml = String::new();
    for (name, port) in ["Anna Berg", "Ben Okafor", "Chloé Martin"]
        .iter()
        .zip(&ports)
    {
        toml += &format!("[[student]]\nname = \"{name}\"\nlink = \"tcp://127.0.0.1:{port}\"\n\n");
    }
    std::fs::write(&roster, toml).unwrap();
    let out_dir = dir.join("reports");
    // Stdin held open: its end (Enter, Ctrl-D) ends every session.
    let proc = Proc::spawn(
        &[
            "check",
            "client",
            "--roster",
            s(&roster),
            "--out",
            s(&out_dir),
            "--duration",
            "300",
        ],
        Stdio::piped(),
    );
    assert!(
        !proc.output().contains("cannot listen"),
        "{}",
        proc.output()
    );
    // Anna's client is correct, Ben's writes VEL to the wrong block, and
    // Carl's never connects.
    let anna = student_client(&format!("127.0.0.1:{}", ports[0]), &[]);
    assert!(anna.status.success(), "{}", text(&anna));
    let ben = student_client(&format!("127.0.0.1:{}", ports[1]), &["writes-wrong-block"]);
    assert!(ben.status.success(), "{}", text(&ben));
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while !(proc.output().contains("  Anna Berg     9 of 9")
        && proc.output().contains("  Ben Okafor    7 of 9"))
    {
        assert!(
            std::time::Instant::now() < deadline,
            "Anna's and Ben's sessions did not end: {}",
            proc.output()
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    // The teacher presses Enter: Carl's session ends too.
    let mut proc = proc;
    drop(proc.child.stdin.take());
    let mut stderr = String::new();
    if let Some(mut e) = proc.child.stderr.take() {
        // Read to its end: the program has exited.
        let _ = std::io::Read::read_to_string(&mut e, &mut stderr);
    }
    let (success, printed) = ended(proc);
    let printed = format!("{printed}\n{stderr}");
    assert!(!success, "{printed}");
    let scores = std::fs::read_to_string(out_dir.join("scores.csv")).unwrap();
    assert_eq!(
        scores.lines().collect::<Vec<_>>(),
        [
            "student,score,points,checks_passed,checks,first_failure,not_applicable",
            "Anna Berg,9,9,6,7,,0",
            "Ben Okafor,7,9,5,7,\"set VEL to half of full scale (SA 00, about 2048)\",0",
            &format!(
                "Chloé Martin,0,9,0,7,no client connected to tcp://127.0.0.1:{} during the session,0",
                ports[2]
            ),
        ],
        "{printed}"
    );
    // The book's class is this one, its folder aside.
    let printed_here = printed.replace(s(&out_dir), "check-meb-client-reports");
    super::held_to_the_book("check::client's a_class_of_clients", &printed_here);
    let ben = std::fs::read_to_string(out_dir.join("Ben_Okafor.txt")).unwrap();
    assert!(
        ben.contains("VEL went to VA 00, not SA 00 (`@01VA00010800"),
        "{ben}"
    );
}

/// The session's recording holds every frame of its connections, each
/// check's in its window, and every frame the report cites: on
/// `/link/client/frames`, from the client's connection or the twin, at
/// its time.
fn every_cited_frame_is_recorded(json: &Path, mcap: &Path) {
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    let recorded = super::recorded::read(mcap);
    assert_eq!(recorded["run"]["role"], "client");
    let frames = recorded["frames"].as_array().unwrap();
    assert!(
        frames.iter().all(|f| f["topic"] == "/link/client/frames"),
        "{recorded}"
    );
    let cited = super::recorded::cited_frames_recorded(&report, &recorded, |client, sent| {
        let from = if sent { "twin" } else { client };
        ("/link/client/frames", from.to_string())
    });
    assert!(cited >= 8, "{cited}");
    // The write to the wrong block, as the client sent it, decoded.
    let write = frames
        .iter()
        .find(|r| r["text"].as_str().unwrap().starts_with("@01VA00010800"))
        .expect("the write");
    assert_eq!(write["cmd"], "VA");
    assert_eq!(write["from"], "client 1");
}

/// `--listen` is read as every link is: a misspelt `tcp://` gets the links'
/// own suggestion, a serial device is refused as not TCP, and a roster's
/// link says which line and student it is.
#[test]
fn a_misspelt_listen_address_gets_the_links_own_message() {
    let refused = |args: &[&str]| {
        let out = crate::support::twin(&[&["check", "client"], args].concat());
        assert!(!out.status.success(), "{}", text(&out));
        text(&out)
    };
    let shown = refused(&["--listen", "tcp:/127.0.0.1:0"]);
    assert!(
        shown.contains("--listen: link `tcp:/127.0.0.1:0` looks like a misspelt TCP address")
            && shown.contains("write `tcp://127.0.0.1:0`"),
        "{shown}"
    );
    let shown = refused(&["--listen", "/dev/null"]);
    assert!(
        shown.contains("`/dev/null` is not tcp://HOST:PORT"),
        "{shown}"
    );
    // A roster's link is read when the roster is: the links' own message,
    // with its line; one that is a serial device is refused as not TCP.
    let roster = scratch("check-client", "misspelt.toml");
    for (link, says) in [
        (
            "tcp:127.0.0.1:0",
            "`Ana`'s link: link `tcp:127.0.0.1:0` looks like a misspelt TCP address",
        ),
        (
            "/dev/null",
            "`Ana`'s client: `/dev/null` is not tcp://HOST:PORT",
        ),
    ] {
        std::fs::write(
            &roster,
            format!("[[student]]\nname = \"Ana\"\nlink = \"{link}\"\n"),
        )
        .unwrap();
        let shown = refused(&["--roster", roster.to_str().unwrap(), "--no-record"]);
        assert!(
            shown.contains(&format!("misspelt.toml, line 1: {says}")),
            "{shown}"
        );
    }
}
