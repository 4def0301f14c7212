//! The faults a master's check needs, switched on from `twin serve`'s
//! console and seen by a real client (a Python peer reading the raw bytes):
//! a reply from the wrong id, a reply split over two writes, junk before or
//! after a reply; over MEB on TCP and Modbus RTU on a pseudo-terminal.

use protocols::meb::{MebCmd, MebRepr, MebWords};
use protocols::modbus::Adu;
use protocols::modbus::rtu;
use std::io::Write;
use std::process::{ChildStdin, Command, Stdio};
use std::time::Duration;

use crate::peers::{PtyPair, run_timeout, scratch, script};
use crate::support::Proc;

/// What the slave's writes brought for one request: each read's bytes.
fn exchange(link: &str, request: &[u8], want: usize) -> Vec<Vec<u8>> {
    let hex: String = request.iter().map(|b| format!("{b:02x}")).collect();
    let out = run_timeout(
        Command::new("python3")
            .arg(script("raw_exchange.py"))
            .args([link, &hex, &want.to_string(), "5"]),
        Duration::from_secs(30),
    );
    assert!(
        out.status.success(),
        "raw_exchange.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| {
            (0..l.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&l[i..i + 2], 16).unwrap())
                .collect()
        })
        .collect()
}

fn say(server: &Proc, console: &mut ChildStdin, line: &str, echo: &str) {
    writeln!(console, "{line}").unwrap();
    assert!(server.printed(echo), "`{line}`: {}", server.output());
}

fn meb_read_ea() -> Vec<u8> {
    let mut out = [0u8; 64];
    let repr = MebRepr {
        id: 1,
        cmd: MebCmd::EA,
        addr: 0,
        cnt: 6,
        data: MebWords::new(),
    };
    let n = repr.emit(&mut out).unwrap();
    out[..n].to_vec()
}

/// Read input register 0 of unit 1.
const RTU_READ: [u8; 8] = [0x01, 0x04, 0x00, 0x00, 0x00, 0x01, 0x31, 0xca];
/// An MEB reply to EA 0..6: 13 bytes and 4 per word.
const MEB_EA_LEN: usize = 13 + 24;

#[test]
fn console_faults_reach_a_real_client_byte_for_byte() {
    let dir = scratch("serve-faults");
    let pair = PtyPair::new(&dir);
    let server = Proc::spawn(
        &[
            "serve",
            "--meb",
            "tcp://127.0.0.1:0",
            "--modbus-rtu",
            pair.a.to_str().unwrap(),
            "--quiet",
            "--no-record",
        ],
        Stdio::piped(),
    );
    let mut server = server;
    let mut console = server.child.stdin.take().expect("stdin");
    let meb = format!("tcp://{}", server.tcp_of("meb"));
    let rtu_link = pair.b.to_str().unwrap().to_string();
    let whole = |chunks: &[Vec<u8>]| chunks.concat();

    // Clean first: one MEB reply, one RTU reply, from id 1.
    let clean = whole(&exchange(&meb, &meb_read_ea(), MEB_EA_LEN));
    assert_eq!(MebRepr::parse(&clean).unwrap().id, 1);
    let clean_rtu = whole(&exchange(&rtu_link, &RTU_READ, 7));
    assert_eq!(rtu::RtuFrame::new_checked(&clean_rtu).unwrap().unit(), 1);

    // Wrong id: a well-formed reply, from slave 7.
    say(
        &server,
        &mut console,
        "fault wrong-id 7",
        "fault wrong-id (replies as id 7) on every link",
    );
    let reply = whole(&exchange(&meb, &meb_read_ea(), MEB_EA_LEN));
    let repr = MebRepr::parse(&reply).unwrap_or_else(|e| panic!("{e}: {reply:02x?}"));
    assert_eq!((repr.id, repr.cmd), (7, MebCmd::EA));
    let reply = whole(&exchange(&rtu_link, &RTU_READ, 7));
    assert_eq!(
        rtu::RtuFrame::new_checked(&reply).unwrap().unit(),
        7,
        "{reply:02x?}"
    );
    // Unchosen: the next id.
    say(
        &server,
        &mut console,
        "fault wrong-id meb",
        "fault wrong-id (replies as the next id) on meb",
    );
    let reply = whole(&exchange(&meb, &meb_read_ea(), MEB_EA_LEN));
    assert_eq!(MebRepr::parse(&reply).unwrap().id, 2);

    // Junk: these bytes before the reply, then the reply whole.
    say(
        &server,
        &mut console,
        "fault junk hex:00ff7e meb",
        "fault junk 00 ff 7e before each reply on meb",
    );
    let reply = whole(&exchange(&meb, &meb_read_ea(), 3 + MEB_EA_LEN));
    assert_eq!(reply[..3], [0x00, 0xff, 0x7e]);
    assert_eq!(MebRepr::parse(&reply[3..]).unwrap().id, 1);
    // Random bytes after the RTU reply (between it and the next request).
    say(
        &server,
        &mut console,
        "fault junk 4 after modbus-rtu",
        "fault junk of 4 random byte(s) after each reply on modbus-rtu",
    );
    let reply = whole(&exchange(&rtu_link, &RTU_READ, 7 + 4));
    assert_eq!(reply.len(), 11, "{reply:02x?}");
    assert_eq!(rtu::RtuFrame::new_checked(&reply[..7]).unwrap().unit(), 1);

    // Split: the reply in two writes, a second apart; together the whole reply.
    say(
        &server,
        &mut console,
        "fault split 1000",
        "fault split (replies in two writes, 1000.0 ms apart) on every link",
    );
    let chunks = exchange(&meb, &meb_read_ea(), MEB_EA_LEN);
    assert_eq!(chunks.len(), 2, "two writes: {chunks:02x?}");
    assert_eq!(chunks[0].len(), MEB_EA_LEN / 2);
    assert_eq!(MebRepr::parse(&whole(&chunks)).unwrap().id, 1);
    let chunks = exchange(&rtu_link, &RTU_READ, 7);
    assert!(chunks.len() >= 2, "two writes: {chunks:02x?}");
    assert_eq!(chunks[0].len(), 3, "{chunks:02x?}");
    assert_eq!(
        rtu::RtuFrame::new_checked(&whole(&chunks)).unwrap().unit(),
        1
    );

    say(&server, &mut console, "fault off", "fault off");
    let reply = whole(&exchange(&meb, &meb_read_ea(), MEB_EA_LEN));
    assert_eq!(MebRepr::parse(&reply).unwrap().id, 1);
    let out = server.output();
    for rust in ["WrongId", "Split(", "Junk {", "Some("] {
        assert!(!out.contains(rust), "a Rust name on the console: {out}");
    }
    drop(pair);
    let _ = std::fs::remove_dir_all(&dir);
}
