//! `twin check slave --bench`: the twin's own controller, on a `twin serve`
//! session with its panel, passes every bench check over MEB (TCP), Modbus
//! RTU (a pseudo-terminal) and Modbus TCP; a class whose roster gives one
//! student a bench runs that student's bench checks there and leaves the
//! other's not applicable; a controller given a student's wrong
//! I/O map (FR on a bit of its own, V1 and V2 swapped) fails exactly the
//! check of that meaning; and without a bench the bench checks are "not
//! applicable" in every report and in a class's scores.csv, not failed.

use super::{check_slave, failed};
use crate::peers::PtyPair;
use crate::support::{Proc, folder, scratch, text, twin};

/// `twin serve` with `links`, its panel on a free loopback port.
fn serve(links: &[&str]) -> Proc {
    let mut args = vec![
        "serve",
        "--no-record",
        "--quiet",
        "--status-every",
        "0",
        "--duration",
        "300",
        "--web",
        "127.0.0.1:0",
    ];
    args.extend_from_slice(links);
    Proc::start(&args)
}

/// The panel's URL, as `twin serve` printed it.
fn panel_of(serve: &Proc) -> String {
    let out = serve.output();
    out.lines()
        .find_map(|l| l.strip_prefix("panel: "))
        .and_then(|l| l.split_whitespace().next())
        .unwrap_or_else(|| panic!("no panel line printed: {out}"))
        .to_string()
}

/// The JSON report's checks whose `result` is `wanted`, by name.
fn with_result(json: &std::path::Path, wanted: &str) -> Vec<String> {
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    run["checks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["result"] == wanted)
        .map(|c| c["name"].as_str().unwrap().to_string())
        .collect()
}

const BENCH_CHECKS: usize = 6;

#[test]
fn the_twins_own_controller_passes_every_bench_check_over_meb_and_modbus_rtu_and_tcp() {
    let dir = folder("check-bench", "own");
    let pair = PtyPair::new(&dir);
    let serve = serve(&[
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus-rtu",
        pair.a.to_str().unwrap(),
        "--modbus",
        "tcp://127.0.0.1:0",
    ]);
    let panel = panel_of(&serve);
    let meb = format!("tcp://{}", serve.tcp_of("meb"));
    let modbus_tcp = format!("tcp://{}", serve.tcp_of("modbus-tcp"));
    for (suite, link) in [
        ("meb-slave", meb.as_str()),
        ("modbus-rtu-slave", pair.b.to_str().unwrap()),
        ("modbus-tcp-slave", modbus_tcp.as_str()),
    ] {
        let json = scratch("check-bench", &format!("{suite}.json"));
        let out = check_slave(
            link,
            &[
                "--suite",
                suite,
                "--bench",
                &panel,
                "--json",
                json.to_str().unwrap(),
            ],
        );
        let shown = text(&out);
        assert!(out.status.success(), "{suite}: {shown}");
        assert_eq!(failed(&json), Vec::<String>::new(), "{suite}: {shown}");
        assert!(with_result(&json, "not applicable").is_empty(), "{shown}");
        let passed = with_result(&json, "pass");
        let bench: Vec<&String> = passed.iter().filter(|n| is_bench(n)).collect();
        assert_eq!(bench.len(), BENCH_CHECKS, "{suite}: {shown}");
        assert!(
            shown.contains(&format!(", bench {}", panel.trim_end_matches('/'))),
            "{shown}"
        );
        assert!(!shown.contains("not applicable"), "{shown}");
    }
    serve.terminate();
}

/// A bench check's name (they say what a register does on the bench).
fn is_bench(name: &str) -> bool {
    [
        "turns the motor",
        "EN off stops",
        "BRK brakes",
        "read the wheel's speed",
        "read the plant",
    ]
    .iter()
    .any(|n| name.contains(n))
}

#[test]
fn a_slave_with_a_meaning_bug_fails_exactly_that_bench_check() {
    let dir = folder("check-bench", "maps");
    // FR on bit 5 of SD 00: the FR a master writes on bit 4 drives nothing.
    let fr_moved = dir.join("fr-moved.toml");
    std::fs::write(
        &fr_moved,
        "[SD]\nEN = \"0.0\"\nBRK = \"0.1\"\nPRO = \"0.2\"\nDES = \"0.3\"\nFR = \"0.5\"\nCHG = \"1.0\"\n",
    )
    .unwrap();
    // V1 and V2 swapped in EA.
    let swapped = dir.join("v-swapped.toml");
    std::fs::write(
        &swapped,
        "[EA]\nV2 = 2\nI = 1\nV1 = 0\nRPM_M = 3\nRPM_L = 4\nLDR = 5\n",
    )
    .unwrap();
    let cases = [
        (
            &fr_moved,
            "FR turns the motor counter-clockwise (SD 00 bit 4)",
            "the plant turns the motor clockwise (FR as the plant sees it) where FR was written counter-clockwise",
        ),
        (
            &swapped,
            "the analog inputs read the plant within the ADC's resolution, the wheel braked at rest (EA 00-05)",
            "; the bus at ",
        ),
    ];
    for (map, check, why) in cases {
        let serve = serve(&["--meb", "tcp://127.0.0.1:0", "--map", map.to_str().unwrap()]);
        let panel = panel_of(&serve);
        let link = format!("tcp://{}", serve.tcp_of("meb"));
        let json = scratch("check-bench", "bug.json");
        let out = check_slave(
            &link,
            &["--bench", &panel, "--json", json.to_str().unwrap()],
        );
        let shown = text(&out);
        assert!(!out.status.success(), "{shown}");
        assert_eq!(failed(&json), vec![check.to_string()], "{shown}");
        assert!(shown.contains(why), "{shown}");
        assert!(shown.contains("error: 1 of 31 checks failed"), "{shown}");
        assert!(!shown.contains("not applicable"), "{shown}");
        if map == &fr_moved {
            the_books_lines_are_printed(&shown);
        }
        serve.terminate();
    }
}

/// Every line of docs/check.md's bench report is printed, in order (its
/// times and ports aside).
fn the_books_lines_are_printed(shown: &str) {
    let page = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/check.md"),
    )
    .unwrap();
    let start = page
        .find("a_slave_with_a_meaning_bug test -->\n```text\n")
        .expect("the bench report on the page");
    let start = start + page[start..].find("```text\n").unwrap() + 8;
    let book = super::comparable(&page[start..start + page[start..].find("\n```").unwrap()]);
    let printed = super::comparable(shown);
    let mut rest = printed.iter();
    for line in &book {
        assert!(
            rest.any(|l| l == line),
            "the page's line {line:?} is not in what the program printed, in order:\n{}",
            printed.join("\n")
        );
    }
}

