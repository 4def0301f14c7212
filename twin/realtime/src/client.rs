//! A remote MEB client over TCP, the third role of the M3CVME tool: one
//! request at a time to a supervisor's server (`twin supervise --listen`) or
//! to an MEB slave served over TCP (`twin serve --meb tcp://…`).

use protocols::meb::{
    MEB_BROADCAST_ID, MEB_MAX_FRAME_LEN, MebAccess, MebCmd, MebDecodeError, MebDecoder,
    MebEmitError, MebErrorCode, MebRepr, MebWords,
};
use protocols::time::SimTime;

use crate::io::spec::{LinkSpec, LinkSpecError};
use crate::typed_line::OnOff;
use clap::Parser;
use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

/// Why a request to an MEB server got no usable answer, or could not be
/// sent.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error(transparent)]
    Url(#[from] LinkSpecError),
    #[error("cannot connect to {url} (is `twin supervise --listen {url}` running?)")]
    Connect {
        url: String,
        #[source]
        source: std::io::Error,
    },
    /// The connection, made, could not be set up (no delay, a read timeout).
    #[error("cannot set up the connection to {peer}")]
    Socket {
        peer: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot build the request")]
    Build(#[source] MebEmitError),
    #[error("the server closed the connection")]
    Send(#[source] std::io::Error),
    /// The server kept quiet for the whole timeout.
    #[error(
        "no reply from {peer} within {timeout_ms} ms to {request}: is a module with id {id} \
         there? A slave answers only its own id (--id; `twin serve --id {id}`, the M3CVME \
         tool's slave number)"
    )]
    NoReply {
        peer: SocketAddr,
        timeout_ms: u128,
        request: String,
        id: u8,
    },
    #[error("{peer} closed the connection")]
    Closed { peer: SocketAddr },
    #[error("reading the reply")]
    Read(#[source] std::io::Error),
    #[error("id 00 is broadcast: a broadcast read is never answered (docs/protocols/meb.md)")]
    BroadcastRead,
    #[error("the reply to {request} carries {got} words, not {wanted}")]
    WordCount {
        request: String,
        got: usize,
        wanted: u8,
    },
    #[error("at most 99 words per write")]
    TooManyWords,
    #[error(
        "{cmd} is written, not read: MEB reads only EA, ED, FA and FD (write it with `write {cmd} ADDR WORD`)"
    )]
    NotRead { cmd: MebCmd },
    #[error(
        "{cmd} is read, not written: MEB writes only SA, SD, VA and VD (read it with `read {cmd} ADDR CNT`)"
    )]
    NotWritten { cmd: MebCmd },
    /// The slave's `ER` reply, with what its code means.
    #[error("slave {id:02} answered {request} with ER {code:02}: {meaning}")]
    Refused {
        id: u8,
        request: String,
        code: u16,
        meaning: &'static str,
    },
}

type Result<T, E = ClientError> = std::result::Result<T, E>;

/// A word, command or count typed (on `twin client`'s command line or its
/// prompt) that does not read as one.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ArgumentError {
    #[error("count `{0}` is not 1-99")]
    Count(String),
    #[error("`{0}` is not a number")]
    NotANumber(String),
    #[error("gain {0} outside 0-65.535")]
    Gain(f64),
    #[error("`{0}` is not a command (EA ED SA SD VA VD FA FD)")]
    Command(String),
    #[error("address `{0}` is not hex 00-FF (addresses are hex, as on the wire: FA 10 is 0x10)")]
    Address(String),
    #[error("value `{0}` is not a 16-bit word (0-65535, or 0x0000-0xFFFF)")]
    Word(String),
}

/// Which way a frame went, for the monitor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Way {
    Sent,
    Received,
}

/// Sees each frame: its direction, seconds since connecting, its bytes.
type Monitor = Box<dyn FnMut(Way, f64, &[u8])>;

/// A connection to an MEB server.
pub struct MebClient {
    stream: TcpStream,
    decoder: MebDecoder,
    timeout: Duration,
    peer: SocketAddr,
    started: Instant,
    monitor: Option<Monitor>,
}

