//! `twin view` on real-time sessions: recordings of `twin serve` and `twin
//! supervise` made by the real binaries on real sockets and pseudo-terminals,
//! turned into `.rrd` files and read back by rerun's own CLI (`rerun rrd
//! print`, PyPI `rerun-sdk==0.36.3`). Servers bind port 0 and the test reads
//! the port they print.

use protocols::meb::{MebCmd, MebRepr, MebWords};
use protocols::modbus::{self, Adu, Request, Response};
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use crate::support;
use crate::view::ok;
use support::Proc;

fn scratch(name: &str) -> PathBuf {
    support::scratch("view-sessions", name)
}

/// `twin view RECORDING --save RRD`: its printed samples per entity, and
/// its whole output.
fn view(recording: &Path, rrd: &Path) -> (BTreeMap<String, u64>, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_twin"))
        .arg("view")
        .arg(recording)
        .arg("--save")
        .arg(rrd)
        .output()
        .expect("twin view runs");
    let text = ok(&o);
    let samples = text
        .lines()
        .filter_map(|l| l.strip_prefix("  "))
        .filter_map(|l| {
            let (entity, n) = l.trim().rsplit_once(' ')?;
            Some((entity.trim().to_string(), n.parse().ok()?))
        })
        .collect();
    (samples, text)
}

/// Rows per entity of the recording in an `.rrd`, named as the session's
/// samples name them (without the leading `/`).
fn rrd_rows(path: &Path) -> BTreeMap<String, u64> {
    crate::view::rrd_rows(path)
        .into_iter()
        .map(|(entity, n)| (entity.trim_start_matches('/').to_string(), n))
        .collect()
}

/// Messages per topic, read with the mcap crate up to where the file ends.
fn mcap_counts(path: &Path) -> BTreeMap<String, u64> {
    let bytes = std::fs::read(path).expect("recording exists");
    let mut counts = BTreeMap::new();
    for m in mcap::MessageStream::new(&bytes).expect("valid MCAP") {
        let Ok(m) = m else { break };
        *counts.entry(m.channel.topic.clone()).or_default() += 1;
    }
    counts
}

fn meb(s: &mut TcpStream, cmd: MebCmd, addr: u8, cnt: u8, data: &[u16]) -> MebRepr {
    let request = MebRepr {
        id: 1,
        cmd,
        addr,
        cnt,
        data: MebWords::from_slice(data).expect("words"),
    };
    let mut frame = [0u8; 512];
    let n = request.emit(&mut frame).expect("emit");
    s.write_all(&frame[..n]).unwrap();
    let mut reply = Vec::new();
    let mut byte = [0u8];
    while reply.last() != Some(&b'\n') {
        s.read_exact(&mut byte).expect("a reply");
        reply.push(byte[0]);
    }
    MebRepr::parse(&reply).expect("a valid MEB reply")
}

fn input_registers(s: &mut TcpStream, tid: u16) -> Vec<u16> {
    let request = Request::ReadInputRegisters {
        address: 0,
        quantity: 6,
    };
    let mut adu = [0u8; 300];
    let n = modbus::tcp::TcpRepr {
        transaction_id: tid,
        unit: 1,
        pdu: &request,
    }
    .emit(&mut adu)
    .expect("emits");
    s.write_all(&adu[..n]).unwrap();
    let mut head = [0u8; 6];
    s.read_exact(&mut head).expect("an MBAP header");
    let mut rest = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]]))];
    s.read_exact(&mut rest).expect("the rest of the reply");
    let whole = [&head[..], &rest].concat();
    let frame = modbus::tcp::TcpFrame::new_checked(&whole).expect("a valid Modbus TCP reply");
    match frame.response() {
        Ok(Ok(Response::ReadInputRegisters(r))) => r.as_slice().to_vec(),
        other => panic!("not an input-register reply: {other:?}"),
    }
}

fn connect(addr: &str) -> TcpStream {
    let s = TcpStream::connect(addr).expect("connects");
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s.set_nodelay(true).unwrap();
    s
}

