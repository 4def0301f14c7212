//! The EV controller as a Modbus RTU slave: the map of `docs/protocols/modbus-map.md`,
//! its reads, writes and exceptions, checked through real RTU frames.

use nodes::firmware::{EvController, EvControllerConfig, SlaveProtocol};
use nodes::node::{Firmware, MAX_FRAME, Node};
use plant::Sensors;
use protocols::modbus::Adu;
use protocols::modbus::rtu;
use protocols::modbus::{
    Bits, EncodePdu, Exception, ExceptionResponse, Registers, Request, Response,
};
use protocols::time::{SimDuration, SimTime};

fn controller() -> EvController {
    EvController::new(EvControllerConfig {
        protocol: SlaveProtocol::ModbusRtu,
        ..EvControllerConfig::default()
    })
}

fn frame(unit: u8, pdu: &(impl EncodePdu + ?Sized)) -> Vec<u8> {
    let mut buf = [0u8; 256];
    let len = rtu::RtuRepr { unit, pdu }.emit(&mut buf).unwrap();
    buf[..len].to_vec()
}

fn transmitted(c: &mut EvController, now: SimTime) -> Option<Vec<u8>> {
    let mut buf = [0u8; MAX_FRAME];
    c.poll_transmit(now, &mut buf)
        .map(|len| buf[..len].to_vec())
}

/// Sends `request` to `unit` and parses the reply, if any.
fn ask_unit(
    c: &mut EvController,
    unit: u8,
    request: &Request,
) -> Option<Result<Response, ExceptionResponse>> {
    c.handle_bytes(SimTime::ZERO, &frame(unit, request));
    let reply = transmitted(c, SimTime::ZERO)?;
    let parsed = rtu::RtuFrame::new_checked(&reply).expect("reply checks");
    assert_eq!(parsed.unit(), 1, "reply carries the slave's unit id");
    Some(parsed.response().expect("reply parses"))
}

fn ask(c: &mut EvController, request: &Request) -> Result<Response, ExceptionResponse> {
    ask_unit(c, 1, request).expect("a reply")
}

fn exception(c: &mut EvController, request: &Request) -> Exception {
    match ask(c, request) {
        Err(e) => {
            assert_eq!(e.function, request.function());
            e.exception
        }
        Ok(r) => panic!("{request:?} answered {r:?}"),
    }
}

fn input_registers(c: &mut EvController, address: u16, quantity: u16) -> Vec<u16> {
    match ask(c, &Request::ReadInputRegisters { address, quantity }) {
        Ok(Response::ReadInputRegisters(r)) => r.as_slice().to_vec(),
        other => panic!("{other:?}"),
    }
}

fn holding_registers(c: &mut EvController) -> Vec<u16> {
    match ask(
        c,
        &Request::ReadHoldingRegisters {
            address: 0,
            quantity: 3,
        },
    ) {
        Ok(Response::ReadHoldingRegisters(r)) => r.as_slice().to_vec(),
        other => panic!("{other:?}"),
    }
}

fn coils(c: &mut EvController) -> Vec<bool> {
    match ask(
        c,
        &Request::ReadCoils {
            address: 0,
            quantity: 9,
        },
    ) {
        Ok(Response::ReadCoils(bits)) => bits.iter().take(9).collect(),
        other => panic!("{other:?}"),
    }
}

fn sensors() -> Sensors {
    let mut s = Sensors {
        bus_counts: 3100,
        current_counts: 2050,
        battery_counts: 3000,
        ldr_counts: 3280,
        soc: 0.8,
        ..Sensors::default()
    };
    s.shaft.hall = 0b101;
    s.shaft.last_hall_edge_at = f64::NAN;
    s
}

#[test]
fn input_registers_hold_the_sampled_values() {
    let mut c = controller();
    assert_eq!(
        input_registers(&mut c, 0, 10),
        vec![0; 10],
        "nothing sampled yet"
    );
    c.loop_tick(SimTime::ZERO, &sensors());
    let values = input_registers(&mut c, 0, 10);
    // V2, I, V1, RPM_M, RPM_L, LDR, HALL, SOC, ERRS, STATUS (FR high at
    // power-up: counter-clockwise).
    assert_eq!(
        values,
        vec![3100, 2050, 3000, 0, 0, 3280, 0b101, 800, 0, 0b10_0000]
    );
    assert_eq!(
        exception(
            &mut c,
            &Request::ReadInputRegisters {
                address: 9,
                quantity: 2
            }
        ),
        Exception::IllegalDataAddress
    );
    assert_eq!(
        exception(
            &mut c,
            &Request::ReadInputRegisters {
                address: 10,
                quantity: 1
            }
        ),
        Exception::IllegalDataAddress
    );
}

