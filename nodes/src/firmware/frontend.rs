//! A slave front end that serves a [`RegisterImage`] it does not own: one per
//! serial port or TCP connection, all serving the same controller's image.
//!
//! [`EvController`](super::EvController) has one serial port and keeps its
//! decoders inside. A real-time server has several links at once (MEB over
//! TCP, Modbus TCP with one decoder per client, RTU on a pty) that must all
//! see one module: each gets a [`SlaveFrontend`] with its own framing and
//! reply queue, and the image is lent to it for every call. The request
//! handling is the controller's own (`meb_slave::serve`,
//! `modbus_slave::serve`); only the framing lives here.

use std::collections::VecDeque;

use crate::node::{MAX_FRAME, NodeEvent};
use protocols::meb::{MebAccess, MebDecodeError, MebDecoder, MebRepr};
use protocols::modbus::pdu::function;
use protocols::modbus::rtu::{Direction, RtuDecoder};
use protocols::modbus::serial::Timing;
use protocols::modbus::tcp::TcpDecoder;
use protocols::modbus::{self, Adu, Drops, MAX_PDU_LEN, ascii::AsciiDecoder};
use protocols::time::{SimDuration, SimTime};

use super::image::{Refusal, RegisterImage};
use super::meb_map::MebMap;
use super::{meb_slave, modbus_slave};

/// Replies the queue is made room for at first. It holds every reply to the
/// bytes of one call, however many requests they pipeline (a caller takes
/// them before it feeds more bytes, so the bytes of one read bound it): no
/// reply is ever dropped.
const FIRST_QUEUED: usize = 16;
/// Events kept until polled.
const MAX_EVENTS: usize = 64;

/// How the front end frames requests and replies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Framing {
    /// MEB (`docs/protocols/meb.md`), on a serial line or TCP.
    Meb,
    /// Modbus RTU on a serial line; this much silence ends a frame.
    ModbusRtu(SimDuration),
    /// Modbus ASCII on a serial line.
    ModbusAscii,
    /// Modbus TCP (MBAP); unit ids 0 and 255 are answered as the slave's own.
    ModbusTcp,
}

impl Framing {
    /// The protocol's name, as the serve command prints it.
    pub fn name(self) -> &'static str {
        match self {
            Framing::Meb => "meb",
            Framing::ModbusRtu(_) => "modbus-rtu",
            Framing::ModbusAscii => "modbus-ascii",
            Framing::ModbusTcp => "modbus-tcp",
        }
    }
}

#[derive(Debug, Clone)]
enum Decoder {
    Meb(Box<MebDecoder>),
    Rtu(Box<RtuDecoder>),
    Ascii(Box<AsciiDecoder>),
    Tcp(Box<TcpDecoder>),
}

/// What a front end has done so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrontendStats {
    /// Well-formed requests addressed to this slave.
    pub requests: u64,
    /// Replies queued (exceptions and error replies included).
    pub replies: u64,
    /// Requests refused because the client is read-only.
    pub read_only_refusals: u64,
    /// Frames dropped for bad form or check.
    pub malformed: u64,
}

/// One link's slave front end. See the module documentation.
#[derive(Debug, Clone)]
pub struct SlaveFrontend {
    framing: Framing,
    id: u8,
    read_only: bool,
    forced: Option<Refusal>,
    /// MEB addresses other than the default map's.
    map: Option<Box<MebMap>>,
    decoder: Decoder,
    /// The PDU of the frame being served.
    pdu: [u8; MAX_PDU_LEN],
    /// Queued replies, back to back; their lengths in `lengths`.
    out: Vec<u8>,
    lengths: VecDeque<usize>,
    /// Drops already added to the image's ERRS.
    counted_drops: u64,
    stats: FrontendStats,
    events: VecDeque<NodeEvent>,
    /// Why the connection must close (a Modbus TCP header that cannot be
    /// valid): nothing after it is served.
    close: Option<String>,
}