#[test]
fn a_serve_session_views_with_the_controllers_readings_and_the_tick_lateness() {
    let mcap = scratch("serve.mcap");
    let out = mcap.to_str().unwrap();
    let live = scratch("serve-live.rrd");
    let server = Proc::start(&[
        "serve",
        "--view",
        live.to_str().unwrap(),
        "--meb",
        "tcp://127.0.0.1:0",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--duration",
        "3",
        "--quiet",
        "--status-every",
        "0",
        "--out",
        out,
    ]);
    let mut m = connect(&server.tcp_of("meb"));
    let mut b = connect(&server.tcp_of("modbus-tcp"));
    // EN and VEL at half scale: the wheel turns, RPM_M grows.
    meb(&mut m, MebCmd::SD, 0, 2, &[0x000E, 0x0001]);
    meb(&mut m, MebCmd::SA, 0, 1, &[2048]);
    let (mut ea_replies, mut modbus_replies, mut last_rpm) = (0u64, 0u64, 0u16);
    for k in 0..8u16 {
        std::thread::sleep(Duration::from_millis(150));
        let r = meb(&mut m, MebCmd::EA, 0, 6, &[]);
        assert_eq!(r.data.as_slice().len(), 6);
        ea_replies += 1;
        let regs = input_registers(&mut b, k + 1);
        assert_eq!(regs.len(), 6);
        modbus_replies += 1;
        last_rpm = regs[3];
    }
    assert!(last_rpm > 500, "the wheel turns: RPM_M {last_rpm}");
    drop((m, b));
    server.wait();

    let rrd = scratch("serve.rrd");
    let (samples, text) = view(&mcap, &rrd);
    let counts = mcap_counts(&mcap);
    // The controller's readings are recorded beside every plant sample, and
    // they give the speed plot its hall and light rpm (the replies on either
    // link carry the same words, less often).
    let readings = counts["/controller/ev1/readings"];
    assert_eq!(readings, counts["/plant/ev1/sensors"], "{counts:?}");
    // By name, as the replies carried them: the wheel turns.
    let bytes = std::fs::read(&mcap).unwrap();
    let last = mcap::MessageStream::new(&bytes)
        .unwrap()
        .filter_map(Result::ok)
        .filter(|m| m.channel.topic == "/controller/ev1/readings")
        .last()
        .expect("a readings message");
    let last: serde_json::Value =
        twin_recording::read::value_of(&last.channel, &last.data).unwrap();
    assert!(last["hall_rpm"].as_u64().unwrap() > 500, "{last}");
    assert_eq!(last["meb"]["RPM_M"], last["hall_rpm"]);
    assert_eq!(samples["ev1/speed/hall_rpm"], readings, "{text}");
    assert_eq!(samples["ev1/speed/light_rpm"], readings);
    // Requests and replies on each link; the plant at its recording rate.
    assert_eq!(samples["bus/meb/frames"], 2 * (ea_replies + 2));
    assert_eq!(samples["bus/modbus-tcp/frames"], 2 * modbus_replies);
    assert_eq!(samples["ev1/speed/wheel_rpm"], counts["/plant/ev1/sensors"]);
    assert_eq!(samples["ev1/voltage/V1"], counts["/plant/ev1/sensors"]);
    assert!(counts["/plant/ev1/sensors"] > 300, "{counts:?}");
    assert_eq!(
        samples["realtime/lateness/p99_us"],
        counts["/realtime/lateness"]
    );
    assert!(counts["/realtime/lateness"] >= 2, "{counts:?}");
    // The .rrd holds what was logged.
    let rows = rrd_rows(&rrd);
    for entity in [
        "ev1/speed/hall_rpm",
        "ev1/speed/wheel_rpm",
        "bus/meb/frames",
        "bus/modbus-tcp/frames",
        "realtime/lateness/max_us",
    ] {
        assert_eq!(rows.get(entity), samples.get(entity), "{entity}: {rows:?}");
    }
    // Streamed live (`--view FILE.rrd`), the session gave the same samples.
    assert_eq!(rrd_rows(&live), rows);
}

