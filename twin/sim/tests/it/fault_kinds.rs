//! Each fault kind a master's check needs, in a scenario file: what the
//! master counts when its slave refuses, answers as another id, splits its
//! replies or sends junk with them, on MEB, Modbus RTU and the
//! Controller_network project's 8-byte Modbus; the same scenario and seed
//! give the same recording, byte for byte; and a fault that does not fit
//! its node is refused with the file, line and field.

use std::collections::BTreeMap;
use std::path::PathBuf;

use twin_sim::scenario::Scenario;
use twin_sim::virtual_run::{RunOutcome, run};

/// An EV controller (slave 1) and a supervisor polling it every 10 ms over
/// `protocol`, for 1 s, with `fault` on the controller from 0.2 s to 0.8 s.
fn ev_scenario(protocol: &str, fault: &str) -> String {
    format!(
        r#"name = "faults-{protocol}"
seed = 3
duration_s = 1.0

[[module]]
name = "ev1"
preset = "vemodule"

[[bus]]
name = "rs485"
baud = 115200

[[node]]
kind = "ev-controller"
name = "ev1"
bus = "rs485"
module = "ev1"
id = 1
protocol = "{protocol}"
turnaround_ms = 0.5

[[node]]
kind = "supervisor"
name = "supervisor"
bus = "rs485"
slaves = [1]
protocol = "{protocol}"
poll_period_ms = 10.0
reply_timeout_ms = 20.0
kp = 0.45
ki = 2.5
set_points = [[0.0, 500.0]]

[[fault]]
node = "ev1"
from_s = 0.2
until_s = 0.8
{fault}
"#
    )
}

/// The Controller_network bench: motor node, light node and the Pi master
/// (with a reply timeout), for 3 s, with `fault` on the motor node from
/// 0.5 s on.
fn cn_scenario(fault: &str) -> String {
    format!(
        r#"name = "faults-modbus8"
seed = 3
duration_s = 3.0

[[module]]
name = "bench"
preset = "controller-network"

[[bus]]
name = "serial"
baud = 115200
wiring = "master-slaves"

[[node]]
kind = "motor-node"
name = "motor"
bus = "serial"
module = "bench"

[[node]]
kind = "light-node"
name = "sensor"
bus = "serial"
module = "bench"

[[node]]
kind = "controller-network-master"
name = "rpi"
bus = "serial"
reply_timeout_ms = 100.0

[[fault]]
node = "motor"
from_s = 0.5
until_s = 3.0
{fault}
"#
    )
}

fn out(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twin-sim-fault-kinds-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(format!("{name}.mcap"))
}

