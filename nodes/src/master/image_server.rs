//! The supervisor's MEB-over-TCP server, sans-IO (`docs/protocols/meb.md`, "The
//! supervisor's image").
//!
//! Remote clients send MEB requests on a byte stream; they are answered from
//! the [`Supervisor`]'s image:
//!
//! - reads of `EA 00`–`05` from the inputs it polled last (`ER 04` before the
//!   first poll answered), and of `ED 00`, `FA 00`–`01`, `FD 00` when the
//!   supervisor reads the status words (`SupervisorConfig::status_every`); the loop's mirrors `FA 10` set point (rpm),
//!   `FA 11` Kp ×1000, `FA 12` Ki ×1000 and `FD 10` bit 0 closed loop;
//! - writes of the loop's variables `VA 10`–`12` and `VD 10` applied at once;
//! - other writes (`SA`, `SD`, the slave's own `VA`/`VD`) forwarded on the bus
//!   and answered when the slave answered: the echo, the slave's own `ER`,
//!   or `ER 04` when it did not answer;
//! - `ER 01` to every write of a read-only client, `ER 02` for addresses the
//!   image does not hold (and ids the supervisor does not poll), `ER 03` for a
//!   count of 0 or a variable out of range.
//!
//! Replies leave in request order, however many requests a client pipelines.
//! Malformed frames are ignored and counted; reply-shaped frames and
//! broadcasts are ignored. A connection is closed (the server says so through
//! [`ImageServer::close_reason`]) only when it holds a partial frame longer than
//! the partial-frame timeout, sends frames faster than the rate limit, or has
//! more replies owed than the pipeline limit. Nothing one client sends changes
//! what another gets, beyond the writes it makes.

use std::collections::VecDeque;

use protocols::meb::{
    MebAccess, MebBlock, MebCmd, MebDecodeError, MebDecoder, MebDecoderStats, MebErrorCode,
    MebRepr, MebWordType, MebWords,
};
use protocols::time::{SimDuration, SimTime};

use super::{ForwardError, LoopMode, Supervisor, WriteOutcome, WriteTicket};

/// First address of the loop's variables and mirrors (`VA 10`, `FA 10`, …).
pub const LOOP_ADDR: u8 = 0x10;
/// Highest set point a client may write, rpm.
pub const SET_POINT_MAX_RPM: u16 = 20_000;
/// The analog inputs the image holds (`EA 00`–`05`).
const IMAGE_INPUTS: u8 = 6;

/// Limits that keep one client from hurting the others.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageServerConfig {
    /// Clients connected at once; one more is refused when it arrives.
    pub max_clients: usize,
    /// A partial frame held longer than this closes the connection (spec: 5 s).
    pub partial_timeout: SimDuration,
    /// Frames (good or bad) a client may send per second on average…
    pub rate_per_second: f64,
    /// …and in one burst.
    pub rate_burst: f64,
    /// Replies owed to one client (pipelined requests not yet answered).
    pub max_pipeline: usize,
    /// Every client is read-only: writes get `ER 01`.
    pub read_only: bool,
    /// A forwarded write still waiting for the line after this long (the bus
    /// is gone: no port, a master not driven) is dropped and answered `ER 04`,
    /// so a client is never left waiting. Longer than the supervisor's retries
    /// take, so a write on the line always gets its own answer.
    pub max_forward_wait: SimDuration,
}

impl Default for ImageServerConfig {
    fn default() -> Self {
        Self {
            max_clients: 8,
            partial_timeout: SimDuration::from_secs(5),
            rate_per_second: 200.0,
            rate_burst: 100.0,
            max_pipeline: 64,
            read_only: false,
            max_forward_wait: SimDuration::from_millis(800),
        }
    }
}

/// One connection, named by the server when it is accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ClientId(pub u64);

/// Why the server wants a connection closed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum CloseReason {
    #[error("a partial frame was held longer than the partial-frame timeout")]
    PartialTimeout,
    #[error("frames arrived faster than the rate limit")]
    RateLimit,
    #[error("more pipelined requests than the limit wait for replies")]
    PipelineFull,
}

/// Why a connection was refused when it arrived.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the server already has {0} clients (the limit)")]
pub struct TooManyClients(pub usize);