#[test]
fn a_killed_serve_session_views_up_to_its_last_flush() {
    let mcap = scratch("killed.mcap");
    let server = Proc::start(&[
        "serve",
        "--meb",
        "tcp://127.0.0.1:0",
        "--quiet",
        "--status-every",
        "0",
        "--out",
        mcap.to_str().unwrap(),
    ]);
    std::thread::sleep(Duration::from_millis(2600));
    drop(server); // SIGKILL: no summary, no index, a chunk cut off.
    let (samples, text) = view(&mcap, &scratch("killed.rrd"));
    // Flushed each second: the first two seconds at 200 Hz survive, give or
    // take the ticks a busy machine skipped.
    assert!(samples["ev1/speed/wheel_rpm"] >= 150, "{text}");
    assert!(samples["realtime/lateness/p99_us"] >= 1, "{text}");
}

#[test]
fn a_supervise_session_views_the_loop_of_each_slave() {
    let (a, b) = (scratch("ttyA"), scratch("ttyB"));
    let (a, b) = (a.to_str().unwrap(), b.to_str().unwrap());
    let _vsp = Proc::start(&["vsp", a, b]);
    let _serve = Proc::start(&[
        "serve",
        "--meb",
        b,
        "--quiet",
        "--status-every",
        "0",
        "--no-record",
    ]);
    let mcap = scratch("supervise.mcap");
    let live = scratch("supervise-live.rrd");
    let supervise = Proc::start(&[
        "supervise",
        "--view",
        live.to_str().unwrap(),
        "--meb",
        a,
        "--listen",
        "tcp://127.0.0.1:0",
        "--set-point",
        "1500",
        "--duration",
        "2",
        "--quiet",
        "--status-every",
        "0",
        "--out",
        mcap.to_str().unwrap(),
    ]);
    supervise.wait();

    // What the recording holds: loop reports, and the slave's EA replies.
    let bytes = std::fs::read(&mcap).unwrap();
    let (mut loops, mut ea_replies) = (0u64, 0u64);
    for m in mcap::MessageStream::new(&bytes).expect("valid MCAP") {
        let m = m.expect("valid message");
        match m.channel.topic.as_str() {
            "/master/supervisor/loop" => loops += 1,
            "/link/bus/frames" => {
                let v: serde_json::Value =
                    twin_recording::read::value_of(&m.channel, &m.data).unwrap();
                let d = &v["decoded"];
                // The reply is the slave's, named by the id it answers with.
                if v["from"] == "slave 01"
                    && d["cmd"] == "EA"
                    && d["data"].as_array().unwrap().len() == 6
                {
                    ea_replies += 1;
                }
            }
            _ => {}
        }
    }
    assert!(loops > 100 && ea_replies > 100, "{loops} {ea_replies}");
    let rrd = scratch("supervise.rrd");
    let (samples, text) = view(&mcap, &rrd);
    assert_eq!(samples["slave01/speed/set_point"], loops, "{text}");
    assert_eq!(samples["slave01/speed/hall_rpm"], ea_replies, "{text}");
    // No plant in a supervisor's recording, and no entity pretends one.
    assert!(!samples.keys().any(|e| e.contains("voltage")), "{text}");
    // Streamed live, the same samples.
    let rows = rrd_rows(&rrd);
    assert_eq!(rows.get("slave01/speed/hall_rpm"), Some(&ea_replies));
    assert_eq!(rrd_rows(&live), rows);
}

#[test]
fn a_session_that_cannot_start_leaves_an_earlier_recording_alone() {
    let missing = scratch("no-such-port");
    for role in ["serve", "supervise"] {
        let earlier = scratch(&format!("earlier-{role}.mcap"));
        std::fs::write(&earlier, b"an earlier session's recording").unwrap();
        let o = Command::new(env!("CARGO_BIN_EXE_twin"))
            .args([role, "--meb", missing.to_str().unwrap(), "--duration", "1"])
            .arg("--out")
            .arg(&earlier)
            .stdin(Stdio::null())
            .output()
            .expect("twin runs");
        assert!(!o.status.success(), "{role} started on a missing port");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains("does not exist"), "{role}: {err}");
        assert_eq!(
            std::fs::read(&earlier).unwrap(),
            b"an earlier session's recording",
            "{role} overwrote the recording"
        );
    }
}