impl SlaveFrontend {
    /// A front end for slave `id` (MEB slave number or Modbus unit id).
    pub fn new(framing: Framing, id: u8) -> Self {
        let decoder = match framing {
            Framing::Meb => Decoder::Meb(Box::default()),
            Framing::ModbusRtu(silence) => Decoder::Rtu(Box::new(RtuDecoder::new(
                Direction::Request,
                Timing::Silence(silence),
            ))),
            Framing::ModbusAscii => Decoder::Ascii(Box::default()),
            Framing::ModbusTcp => Decoder::Tcp(Box::new(TcpDecoder::for_server())),
        };
        SlaveFrontend {
            framing,
            id,
            read_only: false,
            forced: None,
            map: None,
            decoder,
            pdu: [0; MAX_PDU_LEN],
            out: Vec::with_capacity(FIRST_QUEUED * MAX_FRAME),
            lengths: VecDeque::with_capacity(FIRST_QUEUED),
            counted_drops: 0,
            stats: FrontendStats::default(),
            events: VecDeque::with_capacity(MAX_EVENTS),
            close: None,
        }
    }

    /// Refuse every write (MEB `ER 01`, Modbus exception 01).
    pub fn set_read_only(&mut self, read_only: bool) {
        self.read_only = read_only;
    }

    /// Answer every request addressed to this slave with `refusal` instead
    /// (an injected fault), or serve normally again with `None`.
    pub fn set_forced_refusal(&mut self, refusal: Option<Refusal>) {
        self.forced = refusal;
    }

    /// Serve MEB at the addresses `map` gives (the M3CVME tool's configurable I/O
    /// map); the default map needs none.
    pub fn set_meb_map(&mut self, map: Option<MebMap>) {
        self.map = map.filter(|m| !m.is_default()).map(Box::new);
    }

    /// Answer as slave `id` from the next request on (the M3CVME tool's
    /// device number, changed while the slave runs).
    pub fn set_id(&mut self, id: u8) {
        self.id = id;
    }

    /// The framing.
    pub fn framing(&self) -> Framing {
        self.framing
    }

    /// The slave id served.
    pub fn id(&self) -> u8 {
        self.id
    }

    /// What it has done so far.
    pub fn stats(&self) -> &FrontendStats {
        &self.stats
    }

    /// Why the connection must be closed, once a request showed it cannot
    /// go on (a Modbus TCP header that cannot be valid: no frame boundary
    /// can be found after it).
    pub fn close_request(&self) -> Option<&str> {
        self.close.as_deref()
    }

    /// Bytes held for a request that is not complete yet.
    pub fn pending(&self) -> usize {
        match &self.decoder {
            Decoder::Meb(d) => d.buffered(),
            Decoder::Rtu(d) => d.pending(),
            Decoder::Ascii(d) => d.pending(),
            Decoder::Tcp(d) => d.pending(),
        }
    }

    /// Bytes thrown away so far as noise: outside any frame, neither part of
    /// a request nor of a frame in progress (MEB bytes before an `@`,
    /// Modbus ASCII bytes before a `:`). A binary framing has none: any
    /// byte may start a frame.
    pub fn noise_bytes(&self) -> u64 {
        match &self.decoder {
            Decoder::Meb(d) => d.stats().noise_bytes,
            Decoder::Ascii(d) => d.drops().noise.bytes,
            Decoder::Rtu(_) | Decoder::Tcp(_) => 0,
        }
    }

    /// When [`SlaveFrontend::handle_timeout`] is due (RTU's silence rule).
    pub fn poll_timeout(&self) -> Option<SimTime> {
        match &self.decoder {
            Decoder::Rtu(d) => d.poll_timeout(),
            _ => None,
        }
    }

    /// Take the next event to record, if any.
    pub fn poll_event(&mut self) -> Option<NodeEvent> {
        self.events.pop_front()
    }

    /// The oldest queued reply, written to `buf`; its length.
    pub fn poll_transmit(&mut self, buf: &mut [u8]) -> Option<usize> {
        let len = self.lengths.pop_front()?;
        let frame = self.out.get(..len)?;
        let n = len.min(buf.len());
        buf.get_mut(..n)?.copy_from_slice(frame.get(..n)?);
        self.out.drain(..len);
        Some(n)
    }

    /// Bytes that arrived at `now`: serve every complete request from `image`.
    pub fn handle_bytes(&mut self, image: &mut RegisterImage, now: SimTime, bytes: &[u8]) {
        let mut input = bytes;
        while self.close.is_none()
            && let Some(decoded) = self.next_request(now, &mut input)
        {
            self.serve(image, now, decoded);
        }
        self.count_drops(image);
    }

