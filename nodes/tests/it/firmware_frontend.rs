//! The slave front end that real-time links use: every MEB slave vector
//! through it gives the controller's own reply, and several front ends (MEB,
//! Modbus TCP, RTU) serving one image see each other's writes.

use nodes::firmware::{EvController, EvControllerConfig, Framing, Refusal, SlaveFrontend};
use nodes::node::{MAX_FRAME, Node};
use protocols::meb::{MebCmd, MebRepr};
use protocols::modbus::{self, Adu, Exception, Request, Response};
use protocols::time::{SimDuration, SimTime};
use serde::Deserialize;

const VECTORS: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/vectors/meb_slave.jsonl"
));

#[derive(Debug, Deserialize)]
struct Vector {
    request: String,
}

fn reply_of(
    frontend: &mut SlaveFrontend,
    controller: &mut EvController,
    bytes: &[u8],
) -> Option<Vec<u8>> {
    frontend.handle_bytes(controller.image_mut(), SimTime::ZERO, bytes);
    let mut buf = [0u8; MAX_FRAME];
    let reply = frontend.poll_transmit(&mut buf).map(|n| buf[..n].to_vec());
    assert_eq!(
        frontend.poll_transmit(&mut buf),
        None,
        "one reply per request"
    );
    reply
}

#[test]
fn every_meb_vector_gets_the_controllers_own_reply() {
    let mut count = 0;
    for line in VECTORS.lines().filter(|l| !l.trim().is_empty()) {
        let v: Vector = serde_json::from_str(line).expect("JSON");
        let mut reference = EvController::new(EvControllerConfig::default());
        reference.handle_bytes(SimTime::ZERO, v.request.as_bytes());
        let mut buf = [0u8; MAX_FRAME];
        let expected = reference
            .poll_transmit(SimTime::ZERO, &mut buf)
            .map(|n| buf[..n].to_vec());
        let mut served = EvController::new(EvControllerConfig::default());
        let mut frontend = SlaveFrontend::new(Framing::Meb, 1);
        let got = reply_of(&mut frontend, &mut served, v.request.as_bytes());
        assert_eq!(got, expected, "{}", v.request.escape_debug());
        assert_eq!(
            served.image().stored,
            reference.image().stored,
            "{}",
            v.request.escape_debug()
        );
        assert_eq!(
            served.image().errs,
            reference.image().errs,
            "{}",
            v.request.escape_debug()
        );
        count += 1;
    }
    assert_eq!(count, 31);
}