#[test]
fn holding_registers_read_write_and_range() {
    let mut c = controller();
    let threshold = EvControllerConfig::default().light.threshold_counts;
    assert_eq!(holding_registers(&mut c), vec![0, threshold, 100]);
    let write = Request::WriteSingleRegister {
        address: 0,
        value: 2048,
    };
    assert_eq!(
        ask(&mut c, &write),
        Ok(Response::WriteSingleRegister {
            address: 0,
            value: 2048
        })
    );
    let many = Request::WriteMultipleRegisters {
        address: 1,
        registers: Registers::from_slice(&[1000, 50]).unwrap(),
    };
    assert_eq!(
        ask(&mut c, &many),
        Ok(Response::WriteMultipleRegisters {
            address: 1,
            quantity: 2
        })
    );
    assert_eq!(holding_registers(&mut c), vec![2048, 1000, 50]);
    for (address, value) in [(0, 4096), (1, 4096), (2, 0), (2, 1001)] {
        let request = Request::WriteSingleRegister { address, value };
        assert_eq!(
            exception(&mut c, &request),
            Exception::IllegalDataValue,
            "{request:?}"
        );
    }
    // One bad value refuses the whole write.
    let mixed = Request::WriteMultipleRegisters {
        address: 0,
        registers: Registers::from_slice(&[10, 20, 0]).unwrap(),
    };
    assert_eq!(exception(&mut c, &mixed), Exception::IllegalDataValue);
    assert_eq!(holding_registers(&mut c), vec![2048, 1000, 50]);
    let past = Request::WriteSingleRegister {
        address: 3,
        value: 1,
    };
    assert_eq!(exception(&mut c, &past), Exception::IllegalDataAddress);
    let long = Request::WriteMultipleRegisters {
        address: 2,
        registers: Registers::from_slice(&[1, 1]).unwrap(),
    };
    assert_eq!(exception(&mut c, &long), Exception::IllegalDataAddress);
}

#[test]
fn coils_are_the_active_low_pins_with_holes() {
    let mut c = controller();
    // Power-up: EN..FR and CHG high (off), holes 0, LDR_ADAPT 0.
    assert_eq!(
        coils(&mut c),
        vec![true, true, true, true, true, true, false, false, false]
    );
    let enable = Request::WriteSingleCoil {
        address: 0,
        value: false,
    };
    assert_eq!(
        ask(&mut c, &enable),
        Ok(Response::WriteSingleCoil {
            address: 0,
            value: false
        })
    );
    assert_eq!(c.image().stored.sd0, 0x001E);
    let adaptive = Request::WriteSingleCoil {
        address: 8,
        value: true,
    };
    assert!(ask(&mut c, &adaptive).is_ok());
    assert_eq!(c.image().stored.ldr_adaptive, 1);
    // FR and CHG together: FR coil 4 on, CHG coil 5 off (charger connected).
    let several = Request::WriteMultipleCoils {
        address: 3,
        coils: Bits::from_bools(&[true, true, false]).unwrap(),
    };
    assert_eq!(
        ask(&mut c, &several),
        Ok(Response::WriteMultipleCoils {
            address: 3,
            quantity: 3
        })
    );
    assert_eq!((c.image().stored.sd0, c.image().stored.sd1), (0x001E, 0));
    assert_eq!(
        coils(&mut c),
        vec![false, true, true, true, true, false, false, false, true]
    );
    for address in [6, 7, 9] {
        let hole = Request::WriteSingleCoil {
            address,
            value: true,
        };
        assert_eq!(
            exception(&mut c, &hole),
            Exception::IllegalDataAddress,
            "{address}"
        );
    }
    let across_hole = Request::WriteMultipleCoils {
        address: 5,
        coils: Bits::from_bools(&[true, false, false, true]).unwrap(),
    };
    assert_eq!(
        exception(&mut c, &across_hole),
        Exception::IllegalDataAddress
    );
    assert_eq!(c.image().stored.sd1, 0, "a refused write stores nothing");
    let past = Request::ReadCoils {
        address: 0,
        quantity: 10,
    };
    assert_eq!(exception(&mut c, &past), Exception::IllegalDataAddress);
}