#[test]
fn without_a_bench_the_bench_checks_are_not_applicable_in_every_report() {
    let serve = serve(&["--meb", "tcp://127.0.0.1:0"]);
    let link = format!("tcp://{}", serve.tcp_of("meb"));
    let json = scratch("check-bench", "no-bench.json");
    let junit = scratch("check-bench", "no-bench.xml");
    let html = scratch("check-bench", "no-bench.html");
    let out = check_slave(
        &link,
        &[
            "--json",
            json.to_str().unwrap(),
            "--junit",
            junit.to_str().unwrap(),
            "--html",
            html.to_str().unwrap(),
        ],
    );
    let shown = text(&out);
    // Not failures: the run passes, on the points of the checks that apply.
    assert!(out.status.success(), "{shown}");
    assert!(
        shown.contains("6 checks not applicable (not scored): they need the bench (--bench URL)\nscore: 32 of 32 points (25 of 25 checks passed)"),
        "{shown}"
    );
    assert_eq!(shown.matches("\n  n/a   ").count(), BENCH_CHECKS, "{shown}");
    assert!(
        shown.contains("        not applicable: a bench check: give --bench URL, the panel of the twin session the slave is wired to"),
        "{shown}"
    );
    let not_applicable = with_result(&json, "not applicable");
    assert_eq!(not_applicable.len(), BENCH_CHECKS, "{not_applicable:?}");
    assert!(
        not_applicable.iter().all(|n| is_bench(n)),
        "{not_applicable:?}"
    );
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(run["points"], 32);
    assert_eq!(run["score"], 32);

    let xml = std::fs::read_to_string(&junit).unwrap();
    assert!(
        xml.contains("tests=\"31\" failures=\"0\" errors=\"0\" skipped=\"6\""),
        "{xml}"
    );
    assert_eq!(
        xml.matches("<skipped message=\"not applicable: a bench check: give --bench URL")
            .count(),
        BENCH_CHECKS,
        "{xml}"
    );
    let page = std::fs::read_to_string(&html).unwrap();
    assert_eq!(
        page.matches("<td class=\"nj\">not applicable</td>").count(),
        BENCH_CHECKS
    );
    assert!(page.contains("Score: 32 of 32 points (25 of 25 checks passed)"));

    // A class: the students' scores leave the bench checks out, and say so.
    let dir = folder("check-bench", "class");
    let roster = dir.join("class.csv");
    std::fs::write(&roster, format!("student,link\nAnna,{link}\n")).unwrap();
    let out_dir = dir.join("out");
    let out = twin(&[
        "check",
        "slave",
        "--roster",
        roster.to_str().unwrap(),
        "--out",
        out_dir.to_str().unwrap(),
        "--timeout-ms",
        "1000",
        "--no-record",
    ]);
    assert!(out.status.success(), "{}", text(&out));
    let scores = std::fs::read_to_string(out_dir.join("scores.csv")).unwrap();
    assert_eq!(
        scores,
        "student,score,points,checks_passed,checks,first_failure,not_applicable\nAnna,32,32,25,25,,6\n"
    );
    serve.terminate();
}