#[test]
fn front_ends_share_one_image_and_count_their_drops() {
    let mut controller = EvController::new(EvControllerConfig::default());
    let mut meb = SlaveFrontend::new(Framing::Meb, 1);
    let mut tcp = SlaveFrontend::new(Framing::ModbusTcp, 1);
    let mut rtu = SlaveFrontend::new(Framing::ModbusRtu(SimDuration::from_millis(5)), 1);

    // VEL written over MEB reads back over Modbus TCP (holding register 0).
    assert!(reply_of(&mut meb, &mut controller, b"@01SA000108005A*\n").is_some());
    let mut adu = [0u8; 300];
    let read = Request::ReadHoldingRegisters {
        address: 0,
        quantity: 1,
    };
    let n = modbus::tcp::TcpRepr {
        transaction_id: 77,
        unit: 255,
        pdu: &read,
    }
    .emit(&mut adu)
    .unwrap();
    let reply = reply_of(&mut tcp, &mut controller, &adu[..n]).expect("a reply");
    let frame = modbus::tcp::TcpFrame::new_checked(&reply).unwrap();
    assert_eq!(
        (frame.transaction_id(), frame.unit()),
        (77, 255),
        "unit 255 echoed"
    );
    match frame.response().unwrap() {
        Ok(Response::ReadHoldingRegisters(r)) => assert_eq!(r.as_slice(), &[0x0800]),
        other => panic!("{other:?}"),
    }

    // Two frames in one TCP chunk get two replies, in order.
    let mut two = Vec::new();
    for tid in [1u16, 2] {
        let n = modbus::tcp::TcpRepr {
            transaction_id: tid,
            unit: 1,
            pdu: &read,
        }
        .emit(&mut adu)
        .unwrap();
        two.extend_from_slice(&adu[..n]);
    }
    tcp.handle_bytes(controller.image_mut(), SimTime::ZERO, &two);
    let mut buf = [0u8; MAX_FRAME];
    for tid in [1u16, 2] {
        let n = tcp.poll_transmit(&mut buf).expect("pipelined reply");
        assert_eq!(
            modbus::tcp::TcpFrame::new_checked(&buf[..n])
                .unwrap()
                .transaction_id(),
            tid
        );
    }

    // Garbage on RTU and a bad FCS on MEB both land in the shared ERRS.
    let errs = controller.image().errs;
    let n = modbus::rtu::RtuRepr {
        unit: 1,
        pdu: &read,
    }
    .emit(&mut adu)
    .unwrap();
    adu[n - 1] ^= 0xFF;
    assert_eq!(reply_of(&mut rtu, &mut controller, &adu[..n]), None);
    assert_eq!(reply_of(&mut meb, &mut controller, b"@01EA000100*\n"), None);
    assert_eq!(controller.image().errs, errs + 2);
    assert_eq!(rtu.stats().malformed + meb.stats().malformed, 2);
}

#[test]
fn read_only_and_forced_refusals_answer_in_each_protocol() {
    let mut controller = EvController::new(EvControllerConfig::default());
    let mut meb = SlaveFrontend::new(Framing::Meb, 1);
    meb.set_read_only(true);
    let reply = reply_of(&mut meb, &mut controller, b"@01SA000108005A*\n").unwrap();
    let repr = MebRepr::parse(&reply).unwrap();
    assert_eq!(repr.cmd, MebCmd::ER);
    assert_eq!(controller.image().stored.vel, 0, "not written");
    assert_eq!(meb.stats().read_only_refusals, 1);
    let reply = reply_of(&mut meb, &mut controller, b"@01EA000643*\n").unwrap();
    assert_eq!(
        MebRepr::parse(&reply).unwrap().cmd,
        MebCmd::EA,
        "reads are served"
    );

    let mut ascii = SlaveFrontend::new(Framing::ModbusAscii, 1);
    ascii.set_forced_refusal(Some(Refusal::DeviceFailure));
    let mut adu = [0u8; 600];
    let read = Request::ReadInputRegisters {
        address: 0,
        quantity: 2,
    };
    let n = modbus::ascii::AsciiRepr {
        unit: 1,
        pdu: &read,
    }
    .emit(&mut adu)
    .unwrap();
    let reply = reply_of(&mut ascii, &mut controller, &adu[..n]).unwrap();
    let mut scratch = [0u8; modbus::ascii::MAX_BINARY_LEN];
    let frame = modbus::ascii::AsciiFrame::decode_line(&reply, &mut scratch).unwrap();
    let e = frame.response().unwrap().expect_err("an exception");
    assert_eq!(e.exception, Exception::ServerDeviceFailure);
}