/// What one client sent and got.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ClientStats {
    /// Requests answered or being answered.
    pub requests: u64,
    /// Of those, answered with `ER`.
    pub errors: u64,
    /// Well-formed frames ignored: reply-shaped, broadcast.
    pub ignored: u64,
    /// Writes forwarded on the bus.
    pub forwarded: u64,
}

#[derive(Debug, Clone)]
enum Owed {
    Ready(MebRepr),
    /// A forwarded write: the request's header, to echo or to answer `ER`,
    /// and when it was forwarded.
    Forwarded {
        ticket: WriteTicket,
        request: MebRepr,
        since: SimTime,
    },
}

#[derive(Debug)]
struct Client {
    id: ClientId,
    decoder: MebDecoder,
    owed: VecDeque<Owed>,
    read_only: bool,
    tokens: f64,
    refilled_at: SimTime,
    close: Option<CloseReason>,
    stats: ClientStats,
}

/// The server: every connected client's stream state and the replies owed.
#[derive(Debug)]
pub struct ImageServer {
    config: ImageServerConfig,
    clients: Vec<Client>,
    next_id: u64,
}

impl ImageServer {
    pub fn new(config: ImageServerConfig) -> Self {
        Self {
            config,
            clients: Vec::new(),
            next_id: 0,
        }
    }

    pub fn config(&self) -> &ImageServerConfig {
        &self.config
    }

    /// Clients connected now.
    pub fn client_count(&self) -> usize {
        self.clients.len()
    }

    /// A new connection at `now`, or a refusal over the client limit.
    pub fn accept(&mut self, now: SimTime) -> Result<ClientId, TooManyClients> {
        if self.clients.len() >= self.config.max_clients {
            return Err(TooManyClients(self.config.max_clients));
        }
        let id = ClientId(self.next_id);
        self.next_id += 1;
        self.clients.push(Client {
            id,
            decoder: MebDecoder::with_partial_timeout(self.config.partial_timeout),
            owed: VecDeque::new(),
            read_only: self.config.read_only,
            tokens: self.config.rate_burst,
            refilled_at: now,
            close: None,
            stats: ClientStats::default(),
        });
        Ok(id)
    }

    /// The connection is gone (closed by either side). Writes it had forwarded
    /// still complete on the bus; their outcomes are dropped.
    pub fn disconnect(&mut self, client: ClientId) {
        self.clients.retain(|c| c.id != client);
    }

    /// Bytes from `client` at `now`: every complete request in them is answered
    /// (or forwarded) in order.
    pub fn handle_bytes(
        &mut self,
        now: SimTime,
        client: ClientId,
        bytes: &[u8],
        supervisor: &mut Supervisor,
    ) {
        let config = self.config;
        let Some(client) = self.clients.iter_mut().find(|c| c.id == client) else {
            return;
        };
        let mut rest = bytes;
        while !rest.is_empty() && client.close.is_none() {
            let (used, event) = client.decoder.push(now, rest);
            rest = rest.get(used..).unwrap_or_default();
            let request = match event {
                None => continue,
                Some(Err(MebDecodeError::Malformed(_) | MebDecodeError::Interrupted)) => None,
                Some(Ok(frame)) => Some(MebRepr::from_frame(&frame)),
            };
            if !client.take_token(now, &config) {
                client.close = Some(CloseReason::RateLimit);
                break;
            }
            let Some(request) = request else {
                continue;
            };
            let owed = answer(now, &request, client.read_only, supervisor);
            match owed {
                None => client.stats.ignored += 1,
                Some(owed) => {
                    client.stats.requests += 1;
                    match &owed {
                        Owed::Ready(reply) if reply.cmd == MebCmd::ER => client.stats.errors += 1,
                        Owed::Forwarded { .. } => client.stats.forwarded += 1,
                        Owed::Ready(_) => {}
                    }
                    client.owed.push_back(owed);
                    if client.owed.len() > config.max_pipeline {
                        client.close = Some(CloseReason::PipelineFull);
                    }
                }
            }
        }
    }