#[test]
fn discrete_inputs_mirror_status_and_halls() {
    let mut c = controller();
    let mut s = sensors();
    s.charging = true;
    s.brake_applied = true;
    c.loop_tick(SimTime::ZERO, &s);
    let request = Request::ReadDiscreteInputs {
        address: 0,
        quantity: 12,
    };
    let Ok(Response::ReadDiscreteInputs(bits)) = ask(&mut c, &request) else {
        panic!("no discrete inputs");
    };
    let bits: Vec<bool> = bits.iter().take(12).collect();
    // brake (2), charging (4), FR high (5); halls A and C (0b101); flag not seen (lit).
    let expected = [
        false, false, true, false, true, true, false, false, true, false, true, false,
    ];
    assert_eq!(bits, expected);
    let past = Request::ReadDiscreteInputs {
        address: 11,
        quantity: 2,
    };
    assert_eq!(exception(&mut c, &past), Exception::IllegalDataAddress);
}

#[test]
fn unit_filter_broadcast_bad_crc_and_unknown_function() {
    let mut c = controller();
    let read = Request::ReadHoldingRegisters {
        address: 0,
        quantity: 1,
    };
    assert_eq!(ask_unit(&mut c, 2, &read), None, "another unit: silence");
    assert_eq!(ask_unit(&mut c, 0, &read), None, "broadcast read: silence");
    let vel = Request::WriteSingleRegister {
        address: 0,
        value: 300,
    };
    assert_eq!(ask_unit(&mut c, 0, &vel), None, "broadcast write: silence");
    assert_eq!(c.image().stored.vel, 300, "but applied");
    let mut bad = frame(1, &read);
    bad[2] ^= 0x40;
    c.handle_bytes(SimTime::ZERO, &bad);
    assert_eq!(transmitted(&mut c, SimTime::ZERO), None, "bad CRC: silence");
    // The decoder discards what follows a bad frame until the line is quiet.
    let later = SimTime::ZERO + SimDuration::from_millis(10);
    c.handle_timeout(later);
    assert_eq!(c.image().errs, 1, "ERRS counts the bad frame");

    // Function 0x2B: delimited by silence, answered with exception 01.
    c.handle_bytes(later, &frame(1, &[0x2Bu8, 0x0E, 0x01, 0x00][..]));
    assert_eq!(transmitted(&mut c, later), None);
    let due = c.poll_timeout().expect("waits for the silence");
    c.handle_timeout(due);
    let reply = transmitted(&mut c, due).expect("exception reply");
    assert_eq!(reply, frame(1, &[0xABu8, 0x01][..]));
}

#[test]
fn writes_apply_at_the_next_tick_and_enabling_during_a_trip_fails() {
    let mut c = controller();
    let t = SimTime::ZERO;
    assert!(
        ask(
            &mut c,
            &Request::WriteSingleRegister {
                address: 0,
                value: 4095
            }
        )
        .is_ok()
    );
    assert!(
        ask(
            &mut c,
            &Request::WriteSingleCoil {
                address: 0,
                value: false
            }
        )
        .is_ok()
    );
    let act = c.loop_tick(t, &sensors());
    assert!(act.enable);
    assert!((act.vel_volts - 5.0).abs() < 1e-12);

    // The inverter trips with current still flowing: latched, outputs off.
    let mut tripped = sensors();
    tripped.motor_tripped = true;
    tripped.motor_current = 15.0;
    let act = c.loop_tick(t + SimDuration::from_millis(1), &tripped);
    assert!(!act.enable && act.vel_volts == 0.0);
    // Over-current latched; the forced-off FR pin reads counter-clockwise.
    assert_eq!(input_registers(&mut c, 9, 1), vec![0b10_0010]);
    let enable = Request::WriteSingleCoil {
        address: 0,
        value: false,
    };
    assert_eq!(exception(&mut c, &enable), Exception::ServerDeviceFailure);
}
