//! Link specs: where a link is and how it is set up, the one reading of
//! `tcp://HOST:PORT` for the real-time links, `twin client` and `twin
//! panel`, and serve-bench (which builds codecs only, so the grammar lives
//! here rather than beside the links).
//!
//! ```text
//! tcp://HOST:PORT[?turnaround_ms=0]           a TCP listener (port 0: any free port),
//!                                             or the slave a master connects to
//! PATH[?baud=9600&parity=E&stop=2&data=8&turnaround_ms=1&pace=1&silence_ms=5]
//!                                             a serial device or pseudo-terminal
//! ```
//!
//! `silence_ms` is the line quiet that ends a partial frame (the binary
//! framings: Modbus RTU and the 8-byte Modbus). Bytes do not arrive as they
//! were sent: a pty delivers them as the writer's scheduling allows, and a
//! USB serial adapter holds them for up to 16 ms (an FTDI chip's latency
//! timer) before it sends a burst. So the default is the protocol page's 5 ms
//! on a pty and 20 ms on a serial port, where the line's 3.5 characters
//! (0.3 ms at 115 200 baud) would cut every frame a USB adapter splits.
//!
//! Any other `SCHEME://` is refused. Options not given in the spec come from
//! [`LinkDefaults`] (the command line's `--baud`, `--turnaround-ms`,
//! `--pace`); a link that takes none (`twin replay --frames-to`) is parsed
//! by [`LinkSpec::parse_without_options`].

use crate::time::SimDuration;
use std::fmt;
use std::net::{SocketAddr, ToSocketAddrs};
use std::path::{Path, PathBuf};

/// Parity of a serial line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parity {
    None,
    Even,
    Odd,
}

/// A serial line's character format and speed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SerialSettings {
    pub baud: u32,
    pub parity: Parity,
    pub data_bits: u8,
    pub stop_bits: u8,
}

impl SerialSettings {
    /// Bits per character on the wire: start, data, parity, stop.
    pub fn bits_per_char(&self) -> u32 {
        1 + u32::from(self.data_bits)
            + u32::from(self.parity != Parity::None)
            + u32::from(self.stop_bits)
    }

    /// The wire time of `bytes` characters.
    pub fn wire_time(&self, bytes: usize) -> SimDuration {
        SimDuration::bit_times(bytes as u64 * u64::from(self.bits_per_char()), self.baud)
    }
}

impl fmt::Display for SerialSettings {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let parity = match self.parity {
            Parity::None => 'N',
            Parity::Even => 'E',
            Parity::Odd => 'O',
        };
        write!(
            f,
            "{} {}{}{}",
            self.baud, self.data_bits, parity, self.stop_bits
        )
    }
}

/// Where a link is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LinkAddr {
    /// A TCP address to listen on (or connect to).
    Tcp(SocketAddr),
    /// A serial device or pseudo-terminal.
    Serial(PathBuf),
}

/// Defaults for options a spec does not give.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkDefaults {
    pub baud: u32,
    /// Reply turnaround on serial links (`docs/protocols/meb.md`: 1 ms).
    pub serial_turnaround: SimDuration,
    /// Reply turnaround on TCP links.
    pub tcp_turnaround: SimDuration,
    /// Hold each reply for its wire time at the link's baud.
    pub pace: bool,
}

impl Default for LinkDefaults {
    fn default() -> Self {
        Self {
            baud: 115_200,
            serial_turnaround: SimDuration::from_millis(1),
            tcp_turnaround: SimDuration::ZERO,
            pace: false,
        }
    }
}

/// A parsed link spec.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkSpec {
    /// The spec as given.
    pub text: String,
    pub addr: LinkAddr,
    /// Character format (serial links; TCP keeps it for pacing only).
    pub serial: SerialSettings,
    /// From a request's last byte to the reply's write.
    pub turnaround: SimDuration,
    /// Whether replies wait for their wire time.
    pub pace: bool,
    /// The line quiet that ends a partial frame, if the spec gives it (see
    /// [`LinkSpec::silence`] for the default).
    pub silence: Option<SimDuration>,
}

pub use crate::modbus::serial::PTY_SILENCE;
/// The quiet that ends a partial frame on a serial port: longer than the
/// 16 ms a USB adapter may hold bytes for.
pub const SERIAL_PORT_SILENCE: SimDuration = SimDuration::from_millis(20);

