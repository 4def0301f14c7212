//! `twin check server`: a student's supervisor (SUP SRV in the M3CVME
//! paper) checked from both its sides at once. It is master of an RS-485
//! bus, where the twin plays the module's controller ([`bus`]: the twin's
//! own MEB slave, its inputs set by the check), and a TCP server, where the
//! twin connects as the remote clients (TCP CLI). Each check holds the
//! server to the MEB page's "The supervisor's image": reads answered with
//! what the slave holds, writes on the bus in the right block and
//! acknowledged once the slave acknowledged them, bad frames ignored,
//! errors as the page gives them, several clients served, replies in time.
//! The evidence of a check is its frames on both sides, with one clock.

pub mod bus;

use crate::framing::{Protocol, shown_text as shown};
use crate::run::{CheckOutcome, Exchange, Outcome, Peer, Role, SuiteRun, Way};
use crate::wire::{Wire, WireError};
use bus::{Bus, BusFrame};
use protocols::meb::MebCmd;
use std::time::{Duration, Instant};

/// The suite's name in every report.
pub const SUITE: &str = "MEB server";

/// The suite as `twin check --list` names it (and a class's folder).
pub const NAME: &str = "meb-server";

/// What the suite checks, for `twin check --list`.
pub const DESCRIPTION: &str = "A supervisor checked from its bus (the twin plays the module's controller) and its TCP server (the twin connects as the remote clients) at once: reads answered from the image, writes landing on the bus, errors, several clients, timing";

/// How long the supervisor may take to poll the slave again: a supervisor
/// that polls less often than this serves no image worth the name.
const POLL_WAIT: Duration = Duration::from_secs(5);

/// What is checked, and where.
#[derive(Debug, Clone)]
pub struct ServerOptions {
    /// The server: `tcp://HOST:PORT`.
    pub link: String,
    /// The supervisor's bus, where the twin plays the slave: a serial
    /// device or pseudo-terminal, with its options.
    pub bus: String,
    /// The slave's id on the bus.
    pub id: u8,
    /// A read's reply deadline, ms (the MEB page's master timeout: 100).
    pub timeout_ms: u64,
}

/// A check of the server: its name, the requirement, its points and what
/// it does.
struct Spec {
    name: &'static str,
    requirement: &'static str,
    points: u32,
    run: fn(&mut Checker) -> Verdict,
}

type Verdict = Result<(), String>;

const IMAGE: &str = "MEB page, The supervisor's image";
const ERRORS: &str = "MEB page, The supervisor's image and Errors";
const TIMING: &str = "MEB page, Timing (over TCP)";

const CHECKS: &[Spec] = &[
    Spec {
        name: "the supervisor polls the slave on the bus",
        requirement: "M3CVME paper: the supervisor is master of the module's bus",
        points: 1,
        run: polls_the_slave,
    },
    Spec {
        name: "a client's read of the inputs is answered with the slave's values",
        requirement: IMAGE,
        points: 2,
        run: reads_the_inputs,
    },
    Spec {
        name: "new values on the slave reach the clients' reads",
        requirement: IMAGE,
        points: 2,
        run: reads_follow_the_slave,
    },
    Spec {
        name: "pipelined reads are answered in request order",
        requirement: IMAGE,
        points: 1,
        run: pipelined_in_order,
    },
    Spec {
        name: "a client's VEL write (SA 00) goes on the bus as SA 00 and is acknowledged",
        requirement: IMAGE,
        points: 2,
        run: |c| c.write_lands(MebCmd::SA, 0, 0x04D2),
    },
    Spec {
        name: "a client's outputs write (SD 00) goes on the bus as SD 00 and is acknowledged",
        requirement: IMAGE,
        points: 2,
        run: |c| c.write_lands(MebCmd::SD, 0, 0x0015),
    },
    Spec {
        name: "a client's write of the slave's variable VA 00 goes on the bus as VA 00",
        requirement: IMAGE,
        points: 1,
        run: |c| c.write_lands(MebCmd::VA, 0, 0x0123),
    },
    Spec {
        name: "a write the slave refuses gets error 03, not an acknowledgement",
        requirement: ERRORS,
        points: 1,
        run: refused_write,
    },
    Spec {
        name: "a bad FCS gets no reply, and the next good request is answered",
        requirement: "MEB page, Errors and Timing (malformed frames are ignored over TCP too)",
        points: 1,
        run: bad_fcs_ignored,
    },
    Spec {
        name: "an unknown command gets error 01",
        requirement: ERRORS,
        points: 1,
        run: |c| c.error_reply("@{id}XY0001", "00", 1),
    },
    Spec {
        name: "an address the image does not hold gets error 02",
        requirement: ERRORS,
        points: 1,
        run: |c| c.error_reply("@{id}EA4001", "40", 2),
    },
    Spec {
        name: "a count of 00 gets error 03",
        requirement: ERRORS,
        points: 1,
        run: |c| c.error_reply("@{id}EA0000", "00", 3),
    },
    Spec {
        name: "two clients connected at once are both served",
        requirement: "M3CVME paper: remote clients (TCP CLI) of the supervisor's server",
        points: 2,
        run: two_clients,
    },
    Spec {
        name: "a client that hangs up mid-frame does not stop the server",
        requirement: TIMING,
        points: 1,
        run: hang_up_mid_frame,
    },
    Spec {
        name: "20 reads in a row are each answered within the reply timeout",
        requirement: TIMING,
        points: 1,
        run: reads_in_time,
    },
];