#[test]
fn an_io_map_moves_signals_and_keeps_the_checks() {
    use nodes::firmware::MebMap;
    let mut map = MebMap::default();
    map.clear_block("EA");
    map.place("EA", "V1", 0, None).unwrap();
    map.place("EA", "RPM_M", 1, None).unwrap();
    map.clear_block("SD");
    map.place("SD", "EN", 0, Some(4)).unwrap();
    map.place("SD", "FR", 0, Some(0)).unwrap();
    // Mistakes are refused with the reason.
    assert!(
        map.place("EA", "VEL", 3, None)
            .unwrap_err()
            .to_string()
            .contains("belongs in SA")
    );
    assert!(
        map.place("EA", "V2", 0, None)
            .unwrap_err()
            .to_string()
            .contains("share EA 0 with `V1`")
    );
    assert!(
        map.place("SD", "BRK", 0, None)
            .unwrap_err()
            .to_string()
            .contains("WORD.BIT")
    );
    assert!(
        map.place("EA", "FOO", 3, None)
            .unwrap_err()
            .to_string()
            .contains("unknown signal")
    );

    let mut controller = EvController::new(EvControllerConfig::default());
    controller.image_mut().inputs = [11, 22, 33, 44, 55, 66];
    let mut meb = SlaveFrontend::new(Framing::Meb, 1);
    meb.set_meb_map(Some(map));
    let reply = reply_of(&mut meb, &mut controller, b"@01EA000247*\n").expect("a reply");
    assert_eq!(
        MebRepr::parse(&reply).unwrap().data.as_slice(),
        &[33, 44],
        "V1 then RPM_M"
    );
    // EA holds two words now: a third is past the block (ER 02).
    let reply = reply_of(&mut meb, &mut controller, b"@01EA000346*\n").unwrap();
    assert_eq!(MebRepr::parse(&reply).unwrap().cmd, MebCmd::ER);
    // SD word 0: bit 4 low enables, bit 0 high turns counter-clockwise.
    let reply = reply_of(&mut meb, &mut controller, b"@01SD0001000156*\n").unwrap();
    assert_eq!(
        MebRepr::parse(&reply).unwrap().cmd,
        MebCmd::SD,
        "{}",
        String::from_utf8_lossy(&reply)
    );
    let sd0 = controller.image().stored.sd0;
    assert_eq!(sd0 & 0b1, 0, "EN applied (active low): {sd0:#06x}");
    assert_eq!(sd0 & 0b1_0000, 0b1_0000, "FR set: {sd0:#06x}");
}

/// A CRC-valid RTU request whose byte count does not match its quantity is
/// a whole frame with a bad value: exception 03, as over Modbus TCP.
#[test]
fn a_write_whose_count_and_quantity_disagree_gets_exception_03_on_rtu_and_tcp() {
    // Write multiple registers at 0: quantity 2 with a byte count of 2,
    // quantity 1 with a count of 4 (the data as long as the count says).
    for pdu in [
        &[0x10, 0x00, 0x00, 0x00, 0x02, 0x02, 0x12, 0x34][..],
        &[0x10, 0x00, 0x00, 0x00, 0x01, 0x04, 0x12, 0x34, 0x56, 0x78],
        &[0x0F, 0x00, 0x00, 0x00, 0x09, 0x01, 0xFF],
    ] {
        mismatched_write(pdu);
    }
}

fn mismatched_write(pdu: &[u8]) {
    let mut rtu = vec![0x01];
    rtu.extend_from_slice(pdu);
    let crc = protocols::crc::crc16_modbus(&rtu);
    rtu.extend_from_slice(&crc.to_le_bytes());
    let mut tcp = vec![0x00, 0x01, 0x00, 0x00, 0x00, 1 + pdu.len() as u8, 0x01];
    tcp.extend_from_slice(pdu);
    for (framing, bytes) in [
        (Framing::ModbusRtu(SimDuration::from_millis(5)), rtu),
        (Framing::ModbusTcp, tcp),
    ] {
        let mut controller = EvController::new(EvControllerConfig::default());
        let mut frontend = SlaveFrontend::new(framing, 1);
        let reply = reply_of(&mut frontend, &mut controller, &bytes);
        let reply = reply.unwrap_or_else(|| panic!("{framing:?}: no reply"));
        let got = match framing {
            Framing::ModbusTcp => &reply[7..],
            _ => &reply[1..reply.len() - 2],
        };
        assert_eq!(got, [pdu[0] | 0x80, 0x03], "{framing:?} {pdu:02x?}");
    }
}
