//! Every request of `vectors/meb_slave.jsonl` against a freshly started EV
//! controller: the exact reply, silence where the vector says `null`, or a
//! reply of the stated command and count.

use nodes::firmware::{EvController, EvControllerConfig, sd};
use nodes::node::{MAX_FRAME, Node};
use protocols::meb::{MebCmd, MebRepr};
use protocols::time::SimTime;
use serde::Deserialize;

const VECTORS: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/vectors/meb_slave.jsonl"
));

#[derive(Debug, Deserialize)]
struct Shape {
    cmd: String,
    cnt: u8,
}

#[derive(Debug, Deserialize)]
struct Vector {
    request: String,
    #[serde(default)]
    reply: Option<String>,
    #[serde(default)]
    reply_shape: Option<Shape>,
    note: String,
}

/// Sends `request` and collects whatever the controller transmits.
fn exchange(controller: &mut EvController, request: &[u8]) -> Option<Vec<u8>> {
    controller.handle_bytes(SimTime::ZERO, request);
    let mut buf = [0u8; MAX_FRAME];
    let reply = controller
        .poll_transmit(SimTime::ZERO, &mut buf)
        .map(|len| buf[..len].to_vec());
    assert_eq!(
        controller.poll_transmit(SimTime::ZERO, &mut buf),
        None,
        "one reply per request"
    );
    reply
}

#[test]
fn every_slave_vector_gets_its_reply() {
    let vectors: Vec<Vector> = VECTORS
        .lines()
        .filter(|line| !line.trim().is_empty())
        .map(|line| serde_json::from_str(line).expect("vector line is JSON"))
        .collect();
    assert_eq!(vectors.len(), 31, "every vector line is read");
    let mut shaped = 0;
    for v in &vectors {
        let mut controller = EvController::new(EvControllerConfig::default());
        let reply = exchange(&mut controller, v.request.as_bytes());
        match (&v.reply, &v.reply_shape) {
            (Some(expected), _) => {
                let reply = reply.unwrap_or_else(|| panic!("{}: no reply", v.note));
                assert_eq!(
                    String::from_utf8_lossy(&reply),
                    *expected,
                    "{}: {:?}",
                    v.note,
                    v.request
                );
            }
            (None, Some(shape)) => {
                let reply = reply.unwrap_or_else(|| panic!("{}: no reply", v.note));
                let repr = MebRepr::parse(&reply)
                    .unwrap_or_else(|e| panic!("{}: reply {reply:?} malformed: {e}", v.note));
                assert_eq!(repr.id, 1, "{}", v.note);
                assert_eq!(repr.cmd.to_string(), shape.cmd, "{}", v.note);
                assert_eq!(repr.cnt, shape.cnt, "{}", v.note);
                assert_eq!(repr.data.len(), usize::from(shape.cnt), "{}", v.note);
                assert!(reply.ends_with(b"*\n"), "{}: emits *\\n", v.note);
                shaped += 1;
            }
            (None, None) => assert_eq!(reply, None, "{}: must stay silent", v.note),
        }
    }
    assert_eq!(shaped, 6);
}

#[test]
fn broadcast_write_is_stored_without_reply_and_bad_frames_count() {
    let mut controller = EvController::new(EvControllerConfig::default());
    // Broadcast: enable, brake released, everything else off.
    assert_eq!(exchange(&mut controller, b"@00SD0001001E22*\n"), None);
    assert_eq!(controller.image().stored.sd0, 0x001E);
    // A broadcast write that fails a check is neither applied nor answered.
    assert_eq!(exchange(&mut controller, b"@00SA0001100052*\n"), None);
    assert_eq!(controller.image().stored.vel, 0);
    // Bad FCS, then an interrupted frame: two drops in FA1.
    assert_eq!(exchange(&mut controller, b"@01EA000100*\n"), None);
    let reply = exchange(&mut controller, b"@01EA@01FA000244*\n").expect("reply");
    let repr = MebRepr::parse(&reply).unwrap();
    assert_eq!(repr.cmd, MebCmd::FA);
    assert_eq!(repr.data.as_slice(), &[0, 2], "SOC not sampled yet, ERRS 2");
    assert_eq!(sd::SD0_OFF, 0x001F);
}

#[test]
fn a_request_arriving_byte_by_byte_is_answered_after_its_last_byte() {
    let mut controller = EvController::new(EvControllerConfig::default());
    let request = b"@01SA000108005A*\n";
    let mut buf = [0u8; MAX_FRAME];
    for (i, byte) in request.iter().enumerate() {
        let now = SimTime(i as u64 * 6_250_000);
        controller.handle_bytes(now, core::slice::from_ref(byte));
        let reply = controller.poll_transmit(now, &mut buf);
        if i + 1 < request.len() {
            assert_eq!(reply, None, "no reply before byte {i} ends the frame");
        } else {
            let len = reply.expect("reply once the LF arrived");
            assert_eq!(&buf[..len], b"@01SA000152*\n");
        }
    }
    assert_eq!(controller.poll_timeout(), None, "MEB needs no timer");
    assert_eq!(controller.image().stored.vel, 0x0800);
}