/// The inputs the slave holds at first, and after "new values".
const FIRST_INPUTS: [u16; 6] = [0x0A11, 0x0822, 0x0C33, 1500, 1490, 0x0555];
const NEW_INPUTS: [u16; 6] = [0x0B66, 0x0777, 0x0D88, 1200, 1190, 0x0999];

/// The links as a recording names them: the server's TCP connections
/// (the twin's clients) and the supervisor's bus.
const SERVER_LINK: &str = "server";
const BUS_LINK: &str = "bus";

/// The checks of the server at `options.link` whose bus is `options.bus`.
/// Errors only when the bus cannot be opened (the teacher's setup); a
/// server that cannot be reached is a run whose checks all fail with why.
pub fn check_server(options: &ServerOptions) -> Result<SuiteRun, WireError> {
    let started = Instant::now();
    let bus = Bus::open(&options.bus, options.id, FIRST_INPUTS, started)?;
    let mut checker = Checker {
        link: options.link.clone(),
        id: options.id,
        timeout: Duration::from_millis(options.timeout_ms),
        write_timeout: Duration::from_millis(options.timeout_ms.saturating_mul(10)),
        bus,
        started,
        frames: Vec::new(),
        reply_ms: Vec::new(),
    };
    let link = format!("{}, bus {}", options.link, options.bus);
    if let Err(e) = Wire::open(&options.link) {
        return Ok(unreachable(&link, options.id, e.to_string()));
    }
    let mut checks = Vec::with_capacity(CHECKS.len());
    // Every frame of both links, check by check, for the recording: the
    // clients' frames each check noted, and every frame on the bus from
    // the end of the check before (the supervisor polls throughout).
    let mut transcript = Vec::with_capacity(CHECKS.len());
    let mut bus_from = 0.0;
    for (index, spec) in CHECKS.iter().enumerate() {
        checker.frames.clear();
        checker.reply_ms.clear();
        let began = checker.now();
        let mut outcome = match (spec.run)(&mut checker) {
            Ok(()) => Outcome::Pass,
            Err(why) => Outcome::Fail(why),
        };
        if let Some(why) = checker.bus.error() {
            outcome = Outcome::Fail(format!("the bus failed: {why}"));
        }
        let mut frames = std::mem::take(&mut checker.frames);
        frames.sort_by(|a, b| a.at.total_cmp(&b.at));
        let bus_to = if index + 1 == CHECKS.len() {
            f64::INFINITY
        } else {
            checker.now()
        };
        let mut every: Vec<Exchange> = frames
            .iter()
            .filter(|f| f.peer.as_ref().is_some_and(|p| p.link == SERVER_LINK))
            .cloned()
            .collect();
        every.extend(
            checker
                .bus
                .frames_between(bus_from, bus_to)
                .iter()
                .map(|f| bus_exchange(f, options.id)),
        );
        every.sort_by(|a, b| a.at.total_cmp(&b.at));
        transcript.push(every);
        bus_from = bus_to;
        checks.push(CheckOutcome {
            name: spec.name.into(),
            requirement: spec.requirement.into(),
            points: spec.points,
            outcome,
            reply_ms: std::mem::take(&mut checker.reply_ms),
            frames,
            at: began,
            seconds: checker.now() - began,
            notes: Vec::new(),
        });
    }
    Ok(SuiteRun {
        suite: SUITE.into(),
        link,
        id: options.id,
        role: Role::default(),
        protocol: Protocol::Meb,
        ids: Vec::new(),
        checks,
        seconds: checker.now(),
        bench: None,
        patience: 1.0,
        error: None,
        hung_up: None,
        transcript,
    })
}