    /// The silence rule at `now` (RTU): a frame only the silence ends is served.
    pub fn handle_timeout(&mut self, image: &mut RegisterImage, now: SimTime) {
        let pdu = &mut self.pdu;
        let decoded = match &mut self.decoder {
            Decoder::Rtu(decoder) if decoder.poll_timeout().is_some_and(|t| t <= now) => decoder
                .handle_timeout(now)
                .map(|f| modbus_decoded(f.map(|f| (f.unit(), f.pdu(), None)), pdu)),
            _ => None,
        };
        if let Some(decoded) = decoded {
            self.serve(image, now, decoded);
        }
        self.count_drops(image);
    }

    /// The next complete frame (or dropped one) from the front of `input`.
    fn next_request(&mut self, now: SimTime, input: &mut &[u8]) -> Option<Decoded> {
        let pdu = &mut self.pdu;
        match &mut self.decoder {
            Decoder::Meb(decoder) => {
                while !input.is_empty() {
                    let (used, event) = decoder.push(now, input);
                    let event = event.map(|e| e.map(|frame| MebRepr::from_frame(&frame)));
                    *input = input.get(used..).unwrap_or_default();
                    match event {
                        None => {}
                        Some(Ok(request)) => return Some(Decoded::Meb(Box::new(request))),
                        Some(Err(MebDecodeError::Malformed(kind))) => {
                            return Some(Decoded::Bad(kind.name()));
                        }
                        Some(Err(MebDecodeError::Interrupted)) => {
                            return Some(Decoded::Bad("interrupted"));
                        }
                    }
                }
                None
            }
            Decoder::Rtu(decoder) => decoder
                .decode(now, input)
                .map(|f| modbus_decoded(f.map(|f| (f.unit(), f.pdu(), None)), pdu)),
            Decoder::Ascii(decoder) => decoder
                .decode(input)
                .map(|f| modbus_decoded(f.map(|f| (f.unit(), f.pdu(), None)), pdu)),
            // A server's decoder fails only on a header that cannot be valid.
            Decoder::Tcp(decoder) => Some(match decoder.decode(input)? {
                Ok(f) => modbus_decoded(Ok((f.unit(), f.pdu(), Some(f.transaction_id()))), pdu),
                Err(fault) => Decoded::Fatal(fault),
            }),
        }
    }

    fn serve(&mut self, image: &mut RegisterImage, now: SimTime, decoded: Decoded) {
        match decoded {
            Decoded::Meb(request) => self.serve_meb(image, &request),
            Decoded::Modbus {
                unit,
                len,
                transaction,
            } => {
                let pdu = self.pdu;
                self.serve_modbus(image, unit, pdu.get(..len).unwrap_or_default(), transaction);
            }
            Decoded::Bad(why) => {
                self.event(now, "bad_check", why);
                self.count_drops(image);
            }
            Decoded::Fatal(fault) => {
                let why = format!(
                    "Modbus TCP header that cannot be valid ({fault}): no request can be found \
                     after it, so the connection is closed, as Modbus TCP servers do"
                );
                self.close = Some(why);
            }
        }
    }

    fn drops_total(&self) -> u64 {
        let modbus = |d: &Drops| {
            d.bad_check.events + d.timed_out.events + d.oversize.events + d.malformed.events
        };
        match &self.decoder {
            Decoder::Meb(d) => d.stats().dropped_frames(),
            Decoder::Rtu(d) => modbus(d.drops()),
            Decoder::Ascii(d) => modbus(d.drops()),
            Decoder::Tcp(d) => modbus(d.drops()),
        }
    }

    /// Adds this link's new drops to the image's ERRS (shared by every link).
    fn count_drops(&mut self, image: &mut RegisterImage) {
        let total = self.drops_total();
        let new = total.saturating_sub(self.counted_drops);
        if new > 0 {
            self.counted_drops = total;
            self.stats.malformed += new;
            let new = u16::try_from(new).unwrap_or(u16::MAX);
            image.errs = image.errs.saturating_add(new);
        }
    }

    fn event(&mut self, at: SimTime, kind: &'static str, detail: &str) {
        if self.events.len() >= MAX_EVENTS {
            self.events.pop_front();
        }
        self.events.push_back(NodeEvent {
            at,
            kind,
            detail: detail.into(),
        });
    }

