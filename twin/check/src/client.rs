//! `twin check client`: a student's remote client (TCP CLI in the M3CVME
//! paper, or its phone app) checked in a session. The twin is the server
//! it connects to, with the supervisor's image behind it ([`bench`]); a
//! checklist says what to do in the client, in order, and each item is
//! seen in the frames the client sends: its reads, its writes landing in
//! the right block with the right value, and what it does after a fault
//! the twin plays (an error reply, a dropped connection). What only a
//! person can judge (what the client shows) stays on the checklist for
//! the teacher, "not judged". The session's verdicts are a [`SuiteRun`],
//! so its reports read like every other check's.

pub mod bench;

use crate::framing::Protocol;
use crate::run::{CheckOutcome, Exchange, Outcome, Peer, Role, SuiteRun, Way};
use bench::{Bench, Fault, Heard};
use protocols::meb::{MebCmd, MebErrorCode};

/// The suite's name in every report.
pub const SUITE: &str = "MEB client";

/// The suite as `twin check --list` names it (and a class's folder).
pub const NAME: &str = "meb-client";

/// What the session checks, for `twin check --list`.
pub const DESCRIPTION: &str = "A remote client in a session that follows a checklist (the twin is the supervisor's server): reads, writes in the right block, an error reply and a dropped connection, every frame well formed";

/// VEL's full scale (12-bit DAC) and the half a client is asked to set:
/// within 5 % of it passes.
const HALF_VEL: u16 = 2048;
const HALF_VEL_WITHIN: u16 = 102;

/// What an item of the checklist waits for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Wants {
    ReadInputs,
    HalfVel,
    EnableOn,
    /// The twin answers the next request with error 04.
    ErrorShown,
    /// The twin hangs up on the next request; the client reads again on a
    /// new connection.
    Reconnects,
    /// For the teacher.
    Person,
}

/// One item of the checklist.
#[derive(Debug, Clone, Copy)]
pub struct Item {
    /// What to do in the client, as the checklist says it.
    pub todo: &'static str,
    /// The requirement it holds the client to.
    pub requirement: &'static str,
    pub points: u32,
    wants: Wants,
}

const IMAGE: &str = "MEB page, The supervisor's image";

/// The checklist, in order.
pub const CHECKLIST: &[Item] = &[
    Item {
        todo: "read the inputs (EA 00-05)",
        requirement: IMAGE,
        points: 1,
        wants: Wants::ReadInputs,
    },
    Item {
        todo: "set VEL to half of full scale (SA 00, about 2048)",
        requirement: "MEB page, Default map: SA 00 VEL, 12-bit DAC",
        points: 2,
        wants: Wants::HalfVel,
    },
    Item {
        todo: "switch the module on (EN, SD 00 bit 0, to 0: active low)",
        requirement: "MEB page, Default map: SD 00 bit 0 EN, 0 = enabled",
        points: 2,
        wants: Wants::EnableOn,
    },
    Item {
        todo: "read the inputs again: the twin answers error 04 (device failure), which the client must show",
        requirement: "MEB page, Errors",
        points: 1,
        wants: Wants::ErrorShown,
    },
    Item {
        todo: "read the inputs again: the twin hangs up, and the client must connect again and read them",
        requirement: "MEB page, Timing (over TCP)",
        points: 1,
        wants: Wants::Reconnects,
    },
    Item {
        todo: "the client shows the six inputs by name (V2, I, V1, RPM_M, RPM_L, LDR) and error 04 as an error",
        requirement: "M3CVME paper: the remote client's display",
        points: 0,
        wants: Wants::Person,
    },
];

/// Where an item stands.
#[derive(Debug, Clone)]
enum Seen {
    Waiting,
    Done { outcome: Outcome, at: f64 },
}

/// A session: the server listening, the checklist, what was seen.
#[derive(Debug)]
pub struct Session {
    bench: Bench,
    id: u8,
    seen: Vec<Seen>,
    /// When the item now waited for began.
    since: f64,
}

impl Session {
    /// Listens on `addr`, the image of slave `id` behind it.
    pub fn listen(addr: std::net::SocketAddr, id: u8) -> std::io::Result<Session> {
        Ok(Session {
            bench: Bench::listen(addr, id)?,
            id,
            seen: vec![Seen::Waiting; CHECKLIST.len()],
            since: 0.0,
        })
    }

    pub fn addr(&self) -> std::net::SocketAddr {
        self.bench.addr()
    }

    /// Whether a client has connected yet.
    pub fn connected(&self) -> bool {
        self.bench.connections() > 0
    }

    /// The item waited for now, by index.
    fn current(&self) -> Option<usize> {
        self.seen.iter().position(|s| matches!(s, Seen::Waiting))
    }

    /// Whether every item a program can show is seen.
    pub fn done(&self) -> bool {
        self.current().is_none_or(|i| {
            CHECKLIST
                .get(i)
                .is_some_and(|item| item.wants == Wants::Person)
        })
    }