fn run_text(text: &str, name: &str) -> (RunOutcome, Vec<u8>) {
    let scenario = Scenario::parse(text, name).unwrap_or_else(|e| panic!("{name}: {e}"));
    let path = out(name);
    let outcome = run(&scenario, &path, |_| {}).unwrap_or_else(|e| panic!("{name}: {e:#}"));
    let bytes = std::fs::read(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    (outcome, bytes)
}

fn events(o: &RunOutcome) -> &BTreeMap<String, u64> {
    &o.events
}

fn count(o: &RunOutcome, kind: &str) -> u64 {
    events(o).get(kind).copied().unwrap_or(0)
}

/// The supervisor's counter `what` for slave 1, from its last report.
fn supervisor(o: &RunOutcome, what: &str) -> u64 {
    let (_, report) = o
        .telemetry
        .iter()
        .find(|(name, _)| name == "supervisor")
        .expect("the supervisor reports");
    report["loops"][0][what]
        .as_u64()
        .unwrap_or_else(|| panic!("{what} in {report}"))
}

#[test]
fn a_clean_run_has_none_of_what_the_faults_cause() {
    for protocol in ["meb", "modbus-rtu"] {
        let text = ev_scenario(protocol, "kind = \"delay-reply\"\ndelay_ms = 0.0");
        let (o, _) = run_text(&text, &format!("clean-{protocol}"));
        for what in ["timeouts", "bad_checks", "exceptions"] {
            assert_eq!(
                supervisor(&o, what),
                0,
                "{protocol}: {what}: {:?}",
                o.events
            );
        }
    }
    let (o, _) = run_text(
        &cn_scenario("kind = \"delay-reply\"\ndelay_ms = 0.0"),
        "clean-cn",
    );
    for kind in ["exception", "bad_reply", "bad_check", "timeout"] {
        assert_eq!(count(&o, kind), 0, "{kind}: {:?}", o.events);
    }
}

#[test]
fn an_exception_fault_is_counted_as_an_exception_by_each_master() {
    for protocol in ["meb", "modbus-rtu"] {
        let text = ev_scenario(protocol, "kind = \"exception\"\ncode = 2");
        let (o, _) = run_text(&text, &format!("exception-{protocol}"));
        // Refused requests for 0.6 s, polled every 10 ms or so.
        assert!(
            supervisor(&o, "exceptions") > 20,
            "{protocol}: {:?}",
            o.events
        );
        assert_eq!(supervisor(&o, "bad_checks"), 0, "{protocol}");
    }
    let (o, _) = run_text(
        &cn_scenario("kind = \"exception\"\ncode = 3"),
        "exception-cn",
    );
    assert!(count(&o, "exception") > 0, "{:?}", o.events);
    assert!(
        o.log_tail
            .iter()
            .any(|l| l.contains("83") || l.contains("86") || l.contains("ILLEGAL")),
        "the Pi prints the exception: {:?}",
        o.log_tail
    );
}

#[test]
fn a_wrong_id_reply_is_not_taken_for_the_slaves() {
    for protocol in ["meb", "modbus-rtu"] {
        let text = ev_scenario(protocol, "kind = \"wrong-id\"\nid = 5");
        let (o, _) = run_text(&text, &format!("wrong-id-{protocol}"));
        // Every reply in the window is another slave's: the supervisor
        // times out waiting for slave 1's.
        assert!(
            supervisor(&o, "timeouts") > 10,
            "{protocol}: {:?}",
            o.events
        );
        assert!(count(&o, "fault") > 10, "{protocol}: {:?}", o.events);
    }
    let (o, _) = run_text(&cn_scenario("kind = \"wrong-id\""), "wrong-id-cn");
    assert!(count(&o, "bad_reply") > 0, "{:?}", o.events);
}

#[test]
fn a_split_reply_is_whole_over_meb_and_two_bad_frames_over_rtu() {
    // 2 ms of quiet line inside the reply: MEB waits for its `\n`, so the
    // reply is whole; RTU's silence (3.5 characters) ends a frame there.
    let split = "kind = \"split-reply\"\ngap_ms = 2.0";
    let (meb, _) = run_text(&ev_scenario("meb", split), "split-meb");
    assert!(count(&meb, "fault") > 20, "{:?}", meb.events);
    assert_eq!(supervisor(&meb, "timeouts"), 0, "{:?}", meb.events);
    assert_eq!(supervisor(&meb, "bad_checks"), 0, "{:?}", meb.events);
    let (rtu, _) = run_text(&ev_scenario("modbus-rtu", split), "split-rtu");
    assert!(
        supervisor(&rtu, "bad_checks") + supervisor(&rtu, "timeouts") > 10,
        "{:?}",
        rtu.events
    );
    // Longer than the reply timeout: the MEB master gives up first.
    let long = "kind = \"split-reply\"\ngap_ms = 40.0\nsplit_at = 3";
    let (meb, _) = run_text(&ev_scenario("meb", long), "split-long-meb");
    assert!(supervisor(&meb, "timeouts") > 5, "{:?}", meb.events);
    // The 8-byte Modbus drops a partial frame after 5 ms of silence.
    let (cn, _) = run_text(
        &cn_scenario("kind = \"split-reply\"\ngap_ms = 20.0"),
        "split-cn",
    );
    assert!(
        count(&cn, "timeout") + count(&cn, "bad_check") > 0,
        "{:?}",
        cn.events
    );
}

#[test]
fn junk_before_a_reply_is_skipped_by_meb_and_fails_rtus_check() {
    let junk = "kind = \"junk\"\njunk = [0x00, 0xFF, 0x7E]";
    let (meb, _) = run_text(&ev_scenario("meb", junk), "junk-meb");
    assert!(count(&meb, "fault") > 20, "{:?}", meb.events);
    assert_eq!(
        supervisor(&meb, "bad_checks"),
        0,
        "MEB skips bytes before `@`"
    );
    let (rtu, _) = run_text(&ev_scenario("modbus-rtu", junk), "junk-rtu");
    assert!(
        supervisor(&rtu, "bad_checks") + supervisor(&rtu, "timeouts") > 10,
        "{:?}",
        rtu.events
    );
    let (cn, _) = run_text(&cn_scenario("kind = \"junk\"\njunk_count = 3"), "junk-cn");
    assert!(
        count(&cn, "bad_check") + count(&cn, "timeout") > 0,
        "{:?}",
        cn.events
    );
}

#[test]
fn the_same_scenario_and_seed_give_the_same_recording_byte_for_byte() {
    let text = cn_scenario("kind = \"junk\"\njunk_count = 4\njunk_place = \"after\"");
    let (_, a) = run_text(&text, "same-a");
    let (_, b) = run_text(&text, "same-b");
    assert!(a == b, "two runs of one scenario differ");
    let other = text.replace("seed = 3", "seed = 4");
    let (_, c) = run_text(&other, "same-c");
    assert!(a != c, "another seed draws other junk");
}

#[test]
fn a_fault_that_does_not_fit_names_the_file_line_and_field() {
    let cases = [
        (
            cn_scenario("kind = \"exception\"\ncode = 9"),
            ":37: `code` of the fault on `motor` must be 1 (illegal function)",
        ),
        (
            cn_scenario("kind = \"junk\"").replace("node = \"motor\"", "node = \"rpi\""),
            ":36: `kind` `junk` of the fault on `rpi` needs `junk = [0x00, 0xFF]`",
        ),
        (
            cn_scenario("kind = \"exception\"").replace("node = \"motor\"", "node = \"rpi\""),
            ":36: `kind` `exception` of the fault on `rpi`: a master answers no requests",
        ),
        (
            ev_scenario("meb", "kind = \"wrong-id\"\nid = 120"),
            ":39: `id` of the fault on `ev1`: an MEB slave id is 1 to 99, got 120",
        ),
        (
            ev_scenario("meb", "kind = \"wrong-id\"\nid = 1"),
            "`id` of the fault on `ev1` is 1, the node's own id",
        ),
        (
            ev_scenario("meb", "kind = \"bad-check\"\ngap_ms = 3.0"),
            ":39: `gap_ms` is for split-reply faults, and the fault on `ev1` is `bad-check`",
        ),
        (
            ev_scenario("meb", "kind = \"split-reply\""),
            "`split-reply` of the fault on `ev1` needs `gap_ms`",
        ),
        (
            ev_scenario("meb", "kind = \"exception\"")
                .replace("node = \"ev1\"\nfrom", "node = \"supervisor\"\nfrom"),
            "that node is a supervisor, whose frames no fault changes",
        ),
    ];
    for (text, expected) in cases {
        let e = Scenario::parse(&text, "lab.toml")
            .expect_err(expected)
            .to_string();
        assert!(e.starts_with("lab.toml:"), "{e}");
        assert!(e.contains(expected), "{e}\nexpected: {expected}");
        assert!(!e.contains("Some(") && !e.contains("FaultKind"), "{e}");
    }
}