    /// Takes the supervisor's outcomes of this server's forwarded writes into
    /// the replies owed. Call after driving the supervisor.
    pub fn collect(&mut self, supervisor: &mut Supervisor) {
        for client in &mut self.clients {
            for owed in &mut client.owed {
                let Owed::Forwarded {
                    ticket, request, ..
                } = owed
                else {
                    continue;
                };
                let Some(outcome) = supervisor.take_write_outcome(*ticket) else {
                    continue;
                };
                let reply = match outcome {
                    WriteOutcome::Acknowledged => request.acknowledgement(),
                    WriteOutcome::Refused(code) => refused(request, code),
                    WriteOutcome::NoAnswer => {
                        MebRepr::error_reply(request.id, request.addr, DEVICE_FAILURE)
                    }
                };
                if reply.cmd == MebCmd::ER {
                    client.stats.errors += 1;
                }
                *owed = Owed::Ready(reply);
            }
        }
    }

    /// Answers `ER 04` to forwarded writes that waited longer than
    /// [`ImageServerConfig::max_forward_wait`] for the line, and withdraws
    /// them from the supervisor's queue; one already on the line gets its own
    /// answer. Call with the clock now and then (every tick).
    pub fn expire(&mut self, now: SimTime, supervisor: &mut Supervisor) {
        let max_wait = self.config.max_forward_wait;
        for client in &mut self.clients {
            for owed in &mut client.owed {
                let Owed::Forwarded {
                    ticket,
                    request,
                    since,
                } = owed
                else {
                    continue;
                };
                if now.saturating_since(*since) < max_wait {
                    continue;
                }
                if !supervisor.cancel_forward(*ticket) {
                    // Already on the line: the slave may apply it, so only
                    // its own answer (or the supervisor's retries running
                    // out) may reply; an ER 04 now would say it was not.
                    continue;
                }
                client.stats.errors += 1;
                *owed = Owed::Ready(MebRepr::error_reply(
                    request.id,
                    request.addr,
                    DEVICE_FAILURE,
                ));
            }
        }
    }

    /// The next reply for `client`, written to `buf`: only from the front of
    /// its queue, so a reply never overtakes one owed before it.
    pub fn poll_transmit(&mut self, client: ClientId, buf: &mut [u8]) -> Option<usize> {
        let client = self.clients.iter_mut().find(|c| c.id == client)?;
        let Some(Owed::Ready(reply)) = client.owed.front() else {
            return None;
        };
        let len = reply.emit(buf).ok()?;
        client.owed.pop_front();
        Some(len)
    }

    /// The earliest partial-frame deadline of any client.
    pub fn poll_timeout(&self) -> Option<SimTime> {
        self.clients
            .iter()
            .filter_map(|c| c.decoder.poll_timeout())
            .min()
    }

    /// Expires partial frames held too long: those clients are to be closed.
    pub fn handle_timeout(&mut self, now: SimTime) {
        for client in &mut self.clients {
            if client.decoder.handle_timeout(now) && client.close.is_none() {
                client.close = Some(CloseReason::PartialTimeout);
            }
        }
    }

    /// Whether `client` must be closed, and why. The caller closes it and calls
    /// [`disconnect`](Self::disconnect).
    pub fn close_reason(&self, client: ClientId) -> Option<CloseReason> {
        self.client(client).and_then(|c| c.close)
    }

    /// What `client` sent and got.
    pub fn client_stats(&self, client: ClientId) -> Option<ClientStats> {
        self.client(client).map(|c| c.stats)
    }

    /// Bytes of a partial frame `client` holds (for a partial-frame timeout
    /// kept by the caller).
    pub fn pending(&self, client: ClientId) -> usize {
        self.client(client).map_or(0, |c| c.decoder.buffered())
    }

    /// What `client`'s stream decoder dropped (malformed frames by reason).
    pub fn decoder_stats(&self, client: ClientId) -> Option<MebDecoderStats> {
        self.client(client).map(|c| *c.decoder.stats())
    }

    /// Makes one client read-only (or not), whatever the server's default.
    pub fn set_read_only(&mut self, client: ClientId, read_only: bool) {
        if let Some(c) = self.clients.iter_mut().find(|c| c.id == client) {
            c.read_only = read_only;
        }
    }