    /// Looks at what the client did; the items newly seen, with their
    /// outcomes.
    pub fn poll(&mut self) -> Vec<(usize, Outcome)> {
        let mut newly = Vec::new();
        while let Some(index) = self.current() {
            let item = CHECKLIST[index];
            if item.wants == Wants::Person {
                break;
            }
            let heard: Vec<Heard> = self
                .bench
                .heard()
                .into_iter()
                .filter(|h| h.at >= self.since)
                .collect();
            let Some((outcome, at)) = self.judge(item.wants, &heard) else {
                break;
            };
            self.seen[index] = Seen::Done {
                outcome: outcome.clone(),
                at,
            };
            self.since = at;
            newly.push((index, outcome));
            match CHECKLIST.get(index + 1).map(|i| i.wants) {
                Some(Wants::ErrorShown) => {
                    self.bench.play(Fault::Error(MebErrorCode::DeviceFailure))
                }
                Some(Wants::Reconnects) => self.bench.play(Fault::HangUp),
                _ => {}
            }
        }
        newly
    }

    /// Whether `heard` shows the item done; its outcome and when.
    fn judge(&self, wants: Wants, heard: &[Heard]) -> Option<(Outcome, f64)> {
        let id = self.id;
        let replies = || {
            heard
                .iter()
                .filter(move |h| h.way == Way::Sent)
                .filter_map(|h| h.repr.map(|r| (h, r)))
        };
        match wants {
            Wants::ReadInputs => replies()
                .find(|(_, r)| r.cmd == MebCmd::EA && r.id == id && !r.data.is_empty())
                .map(|(h, _)| (Outcome::Pass, h.at)),
            Wants::HalfVel => {
                // The first acknowledged write carrying about half of full
                // scale, wherever it went.
                let (h, request) = acknowledged_writes(heard).find(|(_, r)| {
                    r.data
                        .as_slice()
                        .iter()
                        .any(|&w| w.abs_diff(HALF_VEL) <= HALF_VEL_WITHIN)
                })?;
                let outcome = if request.cmd != MebCmd::SA || request.addr != 0 {
                    Outcome::Fail(format!(
                        "VEL went to {} {:02X}, not SA 00 (`{}`)",
                        request.cmd, request.addr, h.text
                    ))
                } else {
                    Outcome::Pass
                };
                Some((outcome, h.at))
            }
            Wants::EnableOn => acknowledged_writes(heard)
                .find(|(_, r)| {
                    r.cmd == MebCmd::SD
                        && r.addr == 0
                        && r.data.as_slice().first().is_some_and(|w| w & 1 == 0)
                })
                .map(|(h, _)| (Outcome::Pass, h.at)),
            Wants::ErrorShown => (!self.bench.fault_pending())
                .then(|| {
                    replies()
                        .find(|(_, r)| r.cmd == MebCmd::ER)
                        .map(|(h, _)| (Outcome::Pass, h.at))
                })
                .flatten(),
            Wants::Reconnects => {
                let hung = self.bench.hung_up_on()?;
                replies()
                    .find(|(h, r)| h.conn > hung && r.cmd == MebCmd::EA && !r.data.is_empty())
                    .map(|(h, _)| (Outcome::Pass, h.at))
            }
            Wants::Person => None,
        }
    }

    /// The session's verdicts: the checklist's items in order, then
    /// whether every frame the client sent was well formed and for the
    /// slave. `link` names the server in the reports.
    pub fn finish(self, link: &str) -> SuiteRun {
        let heard = self.bench.heard();
        let ended = self.bench.now();
        let mut checks = Vec::new();
        // Every frame, each in the item whose window it fell in (after the
        // item before was seen, up to this one), for the recording; those
        // after the last item seen are the frames check's.
        let mut transcript = Vec::new();
        let mut recorded_to = f64::NEG_INFINITY;
        let mut from = 0.0;
        for (item, seen) in CHECKLIST.iter().zip(&self.seen) {
            let (outcome, until) = match (seen, item.wants) {
                (_, Wants::Person) => (
                    Outcome::NotJudged("the teacher watches the client".into()),
                    from,
                ),
                (Seen::Done { outcome, at }, _) => (outcome.clone(), *at),
                (Seen::Waiting, _) => (
                    Outcome::Fail("not seen before the session ended".into()),
                    ended,
                ),
            };
            transcript.push(window(&heard, recorded_to, until));
            recorded_to = recorded_to.max(until);
            checks.push(CheckOutcome {
                name: item.todo.into(),
                requirement: item.requirement.into(),
                points: item.points,
                outcome,
                reply_ms: Vec::new(),
                frames: evidence(&heard, from, until),
                at: from,
                seconds: until - from,
                notes: Vec::new(),
            });
            from = until;
        }
        checks.push(well_formed(&heard, self.id, ended));
        transcript.push(window(&heard, recorded_to, f64::INFINITY));
        SuiteRun {
            suite: SUITE.into(),
            link: link.into(),
            id: self.id,
            role: Role::default(),
            protocol: Protocol::Meb,
            ids: Vec::new(),
            checks,
            seconds: ended,
            bench: None,
            patience: 1.0,
            error: None,
            hung_up: None,
            transcript,
        }
    }
}

