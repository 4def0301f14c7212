//! The `[[request]]` tables: a master's scripted frames. Each is sent by a
//! `controller-network-master` of the scenario, within the run, and its
//! `send` is the six bytes of an 8-byte Modbus frame before its CRC,
//! written in hex as a check suite's `send`. Errors name the field as
//! `field@request#N` (the N-th `[[request]]`), so the message points at
//! its line.

use protocols::hex;
use protocols::modbus8::Modbus8Repr;

use super::{MasterProgramSpec, NodeSpec, REQUEST_OWNER, Scenario, check::shown};

/// A field (`field@owner`) and what is wrong with it.
type Fault = (String, String);

/// The frame a request's `send` spells (six bytes: id, function, address,
/// value), or why it is none.
pub fn frame(send: &str) -> Result<Modbus8Repr, String> {
    let bytes = hex::bytes(send).map_err(|e| e.to_string())?;
    match bytes[..] {
        [id, function, a0, a1, v0, v1] => Ok(Modbus8Repr {
            id,
            function,
            addr: u16::from_be_bytes([a0, a1]),
            value: u16::from_be_bytes([v0, v1]),
        }),
        _ => Err(format!(
            "`{send}` is {} bytes: an 8-byte Modbus frame is six bytes (id, function, \
             address, value) before its CRC, which the master adds",
            bytes.len()
        )),
    }
}

/// Checks every `[[request]]`, and that a master told to send only its
/// requests has some.
pub fn check(s: &Scenario) -> Result<(), Fault> {
    for (i, r) in s.requests.iter().enumerate() {
        let at = |field: &str, why: String| Err((format!("{field}@{REQUEST_OWNER}{i}"), why));
        let Some(node) = s.nodes.iter().find(|n| n.name() == r.node) else {
            return at(
                "node",
                format!(
                    "`{}` of a request is not a declared node: a request is sent by a \
                     controller-network-master",
                    r.node
                ),
            );
        };
        if !matches!(node, NodeSpec::ControllerNetworkMaster { .. }) {
            return at(
                "node",
                format!(
                    "`{}` of a request is not a controller-network-master: scripted requests \
                     are 8-byte Modbus frames, sent by the Controller_network project's master",
                    r.node
                ),
            );
        }
        if !(r.at_s.is_finite() && (0.0..s.duration_s).contains(&r.at_s)) {
            return at(
                "at_s",
                format!(
                    "of the request from `{}` must be from 0 up to the run's duration_s ({}), \
                     got {}",
                    r.node,
                    shown(s.duration_s),
                    shown(r.at_s)
                ),
            );
        }
        if let Err(why) = frame(&r.send) {
            return at("send", format!("of the request from `{}`: {why}", r.node));
        }
    }
    for n in &s.nodes {
        if let NodeSpec::ControllerNetworkMaster {
            name,
            program: MasterProgramSpec::Requests,
            ..
        } = n
            && !s.requests.iter().any(|r| &r.node == name)
        {
            return Err((
                format!("program@{name}"),
                format!(
                    "of node `{name}` is `requests`, but no [[request]] names it: it would \
                     send nothing"
                ),
            ));
        }
    }
    Ok(())
}