#[test]
fn a_class_runs_each_students_bench_checks_on_their_own_bench() {
    // Anna's slave is the twin's own controller, wired to the bench of its
    // session; Ben's is a student's program with no bench behind it.
    let serve = serve(&["--meb", "tcp://127.0.0.1:0"]);
    let panel = panel_of(&serve);
    let anna = format!("tcp://{}", serve.tcp_of("meb"));
    let ben = super::student("bench-class-ben", &[]);
    let dir = folder("check-bench", "class-benches");
    let roster = dir.join("class.csv");
    std::fs::write(
        &roster,
        format!(
            "student,link,bench\nAnna Berg,{anna},{panel}\nBen Okafor,{},\n",
            ben.link
        ),
    )
    .unwrap();
    let out_dir = dir.join("out");
    let out = twin(&[
        "check",
        "slave",
        "--roster",
        roster.to_str().unwrap(),
        "--out",
        out_dir.to_str().unwrap(),
        "--timeout-ms",
        "1000",
        "--no-record",
    ]);
    let shown = text(&out);
    assert!(out.status.success(), "{shown}");
    let scores = std::fs::read_to_string(out_dir.join("scores.csv")).unwrap();
    let rows: Vec<&str> = scores.lines().collect();
    assert_eq!(rows.len(), 3, "{scores}");
    // Anna: every check, the bench's too; Ben: the bench's not applicable.
    let anna_row: Vec<&str> = rows[1].split(',').collect();
    assert_eq!(anna_row[0], "Anna Berg");
    assert_eq!(
        (anna_row[1], anna_row[2]),
        (anna_row[2], anna_row[2]),
        "{scores}"
    );
    assert_eq!(&anna_row[3..], ["31", "31", "", "0"], "{scores}");
    assert_eq!(rows[2], "Ben Okafor,32,32,25,25,,6", "{scores}");
    let anna_txt = std::fs::read_to_string(out_dir.join("Anna_Berg.txt")).unwrap();
    assert!(
        anna_txt.contains(&format!(", bench {}", panel.trim_end_matches('/'))),
        "{anna_txt}"
    );
    let ben_json = out_dir.join("Ben_Okafor.json");
    assert_eq!(with_result(&ben_json, "not applicable").len(), BENCH_CHECKS);
    let anna_json = out_dir.join("Anna_Berg.json");
    let passed = with_result(&anna_json, "pass");
    assert_eq!(
        passed.iter().filter(|n| is_bench(n)).count(),
        BENCH_CHECKS,
        "{anna_txt}"
    );

    // One bench for the whole class is refused: each student has their own.
    let out = twin(&[
        "check",
        "slave",
        "--roster",
        roster.to_str().unwrap(),
        "--bench",
        &panel,
    ]);
    assert!(
        text(&out).contains("error: --bench is one slave's bench: with --roster, give each student's in the roster's `bench` column"),
        "{}",
        text(&out)
    );
    serve.terminate();
}