/// Why a link spec is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LinkSpecError {
    #[error("link `{spec}`: empty")]
    Empty { spec: String },
    #[error(
        "unknown link `{spec}`: use tcp://HOST:PORT or a serial device or pseudo-terminal path"
    )]
    UnknownScheme { spec: String },
    #[error(
        "link `{spec}` looks like a misspelt TCP address, not a serial device: write `{suggestion}`"
    )]
    MisspeltTcp { spec: String, suggestion: String },
    #[error("`{spec}` is not tcp://HOST:PORT")]
    NotTcp { spec: String },
    #[error("link `{spec}`: `{host}` is not HOST:PORT ({why})")]
    BadTcp {
        spec: String,
        host: String,
        why: String,
    },
    #[error("link `{spec}`: unknown option `{key}` (known: {known})")]
    UnknownOption {
        spec: String,
        key: String,
        known: &'static str,
    },
    #[error("link `{spec}`: option `{key}` = `{value}`: {why}")]
    BadValue {
        spec: String,
        key: String,
        value: String,
        why: &'static str,
    },
    #[error("link `{spec}`: option `{key}` is not taken here ({why})")]
    NotTaken {
        spec: String,
        key: String,
        why: &'static str,
    },
}

/// `tcp:/127.0.0.1:5000`, `tcp:127.0.0.1:5000`, `TCP://…` or a bare
/// `127.0.0.1:5000`: what `tcp://HOST:PORT` was meant to be, unless a file
/// of that name exists (a device path may hold colons, as
/// /dev/serial/by-path/ names do, but those begin with `/`).
fn misspelt_tcp(location: &str) -> Option<String> {
    if Path::new(location).exists() {
        return None;
    }
    let lower = location.to_ascii_lowercase();
    let rest = if let Some(rest) = lower.strip_prefix("tcp") {
        let rest = rest.trim_start_matches([':', '/', ';', '.']);
        (rest.len() < lower.len() - 3).then_some(rest)?
    } else {
        // HOST:PORT with no scheme: a name or address, a colon, a port.
        let (host, port) = lower.rsplit_once(':')?;
        let host_like = !host.is_empty()
            && !host.starts_with(['.', '/', '~'])
            && host
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '[' | ']' | ':'));
        (host_like && !port.is_empty() && port.chars().all(|c| c.is_ascii_digit()))
            .then_some(lower.as_str())?
    };
    let start = location.len() - rest.len();
    Some(format!("tcp://{}", &location[start..]))
}

const SERIAL_OPTIONS: &str = "baud, parity, stop, data, turnaround_ms, pace, silence_ms";
const TCP_OPTIONS: &str = "turnaround_ms, pace, baud";

