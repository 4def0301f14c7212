//! What a new user meets first, in their words: numbers with a minus sign,
//! misspelt links, a missing bus, a scenario with a typo, the
//! controller-network summary. The real binary, run as a user runs it.

use crate::support;
use std::path::PathBuf;
use std::process::{Command, Output};

fn twin(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twin"))
        .args(args)
        .current_dir(std::env::temp_dir())
        .output()
        .expect("twin runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn scratch(name: &str) -> PathBuf {
    support::scratch("words-cli", name)
}

#[test]
fn negative_numbers_are_parsed_or_refused_in_words_never_taken_for_flags() {
    let refused: [(&[&str], &str); 12] = [
        (
            &["run", "--duration", "-5"],
            "'--duration <SECONDS>': must be above 0, got -5",
        ),
        (&["run", "--seed", "-1"], "must be a whole number from 0 to"),
        (
            &["run", "--open-loop", "--record-hz", "-200"],
            "must be above 0, got -200",
        ),
        (&["serve", "--duration", "-5"], "must be above 0, got -5"),
        (
            &[
                "serve",
                "--meb",
                "tcp://127.0.0.1:0",
                "--idle-timeout",
                "-1",
            ],
            "--idle-timeout -1: give seconds above 0",
        ),
        (
            &["serve", "--baud", "-9600"],
            "must be a whole number from 0 to",
        ),
        (
            &["supervise", "--duration", "-5"],
            "must be above 0, got -5",
        ),
        (&["step", "--duration", "-5"], "must be above 0, got -5"),
        (&["sweep", "--settle", "-3"], "must be above 0, got -3"),
        (
            &["vsp", "/tmp/a", "/tmp/b", "--stats-every", "-1"],
            "must be 0 or more, got -1",
        ),
        (
            &["client", "tcp://127.0.0.1:1", "watch", "--every", "-0.5"],
            "must be above 0, got -0.5",
        ),
        (
            &["experiment", "pwmcap", "--noise-mv", "-1"],
            "must be 0 or more, got -1",
        ),
    ];
    for (args, said) in refused {
        let o = twin(args);
        let e = stderr(&o);
        assert!(!o.status.success(), "{args:?}");
        assert!(e.contains(said), "{args:?}: {e}");
        assert!(!e.contains("-- -"), "{args:?} advised `-- -N`: {e}");
    }
    // Numbers that may be negative are read as numbers, and judged by what
    // they mean: a set point below 0 rpm is out of the loop's range.
    let o = twin(&[
        "supervise",
        "--meb",
        "/nonexistent/tty",
        "--set-point",
        "-5",
    ]);
    let e = stderr(&o);
    assert!(e.contains("--set-point -5: must be 0-20000 rpm"), "{e}");
    let o = twin(&["run", "--open-loop", "--vel", "-0.5"]);
    let e = stderr(&o);
    assert!(
        e.contains("--vel is a fraction of the 5 V range: 0 to 1, got -0.5"),
        "{e}"
    );
}

#[test]
fn a_misspelt_tcp_address_is_named_as_such() {
    for args in [
        ["serve", "--meb", "tcp:/127.0.0.1:5000"],
        ["supervise", "--meb", "tcp:/127.0.0.1:5000"],
    ] {
        let o = twin(&args);
        let e = stderr(&o);
        assert!(!o.status.success());
        assert!(
            e.contains("looks like a misspelt TCP address, not a serial device: write `tcp://127.0.0.1:5000`"),
            "{args:?}: {e}"
        );
    }
}

#[test]
fn supervise_without_a_bus_offers_both_links() {
    let o = twin(&["supervise"]);
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(e.contains("--meb LINK"), "{e}");
    assert!(e.contains("--modbus-rtu LINK"), "{e}");
    assert!(!e.contains("required"), "{e}");
}

#[test]
fn a_scenario_typo_is_reported_at_its_own_line_in_words() {
    let path = scratch("typo.toml");
    let text = "name = \"typo\"\nduration_s = 1.0\n\n[[module]]\nname = \"ev1\"\n\n[[bus]]\nname = \"rs485\"\n\n\
                [[node]]\nkind = \"ev-controller\"\nname = \"ev1\"\nbus = \"rs485\"\nmodule = \"ev1\"\n\
                turnaround_ms = \"quick\"\n";
    std::fs::write(&path, text).expect("write scenario");
    let o = twin(&["run", path.to_str().unwrap()]);
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(
        e.contains(&format!(
            "{}:15:1: `turnaround_ms`: expected a number, found the string \"quick\"",
            path.display()
        )),
        "{e}"
    );
    assert!(!e.contains("f64"), "{e}");
}

#[test]
fn the_controller_network_summary_says_which_rpm_is_which() {
    let out = scratch("cn.mcap");
    let o = twin(&[
        "run",
        "controller-network",
        "--duration",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{text}{}", stderr(&o));
    for label in [
        "rpm (its true speed)",
        "(motor node): operational",
        "its encoder: motor shaft ",
        "(light-sensor node): wheel ",
        "(Raspberry Pi master): running",
        "last read: motor shaft ",
        "from the light-sensor node",
    ] {
        assert!(text.contains(label), "`{label}` missing: {text}");
    }
    assert!(!text.contains("{\""), "raw JSON printed: {text}");
}
