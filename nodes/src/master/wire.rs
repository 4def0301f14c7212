//! What the supervisor puts on the wire and how it reads the answers, for
//! both protocols: requests are emitted straight into the caller's buffer,
//! replies are classified against the request they should answer.

use protocols::meb::{MebCmd, MebDecodeError, MebDecoder, MebRepr, MebWords};
use protocols::modbus::pdu::function;
use protocols::modbus::rtu::{self, Direction, RtuDecoder};
use protocols::modbus::serial::Timing;
use protocols::modbus::{Adu, Bits, ExceptionResponse, PduError, Request, Response};
use protocols::time::{SimDuration, SimTime};

use super::layout::MebLayout;
use super::{Protocol, StartupOutputs};

pub(crate) use super::layout::INPUT_WORDS;

/// One request/reply exchange with a slave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Transaction {
    /// Enable the module: write `SD0`, `SD1` (RTU: coils 0–5); on MEB, the
    /// slave's map's span of `SD` words numbered by the second field.
    Startup(StartupOutputs, u8),
    /// Read the six analog inputs: on MEB, the slave's map's span of `EA`
    /// addresses numbered by the field.
    ReadInputs(u8),
    /// Write `VEL`.
    WriteVel(u16),
    /// One block of the slave's status words (MEB only).
    ReadStatus(StatusBlock),
    /// A remote client's MEB write, forwarded (MEB only). The words live in
    /// the supervisor, so this stays a small `Copy` value.
    Forward { cmd: MebCmd, addr: u8, cnt: u8 },
}

impl Transaction {
    /// A short name for events.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Transaction::Startup(..) => "startup write",
            Transaction::ReadInputs(_) => "input read",
            Transaction::WriteVel(_) => "VEL write",
            Transaction::Forward { .. } => "forwarded write",
            Transaction::ReadStatus(_) => "status read",
        }
    }

    /// Emits the request to slave `id` into `out`; `None` if `out` is too small
    /// (or a forwarded write meets a Modbus bus, which the supervisor refuses
    /// before it gets here). `forwarded` holds the words of a `Forward`.
    pub(crate) fn emit(
        self,
        protocol: Protocol,
        id: u8,
        layout: &MebLayout,
        forwarded: &[u16],
        out: &mut [u8],
    ) -> Option<usize> {
        match (protocol, self) {
            (Protocol::Meb, Transaction::Forward { cmd, addr, cnt }) => MebRepr {
                id,
                cmd,
                addr,
                cnt,
                data: MebWords::from_slice(forwarded)?,
            }
            .emit(out)
            .ok(),
            (Protocol::Meb, _) => self.meb_request(id, layout).emit(out).ok(),
            (Protocol::ModbusRtu, _) => rtu::RtuRepr {
                unit: id,
                pdu: &self.rtu_request()?,
            }
            .emit(out)
            .ok(),
        }
    }

    /// The request's header (a forwarded write's words are not held here).
    fn meb_request(self, id: u8, layout: &MebLayout) -> MebRepr {
        let mut data = MebWords::new();
        let (cmd, addr, cnt) = match self {
            Transaction::Startup(outputs, part) => {
                let (first, count) = layout.sd_spans().get(part).unwrap_or((0, 0));
                for word in first..first + count {
                    let _ = data.push(layout.sd_word(word, [outputs.sd0, outputs.sd1]));
                }
                (MebCmd::SD, first, count)
            }
            Transaction::ReadInputs(part) => {
                let (first, count) = layout.input_spans().get(part).unwrap_or((0, 0));
                (MebCmd::EA, first, count)
            }
            Transaction::WriteVel(vel) => {
                let _ = data.push(vel);
                (MebCmd::SA, layout.vel(), 1)
            }
            Transaction::Forward { cmd, addr, cnt } => (cmd, addr, cnt),
            Transaction::ReadStatus(block) => block.header(layout).unwrap_or((MebCmd::FD, 0, 1)),
        };
        MebRepr {
            id,
            cmd,
            addr,
            cnt,
            data,
        }
    }

    /// `None` for a forwarded MEB write, which has no Modbus form.
    fn rtu_request(self) -> Option<Request> {
        Some(match self {
            Transaction::Startup(outputs, _) => {
                let bit = |word: u16, n: u8| word & (1 << n) != 0;
                let coils = [
                    bit(outputs.sd0, 0),
                    bit(outputs.sd0, 1),
                    bit(outputs.sd0, 2),
                    bit(outputs.sd0, 3),
                    bit(outputs.sd0, 4),
                    bit(outputs.sd1, 0),
                ];
                Request::WriteMultipleCoils {
                    address: 0,
                    coils: Bits::from_bools(&coils).unwrap_or_default(),
                }
            }
            Transaction::ReadInputs(_) => Request::ReadInputRegisters {
                address: 0,
                quantity: INPUT_WORDS as u16,
            },
            Transaction::WriteVel(vel) => Request::WriteSingleRegister {
                address: 0,
                value: vel,
            },
            Transaction::Forward { .. } | Transaction::ReadStatus(_) => return None,
        })
    }

    fn rtu_function(self) -> u8 {
        match self {
            Transaction::Startup(..) => function::WRITE_MULTIPLE_COILS,
            Transaction::ReadInputs(_) => function::READ_INPUT_REGISTERS,
            Transaction::WriteVel(_) => function::WRITE_SINGLE_REGISTER,
            // Never sent on a Modbus bus; no function code answers it.
            Transaction::Forward { .. } | Transaction::ReadStatus(_) => 0,
        }
    }
}

