//! The `[[fault]]` tables: each kind's own fields, and whether the node it
//! names can have it. Errors name the field as `field@fault#N` (the N-th
//! `[[fault]]`), so the message points at its line.

use super::{FAULT_OWNER, FaultKind, FaultSpec, NodeSpec, ProtocolSpec, Scenario};

/// A field (`field@owner`) and what is wrong with it.
type Fault = (String, String);

/// Most junk bytes a fault sends with one reply.
const MAX_JUNK: usize = nodes::link::MAX_JUNK;
/// Longest split gap (ms): longer is a lost reply, `drop-reply`'s business.
const MAX_GAP_MS: f64 = 10_000.0;

/// Whose frames a node's faults change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    /// A slave of this protocol with this id.
    Slave { meb: bool, id: u8 },
    /// The Controller_network project's master (its requests).
    Master,
    /// A node whose frames the fault wrapper does not carry.
    Other(&'static str),
}

fn role(node: &NodeSpec) -> Role {
    match node {
        NodeSpec::EvController { id, protocol, .. } => Role::Slave {
            meb: *protocol == ProtocolSpec::Meb,
            id: *id,
        },
        NodeSpec::MotorNode { .. } => Role::Slave {
            meb: false,
            id: nodes::controller_network::MOTOR_ID,
        },
        NodeSpec::LightNode { .. } => Role::Slave {
            meb: false,
            id: nodes::controller_network::LIGHT_ID,
        },
        NodeSpec::ControllerNetworkMaster { .. } => Role::Master,
        NodeSpec::Supervisor { .. } => Role::Other("a supervisor"),
        NodeSpec::ParallelMaster { .. } => Role::Other("a parallel-module master"),
        NodeSpec::PwmSlave { .. } => Role::Other("a PWM-capture slave"),
        NodeSpec::Firmware { .. } => Role::Other("a compiled sketch"),
    }
}

/// Checks every fault of the newer kinds (and that no fault sets a field
/// of another kind).
pub fn check(s: &Scenario) -> Result<(), Fault> {
    for (i, f) in s.faults.iter().enumerate() {
        let owner = format!("{FAULT_OWNER}{i}");
        let at = |field: &str, why: String| Err((format!("{field}@{owner}"), why));
        let kind = f.kind.name();
        for (field, set, belongs) in fields(f) {
            if set && belongs != f.kind {
                return at(
                    field,
                    format!(
                        "is for {} faults, and the fault on `{}` is `{kind}`",
                        belongs.name(),
                        f.node
                    ),
                );
            }
        }
        let Some(node) = s.nodes.iter().find(|n| n.name() == f.node) else {
            continue;
        };
        let role = role(node);
        let old_kind = matches!(
            f.kind,
            FaultKind::BadCheck | FaultKind::DropReply | FaultKind::DelayReply | FaultKind::Silent
        );
        if old_kind {
            continue;
        }
        let slave_only = matches!(f.kind, FaultKind::Exception | FaultKind::WrongId);
        match role {
            Role::Other(what) => {
                return at(
                    "kind",
                    format!(
                        "`{kind}` of the fault on `{}`: that node is {what}, whose frames no \
                         fault changes; `{kind}` is for ev-controller, motor-node and light-node{}",
                        f.node,
                        if slave_only {
                            ""
                        } else {
                            " (and the controller-network-master's requests)"
                        }
                    ),
                );
            }
            Role::Master if slave_only => {
                return at(
                    "kind",
                    format!(
                        "`{kind}` of the fault on `{}`: a master answers no requests; \
                         `{kind}` is for a slave (ev-controller, motor-node, light-node)",
                        f.node
                    ),
                );
            }
            _ => {}
        }
        match f.kind {
            FaultKind::Exception => {
                if let Some(code) = f.code.filter(|c| !(1..=4).contains(c)) {
                    return at(
                        "code",
                        format!(
                            "of the fault on `{}` must be 1 (illegal function), 2 (illegal \
                             address), 3 (illegal data) or 4 (device failure), got {code}",
                            f.node
                        ),
                    );
                }
            }
            FaultKind::WrongId => {
                if let (Some(id), Role::Slave { meb, id: own }) = (f.id, role) {
                    let max = if meb { 99 } else { 247 };
                    if id == 0 || id > max {
                        let on = if meb { "an MEB" } else { "a Modbus" };
                        return at(
                            "id",
                            format!(
                                "of the fault on `{}`: {on} slave id is 1 to {max}, got {id}",
                                f.node
                            ),
                        );
                    }
                    if id == own {
                        return at(
                            "id",
                            format!(
                                "of the fault on `{}` is {id}, the node's own id: a wrong id \
                                 must be another",
                                f.node
                            ),
                        );
                    }
                }
            }
            FaultKind::SplitReply => {
                let Some(gap) = f.gap_ms else {
                    return at(
                        "kind",
                        format!(
                            "`split-reply` of the fault on `{}` needs `gap_ms`, the quiet line \
                             between the two writes (ms)",
                            f.node
                        ),
                    );
                };
                if !(gap.is_finite() && (0.0..=MAX_GAP_MS).contains(&gap)) {
                    return at(
                        "gap_ms",
                        format!(
                            "of the fault on `{}` must be 0 to {MAX_GAP_MS} ms, got {gap}",
                            f.node
                        ),
                    );
                }
                if f.split_at == Some(0) {
                    return at(
                        "split_at",
                        format!(
                            "of the fault on `{}` must be at least 1 (bytes in the first write)",
                            f.node
                        ),
                    );
                }
            }
            FaultKind::Junk => junk(f, &at)?,
            _ => {}
        }
    }
    Ok(())
}

fn junk(f: &FaultSpec, at: &dyn Fn(&str, String) -> Result<(), Fault>) -> Result<(), Fault> {
    match (&f.junk, f.junk_count) {
        (Some(_), Some(_)) => at(
            "junk_count",
            format!(
                "of the fault on `{}`: give `junk` (the bytes) or `junk_count` (random \
                 bytes), not both",
                f.node
            ),
        ),
        (None, None) => at(
            "kind",
            format!(
                "`junk` of the fault on `{}` needs `junk = [0x00, 0xFF]` (the bytes) or \
                 `junk_count = 4` (random bytes from the scenario's seed)",
                f.node
            ),
        ),
        (Some(bytes), None) if bytes.is_empty() || bytes.len() > MAX_JUNK => at(
            "junk",
            format!(
                "of the fault on `{}` must hold 1 to {MAX_JUNK} bytes, got {}",
                f.node,
                bytes.len()
            ),
        ),
        (None, Some(n)) if n == 0 || n as usize > MAX_JUNK => at(
            "junk_count",
            format!(
                "of the fault on `{}` must be 1 to {MAX_JUNK}, got {n}",
                f.node
            ),
        ),
        _ => Ok(()),
    }
}

/// Each kind's own fields: (name, whether set, the kind it belongs to).
fn fields(f: &FaultSpec) -> [(&'static str, bool, FaultKind); 7] {
    [
        ("code", f.code.is_some(), FaultKind::Exception),
        ("id", f.id.is_some(), FaultKind::WrongId),
        ("gap_ms", f.gap_ms.is_some(), FaultKind::SplitReply),
        ("split_at", f.split_at.is_some(), FaultKind::SplitReply),
        ("junk", f.junk.is_some(), FaultKind::Junk),
        ("junk_count", f.junk_count.is_some(), FaultKind::Junk),
        ("junk_place", f.junk_place.is_some(), FaultKind::Junk),
    ]
}
