//! Standard Modbus frames cross-checked against an implementation we did not
//! write: pymodbus 3.x (PyPI), run as `python3 tests/pymodbus/check.py`.
//!
//! For every function code (request and reply) and exception replies, over
//! RTU, ASCII and TCP framing, both ways: pymodbus' framers and PDU decoders
//! read the frames we emit and must find the same fields, and frames pymodbus
//! builds from those fields must parse here to the same values (and are
//! compared byte for byte with ours).
//!
//! This test fails, rather than skips, when python3 or pymodbus is missing.

use std::io::Write;
use std::process::{Command, Stdio};

use protocols::modbus::{
    Adu, Bits, EncodePdu, Exception, ExceptionResponse, Registers, Request, Response, ascii, rtu,
    tcp,
};
use serde_json::{Value, json};

const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/pymodbus/check.py");
const PYMODBUS: &str = "pymodbus==3.16.1";

#[derive(Debug, Clone, Copy, PartialEq)]
enum Framing {
    Rtu,
    Ascii,
    Tcp,
}

impl Framing {
    fn pymodbus_name(self) -> &'static str {
        match self {
            Framing::Rtu => "rtu",
            Framing::Ascii => "ascii",
            Framing::Tcp => "socket",
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
enum Pdu {
    Request(Request),
    Reply(Result<Response, ExceptionResponse>),
}

#[derive(Debug)]
struct Case {
    framing: Framing,
    unit: u8,
    tid: u16,
    pdu: Pdu,
}

impl Case {
    fn kind(&self) -> &'static str {
        match self.pdu {
            Pdu::Request(_) => "request",
            Pdu::Reply(_) => "response",
        }
    }

    fn emit(&self) -> Vec<u8> {
        let mut out = vec![0u8; 600];
        let n = match &self.pdu {
            Pdu::Request(r) => frame(self.framing, self.tid, self.unit, r, &mut out),
            Pdu::Reply(r) => frame(self.framing, self.tid, self.unit, r, &mut out),
        };
        out.truncate(n);
        out
    }

    /// Reads a frame with our codec: unit, transaction id (0 on serial), PDU value.
    fn parse(&self, bytes: &[u8]) -> (u8, u16, Pdu) {
        let mut scratch = [0u8; ascii::MAX_BINARY_LEN];
        let (unit, tid, pdu) = match self.framing {
            Framing::Rtu => {
                let f = rtu::RtuFrame::new_checked(bytes).expect("RTU frame");
                (f.unit(), 0, f.pdu())
            }
            Framing::Ascii => {
                let f = ascii::AsciiFrame::decode_line(bytes, &mut scratch).expect("ASCII frame");
                (f.unit(), 0, f.pdu())
            }
            Framing::Tcp => {
                let f = tcp::TcpFrame::new_checked(bytes).expect("TCP frame");
                (f.unit(), f.transaction_id(), f.pdu())
            }
        };
        let value = match self.pdu {
            Pdu::Request(_) => Pdu::Request(Request::parse(pdu).expect("request PDU")),
            Pdu::Reply(_) => Pdu::Reply(Response::parse(pdu).expect("reply PDU")),
        };
        (unit, tid, value)
    }

    /// The fields pymodbus should read from this frame, named as its PDU
    /// classes name them.
    fn fields(&self) -> Value {
        let bools = |b: &Bits| b.iter().map(u8::from).collect::<Vec<_>>();
        let mut f = match &self.pdu {
            Pdu::Request(r) => match r {
                Request::ReadCoils { address, quantity }
                | Request::ReadDiscreteInputs { address, quantity }
                | Request::ReadHoldingRegisters { address, quantity }
                | Request::ReadInputRegisters { address, quantity } => {
                    json!({"address": address, "count": quantity})
                }
                Request::WriteSingleCoil { address, value } => {
                    json!({"address": address, "bits": [u8::from(*value)]})
                }
                Request::WriteSingleRegister { address, value } => {
                    json!({"address": address, "registers": [value]})
                }
                Request::WriteMultipleCoils { address, coils } => {
                    json!({"address": address, "count": coils.quantity(), "bits": bools(coils)})
                }
                Request::WriteMultipleRegisters { address, registers } => json!({
                    "address": address,
                    "count": registers.len(),
                    "registers": registers.as_slice(),
                }),
            },
            Pdu::Reply(Ok(r)) => match r {
                Response::ReadCoils(bits) | Response::ReadDiscreteInputs(bits) => {
                    json!({"bits": bools(bits)})
                }
                Response::ReadHoldingRegisters(regs) | Response::ReadInputRegisters(regs) => {
                    json!({"registers": regs.as_slice()})
                }
                Response::WriteSingleCoil { address, value } => {
                    json!({"address": address, "bits": [u8::from(*value)]})
                }
                Response::WriteSingleRegister { address, value } => {
                    json!({"address": address, "registers": [value]})
                }
                Response::WriteMultipleCoils { address, quantity }
                | Response::WriteMultipleRegisters { address, quantity } => {
                    json!({"address": address, "count": quantity})
                }
            },
            Pdu::Reply(Err(e)) => json!({"exception_code": e.exception.code()}),
        };
        let fc = match &self.pdu {
            Pdu::Request(r) => r.function(),
            Pdu::Reply(Ok(r)) => r.function(),
            Pdu::Reply(Err(e)) => e.function | 0x80,
        };
        let map = f.as_object_mut().expect("object");
        map.insert("fc".into(), json!(fc));
        map.insert("dev_id".into(), json!(self.unit));
        map.insert("tid".into(), json!(self.tid));
        f
    }
}

fn frame(
    framing: Framing,
    tid: u16,
    unit: u8,
    pdu: &(impl EncodePdu + ?Sized),
    out: &mut [u8],
) -> usize {
    match framing {
        Framing::Rtu => rtu::RtuRepr { unit, pdu }.emit(out),
        Framing::Ascii => ascii::AsciiRepr { unit, pdu }.emit(out),
        Framing::Tcp => tcp::TcpRepr {
            transaction_id: tid,
            unit,
            pdu,
        }
        .emit(out),
    }
    .expect("emit")
}

fn bits(values: &[bool]) -> Bits {
    Bits::from_bools(values).unwrap()
}

fn regs(values: &[u16]) -> Registers {
    Registers::from_slice(values).unwrap()
}

/// Every function code, request and reply, at ordinary and limit sizes, and
/// exceptions 01–04 for every function code.
fn pdus() -> Vec<Pdu> {
    let coils37: Vec<bool> = (0..37).map(|i| i % 3 == 0).collect();
    let coils1968: Vec<bool> = (0..1968).map(|i| i % 7 < 3).collect();
    let regs123: Vec<u16> = (0..123).map(|i| i * 517).collect();
    let regs125: Vec<u16> = (0..125).map(|i| 0xFFFF - i * 3).collect();
    let packed250: Vec<u8> = (0..250).map(|i| (i * 37) as u8).collect();
    let mut pdus = vec![
        Pdu::Request(Request::ReadCoils {
            address: 0x13,
            quantity: 37,
        }),
        Pdu::Request(Request::ReadCoils {
            address: 0,
            quantity: 2000,
        }),
        Pdu::Request(Request::ReadDiscreteInputs {
            address: 0xC4,
            quantity: 22,
        }),
        Pdu::Request(Request::ReadHoldingRegisters {
            address: 0x6B,
            quantity: 3,
        }),
        Pdu::Request(Request::ReadHoldingRegisters {
            address: 0xFF00,
            quantity: 125,
        }),
        Pdu::Request(Request::ReadInputRegisters {
            address: 8,
            quantity: 1,
        }),
        Pdu::Request(Request::WriteSingleCoil {
            address: 0xAC,
            value: true,
        }),
        Pdu::Request(Request::WriteSingleCoil {
            address: 1,
            value: false,
        }),
        Pdu::Request(Request::WriteSingleRegister {
            address: 1,
            value: 0xBEEF,
        }),
        Pdu::Request(Request::WriteMultipleCoils {
            address: 0x13,
            coils: bits(&coils37),
        }),
        Pdu::Request(Request::WriteMultipleCoils {
            address: 0,
            coils: bits(&coils1968),
        }),
        Pdu::Request(Request::WriteMultipleRegisters {
            address: 1,
            registers: regs(&[10, 258]),
        }),
        Pdu::Request(Request::WriteMultipleRegisters {
            address: 2,
            registers: regs(&regs123),
        }),
        Pdu::Reply(Ok(Response::ReadCoils(
            Bits::from_packed(&[0xCD, 0x6B, 0x05], 24).unwrap(),
        ))),
        Pdu::Reply(Ok(Response::ReadCoils(
            Bits::from_packed(&packed250, 2000).unwrap(),
        ))),
        Pdu::Reply(Ok(Response::ReadDiscreteInputs(
            Bits::from_packed(&[0xAC, 0xDB, 0x35], 24).unwrap(),
        ))),
        Pdu::Reply(Ok(Response::ReadHoldingRegisters(regs(&[0x022B, 0, 0x64])))),
        Pdu::Reply(Ok(Response::ReadHoldingRegisters(regs(&regs125)))),
        Pdu::Reply(Ok(Response::ReadInputRegisters(regs(&[0x000A])))),
        Pdu::Reply(Ok(Response::WriteSingleCoil {
            address: 0xAC,
            value: true,
        })),
        Pdu::Reply(Ok(Response::WriteSingleRegister {
            address: 1,
            value: 3,
        })),
        Pdu::Reply(Ok(Response::WriteMultipleCoils {
            address: 0x13,
            quantity: 10,
        })),
        Pdu::Reply(Ok(Response::WriteMultipleRegisters {
            address: 1,
            quantity: 2,
        })),
    ];
    for function in [1u8, 2, 3, 4, 5, 6, 15, 16] {
        for code in 1..=4 {
            pdus.push(Pdu::Reply(Err(ExceptionResponse {
                function,
                exception: Exception::from_code(code),
            })));
        }
    }
    pdus
}

fn cases() -> Vec<Case> {
    let mut cases = Vec::new();
    for framing in [Framing::Rtu, Framing::Ascii, Framing::Tcp] {
        for (i, pdu) in pdus().into_iter().enumerate() {
            let i = i as u16;
            cases.push(Case {
                framing,
                unit: (1 + i * 13 % 247) as u8,
                // Serial framings have no transaction id; pymodbus reads 0.
                tid: if framing == Framing::Tcp {
                    0x1200 + i * 257
                } else {
                    0
                },
                pdu,
            });
        }
    }
    cases
}

/// Runs the pymodbus script over every case; one JSON reply per case.
fn run_pymodbus(cases: &[Case]) -> Vec<Value> {
    let mut child = Command::new("python3")
        .arg(SCRIPT)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| {
            panic!("cannot run python3 ({e}): install Python 3, then `pip install {PYMODBUS}`")
        });
    let mut input = String::new();
    for case in cases {
        let line = json!({
            "framer": case.framing.pymodbus_name(),
            "kind": case.kind(),
            "hex": hex(&case.emit()),
            "pdu": case.fields(),
        });
        input.push_str(&line.to_string());
        input.push('\n');
    }
    let mut stdin = child.stdin.take().expect("stdin");
    let writer = std::thread::spawn(move || stdin.write_all(input.as_bytes()));
    let output = child.wait_with_output().expect("python3 output");
    writer.join().expect("writer thread").expect("write cases");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "pymodbus cross-check could not run ({}): {stderr}\nCI installs it with `pip install {PYMODBUS}`",
        output.status
    );
    let replies: Vec<Value> = String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("JSON from check.py"))
        .collect();
    assert_eq!(
        replies.len(),
        cases.len(),
        "one reply per case; stderr: {stderr}"
    );
    replies
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(text: &str) -> Vec<u8> {
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).expect("hex from pymodbus"))
        .collect()
}