/// The slave's status words a supervisor reads now and then, one block per request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum StatusBlock {
    /// `ED 00`: hall code and flag bit.
    Hall,
    /// `FA 00`–`01`: SOC and ERRS (SOC alone where the map puts it apart).
    Flags,
    /// `FA 01`: ERRS, when the map puts SOC apart from it.
    Errs,
    /// `FD 00`: STATUS.
    Status,
}

impl StatusBlock {
    /// The read, or `None` where the map places nothing to read.
    pub(crate) fn header(self, layout: &MebLayout) -> Option<(MebCmd, u8, u8)> {
        match self {
            StatusBlock::Hall => layout.hall().map(|a| (MebCmd::ED, a, 1)),
            StatusBlock::Flags => layout.flags_read().map(|(a, n, _)| (MebCmd::FA, a, n)),
            StatusBlock::Errs => layout.errs_apart().then_some((MebCmd::FA, 1, 1)),
            StatusBlock::Status => Some((MebCmd::FD, 0, 1)),
        }
    }

    /// The first block of a status round.
    pub(crate) fn first(layout: &MebLayout) -> StatusBlock {
        match StatusBlock::Hall.header(layout) {
            Some(_) => StatusBlock::Hall,
            None => StatusBlock::Hall
                .next(layout)
                .unwrap_or(StatusBlock::Status),
        }
    }

    /// The block read after this one in a status round.
    pub(crate) fn next(self, layout: &MebLayout) -> Option<StatusBlock> {
        let mut block = self;
        loop {
            block = match block {
                StatusBlock::Hall => StatusBlock::Flags,
                StatusBlock::Flags => StatusBlock::Errs,
                StatusBlock::Errs => StatusBlock::Status,
                StatusBlock::Status => return None,
            };
            if block.header(layout).is_some() {
                return Some(block);
            }
        }
    }
}

/// What a frame that reached the supervisor means for the pending request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Reply {
    /// The analog inputs asked for: the words and how many.
    Inputs([u16; INPUT_WORDS], u8),
    /// The words of a status block (the second unused for one-word blocks).
    Status(StatusBlock, [u16; 2]),
    /// The write was acknowledged.
    Ack,
    /// The slave refused: MEB `ER` code or Modbus exception code.
    Exception(u8),
    /// The bytes failed the check (FCS, CRC) or the frame's form.
    Bad,
    /// A well-formed frame that answers something else (another slave, a late
    /// reply to an earlier request): not used, the wait goes on.
    Unexpected,
}

/// The stream decoder of replies, per protocol. Reset before each request so
/// that a partial frame left from an earlier exchange cannot swallow the reply.
#[derive(Debug, Clone)]
pub(crate) enum ReplyDecoder {
    Meb(MebDecoder),
    Rtu(RtuDecoder),
}

impl ReplyDecoder {
    pub(crate) fn new(protocol: Protocol, rtu_silence: SimDuration) -> Self {
        match protocol {
            Protocol::Meb => ReplyDecoder::Meb(MebDecoder::new()),
            Protocol::ModbusRtu => ReplyDecoder::Rtu(RtuDecoder::new(
                Direction::Response,
                Timing::Silence(rtu_silence),
            )),
        }
    }