impl LinkSpec {
    /// Parses `text`, taking options it does not give from `defaults`.
    pub fn parse(text: &str, defaults: &LinkDefaults) -> Result<Self, LinkSpecError> {
        let spec = || text.to_string();
        let (location, options) = split(text);
        if location.is_empty() {
            return Err(LinkSpecError::Empty { spec: spec() });
        }
        let (addr, known) = match location.strip_prefix("tcp://") {
            Some(host) => (LinkAddr::Tcp(resolve(text, host)?), TCP_OPTIONS),
            None => {
                if let Some(suggestion) = misspelt_tcp(location) {
                    return Err(LinkSpecError::MisspeltTcp {
                        spec: spec(),
                        suggestion,
                    });
                }
                if location.contains("://") {
                    return Err(LinkSpecError::UnknownScheme { spec: spec() });
                }
                (LinkAddr::Serial(PathBuf::from(location)), SERIAL_OPTIONS)
            }
        };
        let tcp = matches!(addr, LinkAddr::Tcp(_));
        let mut link = LinkSpec {
            text: text.to_string(),
            addr,
            serial: SerialSettings {
                baud: defaults.baud,
                parity: Parity::None,
                data_bits: 8,
                stop_bits: 1,
            },
            turnaround: if tcp {
                defaults.tcp_turnaround
            } else {
                defaults.serial_turnaround
            },
            pace: defaults.pace,
            silence: None,
        };
        for (key, value) in options {
            let bad = |why| LinkSpecError::BadValue {
                spec: spec(),
                key: key.into(),
                value: value.into(),
                why,
            };
            match key {
                "baud" => {
                    link.serial.baud = value
                        .parse()
                        .ok()
                        .filter(|b| (50..=4_000_000).contains(b))
                        .ok_or_else(|| bad("a baud rate from 50 to 4000000"))?;
                }
                "parity" if !tcp => {
                    link.serial.parity = match value.to_ascii_lowercase().as_str() {
                        "n" | "none" => Parity::None,
                        "e" | "even" => Parity::Even,
                        "o" | "odd" => Parity::Odd,
                        _ => return Err(bad("N, E or O")),
                    };
                }
                "stop" if !tcp => {
                    link.serial.stop_bits = match value {
                        "1" => 1,
                        "2" => 2,
                        _ => return Err(bad("1 or 2")),
                    };
                }
                "data" if !tcp => {
                    link.serial.data_bits = match value {
                        "7" => 7,
                        "8" => 8,
                        _ => return Err(bad("7 or 8")),
                    };
                }
                "turnaround_ms" => {
                    let ms: f64 = value
                        .parse()
                        .ok()
                        .filter(|v: &f64| v.is_finite() && (0.0..=10_000.0).contains(v))
                        .ok_or_else(|| bad("milliseconds from 0 to 10000"))?;
                    link.turnaround = SimDuration::from_secs_f64(ms / 1000.0);
                }
                "silence_ms" if !tcp => {
                    let ms: f64 = value
                        .parse()
                        .ok()
                        .filter(|v: &f64| v.is_finite() && (0.01..=10_000.0).contains(v))
                        .ok_or_else(|| bad("milliseconds from 0.01 to 10000"))?;
                    link.silence = Some(SimDuration::from_secs_f64(ms / 1000.0));
                }
                "pace" => {
                    link.pace = match value {
                        "" | "1" | "true" | "on" | "yes" => true,
                        "0" | "false" | "off" | "no" => false,
                        _ => return Err(bad("1 or 0")),
                    };
                }
                _ => {
                    return Err(LinkSpecError::UnknownOption {
                        spec: spec(),
                        key: key.into(),
                        known,
                    });
                }
            }
        }
        Ok(link)
    }

    /// Parses `text` for a link used as it is found, which takes no options
    /// (`twin replay --frames-to`); `why` says why if the spec gives some.
    pub fn parse_without_options(text: &str, why: &'static str) -> Result<Self, LinkSpecError> {
        if let Some((key, _)) = split(text).1.next() {
            return Err(LinkSpecError::NotTaken {
                spec: text.into(),
                key: key.into(),
                why,
            });
        }
        Self::parse(text, &LinkDefaults::default())
    }

    /// The address of a peer only ever reached over TCP (a supervisor's
    /// clients, a load generator's server): `tcp://HOST:PORT`, or
    /// `HOST:PORT` alone; no options (`why` says why if some are given).
    pub fn parse_tcp_peer(text: &str, why: &'static str) -> Result<SocketAddr, LinkSpecError> {
        // Anything with a slash is read as written, so a misspelt `tcp:/…`
        // gets the links' own suggestion.
        let spec = if text.contains('/') {
            Self::parse_without_options(text, why)?
        } else {
            Self::parse_without_options(&format!("tcp://{text}"), why)?
        };
        match spec.addr {
            LinkAddr::Tcp(addr) => Ok(addr),
            LinkAddr::Serial(_) => Err(LinkSpecError::NotTcp { spec: text.into() }),
        }
    }

    /// Whether this is a TCP link.
    pub fn is_tcp(&self) -> bool {
        matches!(self.addr, LinkAddr::Tcp(_))
    }

    /// The line quiet that ends a partial frame on this serial link: the
    /// spec's `silence_ms`, or [`PTY_SILENCE`] on a pty and
    /// [`SERIAL_PORT_SILENCE`] on a serial port.
    pub fn silence(&self) -> SimDuration {
        self.silence_with(SERIAL_PORT_SILENCE)
    }

    /// The same, with `serial_port` as the default on a serial port.
    pub fn silence_with(&self, serial_port: SimDuration) -> SimDuration {
        self.silence.unwrap_or(match &self.addr {
            LinkAddr::Serial(path) if is_pty(path) => PTY_SILENCE,
            _ => serial_port,
        })
    }
}

/// Whether `path` is (a link to) a pseudo-terminal: bytes on a pty carry no
/// timing, so a Modbus RTU decoder needs a longer silence there.
pub fn is_pty(path: &Path) -> bool {
    std::fs::canonicalize(path).is_ok_and(|p| p.starts_with("/dev/pts") || p.ends_with("ptmx"))
}