#[test]
fn pymodbus_agrees_with_our_frames_both_ways() {
    let cases = cases();
    let replies = run_pymodbus(&cases);
    let mut checked_fields = 0;
    for (case, reply) in cases.iter().zip(&replies) {
        let ours = case.emit();
        let what = format!("{:?} {} {:?}", case.framing, hex(&ours), case.pdu);

        // pymodbus reads our frame to the same fields.
        let decoded = &reply["decoded"];
        assert!(
            decoded.get("error").is_none(),
            "{what}: pymodbus: {decoded}"
        );
        let expected = case.fields();
        for (key, want) in expected.as_object().expect("object") {
            assert_eq!(&decoded[key], want, "{what}: field {key}");
            checked_fields += 1;
        }

        // We read pymodbus' frame to the same value, and it is our frame.
        let built = reply["built_hex"]
            .as_str()
            .unwrap_or_else(|| panic!("{what}: pymodbus could not build: {reply}"));
        let theirs = unhex(built);
        assert_eq!(
            case.parse(&theirs),
            (case.unit, case.tid, case.pdu.clone()),
            "{what}"
        );
        assert_eq!(hex(&theirs), hex(&ours), "{what}: byte-for-byte");
    }
    // Guard against a silently empty run.
    assert!(cases.len() >= 3 * 50, "{} cases", cases.len());
    assert!(checked_fields > cases.len() * 4, "{checked_fields} fields");
}