    pub(crate) fn reset(&mut self) {
        match self {
            ReplyDecoder::Meb(decoder) => *decoder = MebDecoder::new(),
            ReplyDecoder::Rtu(decoder) => {
                *decoder = RtuDecoder::new(Direction::Response, decoder.timing());
            }
        }
    }

    /// Takes bytes from the front of `input` up to the next frame or drop and
    /// classifies it against `pending` (slave id and request). `None` once
    /// `input` is used up without a further frame.
    pub(crate) fn next_reply(
        &mut self,
        now: SimTime,
        input: &mut &[u8],
        pending: (u8, Transaction),
        layout: &MebLayout,
    ) -> Option<Reply> {
        match self {
            ReplyDecoder::Meb(decoder) => loop {
                if input.is_empty() {
                    return None;
                }
                let (used, event) = decoder.push(now, input);
                let reply = event.map(|event| match event {
                    Ok(frame) => classify_meb(&MebRepr::from_frame(&frame), pending, layout),
                    // A new `@` before `\n`: the bytes were cut, which is all a
                    // master can tell of a corrupted terminator.
                    Err(MebDecodeError::Interrupted | MebDecodeError::Malformed(_)) => Reply::Bad,
                });
                *input = input.get(used..).unwrap_or_default();
                if reply.is_some() {
                    return reply;
                }
            },
            ReplyDecoder::Rtu(decoder) => {
                let item = decoder.decode(now, input)?;
                Some(match item {
                    Ok(frame) if frame.unit() != pending.0 => Reply::Unexpected,
                    Ok(frame) => classify_rtu(frame.response(), pending.1),
                    // A failed CRC, or bytes no reply can start with.
                    Err(_) => Reply::Bad,
                })
            }
        }
    }
}

fn classify_meb(
    reply: &MebRepr,
    (id, transaction): (u8, Transaction),
    layout: &MebLayout,
) -> Reply {
    if reply.id != id {
        return Reply::Unexpected;
    }
    if reply.cmd == MebCmd::ER {
        return match reply.data.as_slice() {
            &[code] => Reply::Exception(u8::try_from(code).unwrap_or(u8::MAX)),
            _ => Reply::Bad,
        };
    }
    let expected = transaction.meb_request(id, layout);
    if reply.cmd != expected.cmd || reply.addr != expected.addr || reply.cnt != expected.cnt {
        return Reply::Unexpected;
    }
    match transaction {
        Transaction::ReadInputs(_) => inputs(reply.data.as_slice(), expected.cnt),
        Transaction::ReadStatus(block) => {
            let words = reply.data.as_slice();
            match (words.len() == usize::from(expected.cnt), words) {
                (true, &[a]) => Reply::Status(block, [a, 0]),
                (true, &[a, b]) => Reply::Status(block, [a, b]),
                _ => Reply::Unexpected,
            }
        }
        Transaction::Startup(..) | Transaction::WriteVel(_) | Transaction::Forward { .. }
            if reply.data.is_empty() =>
        {
            Reply::Ack
        }
        _ => Reply::Unexpected,
    }
}

fn classify_rtu(
    parsed: Result<Result<Response, ExceptionResponse>, PduError>,
    transaction: Transaction,
) -> Reply {
    let response = match parsed {
        Err(_) => return Reply::Bad,
        Ok(Err(exception)) if exception.function == transaction.rtu_function() => {
            return Reply::Exception(exception.exception.code());
        }
        Ok(Err(_)) => return Reply::Unexpected,
        Ok(Ok(response)) => response,
    };
    match (transaction, response) {
        (Transaction::ReadInputs(_), Response::ReadInputRegisters(values)) => {
            inputs(values.as_slice(), INPUT_WORDS as u8)
        }
        (
            Transaction::Startup(..),
            Response::WriteMultipleCoils {
                address: 0,
                quantity: 6,
            },
        ) => Reply::Ack,
        (Transaction::WriteVel(vel), Response::WriteSingleRegister { address: 0, value })
            if value == vel =>
        {
            Reply::Ack
        }
        _ => Reply::Unexpected,
    }
}

/// The words of an input read, if they are as many as asked for.
fn inputs(words: &[u16], count: u8) -> Reply {
    let mut out = [0; INPUT_WORDS];
    match out.get_mut(..words.len()) {
        Some(slots) if words.len() == usize::from(count) => {
            slots.copy_from_slice(words);
            Reply::Inputs(out, count)
        }
        _ => Reply::Unexpected,
    }
}