    /// Appends a reply; `emit` writes it into the slot it is given.
    fn queue(&mut self, emit: impl FnOnce(&mut [u8]) -> Option<usize>) {
        let start = self.out.len();
        self.out.resize(start + MAX_FRAME, 0);
        let len = self.out.get_mut(start..).and_then(emit);
        self.out.truncate(start + len.unwrap_or(0));
        if let Some(len) = len {
            self.lengths.push_back(len);
            self.stats.replies += 1;
        }
    }

    /// What a request is refused with before it is served: an injected
    /// fault, or a write from a read-only client.
    fn refusal(&mut self, write: bool) -> Option<Refusal> {
        if self.forced.is_some() {
            return self.forced;
        }
        (self.read_only && write).then(|| {
            self.stats.read_only_refusals += 1;
            Refusal::IllegalCommand
        })
    }

    fn serve_meb(&mut self, image: &mut RegisterImage, request: &MebRepr) {
        if request.shape().is_reply() || (request.id != self.id && !request.is_broadcast()) {
            return;
        }
        self.stats.requests += 1;
        let write = request
            .cmd
            .block()
            .is_some_and(|(block, _)| block.access() == MebAccess::Write);
        let refusal = self.refusal(write);
        let reply = match refusal {
            Some(refusal) => meb_slave::refuse(self.id, request, refusal),
            None => meb_slave::serve_mapped(image, self.id, request, self.map.as_deref()),
        };
        if let Some(reply) = reply {
            self.queue(|slot| reply.emit(slot).ok());
        }
    }

    fn serve_modbus(
        &mut self,
        image: &mut RegisterImage,
        unit: u8,
        pdu: &[u8],
        transaction: Option<u16>,
    ) {
        // Over TCP the unit id picks a device behind a gateway: 0 and 255
        // mean "this device" (docs/protocols/modbus-map.md).
        let request_unit = unit;
        let unit = match transaction {
            Some(_) if unit == 0 || unit == 255 => self.id,
            _ => unit,
        };
        let broadcast = unit == 0;
        if unit != self.id && !broadcast {
            return;
        }
        let Some(&code) = pdu.first() else { return };
        self.stats.requests += 1;
        let write = matches!(
            code,
            function::WRITE_SINGLE_COIL
                | function::WRITE_SINGLE_REGISTER
                | function::WRITE_MULTIPLE_COILS
                | function::WRITE_MULTIPLE_REGISTERS
        );
        let refusal = self.refusal(write);
        let reply = match refusal {
            Some(refusal) => modbus_slave::refuse(self.id, unit, pdu, refusal),
            None => modbus_slave::serve(image, self.id, unit, pdu),
        };
        let Some(reply) = reply else { return };
        let id = self.id;
        let framing = self.framing;
        let reply_unit = transaction.map_or(id, |_| request_unit);
        self.queue(|slot| match (framing, transaction) {
            (Framing::ModbusTcp, Some(tid)) => modbus::tcp::TcpRepr {
                transaction_id: tid,
                unit: reply_unit,
                pdu: &reply,
            }
            .emit(slot)
            .ok(),
            (Framing::ModbusAscii, _) => modbus::ascii::AsciiRepr {
                unit: id,
                pdu: &reply,
            }
            .emit(slot)
            .ok(),
            _ => modbus::rtu::RtuRepr {
                unit: id,
                pdu: &reply,
            }
            .emit(slot)
            .ok(),
        });
    }
}

/// A frame out of a decoder, its PDU copied out so the decoder can go on.
#[derive(Debug)]
enum Decoded {
    Meb(Box<MebRepr>),
    Modbus {
        unit: u8,
        len: usize,
        transaction: Option<u16>,
    },
    Bad(&'static str),
    /// A framing fault no later frame can be found after.
    Fatal(modbus::FrameError),
}

fn modbus_decoded(
    frame: Result<(u8, &[u8], Option<u16>), modbus::FrameError>,
    dst: &mut [u8; MAX_PDU_LEN],
) -> Decoded {
    match frame {
        Ok((unit, src, transaction)) => {
            let len = src.len().min(MAX_PDU_LEN);
            dst[..len].copy_from_slice(&src[..len]);
            Decoded::Modbus {
                unit,
                len,
                transaction,
            }
        }
        Err(_) => Decoded::Bad("modbus frame"),
    }
}