    fn client(&self, client: ClientId) -> Option<&Client> {
        self.clients.iter().find(|c| c.id == client)
    }
}

impl Client {
    /// A token bucket: `rate_burst` frames at once, `rate_per_second` after.
    fn take_token(&mut self, now: SimTime, config: &ImageServerConfig) -> bool {
        let elapsed = now.saturating_since(self.refilled_at).as_secs_f64();
        self.refilled_at = self.refilled_at.max(now);
        self.tokens = (self.tokens + elapsed * config.rate_per_second).min(config.rate_burst);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

const DEVICE_FAILURE: MebErrorCode = MebErrorCode::DeviceFailure;

fn error(request: &MebRepr, code: MebErrorCode) -> Option<Owed> {
    Some(Owed::Ready(MebRepr::error_reply(
        request.id,
        request.addr,
        code,
    )))
}

/// The slave's own `ER` code, passed on (a code outside 01–04 as 04).
fn refused(request: &MebRepr, code: u8) -> MebRepr {
    let code = MebErrorCode::from_word(u16::from(code)).unwrap_or(DEVICE_FAILURE);
    MebRepr::error_reply(request.id, request.addr, code)
}

fn words_reply(request: &MebRepr, words: &[u16]) -> Option<Owed> {
    Some(Owed::Ready(MebRepr {
        data: MebWords::from_slice(words)?,
        ..*request
    }))
}

/// The reply owed to `request`, or `None` for frames that get none.
fn answer(
    now: SimTime,
    request: &MebRepr,
    read_only: bool,
    supervisor: &mut Supervisor,
) -> Option<Owed> {
    if request.shape().is_reply() || request.is_broadcast() {
        return None;
    }
    let id = request.id;
    if !supervisor.slave_ids().any(|polled| polled == id) {
        return error(request, MebErrorCode::IllegalAddress);
    }
    let Some((block, word_type)) = request.cmd.block() else {
        return error(request, MebErrorCode::IllegalCommand);
    };
    if request.cnt == 0 {
        return error(request, MebErrorCode::IllegalData);
    }
    if block.access() == MebAccess::Write && read_only {
        return error(request, MebErrorCode::IllegalCommand);
    }
    let first = usize::from(request.addr);
    let end = first + usize::from(request.cnt);
    let in_loop_range =
        |count: usize| first >= usize::from(LOOP_ADDR) && end <= usize::from(LOOP_ADDR) + count;
    match (block, word_type) {
        (MebBlock::Inputs, MebWordType::Analog) if end <= usize::from(IMAGE_INPUTS) => {
            let state = supervisor.loop_state(id)?;
            if state.measured_at.is_none() {
                return error(request, DEVICE_FAILURE);
            }
            words_reply(request, state.inputs.get(first..end)?)
        }
        (MebBlock::Flags, MebWordType::Analog) if in_loop_range(3) => {
            let mirrors = loop_mirrors(now, id, supervisor)?;
            let from = first - usize::from(LOOP_ADDR);
            words_reply(request, mirrors.get(from..from + usize::from(request.cnt))?)
        }
        (MebBlock::Flags, MebWordType::Digital) if in_loop_range(1) => {
            let closed = matches!(supervisor.mode(id)?, LoopMode::Closed);
            words_reply(request, &[u16::from(closed)])
        }
        (MebBlock::Variables, _) if first >= usize::from(LOOP_ADDR) => {
            write_loop_variables(request, word_type, supervisor)
        }
        (MebBlock::Inputs, MebWordType::Digital) if end <= 1 && supervisor.reads_status() => {
            let hall = supervisor.loop_state(id)?.status.hall;
            status_reply(
                request,
                hall.map(|w| [w]).as_ref().map(|w| &w[..]),
                first,
                end,
            )
        }
        (MebBlock::Flags, MebWordType::Analog) if end <= 2 && supervisor.reads_status() => {
            let flags = supervisor.loop_state(id)?.status.flags;
            status_reply(request, flags.as_ref().map(|w| &w[..]), first, end)
        }
        (MebBlock::Flags, MebWordType::Digital) if end <= 1 && supervisor.reads_status() => {
            let status = supervisor.loop_state(id)?.status.status;
            status_reply(
                request,
                status.map(|w| [w]).as_ref().map(|w| &w[..]),
                first,
                end,
            )
        }
        (MebBlock::Inputs | MebBlock::Flags, _) => error(request, MebErrorCode::IllegalAddress),
        // A write that runs from the slave's variables into the loop's.
        (MebBlock::Variables, _) if end > usize::from(LOOP_ADDR) => {
            error(request, MebErrorCode::IllegalAddress)
        }
        // Outputs, and the slave's own variables below the loop's.
        (MebBlock::Outputs | MebBlock::Variables, _) => {
            match supervisor.forward_write(
                now,
                id,
                request.cmd,
                request.addr,
                request.data.as_slice(),
            ) {
                Ok(ticket) => Some(Owed::Forwarded {
                    ticket,
                    request: *request,
                    since: now,
                }),
                Err(ForwardError::NotMeb) => error(request, MebErrorCode::IllegalCommand),
                Err(ForwardError::UnknownSlave(_)) => error(request, MebErrorCode::IllegalAddress),
                Err(ForwardError::QueueFull) => error(request, DEVICE_FAILURE),
                Err(ForwardError::NotAWrite) => error(request, MebErrorCode::IllegalData),
                // The default map's address has no place, or no single
                // place, in the slave's map.
                Err(ForwardError::Map(_)) => error(request, MebErrorCode::IllegalAddress),
            }
        }
    }
}

/// Status words as last read, `ER 04` before the first read.
fn status_reply(
    request: &MebRepr,
    words: Option<&[u16]>,
    first: usize,
    end: usize,
) -> Option<Owed> {
    match words.and_then(|w| w.get(first..end)) {
        Some(words) => words_reply(request, words),
        None => error(request, DEVICE_FAILURE),
    }
}

/// `FA 10`–`12`: set point (rpm, rounded), Kp ×1000, Ki ×1000, each clamped to a word.
fn loop_mirrors(now: SimTime, id: u8, supervisor: &Supervisor) -> Option<[u16; 3]> {
    let word = |x: f64| x.round().clamp(0.0, f64::from(u16::MAX)) as u16;
    let (kp, ki) = supervisor.gains(id)?;
    Some([
        word(supervisor.set_point(id, now)?),
        word(kp * 1000.0),
        word(ki * 1000.0),
    ])
}

/// `VA 10`–`12` and `VD 10`, checked whole before any is applied.
fn write_loop_variables(
    request: &MebRepr,
    word_type: MebWordType,
    supervisor: &mut Supervisor,
) -> Option<Owed> {
    let id = request.id;
    let first = usize::from(request.addr - LOOP_ADDR);
    let words = request.data.as_slice();
    match word_type {
        MebWordType::Analog => {
            if first + words.len() > 3 {
                return error(request, MebErrorCode::IllegalAddress);
            }
            let (mut kp, mut ki) = supervisor.gains(id)?;
            let mut set_point = None;
            for (offset, &word) in words.iter().enumerate() {
                match first + offset {
                    0 if word > SET_POINT_MAX_RPM => {
                        return error(request, MebErrorCode::IllegalData);
                    }
                    0 => set_point = Some(f64::from(word)),
                    1 => kp = f64::from(word) / 1000.0,
                    _ => ki = f64::from(word) / 1000.0,
                }
            }
            if let Some(rpm) = set_point {
                supervisor.set_set_point(id, Some(rpm));
            }
            supervisor.set_gains(id, kp, ki);
        }
        MebWordType::Digital => {
            let &[word] = words else {
                return error(request, MebErrorCode::IllegalAddress);
            };
            if first != 0 {
                return error(request, MebErrorCode::IllegalAddress);
            }
            if word & !1 != 0 {
                return error(request, MebErrorCode::IllegalData);
            }
            let mode = if word & 1 == 1 {
                LoopMode::Closed
            } else {
                // Opening the loop holds the last VEL the slave has.
                let state = supervisor.loop_state(id)?;
                LoopMode::Open {
                    vel: state.vel_written.unwrap_or(state.output),
                }
            };
            if supervisor.mode(id)? != mode {
                supervisor.set_mode(id, mode);
            }
        }
    }
    Some(Owed::Ready(request.acknowledgement()))
}