/// The frames of `heard` after `after` up to `until`, every one.
fn window(heard: &[Heard], after: f64, until: f64) -> Vec<Exchange> {
    heard
        .iter()
        .filter(|h| h.at > after && h.at <= until)
        .map(exchange)
        .collect()
}

/// A session that never began (the twin could not listen): every check
/// fails with why.
pub fn unreachable(link: &str, id: u8, why: String) -> SuiteRun {
    let checks = listed(id)
        .into_iter()
        .map(|(name, requirement, points)| CheckOutcome {
            name,
            requirement: requirement.into(),
            points,
            outcome: Outcome::Fail(why.clone()),
            reply_ms: Vec::new(),
            frames: Vec::new(),
            at: 0.0,
            seconds: 0.0,
            notes: Vec::new(),
        })
        .collect();
    SuiteRun {
        suite: SUITE.into(),
        link: link.into(),
        id,
        role: Role::default(),
        protocol: Protocol::Meb,
        ids: Vec::new(),
        checks,
        seconds: 0.0,
        bench: None,
        patience: 1.0,
        error: Some(why),
        hung_up: None,
        transcript: Vec::new(),
    }
}

/// Write requests the twin acknowledged, each with its request.
fn acknowledged_writes(heard: &[Heard]) -> impl Iterator<Item = (&Heard, protocols::meb::MebRepr)> {
    heard.iter().enumerate().filter_map(move |(i, h)| {
        let request = h
            .repr
            .filter(|r| h.way == Way::Received && !r.data.is_empty())?;
        let acked = heard.get(i + 1..)?.iter().any(|reply| {
            reply.conn == h.conn
                && reply.way == Way::Sent
                && reply.repr.is_some_and(|r| {
                    r.cmd == request.cmd && r.addr == request.addr && r.data.is_empty()
                })
        });
        acked.then_some((h, request))
    })
}

/// The frames of `heard` from `from` to `until` (the last 12 of them).
fn evidence(heard: &[Heard], from: f64, until: f64) -> Vec<Exchange> {
    let frames: Vec<Exchange> = heard
        .iter()
        .filter(|h| h.at >= from && h.at <= until)
        .map(exchange)
        .collect();
    let skip = frames.len().saturating_sub(12);
    frames.into_iter().skip(skip).collect()
}

fn exchange(h: &Heard) -> Exchange {
    // The twin is the server: what the client sent it received.
    let client = format!("client {}", h.conn);
    Exchange {
        at: h.at,
        way: h.way,
        text: format!("{client:<8}  {}", h.text),
        bytes: h.bytes.clone(),
        peer: Some(Peer {
            link: "client",
            from: match h.way {
                Way::Received => client,
                Way::Sent => "twin".into(),
            },
        }),
    }
}

/// The checks as `twin check --list` shows them (name, requirement,
/// points), for slave `id`: the checklist's items, then the frames'.
pub fn listed(id: u8) -> Vec<(String, &'static str, u32)> {
    CHECKLIST
        .iter()
        .map(|item| (item.todo.to_string(), item.requirement, item.points))
        .chain(std::iter::once((
            well_formed_name(id),
            WELL_FORMED_REQUIREMENT,
            WELL_FORMED_POINTS,
        )))
        .collect()
}

const WELL_FORMED_REQUIREMENT: &str = "MEB page, Frame";
const WELL_FORMED_POINTS: u32 = 2;

fn well_formed_name(id: u8) -> String {
    format!("every frame the client sent is well formed, its FCS right, for slave {id:02}")
}

/// Every frame the client sent parsed, with a right FCS, for slave `id`.
fn well_formed(heard: &[Heard], id: u8, ended: f64) -> CheckOutcome {
    let sent: Vec<&Heard> = heard.iter().filter(|h| h.way == Way::Received).collect();
    let bad = sent.iter().find(|h| h.repr.is_none_or(|r| r.id != id));
    let outcome = match (bad, sent.is_empty()) {
        (_, true) => Outcome::Fail("the client sent nothing".into()),
        (None, false) => Outcome::Pass,
        (Some(h), false) => Outcome::Fail(match h.repr {
            None => format!(
                "`{}` is not a well-formed MEB frame (form, FCS or ending)",
                h.text
            ),
            Some(r) => format!("`{}` is for slave {:02}, not {id:02}", h.text, r.id),
        }),
    };
    let frames = match bad {
        Some(h) => vec![exchange(h)],
        None => Vec::new(),
    };
    CheckOutcome {
        name: well_formed_name(id),
        requirement: WELL_FORMED_REQUIREMENT.into(),
        points: WELL_FORMED_POINTS,
        outcome,
        reply_ms: Vec::new(),
        frames,
        at: 0.0,
        seconds: ended,
        notes: Vec::new(),
    }
}