/// The checks as `twin check --list` shows them (name, requirement,
/// points), from the table the run plays.
pub fn listed() -> impl Iterator<Item = (&'static str, &'static str, u32)> {
    CHECKS.iter().map(|c| (c.name, c.requirement, c.points))
}

/// A run whose server could not be reached (or its bus opened): every
/// check fails with why.
pub fn unreachable(link: &str, id: u8, why: String) -> SuiteRun {
    SuiteRun {
        suite: SUITE.into(),
        link: link.into(),
        id,
        role: Role::default(),
        protocol: Protocol::Meb,
        ids: Vec::new(),
        checks: CHECKS
            .iter()
            .map(|spec| CheckOutcome {
                name: spec.name.into(),
                requirement: spec.requirement.into(),
                points: spec.points,
                outcome: Outcome::Fail(why.clone()),
                reply_ms: Vec::new(),
                frames: Vec::new(),
                at: 0.0,
                seconds: 0.0,
                notes: Vec::new(),
            })
            .collect(),
        seconds: 0.0,
        bench: None,
        patience: 1.0,
        error: Some(why),
        hung_up: None,
        transcript: Vec::new(),
    }
}

/// One remote client's connection, as the twin plays it.
struct Client {
    wire: Wire,
    name: &'static str,
    pending: Vec<u8>,
    /// When the last request's last byte went out.
    sent_at: Option<Instant>,
}

struct Checker {
    link: String,
    id: u8,
    timeout: Duration,
    /// A forwarded write's deadline: it waits for its turn on the bus and
    /// the slave's reply.
    write_timeout: Duration,
    bus: Bus,
    started: Instant,
    /// This check's frames, both sides.
    frames: Vec<Exchange>,
    reply_ms: Vec<f64>,
}

/// A frame on the bus: the supervisor's request (`Received` by the twin's
/// slave) or the reply of slave `id` (`Sent`).
fn bus_exchange(frame: &BusFrame, id: u8) -> Exchange {
    let from = match frame.way {
        Way::Received => "supervisor".to_string(),
        Way::Sent => format!("slave {id:02}"),
    };
    Exchange {
        at: frame.at,
        way: frame.way,
        text: format!("{:<8}  {}", "bus", frame.text),
        bytes: frame.bytes.clone(),
        peer: Some(Peer {
            link: BUS_LINK,
            from,
        }),
    }
}

/// `body` with its FCS and `*\n`.
fn framed(body: &str) -> String {
    let fcs = body.bytes().fold(0u8, |x, b| x ^ b);
    format!("{body}{fcs:02X}*\n")
}