impl std::fmt::Debug for MebClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MebClient")
            .field("peer", &self.peer)
            .finish_non_exhaustive()
    }
}

/// `tcp://HOST:PORT` (or `HOST:PORT`) to a socket address, read as every
/// link of the twin is ([`LinkSpec`]), so a mistake gets the same words.
pub fn parse_url(url: &str) -> Result<SocketAddr> {
    Ok(LinkSpec::parse_tcp_peer(
        url,
        "a client's address takes no options",
    )?)
}

impl MebClient {
    /// Connects within `timeout`; each reply is waited for that long too.
    pub fn connect(url: &str, timeout: Duration) -> Result<Self> {
        let peer = parse_url(url)?;
        let stream =
            TcpStream::connect_timeout(&peer, timeout).map_err(|source| ClientError::Connect {
                url: url.to_string(),
                source,
            })?;
        stream
            .set_nodelay(true)
            .map_err(|source| ClientError::Socket { peer, source })?;
        Ok(Self {
            stream,
            decoder: MebDecoder::new(),
            timeout,
            peer,
            started: Instant::now(),
            monitor: None,
        })
    }

    /// Shows every frame both ways (`-v`).
    pub fn set_monitor(&mut self, monitor: impl FnMut(Way, f64, &[u8]) + 'static) {
        self.monitor = Some(Box::new(monitor));
    }

    fn show(&mut self, way: Way, bytes: &[u8]) {
        let at = self.started.elapsed().as_secs_f64();
        if let Some(monitor) = &mut self.monitor {
            monitor(way, at, bytes);
        }
    }

    /// Sends `request` and waits for its reply: the reply frame, which may be
    /// an `ER` (see [`check`]). Frames that do not answer it (another id or
    /// command) are skipped; malformed bytes are dropped.
    pub fn request(&mut self, request: &MebRepr) -> Result<MebRepr> {
        let mut out = [0u8; MEB_MAX_FRAME_LEN];
        let len = request.emit(&mut out).map_err(ClientError::Build)?;
        self.show(Way::Sent, &out[..len]);
        self.stream
            .write_all(&out[..len])
            .map_err(ClientError::Send)?;
        let deadline = Instant::now() + self.timeout;
        let mut buf = [0u8; 1024];
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(ClientError::NoReply {
                    peer: self.peer,
                    timeout_ms: self.timeout.as_millis(),
                    request: describe(request),
                    id: request.id,
                });
            }
            self.stream
                .set_read_timeout(Some(left))
                .map_err(|source| ClientError::Socket {
                    peer: self.peer,
                    source,
                })?;
            let n = match self.stream.read(&mut buf) {
                Ok(0) => return Err(ClientError::Closed { peer: self.peer }),
                Ok(n) => n,
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {
                    continue;
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => continue,
                Err(e) => return Err(ClientError::Read(e)),
            };
            let mut rest = &buf[..n];
            while !rest.is_empty() {
                let (used, event) = self.decoder.push(SimTime::ZERO, rest);
                let frame = match event {
                    Some(Ok(frame)) => {
                        Some((MebRepr::from_frame(&frame), frame.as_bytes().to_vec()))
                    }
                    Some(Err(MebDecodeError::Malformed(_) | MebDecodeError::Interrupted))
                    | None => None,
                };
                rest = &rest[used..];
                if let Some((reply, bytes)) = frame {
                    self.show(Way::Received, &bytes);
                    if answers(request, &reply) {
                        return Ok(reply);
                    }
                }
            }
        }
    }

    /// Reads `cnt` words from `cmd addr`.
    pub fn read(&mut self, id: u8, cmd: MebCmd, addr: u8, cnt: u8) -> Result<Vec<u16>> {
        if id == MEB_BROADCAST_ID {
            return Err(ClientError::BroadcastRead);
        }
        refuse_wrong_direction(cmd, MebAccess::Read)?;
        let request = MebRepr {
            id,
            cmd,
            addr,
            cnt,
            data: MebWords::new(),
        };
        let reply = check(&request, self.request(&request)?)?;
        if reply.data.len() != usize::from(cnt) {
            return Err(ClientError::WordCount {
                request: describe(&request),
                got: reply.data.len(),
                wanted: cnt,
            });
        }
        Ok(reply.data.as_slice().to_vec())
    }

    /// Writes `words` to `cmd addr`; `Ok` once acknowledged.
    pub fn write(&mut self, id: u8, cmd: MebCmd, addr: u8, words: &[u16]) -> Result<()> {
        let data = MebWords::from_slice(words).ok_or(ClientError::TooManyWords)?;
        refuse_wrong_direction(cmd, MebAccess::Write)?;
        let request = MebRepr {
            id,
            cmd,
            addr,
            cnt: data.len() as u8,
            data,
        };
        if id == MEB_BROADCAST_ID {
            // Every slave applies it, none answers: nothing to wait for.
            let mut out = [0u8; MEB_MAX_FRAME_LEN];
            let len = request.emit(&mut out).map_err(ClientError::Build)?;
            self.show(Way::Sent, &out[..len]);
            return self
                .stream
                .write_all(&out[..len])
                .map_err(ClientError::Send);
        }
        check(&request, self.request(&request)?).map(|_| ())
    }
}