/// A spec's location, and its options: `KEY=VALUE` pairs after `?`, joined
/// by `&` (a bare `KEY` has an empty value).
fn split(text: &str) -> (&str, impl Iterator<Item = (&str, &str)>) {
    let (location, query) = text.split_once('?').unwrap_or((text, ""));
    let options = query
        .split('&')
        .filter(|p| !p.is_empty())
        .map(|p| p.split_once('=').unwrap_or((p, "")));
    (location, options)
}

fn resolve(spec: &str, host: &str) -> Result<SocketAddr, LinkSpecError> {
    let bad = |why: String| LinkSpecError::BadTcp {
        spec: spec.into(),
        host: host.into(),
        why,
    };
    // `tcp://:5020` means the loopback address: safe by default.
    let full = match host.strip_prefix(':') {
        Some(port) => format!("127.0.0.1:{port}"),
        None => host.to_string(),
    };
    let (_, port) = full.rsplit_once(':').ok_or_else(|| bad("no port".into()))?;
    port.parse::<u16>()
        .map_err(|_| bad(format!("port `{port}` is not 0-65535")))?;
    full.to_socket_addrs()
        .map_err(|e| bad(e.to_string()))?
        .next()
        .ok_or_else(|| bad("no address".into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_misspelt_tcp_address_is_not_taken_for_a_serial_port() {
        for (written, meant) in [
            ("tcp:/127.0.0.1:5000", "tcp://127.0.0.1:5000"),
            ("tcp:127.0.0.1:5000", "tcp://127.0.0.1:5000"),
            ("tcp//localhost:5020", "tcp://localhost:5020"),
            ("TCP:/127.0.0.1:5000", "tcp://127.0.0.1:5000"),
            ("127.0.0.1:5000", "tcp://127.0.0.1:5000"),
            ("localhost:5020", "tcp://localhost:5020"),
        ] {
            let e = LinkSpec::parse(written, &LinkDefaults::default())
                .expect_err(written)
                .to_string();
            assert_eq!(
                e,
                format!(
                    "link `{written}` looks like a misspelt TCP address, not a serial device: write `{meant}`"
                )
            );
        }
        for serial in [
            "/dev/ttyUSB0",
            "/tmp/ttyV0",
            "/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0-port0",
            "ttyS0",
        ] {
            let l = LinkSpec::parse(serial, &LinkDefaults::default()).expect(serial);
            assert!(!l.is_tcp(), "{serial}");
        }
    }

    #[test]
    fn serial_options_override_the_defaults() {
        let d = LinkDefaults::default();
        let l = LinkSpec::parse("/tmp/ttyV1?baud=9600&parity=E&stop=2", &d).unwrap();
        assert_eq!(l.addr, LinkAddr::Serial("/tmp/ttyV1".into()));
        assert_eq!(l.serial.baud, 9600);
        assert_eq!(l.serial.parity, Parity::Even);
        assert_eq!(l.serial.bits_per_char(), 12);
        assert_eq!(l.turnaround, SimDuration::from_millis(1));
        let l = LinkSpec::parse("/dev/ttyUSB0", &d).unwrap();
        assert_eq!(l.serial.to_string(), "115200 8N1");
        // 13 MEB bytes at 115200 8N1 take 1.128 ms.
        let t = l.serial.wire_time(13).as_secs_f64();
        assert!((t - 13.0 * 10.0 / 115_200.0).abs() < 1e-12);
    }

    #[test]
    fn the_silence_is_the_specs_or_the_mediums() {
        let d = LinkDefaults::default();
        let l = LinkSpec::parse("/tmp/ttyV1?silence_ms=12.5", &d).unwrap();
        assert_eq!(l.silence(), SimDuration::from_micros(12_500));
        // Not a pty (it does not even exist): a serial port's.
        let l = LinkSpec::parse("/tmp/no-such-port", &d).unwrap();
        assert_eq!(l.silence(), SERIAL_PORT_SILENCE);
        let e = LinkSpec::parse("/tmp/x?silence_ms=0", &d).unwrap_err();
        assert!(e.to_string().contains("from 0.01 to 10000"), "{e}");
        let e = LinkSpec::parse("tcp://127.0.0.1:1?silence_ms=5", &d).unwrap_err();
        assert!(e.to_string().contains("unknown option `silence_ms`"), "{e}");
    }

    #[test]
    fn tcp_specs_resolve_and_port_zero_is_allowed() {
        let d = LinkDefaults::default();
        let l = LinkSpec::parse("tcp://127.0.0.1:0", &d).unwrap();
        assert_eq!(l.addr, LinkAddr::Tcp("127.0.0.1:0".parse().unwrap()));
        assert_eq!(l.turnaround, SimDuration::ZERO);
        let l = LinkSpec::parse("tcp://:5020?turnaround_ms=2", &d).unwrap();
        assert_eq!(l.addr, LinkAddr::Tcp("127.0.0.1:5020".parse().unwrap()));
        assert_eq!(l.turnaround, SimDuration::from_millis(2));
    }

    #[test]
    fn bad_specs_say_what_is_wrong() {
        let d = LinkDefaults::default();
        let e = LinkSpec::parse("/tmp/x?baud=fast", &d).unwrap_err();
        assert!(e.to_string().contains("`baud` = `fast`"), "{e}");
        let e = LinkSpec::parse("/tmp/x?speed=9600", &d).unwrap_err();
        assert!(e.to_string().contains("unknown option `speed`"), "{e}");
        let e = LinkSpec::parse("tcp://127.0.0.1", &d).unwrap_err();
        assert!(e.to_string().contains("no port"), "{e}");
        let e = LinkSpec::parse("tcp://127.0.0.1:70000", &d).unwrap_err();
        assert!(e.to_string().contains("not 0-65535"), "{e}");
        let e = LinkSpec::parse("tcp://127.0.0.1:1?parity=E", &d).unwrap_err();
        assert!(e.to_string().contains("unknown option `parity`"), "{e}");
        assert!(LinkSpec::parse("", &d).is_err());
        let e = LinkSpec::parse("udp://x", &d).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("unknown link `udp://x`: use tcp://"),
            "{e}"
        );
    }

    #[test]
    fn a_link_without_options_refuses_them_and_names_the_first() {
        let l = LinkSpec::parse_without_options("/tmp/ttyA", "as it is").unwrap();
        assert_eq!(l.addr, LinkAddr::Serial("/tmp/ttyA".into()));
        let l = LinkSpec::parse_without_options("tcp://127.0.0.1:5020", "as it is").unwrap();
        assert_eq!(l.addr, LinkAddr::Tcp("127.0.0.1:5020".parse().unwrap()));
        // An empty query gives no option.
        let l = LinkSpec::parse_without_options("/tmp/ttyA?", "as it is").unwrap();
        assert_eq!(l.addr, LinkAddr::Serial("/tmp/ttyA".into()));
        let e =
            LinkSpec::parse_without_options("/tmp/ttyA?baud=9600&pace", "as it is").unwrap_err();
        assert_eq!(
            e.to_string(),
            "link `/tmp/ttyA?baud=9600&pace`: option `baud` is not taken here (as it is)"
        );
        let e = LinkSpec::parse_without_options("udp://x", "as it is").unwrap_err();
        assert!(e.to_string().starts_with("unknown link `udp://x`"), "{e}");
    }

    #[test]
    fn a_tcp_peer_may_leave_out_the_scheme_and_nothing_else() {
        let local: SocketAddr = "127.0.0.1:5701".parse().unwrap();
        assert_eq!(
            LinkSpec::parse_tcp_peer("tcp://127.0.0.1:5701", "x"),
            Ok(local)
        );
        assert_eq!(LinkSpec::parse_tcp_peer("127.0.0.1:5701", "x"), Ok(local));
        let e = LinkSpec::parse_tcp_peer("/dev/ttyUSB0", "x").unwrap_err();
        assert_eq!(e.to_string(), "`/dev/ttyUSB0` is not tcp://HOST:PORT");
        let e = LinkSpec::parse_tcp_peer("tcp:/127.0.0.1:5701", "x").unwrap_err();
        assert!(
            e.to_string().contains("write `tcp://127.0.0.1:5701`"),
            "{e}"
        );
        let e = LinkSpec::parse_tcp_peer("127.0.0.1:5701?pace", "no options").unwrap_err();
        assert!(
            e.to_string().ends_with("is not taken here (no options)"),
            "{e}"
        );
    }
}