impl Checker {
    fn now(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    fn fill(&self, body: &str) -> String {
        body.replace("{id}", &format!("{:02}", self.id))
    }

    fn connect(&mut self, name: &'static str) -> Result<Client, String> {
        let wire = Wire::open(&self.link).map_err(|e| e.to_string())?;
        Ok(Client {
            wire,
            name,
            pending: Vec::new(),
            sent_at: None,
        })
    }

    /// A frame on a client's connection: `Sent` by the twin's client
    /// `side`, `Received` from the supervisor.
    fn note(&mut self, at: f64, way: Way, side: &str, bytes: &[u8]) {
        let from = match way {
            Way::Sent => side.to_string(),
            Way::Received => "supervisor".to_string(),
        };
        self.frames.push(Exchange {
            at,
            way,
            text: format!("{side:<8}  {}", shown(bytes)),
            bytes: bytes.to_vec(),
            peer: Some(Peer {
                link: SERVER_LINK,
                from,
            }),
        });
    }

    /// A mark that is no frame (a client hanging up): in the report only.
    fn note_mark(&mut self, side: &str, what: &str) {
        self.frames.push(Exchange {
            at: self.now(),
            way: Way::Sent,
            text: format!("{side:<8}  {what}"),
            bytes: Vec::new(),
            peer: None,
        });
    }

    fn note_bus(&mut self, frame: &BusFrame) {
        self.frames.push(bus_exchange(frame, self.id));
    }

    /// Sends `bytes` as they are.
    fn send_raw(&mut self, client: &mut Client, bytes: &[u8]) -> Verdict {
        self.note(self.now(), Way::Sent, client.name, bytes);
        client
            .wire
            .send(bytes)
            .map_err(|e| format!("{}: {e}", client.name))?;
        client.sent_at = Some(Instant::now());
        Ok(())
    }

    /// Sends the frame `body` (`{id}` filled) with its FCS.
    fn send(&mut self, client: &mut Client, body: &str) -> Verdict {
        let frame = framed(&self.fill(body));
        self.send_raw(client, frame.as_bytes())
    }

    /// The next whole frame from `client` within `within` of its request.
    fn reply(&mut self, client: &mut Client, within: Duration) -> Result<String, String> {
        let deadline = client.sent_at.unwrap_or_else(Instant::now) + within;
        let mut first_at = None;
        loop {
            if let Some(end) = client.pending.iter().position(|&b| b == b'\n') {
                let frame: Vec<u8> = client.pending.drain(..=end).collect();
                let at = first_at.unwrap_or_else(|| self.now());
                self.note(at, Way::Received, client.name, &frame);
                return Ok(String::from_utf8_lossy(&frame).into_owned());
            }
            let before = client.pending.len();
            let came = match client.wire.receive(&mut client.pending, deadline) {
                Ok(n) => n,
                Err(WireError::Closed { .. }) => {
                    return Err(format!(
                        "the server closed {}'s connection where a reply was due",
                        client.name
                    ));
                }
                Err(e) => return Err(e.to_string()),
            };
            if came == 0 {
                let ms = within.as_millis();
                if client.pending.is_empty() {
                    return Err(format!("no reply within {ms} ms"));
                }
                let got = std::mem::take(&mut client.pending);
                self.note(self.now(), Way::Received, client.name, &got);
                return Err(format!(
                    "`{}` came, no whole frame (`*\\n` missing) within {ms} ms",
                    shown(&got)
                ));
            }
            if before == 0 {
                first_at.get_or_insert_with(|| self.now());
                if let Some(sent) = client.sent_at.take() {
                    self.reply_ms.push(sent.elapsed().as_secs_f64() * 1e3);
                }
            }
        }
    }

    /// The next reply must be exactly the frame `body` (`{id}` filled).
    fn expect(&mut self, client: &mut Client, body: &str, within: Duration) -> Verdict {
        let wanted = framed(&self.fill(body));
        let got = self.reply(client, within).map_err(|why| {
            format!(
                "{}: {why}; expected `{}`",
                client.name,
                shown(wanted.as_bytes())
            )
        })?;
        if got == wanted {
            return Ok(());
        }
        Err(format!(
            "{} got `{}`; expected `{}`",
            client.name,
            shown(got.as_bytes()),
            shown(wanted.as_bytes())
        ))
    }

    /// A read of `cnt` inputs from `addr`, and the reply the slave's values give.
    fn read_inputs(&mut self, client: &mut Client, addr: usize, cnt: usize) -> Verdict {
        let body = format!("@{{id}}EA{addr:02X}{cnt:02}");
        self.send(client, &body)?;
        let words: String = self
            .bus
            .inputs()
            .iter()
            .skip(addr)
            .take(cnt)
            .map(|w| format!("{w:04X}"))
            .collect();
        let timeout = self.timeout;
        self.expect(client, &format!("{body}{words}"), timeout)
    }

    /// Waits until the supervisor has read every input (EA 00-05) from the
    /// slave since `since` and gone on to its next request, so its image
    /// holds what the slave holds now.
    fn wait_polled(&mut self, since: f64) -> Verdict {
        let give_up = Instant::now() + POLL_WAIT;
        let mut covered = [false; 6];
        let mut last_reply = None;
        loop {
            for frame in self.bus.frames_since(since) {
                let Some(repr) = frame.repr.filter(|r| r.id == self.id) else {
                    continue;
                };
                if frame.way == Way::Sent && repr.cmd == MebCmd::EA && !repr.data.is_empty() {
                    let from = usize::from(repr.addr);
                    for slot in covered.iter_mut().skip(from).take(usize::from(repr.cnt)) {
                        *slot = true;
                    }
                    if covered.iter().all(|&c| c) && last_reply.is_none() {
                        last_reply = Some(frame.clone());
                    }
                } else if frame.way == Way::Received
                    && let Some(reply) = &last_reply
                    && frame.at > reply.at
                {
                    let reply = reply.clone();
                    self.note_bus(&reply);
                    return Ok(());
                }
            }
            if Instant::now() > give_up {
                if let Some(reply) = last_reply {
                    // Read, and nothing after: its image holds them anyway.
                    self.note_bus(&reply);
                    return Ok(());
                }
                return Err(format!(
                    "the supervisor did not read the slave's inputs (EA 00-05) on the bus within {} s",
                    POLL_WAIT.as_secs()
                ));
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// A client writes `value` to `cmd addr`: it must go on the bus there,
    /// and the client get the acknowledgement after the slave gave its.
    fn write_lands(&mut self, cmd: MebCmd, addr: u8, value: u16) -> Verdict {
        let mut client = self.connect("client")?;
        let since = self.now();
        self.send(&mut client, &format!("@{{id}}{cmd}{addr:02X}01{value:04X}"))?;
        let timeout = self.write_timeout;
        let reply = self.reply(&mut client, timeout);
        let replied_at = self.frames.last().map_or(f64::MAX, |f| f.at);
        let frames = self.bus.frames_since(since);
        let carried = frames.iter().position(|f| {
            f.way == Way::Received
                && f.repr
                    .is_some_and(|r| r.id == self.id && r.data.as_slice() == [value])
        });
        let Some(at) = carried else {
            for f in frames.iter().filter(|f| f.way == Way::Received) {
                if f.repr.is_some_and(|r| {
                    r.cmd
                        .block()
                        .is_some_and(|(b, _)| b.access() == protocols::meb::MebAccess::Write)
                }) {
                    self.note_bus(f);
                }
            }
            return Err(format!(
                "no write of {value:04X} came on the bus within {} ms",
                timeout.as_millis()
            ));
        };
        let request = frames[at].clone();
        self.note_bus(&request);
        let slave_reply = frames[at + 1..]
            .iter()
            .find(|f| f.way == Way::Sent)
            .cloned();
        if let Some(r) = &slave_reply {
            self.note_bus(r);
        }
        if let Some(r) = request.repr
            && (r.cmd != cmd || r.addr != addr)
        {
            return Err(format!(
                "the write went on the bus as {} {:02X} (`{}`), not {cmd} {addr:02X}",
                r.cmd, r.addr, request.text
            ));
        }
        let wanted = framed(&self.fill(&format!("@{{id}}{cmd}{addr:02X}01")));
        let got = reply.map_err(|why| format!("{why}; expected `{}`", shown(wanted.as_bytes())))?;
        if got != wanted {
            return Err(format!(
                "the client got `{}`; expected the acknowledgement `{}`",
                shown(got.as_bytes()),
                shown(wanted.as_bytes())
            ));
        }
        if slave_reply.is_none_or(|r| r.at > replied_at) {
            return Err(
                "the client was acknowledged before the slave acknowledged the write on the bus"
                    .into(),
            );
        }
        Ok(())
    }

    /// `body` (no DATA) must get `@{id}ER{addr}01{code}`.
    fn error_reply(&mut self, body: &str, addr: &str, code: u16) -> Verdict {
        let mut client = self.connect("client")?;
        self.send(&mut client, body)?;
        let timeout = self.timeout;
        self.expect(
            &mut client,
            &format!("@{{id}}ER{addr}01{code:04X}"),
            timeout,
        )
    }
}

fn polls_the_slave(c: &mut Checker) -> Verdict {
    let give_up = Instant::now() + POLL_WAIT;
    loop {
        let frames = c.bus.frames_since(0.0);
        if let Some(reply) = frames.iter().position(|f| f.way == Way::Sent) {
            if let Some(request) = frames[..reply]
                .iter()
                .rev()
                .find(|f| f.way == Way::Received)
            {
                c.note_bus(request);
            }
            c.note_bus(&frames[reply]);
            return Ok(());
        }
        if Instant::now() > give_up {
            for f in frames.iter().take(4) {
                c.note_bus(f);
            }
            return Err(match frames.len() {
                0 => format!(
                    "nothing came on the bus within {} s: is the supervisor's master on it, at its baud rate?",
                    POLL_WAIT.as_secs()
                ),
                n => format!(
                    "{n} frames came on the bus within {} s, none a request slave {:02} could answer",
                    POLL_WAIT.as_secs(),
                    c.id
                ),
            });
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

fn reads_the_inputs(c: &mut Checker) -> Verdict {
    c.wait_polled(0.0)?;
    let mut client = c.connect("client")?;
    c.read_inputs(&mut client, 0, 6)
}

fn reads_follow_the_slave(c: &mut Checker) -> Verdict {
    c.bus.set_inputs(NEW_INPUTS);
    let since = c.now();
    c.wait_polled(since)?;
    let mut client = c.connect("client")?;
    c.read_inputs(&mut client, 0, 6)
}

fn pipelined_in_order(c: &mut Checker) -> Verdict {
    let mut client = c.connect("client")?;
    let inputs = c.bus.inputs();
    let reads = [0usize, 3, 5];
    let mut bytes = String::new();
    for addr in reads {
        bytes += &framed(&c.fill(&format!("@{{id}}EA{addr:02X}01")));
    }
    c.send_raw(&mut client, bytes.as_bytes())?;
    let timeout = c.timeout;
    for addr in reads {
        let word = inputs.get(addr).copied().unwrap_or_default();
        c.expect(
            &mut client,
            &format!("@{{id}}EA{addr:02X}01{word:04X}"),
            timeout,
        )?;
    }
    Ok(())
}

fn refused_write(c: &mut Checker) -> Verdict {
    // One above the 12-bit DAC's full scale: the slave answers ER 03.
    let mut client = c.connect("client")?;
    let since = c.now();
    c.send(&mut client, "@{id}SA00011000")?;
    let timeout = c.write_timeout;
    let verdict = c.expect(&mut client, "@{id}ER00010003", timeout);
    for f in c.bus.frames_since(since) {
        if f.text.contains("SA00011000") || f.text.contains("ER0001") {
            c.note_bus(&f);
        }
    }
    verdict
}

fn bad_fcs_ignored(c: &mut Checker) -> Verdict {
    let mut client = c.connect("client")?;
    let good = framed(&c.fill("@{id}EA0006"));
    let mut bad = good.clone().into_bytes();
    // The FCS's last digit changed: still hex, no longer the XOR.
    if let Some(digit) = bad.get_mut(good.len() - 3) {
        *digit = if *digit == b'0' { b'1' } else { b'0' };
    }
    c.send_raw(&mut client, &bad)?;
    let quiet = c.timeout;
    let until = Instant::now() + quiet;
    let mut got = Vec::new();
    while Instant::now() < until {
        match client.wire.receive(&mut got, until) {
            Ok(_) => {}
            Err(e) => return Err(e.to_string()),
        }
    }
    if !got.is_empty() {
        c.note(c.now(), Way::Received, client.name, &got);
        return Err(format!(
            "answered `{}` where it must stay silent for {} ms",
            shown(&got),
            quiet.as_millis()
        ));
    }
    c.read_inputs(&mut client, 0, 6)
}

fn two_clients(c: &mut Checker) -> Verdict {
    let mut first = c.connect("client 1")?;
    let mut second = c.connect("client 2")?;
    // The newer one first: a server that serves one client at a time
    // serves the first until it leaves.
    c.read_inputs(&mut second, 0, 1)?;
    c.read_inputs(&mut first, 1, 1)?;
    c.send(&mut first, "@{id}EA0201")?;
    c.read_inputs(&mut second, 3, 1)?;
    let word = c.bus.inputs()[2];
    let timeout = c.timeout;
    c.expect(&mut first, &format!("@{{id}}EA0201{word:04X}"), timeout)
}

fn hang_up_mid_frame(c: &mut Checker) -> Verdict {
    let mut leaving = c.connect("client 1")?;
    let partial = c.fill("@{id}EA00");
    c.send_raw(&mut leaving, partial.as_bytes())?;
    drop(leaving);
    c.note_mark("client 1", "(hangs up)");
    let mut next = c.connect("client 2")?;
    c.read_inputs(&mut next, 0, 6)
}

fn reads_in_time(c: &mut Checker) -> Verdict {
    let mut client = c.connect("client")?;
    for _ in 0..20 {
        c.read_inputs(&mut client, 0, 6)?;
    }
    Ok(())
}