/// A read of a write-only block (or the reverse) has the shape of a reply, and
/// the MEB page says reply-shaped frames are never answered: refuse it here
/// rather than wait for a reply that cannot come.
fn refuse_wrong_direction(cmd: MebCmd, wanted: MebAccess) -> Result<()> {
    let Some((block, _)) = cmd.block() else {
        return Ok(());
    };
    match (wanted, block.access()) {
        (MebAccess::Read, MebAccess::Write) => Err(ClientError::NotRead { cmd }),
        (MebAccess::Write, MebAccess::Read) => Err(ClientError::NotWritten { cmd }),
        _ => Ok(()),
    }
}

/// Whether `reply` answers `request`: same id, and its command or `ER` at its address.
fn answers(request: &MebRepr, reply: &MebRepr) -> bool {
    reply.id == request.id
        && (reply.cmd == MebCmd::ER && reply.addr == request.addr
            || reply.cmd == request.cmd && reply.addr == request.addr && reply.cnt == request.cnt)
        && reply.shape().is_reply()
}

/// An `ER` reply as an error that says what it means.
pub fn check(request: &MebRepr, reply: MebRepr) -> Result<MebRepr> {
    if reply.cmd != MebCmd::ER {
        return Ok(reply);
    }
    let code = reply.data.as_slice().first().copied().unwrap_or(0);
    let meaning = match MebErrorCode::from_word(code) {
        Some(MebErrorCode::IllegalCommand) => {
            "illegal command (unknown, a write to a read-only server, or one it cannot forward)"
        }
        Some(MebErrorCode::IllegalAddress) => {
            "illegal address (not in the image or the slave's map)"
        }
        Some(MebErrorCode::IllegalData) => "illegal data (count 0 or a value out of range)",
        Some(MebErrorCode::DeviceFailure) => {
            "device failure (the slave did not answer, or cannot apply it now)"
        }
        None => "unknown error code",
    };
    Err(ClientError::Refused {
        id: request.id,
        request: describe(request),
        code,
        meaning,
    })
}

