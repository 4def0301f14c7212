//! `twin scope` of a real-time session: `twin serve` answers Modbus RTU on
//! a pseudo-terminal at 19 200 baud 8E1, records, and the scope lays the
//! recorded frames out at the link's baud and character format (a
//! pseudo-terminal carries bytes, not bits: the waveform is reconstructed
//! from the byte times, and says so). sigrok's `uart` decoder reads every
//! byte back, in the order the request and replies went, with no parity
//! error.

use std::io::{Read, Write};
use std::path::Path;
use std::process::Command;
use std::time::Duration;

use protocols::modbus::{self, Request};
use twin_recording::read::Recording;
use twin_recording::topics::{FrameSample, Topic};

use crate::scope::s;
use crate::support::{self, Proc, text, twin};

/// The link's frames in the order they went: sender and bytes.
fn link_frames(path: &Path) -> Vec<(String, f64, Vec<u8>)> {
    let mut frames = Vec::new();
    Recording::scan(path, |m| {
        if let Topic::LinkFrames(_) = Topic::parse(m.topic) {
            let f: FrameSample = m.json()?;
            let bytes = (0..f.hex.len() / 2)
                .map(|i| u8::from_str_radix(&f.hex[2 * i..2 * i + 2], 16).unwrap())
                .collect();
            frames.push((f.from, f.start_s, bytes));
        }
        Ok(())
    })
    .unwrap();
    frames.sort_by(|a, b| a.1.total_cmp(&b.1));
    frames
}

/// `sigrok-cli -i FILE -P DECODERS -A SHOW`: the annotations' texts.
fn decode(file: &Path, decoders: &str, show: &str) -> Vec<String> {
    let o = Command::new("sigrok-cli")
        .args(["-i", s(file), "-P", decoders, "-A", show])
        .output()
        .expect("sigrok-cli runs (.ci/install installs it)");
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    out.lines()
        .filter_map(|l| l.split_once(": ").map(|(_, t)| t.to_string()))
        .collect()
}

#[test]
fn a_serve_sessions_recording_decodes_in_the_order_the_bytes_went() {
    let out = support::scratch("scope-session", "serve.mcap");
    let (mut port, _slave, path) = {
        use serialport::SerialPort;
        let (mut master, slave) = serialport::TTYPort::pair().expect("a pty pair");
        master.set_timeout(Duration::from_secs(5)).unwrap();
        let name = slave.name().expect("slave path");
        (master, slave, name)
    };
    let server = Proc::start(&[
        "serve",
        "--modbus-rtu",
        &format!("{path}?baud=19200&parity=E"),
        "--quiet",
        "--out",
        s(&out),
    ]);
    let mut frame = [0u8; 300];
    for (address, quantity) in [(0u16, 10u16), (2, 1), (5, 3)] {
        let request = Request::ReadInputRegisters { address, quantity };
        let n = modbus::rtu::RtuRepr {
            unit: 1,
            pdu: &request,
        }
        .emit(&mut frame)
        .unwrap();
        port.write_all(&frame[..n]).unwrap();
        // unit, function, byte count, the registers, CRC
        let mut reply = vec![0u8; 5 + 2 * usize::from(quantity)];
        port.read_exact(&mut reply).expect("a reply on the pty");
        assert!(
            modbus::rtu::RtuFrame::new_checked(&reply).is_ok(),
            "{reply:02x?}"
        );
    }
    let printed = server.terminate();
    assert!(printed.contains("stopped"), "{printed}");

    let frames = link_frames(&out);
    assert_eq!(
        frames.len(),
        6,
        "three requests and their replies: {frames:?}"
    );
    let sr = support::scratch("scope-session", "serve.sr");
    let o = twin(&["scope", s(&out), "--sr", s(&sr)]);
    assert!(o.status.success(), "{}", text(&o));
    let said = text(&o);
    assert!(
        said.contains("link.modbus-rtu from ")
            && said.contains(
                "6 frames at 19200 baud (8E1); reconstructed from the recorded byte times"
            ),
        "{said}"
    );
    assert!(
        said.contains(
            "decode: sigrok-cli -i FILE -P uart:rx=link.modbus-rtu.line:baudrate=19200:parity=even"
        ),
        "{said}"
    );

    let uart = "uart:rx=link.modbus-rtu.line:baudrate=19200:parity=even";
    let got: Vec<u8> = decode(&sr, uart, "uart=rx-data")
        .iter()
        .map(|t| u8::from_str_radix(t, 16).expect("a byte in hex"))
        .collect();
    let want: Vec<u8> = frames.iter().flat_map(|f| f.2.clone()).collect();
    assert_eq!(got, want, "the bytes in the order they went");
    let errors = decode(&sr, uart, "uart=rx-warnings");
    assert!(errors.is_empty(), "{errors:?}");
    // Each side's TX carries its own frames.
    let twin_tx: Vec<u8> = frames
        .iter()
        .filter(|f| f.0 == "twin")
        .flat_map(|f| f.2.clone())
        .collect();
    assert_eq!(twin_tx.len(), 25 + 7 + 11, "{frames:?}");
    let got: Vec<u8> = decode(
        &sr,
        "uart:rx=link.modbus-rtu.twin.tx:baudrate=19200:parity=even",
        "uart=rx-data",
    )
    .iter()
    .map(|t| u8::from_str_radix(t, 16).unwrap())
    .collect();
    assert_eq!(got, twin_tx);
}
