//! `twin check slave --roster`: a class checked at once. A roster of three
//! (a correct slave, one with a planted bug, a port nobody listens on)
//! gives the right scores and a report each; a class of ten correct slaves
//! finishes all at once; a roster with a mistake is refused with its line.

use super::{junit_read, student};
use crate::support::{cores_to_myself, folder, text, twin};
use std::time::Instant;

/// A port on this machine that nobody listens on (bound, then let go).
fn free_port() -> u16 {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.local_addr().unwrap().port()
}

#[test]
fn a_class_gets_its_scores_a_report_each_and_the_unreachable_an_error() {
    let dir = folder("check", "class3");
    let (anna, ben) = (student("anna", &[]), student("ben", &["answers-broadcast"]));
    let nobody = format!("tcp://127.0.0.1:{}", free_port());
    let roster = dir.join("class.csv");
    std::fs::write(
        &roster,
        format!(
            "student,link\nAnna Müller,{}\nBen,{}\nCarl,{nobody}\n",
            anna.link, ben.link
        ),
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
    ]);
    let shown = text(&out);
    assert_eq!(out.status.code(), Some(1), "{shown}");
    let scores = std::fs::read_to_string(out_dir.join("scores.csv")).unwrap();
    let refused =
        format!("cannot connect to {nobody}: connection refused (is the program listening there?)");
    assert_eq!(
        scores.lines().collect::<Vec<_>>(),
        [
            "student,score,points,checks_passed,checks,first_failure,not_applicable",
            "Anna Müller,32,32,25,25,,6",
            "Ben,30,32,24,25,a broadcast write (id 00) is not answered,6",
            &format!("Carl,0,32,0,25,{refused},6"),
        ],
        "{shown}"
    );
    // A line per student as each finishes, then the class.
    assert!(
        shown.contains("  Anna Müller  32 of 32 points, 25 of 25 checks\n"),
        "{shown}"
    );
    assert!(
        shown.contains(&format!("  Carl         could not be checked: {refused}\n")),
        "{shown}"
    );
    assert!(
        shown.contains("1 passed every check, 1 failed a check, 1 could not be checked"),
        "{shown}"
    );
    assert!(
        shown.contains("error: 2 of 3 students did not pass every check"),
        "{shown}"
    );
    for stem in ["Anna_Müller", "Ben", "Carl"] {
        for ext in ["txt", "json", "html", "junit.xml", "mcap"] {
            assert!(
                out_dir.join(format!("{stem}.{ext}")).is_file(),
                "{stem}.{ext}"
            );
        }
    }
    let ben_txt = std::fs::read_to_string(out_dir.join("Ben.txt")).unwrap();
    assert!(
        ben_txt.starts_with("Ben\nMEB slave suite, slave 01 on tcp://"),
        "{ben_txt}"
    );
    assert!(
        ben_txt.contains("  FAIL  a broadcast write (id 00) is not answered"),
        "{ben_txt}"
    );
    let carl_txt = std::fs::read_to_string(out_dir.join("Carl.txt")).unwrap();
    assert!(
        carl_txt.contains(&format!("could not be checked: {refused}")),
        "{carl_txt}"
    );
    assert!(
        carl_txt.contains("score: 0 of 32 points (0 of 25 checks passed)"),
        "{carl_txt}"
    );
    // To a CI system the unreachable program is an error each check (none
    // ran), a wrong reply a failure.
    let carl = junit_read(&out_dir.join("Carl.junit.xml"));
    assert_eq!(
        (carl["errors"].as_u64(), carl["failures"].as_u64()),
        (Some(25), Some(0))
    );
    assert_eq!(carl["cases"][0]["message"], refused.as_str());
    let ben = junit_read(&out_dir.join("Ben.junit.xml"));
    assert_eq!(
        (ben["errors"].as_u64(), ben["failures"].as_u64()),
        (Some(0), Some(1))
    );
    let carl_page = std::fs::read_to_string(out_dir.join("Carl.html")).unwrap();
    assert!(
        carl_page.contains(&format!("Could not be checked: {refused}")),
        "{carl_page}"
    );
    assert!(
        carl_page.contains("<h1>MEB slave: Carl</h1>"),
        "{carl_page}"
    );
}

#[test]
fn a_class_of_ten_is_checked_at_once() {
    let _cores = cores_to_myself();
    let dir = folder("check", "class10");
    let slaves: Vec<_> = (0..10).map(|i| student(&format!("ten{i}"), &[])).collect();
    let roster = dir.join("class.toml");
    let mut toml = String::new();
    for (i, slave) in slaves.iter().enumerate() {
        toml += &format!(
            "[[student]]\nname = \"student {i:02}\"\nlink = \"{}\"\n\n",
            slave.link
        );
    }
    std::fs::write(&roster, toml).unwrap();
    let started = Instant::now();
    let out = twin(&[
        "check",
        "slave",
        "--timeout-ms",
        "1000",
        "--roster",
        roster.to_str().unwrap(),
        "--out",
        dir.to_str().unwrap(),
    ]);
    let took = started.elapsed();
    eprintln!("a class of 10 checked in {took:.1?}");
    assert!(out.status.success(), "{}", text(&out));
    let scores = std::fs::read_to_string(dir.join("scores.csv")).unwrap();
    let rows: Vec<_> = scores.lines().skip(1).collect();
    assert_eq!(rows.len(), 10, "{scores}");
    for (i, row) in rows.iter().enumerate() {
        assert_eq!(*row, format!("student {i:02},32,32,25,25,,6"), "{scores}");
    }
    // How long it took is a figure, not a test (a loaded machine is slow):
    // eight at once, the ten take about two suites' time, not ten.
}

#[test]
fn a_roster_with_a_mistake_is_refused_with_its_file_and_line() {
    let dir = folder("check", "class-typo");
    let roster = dir.join("class.csv");
    std::fs::write(
        &roster,
        "student,link\nAnna,tcp://127.0.0.1:5701\nBen,tcp://127.0.0.1:5702\nAnna,tcp://127.0.0.1:5703\n",
    )
    .unwrap();
    let out = twin(&["check", "slave", "--roster", roster.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out).contains("class.csv, line 4: `Anna` is on line 2 already"),
        "{}",
        text(&out)
    );
    // An id is held to the suite's protocol: 120 is no MEB device number,
    // 248 no Modbus unit id.
    for (suite, id, why) in [
        (
            "meb-slave",
            "120",
            "an MEB slave's device number is 1 to 99",
        ),
        ("modbus-tcp-slave", "248", "a Modbus unit id is 1 to 247"),
    ] {
        std::fs::write(
            &roster,
            format!("student,link,id\nAnna,tcp://127.0.0.1:5701,\nBen,tcp://127.0.0.1:5702,{id}\n"),
        )
        .unwrap();
        let out = twin(&[
            "check",
            "slave",
            "--suite",
            suite,
            "--roster",
            roster.to_str().unwrap(),
        ]);
        assert_eq!(out.status.code(), Some(1));
        assert!(
            text(&out).contains(&format!("class.csv, line 3: id `{id}`: {why}")),
            "{}",
            text(&out)
        );
    }
}
