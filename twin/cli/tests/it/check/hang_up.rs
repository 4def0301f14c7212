//! A student's slave that hangs up in the middle of a run (it closes the
//! connection, as a program that crashes does): the checks run before keep
//! their verdicts and count in the score, the one running and those after
//! it fail saying so, and the report says it once at the top; a class too.

use super::{check_slave, junit_read, student};
use crate::support::{folder, scratch, text, twin};

/// The first five checks of the MEB slave suite are one request and its
/// reply each, a point each; the sixth is the write of the outputs.
const SIXTH: &str =
    "acknowledges a write of the outputs (SD 00, everything off) by echoing its header";

#[test]
fn a_slave_that_hangs_up_keeps_the_checks_it_passed() {
    let (json, junit) = (
        scratch("check", "hang-up.json"),
        scratch("check", "hang-up.junit.xml"),
    );
    let slave = student("hang-up", &["hangs-up-after 5"]);
    let out = check_slave(
        &slave.link,
        &[
            "--json",
            json.to_str().unwrap(),
            "--junit",
            junit.to_str().unwrap(),
        ],
    );
    let shown = text(&out);
    assert_eq!(out.status.code(), Some(1), "{shown}");
    let lines: Vec<&str> = shown.lines().collect();
    assert!(
        lines[1].starts_with("  the program hung up at ")
            && lines[1].ends_with(&format!(
                " s (it closed the connection), during `{SIXTH}`: the 5 checks before it keep their verdicts; it and the 19 after it fail"
            )),
        "{shown}"
    );
    assert!(
        shown.contains("score: 5 of 32 points (5 of 25 checks passed)"),
        "{shown}"
    );
    assert!(!shown.contains("could not be checked"), "{shown}");
    // The book shows these two lines as the program prints them.
    let page = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/check.md"),
    )
    .unwrap();
    let section = &page[page.find("## A program that hangs up").unwrap()..];
    let start = section.find("```text\n").unwrap() + 8;
    let book: Vec<String> = section[start..start + section[start..].find("\n```").unwrap()]
        .lines()
        .map(without_port_and_time)
        .collect();
    let printed: Vec<String> = lines[..2]
        .iter()
        .map(|l| without_port_and_time(l))
        .collect();
    assert_eq!(book, printed);

    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(run["score"], 5);
    assert_eq!(run["hung_up"]["check"], SIXTH);
    assert_eq!(run["hung_up"]["how"], "it closed the connection");
    let checks = run["checks"].as_array().unwrap();
    assert!(checks[..5].iter().all(|c| c["result"] == "pass"), "{run}");
    // The check that was running keeps what it sent, and says when the
    // program hung up.
    let sixth = &checks[5];
    assert_eq!(sixth["name"], SIXTH);
    assert!(
        sixth["why"]
            .as_str()
            .unwrap()
            .starts_with("the program hung up at "),
        "{sixth}"
    );
    assert_eq!(sixth["frames"][0]["text"], "@01SD0001001F20*\\n");
    assert_eq!(sixth["frames"].as_array().unwrap().len(), 1, "{sixth}");
    // Every later check but the bench checks, which stay not applicable.
    for later in checks[6..]
        .iter()
        .filter(|c| c["result"] != "not applicable")
    {
        assert!(
            later["why"]
                .as_str()
                .unwrap()
                .starts_with("not run: the program hung up at "),
            "{later}"
        );
        assert_eq!(later["frames"].as_array().unwrap().len(), 0, "{later}");
    }

    // To a CI system: five pass, twenty fail.
    let read = junit_read(&junit);
    assert_eq!(
        (read["failures"].as_u64(), read["errors"].as_u64()),
        (Some(20), Some(0))
    );
    assert!(read["cases"][4]["message"].is_null());
}

#[test]
fn a_class_keeps_what_a_student_passed_before_the_hang_up() {
    let dir = folder("check", "class-hang-up");
    let (anna, ben) = (
        student("anna-h", &["hangs-up-after 5"]),
        student("ben-h", &[]),
    );
    let roster = dir.join("class.csv");
    std::fs::write(
        &roster,
        format!("student,link\nAnna,{}\nBen,{}\n", anna.link, ben.link),
    )
    .unwrap();
    let out_dir = dir.join("reports");
    let out = twin(&[
        "check",
        "slave",
        "--timeout-ms",
        "1000",
        "--roster",
        roster.to_str().unwrap(),
        "--out",
        out_dir.to_str().unwrap(),
        "--no-record",
    ]);
    let shown = text(&out);
    assert_eq!(out.status.code(), Some(1), "{shown}");
    let scores = std::fs::read_to_string(out_dir.join("scores.csv")).unwrap();
    assert_eq!(
        scores.lines().collect::<Vec<_>>(),
        [
            "student,score,points,checks_passed,checks,first_failure,not_applicable",
            // Quoted: the check's name holds a comma.
            &format!("Anna,5,32,5,25,\"{SIXTH}\",6"),
            "Ben,32,32,25,25,,6",
        ],
        "{shown}"
    );
    assert!(
        shown.contains("  Anna  5 of 32 points, 5 of 25 checks; hung up at "),
        "{shown}"
    );
    assert!(
        shown.contains("1 passed every check, 1 failed a check, 0 could not be checked"),
        "{shown}"
    );
    let anna_txt = std::fs::read_to_string(out_dir.join("Anna.txt")).unwrap();
    assert!(anna_txt.contains("  the program hung up at "), "{anna_txt}");
    let page = std::fs::read_to_string(out_dir.join("Anna.html")).unwrap();
    assert!(
        page.contains("<p class=\"fail\">The program hung up at "),
        "{page}"
    );
}

/// A report's line with what differs from run to run taken out.
fn without_port_and_time(line: &str) -> String {
    if let Some((head, _)) = line.split_once(" on tcp://") {
        return format!("{head} on tcp://…");
    }
    match line.split_once("hung up at ") {
        Some((head, rest)) => {
            let after = rest.split_once(" s ").map_or("", |(_, a)| a);
            format!("{head}hung up at … s {after}")
        }
        None => line.to_string(),
    }
}

/// The same student on a pseudo-terminal it opened itself, which goes away
/// when it hangs up, as a board's serial port does when it is unplugged.
#[test]
fn a_pseudo_terminal_that_goes_away_keeps_the_checks_passed_too() {
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/meb_student_slave.py");
    let path_file = scratch("check", "hang-up-pty.path");
    let _ = std::fs::remove_file(&path_file);
    let mut child = std::process::Command::new("python3")
        .arg(script)
        .arg(&path_file)
        .args(["--pty", "--bug", "hangs-up-after", "5"])
        .spawn()
        .expect("python3 runs");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    let path = loop {
        if let Ok(path) = std::fs::read_to_string(&path_file) {
            break path;
        }
        assert!(std::time::Instant::now() < deadline, "no pseudo-terminal");
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    let out = check_slave(path.trim(), &[]);
    let _ = child.kill();
    let _ = child.wait();
    let shown = text(&out);
    assert!(
        shown.contains(&format!(
            " s (the serial port or pseudo-terminal went away), during `{SIXTH}`: the 5 checks before it keep their verdicts"
        )),
        "{shown}"
    );
    assert!(
        shown.contains("score: 5 of 32 points (5 of 25 checks passed)"),
        "{shown}"
    );
}