/// `EA 00 CNT 03`, as a user would say it.
pub fn describe(request: &MebRepr) -> String {
    match request.cmd.block().map(|(block, _)| block.access()) {
        Some(MebAccess::Write) => format!(
            "{} {:02X} = {}",
            request.cmd,
            request.addr,
            request
                .data
                .iter()
                .map(u16::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
        _ => format!("{} {:02X} count {}", request.cmd, request.addr, request.cnt),
    }
}

/// The tag of a word in the default map and the supervisor's image, if it has one.
pub fn tag(cmd: MebCmd, addr: usize) -> Option<&'static str> {
    Some(match (&cmd.letters(), addr) {
        (b"EA", 0) => "V2",
        (b"EA", 1) => "I",
        (b"EA", 2) => "V1",
        (b"EA", 3) => "RPM_M",
        (b"EA", 4) => "RPM_L",
        (b"EA", 5) => "LDR",
        (b"ED", 0) => "HALL",
        (b"SA", 0) => "VEL",
        (b"SD", 0) => "EN/BRK/PRO/DES/FR",
        (b"SD", 1) => "CHG",
        (b"VA", 0) => "LDR_TH",
        (b"VA", 1) => "RPM_WIN",
        (b"VD", 0) => "LDR_ADAPT",
        (b"FA", 0) => "SOC",
        (b"FA", 1) => "ERRS",
        (b"FD", 0) => "STATUS",
        (b"VA" | b"FA", 0x10) => "SET_POINT",
        (b"VA" | b"FA", 0x11) => "KP_x1000",
        (b"VA" | b"FA", 0x12) => "KI_x1000",
        (b"VD" | b"FD", 0x10) => "LOOP_CLOSED",
        _ => return None,
    })
}

/// The interactive prompt's commands (`twin client` without a command),
/// one a line.
#[derive(Debug, Parser)]
#[command(
    name = "meb>",
    no_binary_name = true,
    disable_help_flag = true,
    disable_version_flag = true,
    override_usage = "<COMMAND> [ARGS]...",
    help_template = "Commands, one a line (`help COMMAND` tells more of one):\n{subcommands}",
    max_term_width = 100
)]
pub enum Prompt {
    /// The inputs and the loop
    Show,
    /// Read CNT words from CMD ADDR, e.g. `read EA 0 6`, `read FA 10 3`
    Read {
        /// Two letters: EA, ED, FA or FD (the blocks read)
        #[arg(value_parser = parse_cmd)]
        cmd: MebCmd,
        /// Hex, as on the wire
        #[arg(value_parser = parse_addr)]
        addr: u8,
        /// How many words, 1-99
        #[arg(default_value_t = 1, value_parser = parse_count)]
        cnt: u8,
    },
    /// Write words to CMD ADDR, e.g. `write SA 0 2048`
    Write {
        /// Two letters: SA, SD, VA or VD (the blocks written)
        #[arg(value_parser = parse_cmd)]
        cmd: MebCmd,
        /// Hex, as on the wire
        #[arg(value_parser = parse_addr)]
        addr: u8,
        /// Decimal, or hex with 0x
        #[arg(required = true, value_parser = parse_word)]
        values: Vec<u16>,
    },
    /// VA 10: the loop's set point
    SetPoint {
        #[arg(value_parser = parse_word)]
        rpm: u16,
    },
    /// VA 11, VA 12: the loop's gains (x1000 on the wire)
    Gains {
        #[arg(value_parser = parse_gain, allow_negative_numbers = true)]
        kp: u16,
        #[arg(value_parser = parse_gain, allow_negative_numbers = true)]
        ki: u16,
    },
    /// VD 10: close or open the loop
    Loop {
        #[arg(value_enum, value_name = "on|off")]
        on: OnOff,
    },
    /// SA 00: VEL (the loop rewrites it while closed)
    Vel {
        #[arg(value_parser = parse_word)]
        counts: u16,
    },
    /// SD 00: EN with the brake released
    Enable,
    /// SD 00: everything off
    Disable,
    /// End the session
    #[command(alias = "exit")]
    Quit,
}

/// A count of words, as MEB carries: 1 to 99.
pub fn parse_count(text: &str) -> Result<u8, ArgumentError> {
    text.parse::<u8>()
        .ok()
        .filter(|n| (1..=99).contains(n))
        .ok_or_else(|| ArgumentError::Count(text.to_string()))
}

/// A gain as typed (`0.45`) to its word on the wire (x1000).
pub fn parse_gain(text: &str) -> Result<u16, ArgumentError> {
    let v: f64 = text
        .parse()
        .map_err(|_| ArgumentError::NotANumber(text.to_string()))?;
    if !(0.0..=65.535).contains(&v) {
        return Err(ArgumentError::Gain(v));
    }
    Ok((v * 1000.0).round() as u16)
}

