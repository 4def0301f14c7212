//! Whatever comes back on the wire, the supervisor neither panics nor loses
//! count: every request ends in exactly one outcome, the output stays in the
//! DAC range, and it always knows when to wake next, never in the past.

use nodes::master::{Protocol, SetPointStep, SlaveLoopConfig, Supervisor, SupervisorConfig};
use nodes::node::{MAX_FRAME, Node};
use proptest::prelude::*;
use protocols::meb::{MebCmd, MebRepr, MebWords};
use protocols::modbus::{Adu, ExceptionResponse, Registers, Response, rtu};
use protocols::time::{SimDuration, SimTime};

/// What the fake slave does with one request.
#[derive(Debug, Clone)]
enum Answer {
    /// Nothing: the master times out.
    Silence,
    /// The right reply, with these six inputs.
    Inputs([u16; 6]),
    /// The right reply with one byte flipped.
    Corrupted([u16; 6], usize, u8),
    /// Arbitrary bytes, in chunks.
    Noise(Vec<Vec<u8>>),
}

fn answer() -> impl Strategy<Value = Answer> {
    prop_oneof![
        Just(Answer::Silence),
        any::<[u16; 6]>().prop_map(Answer::Inputs),
        (any::<[u16; 6]>(), any::<usize>(), 1..=255u8)
            .prop_map(|(words, at, mask)| Answer::Corrupted(words, at, mask)),
        prop::collection::vec(prop::collection::vec(any::<u8>(), 0..40), 1..4)
            .prop_map(Answer::Noise),
    ]
}

fn reply_to(protocol: Protocol, request: &[u8], words: [u16; 6]) -> Vec<u8> {
    let mut out = [0u8; MAX_FRAME];
    match protocol {
        Protocol::Meb => {
            let request = MebRepr::parse(request).unwrap();
            let data = if request.cmd == MebCmd::EA {
                MebWords::from_slice(&words).unwrap()
            } else {
                MebWords::new()
            };
            let n = MebRepr { data, ..request }.emit(&mut out).unwrap();
            out[..n].to_vec()
        }
        Protocol::ModbusRtu => {
            let frame = rtu::RtuFrame::new_checked(request).unwrap();
            let response = match frame.request().unwrap() {
                protocols::modbus::Request::ReadInputRegisters { .. } => {
                    Response::ReadInputRegisters(Registers::from_slice(&words).unwrap())
                }
                protocols::modbus::Request::WriteSingleRegister { address, value } => {
                    Response::WriteSingleRegister { address, value }
                }
                protocols::modbus::Request::WriteMultipleCoils { address, coils } => {
                    Response::WriteMultipleCoils {
                        address,
                        quantity: coils.quantity(),
                    }
                }
                other => panic!("unexpected request {other:?}"),
            };
            let reply: Result<Response, ExceptionResponse> = Ok(response);
            let n = rtu::RtuRepr {
                unit: 1,
                pdu: &reply,
            }
            .emit(&mut out)
            .unwrap();
            out[..n].to_vec()
        }
    }
}

fn check(protocol: Protocol, answers: &[Answer]) -> Result<(), TestCaseError> {
    let slave = SlaveLoopConfig {
        kp: 0.3,
        ki: 1.0,
        set_points: vec![SetPointStep {
            at: SimTime::ZERO,
            rpm: 2500.0,
        }],
        ..SlaveLoopConfig::new(1)
    };
    let mut master = Supervisor::new(SupervisorConfig::new(protocol, vec![slave])).unwrap();
    let byte = SimDuration::bit_times(10, 115_200);
    let mut now = SimTime::ZERO;
    let mut buf = [0u8; MAX_FRAME];
    for answer in answers {
        // Wake the master until it sends.
        let request = loop {
            if let Some(n) = master.poll_transmit(now, &mut buf) {
                break buf[..n].to_vec();
            }
            let at = master.poll_timeout();
            prop_assert!(at.is_some_and(|at| at >= now), "{at:?} at {now:?}");
            now = at.unwrap_or(now);
            master.handle_timeout(now);
        };
        now += SimDuration(byte.0 * request.len() as u64);
        master.transmit_done(now);
        now += SimDuration::from_millis(1);
        match answer {
            Answer::Silence => {}
            Answer::Inputs(words) => {
                master.handle_bytes(now, &reply_to(protocol, &request, *words))
            }
            Answer::Corrupted(words, at, mask) => {
                let mut reply = reply_to(protocol, &request, *words);
                let at = at % reply.len();
                reply[at] ^= mask;
                master.handle_bytes(now, &reply);
            }
            Answer::Noise(chunks) => {
                for chunk in chunks {
                    now += SimDuration(byte.0 * chunk.len() as u64);
                    master.handle_bytes(now, chunk);
                }
            }
        }
        let state = master.loop_state(1).unwrap();
        let c = state.counters;
        let ended = c.replies + c.timeouts + c.bad_checks + c.exceptions;
        // At most the request just answered (or not) is still open.
        prop_assert!(c.requests == ended || c.requests == ended + 1, "{c:?}");
        prop_assert!(c.retries <= c.requests && c.lost <= c.requests, "{c:?}");
        prop_assert!(state.output <= 4095);
        prop_assert!((0.0..=4095.0).contains(&state.integral));
    }
    Ok(())
}

proptest! {
    #[test]
    fn meb_survives_any_reply(answers in prop::collection::vec(answer(), 1..40)) {
        check(Protocol::Meb, &answers)?;
    }

    #[test]
    fn rtu_survives_any_reply(answers in prop::collection::vec(answer(), 1..40)) {
        check(Protocol::ModbusRtu, &answers)?;
    }
}