/// A command as typed: two letters, any case (the server judges it).
pub fn parse_cmd(text: &str) -> Result<MebCmd, ArgumentError> {
    match text.as_bytes() {
        &[a, b] => MebCmd::new([a.to_ascii_uppercase(), b.to_ascii_uppercase()]),
        _ => None,
    }
    .ok_or_else(|| ArgumentError::Command(text.to_string()))
}

/// An address as on the wire: hex, `00`–`FF` (`0x` allowed).
pub fn parse_addr(text: &str) -> Result<u8, ArgumentError> {
    let digits = text.strip_prefix("0x").unwrap_or(text);
    u8::from_str_radix(digits, 16).map_err(|_| ArgumentError::Address(text.to_string()))
}

/// A word value: decimal, or hex with `0x`.
pub fn parse_word(text: &str) -> Result<u16, ArgumentError> {
    let parsed = match text.strip_prefix("0x") {
        Some(hex) => u16::from_str_radix(hex, 16),
        None => text.parse(),
    };
    parsed.map_err(|_| ArgumentError::Word(text.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn typed_arguments_parse_as_the_help_says() {
        assert_eq!(parse_addr("10").unwrap(), 0x10);
        assert_eq!(parse_addr("0x0a").unwrap(), 0x0A);
        assert!(parse_addr("100").is_err());
        assert_eq!(parse_word("2048").unwrap(), 2048);
        assert_eq!(parse_word("0x001D").unwrap(), 0x1D);
        assert!(parse_word("70000").is_err());
        assert_eq!(parse_cmd("ea").unwrap(), MebCmd::EA);
        assert!(parse_cmd("E1").is_err());
    }

    #[test]
    fn the_prompt_reads_its_commands_and_says_what_is_wrong() {
        use crate::typed_line::{self, Typed};
        let read = |line: &str| typed_line::read::<Prompt>(line);
        assert!(matches!(
            read("read fa 10 3"),
            Ok(Typed::Command(Prompt::Read {
                cmd: MebCmd::FA,
                addr: 0x10,
                cnt: 3
            }))
        ));
        assert!(matches!(
            read("read EA 0"),
            Ok(Typed::Command(Prompt::Read { cnt: 1, .. }))
        ));
        assert!(matches!(
            read("write SD 0 0x000E 1"),
            Ok(Typed::Command(Prompt::Write { values, .. })) if values == [0x0E, 1]
        ));
        assert!(matches!(
            read("gains 0.45 2.5"),
            Ok(Typed::Command(Prompt::Gains { kp: 450, ki: 2500 }))
        ));
        assert!(matches!(
            read("loop off"),
            Ok(Typed::Command(Prompt::Loop { on: OnOff::Off }))
        ));
        for (line, prompt) in [
            ("show", "Show"),
            ("set-point 1500", "SetPoint"),
            ("vel 1000", "Vel"),
            ("enable", "Enable"),
            ("disable", "Disable"),
            ("quit", "Quit"),
            ("exit", "Quit"),
        ] {
            let got = format!("{:?}", read(line));
            assert!(got.contains(prompt), "{line}: {got}");
        }
        assert!(matches!(read("  "), Ok(Typed::Blank)));
        let Ok(Typed::Help(help)) = read("help") else {
            panic!("no help")
        };
        for command in [
            "show",
            "read",
            "write",
            "set-point",
            "gains",
            "loop",
            "vel",
            "enable",
            "disable",
            "quit",
        ] {
            assert!(
                help.contains(&format!("\n  {command} ")),
                "{command}: {help}"
            );
        }
        for (line, why) in [
            ("write VA 10 70000", "value `70000` is not a 16-bit word"),
            ("write VA 10", "<VALUES>..."),
            ("read EA zz", "address `zz` is not hex"),
            ("read E1 0", "`E1` is not a command"),
            ("read EA 0 100", "count `100` is not 1-99"),
            ("gains 70 1", "gain 70 outside 0-65.535"),
            ("gains -1 1", "gain -1 outside"),
            ("loop maybe", "[possible values: on, off]"),
            ("bogus", "unrecognized subcommand 'bogus'"),
        ] {
            let e = read(line).err().unwrap_or_default();
            assert!(e.starts_with("error: ") && e.contains(why), "{line}: {e}");
        }
    }
}
