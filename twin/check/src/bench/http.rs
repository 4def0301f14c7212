//! Just enough HTTP/1.1 to read a panel's JSON API (`docs/panel-api.md`):
//! a `GET` on a fresh connection, `Connection: close`, the body read to
//! its end (whole, or in chunks). The panel is the twin's own, on the
//! lab's network: a client crate (and its TLS stack) would be more code
//! than this.

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

/// A panel's address: `http://HOST:PORT`, with its token when the URL
/// carried one (`?token=…`, as twin prints it).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Panel {
    pub host_port: String,
    pub token: Option<String>,
    /// As given, the token left out, for messages.
    pub shown: String,
}

/// The longest a panel may take to answer.
const TIMEOUT: Duration = Duration::from_secs(5);
/// A body larger than this is no panel's answer.
const MAX_BODY: usize = 1 << 20;

impl Panel {
    /// Reads `http://HOST:PORT[/][?token=TOKEN]`.
    pub fn parse(url: &str) -> Result<Self, String> {
        let Some(rest) = url.strip_prefix("http://") else {
            return Err(format!(
                "`{url}` is not a panel's address: it is http://HOST:PORT, as `twin serve --web` prints it"
            ));
        };
        let (host_port, query) = match rest.split_once(['/', '?']) {
            Some((host, tail)) => (host, tail.split_once('?').map_or(tail, |(_, q)| q)),
            None => (rest, ""),
        };
        if host_port.is_empty() || !host_port.contains(':') {
            return Err(format!(
                "`{url}`: the panel's address needs its port, http://HOST:PORT"
            ));
        }
        let token = query
            .split('&')
            .find_map(|pair| pair.strip_prefix("token="))
            .filter(|t| !t.is_empty())
            .map(str::to_string);
        Ok(Panel {
            host_port: host_port.to_string(),
            token,
            shown: format!("http://{host_port}"),
        })
    }

    /// `GET path`: the body of a 200 answer, or why there is none.
    pub fn get(&self, path: &str) -> Result<String, String> {
        let addr = self
            .host_port
            .to_socket_addrs()
            .map_err(|e| format!("{}: {e}", self.shown))?
            .next()
            .ok_or_else(|| format!("{}: the host has no address", self.shown))?;
        let mut stream = TcpStream::connect_timeout(&addr, TIMEOUT).map_err(|e| {
            let why = match e.kind() {
                std::io::ErrorKind::ConnectionRefused => "connection refused".to_string(),
                std::io::ErrorKind::TimedOut => "no answer".to_string(),
                _ => e.to_string(),
            };
            format!(
                "cannot reach the bench's panel at {}: {why} (is `twin serve --web` running there?)",
                self.shown
            )
        })?;
        let _ = stream.set_read_timeout(Some(TIMEOUT));
        let _ = stream.set_write_timeout(Some(TIMEOUT));
        let auth = self
            .token
            .as_ref()
            .map(|t| format!("Authorization: Bearer {t}\r\n"))
            .unwrap_or_default();
        let request = format!(
            "GET {path} HTTP/1.1\r\nHost: {}\r\nAccept: application/json\r\n{auth}Connection: close\r\n\r\n",
            self.host_port
        );
        stream
            .write_all(request.as_bytes())
            .map_err(|e| format!("the bench's panel at {}: {e}", self.shown))?;
        let mut raw = Vec::new();
        stream
            .take(MAX_BODY as u64 + 4096)
            .read_to_end(&mut raw)
            .map_err(|e| format!("the bench's panel at {} did not answer: {e}", self.shown))?;
        let (status, body) = response(&raw)
            .ok_or_else(|| format!("the bench's panel at {} answered no HTTP", self.shown))?;
        if status != 200 {
            let said = serde_json::from_str::<serde_json::Value>(&body)
                .ok()
                .and_then(|v| v["error"].as_str().map(str::to_string))
                .unwrap_or(body);
            return Err(format!(
                "the bench's panel at {} answered {path} with {status}: {said}",
                self.shown
            ));
        }
        Ok(body)
    }
}

/// The status and body of a whole HTTP/1.1 response.
fn response(raw: &[u8]) -> Option<(u16, String)> {
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = std::str::from_utf8(&raw[..split]).ok()?;
    let body = &raw[split + 4..];
    let status = head.split_whitespace().nth(1)?.parse().ok()?;
    let chunked = head.lines().any(|l| {
        let l = l.to_ascii_lowercase();
        l.starts_with("transfer-encoding:") && l.contains("chunked")
    });
    let body = if chunked {
        dechunk(body)?
    } else {
        body.to_vec()
    };
    Some((status, String::from_utf8_lossy(&body).into_owned()))
}

/// A chunked body put back together.
fn dechunk(mut rest: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let line_end = rest.windows(2).position(|w| w == b"\r\n")?;
        let size_text = std::str::from_utf8(&rest[..line_end]).ok()?;
        let size = usize::from_str_radix(size_text.split(';').next()?.trim(), 16).ok()?;
        rest = &rest[line_end + 2..];
        if size == 0 {
            return Some(out);
        }
        out.extend_from_slice(rest.get(..size)?);
        rest = rest.get(size + 2..)?;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panel_url_gives_its_address_and_token() {
        let p = Panel::parse("http://127.0.0.1:8080/?token=5f0c").unwrap();
        assert_eq!(p.host_port, "127.0.0.1:8080");
        assert_eq!(p.token.as_deref(), Some("5f0c"));
        assert_eq!(p.shown, "http://127.0.0.1:8080");
        let p = Panel::parse("http://lab:8101").unwrap();
        assert_eq!(p.token, None);
        assert!(Panel::parse("tcp://127.0.0.1:5700").is_err());
        assert!(Panel::parse("http://lab/").unwrap_err().contains("port"));
    }

    #[test]
    fn whole_and_chunked_bodies_are_read() {
        let whole = b"HTTP/1.1 200 OK\r\ncontent-length: 2\r\n\r\n{}";
        assert_eq!(response(whole), Some((200, "{}".into())));
        let chunked =
            b"HTTP/1.1 404 Not Found\r\nTransfer-Encoding: chunked\r\n\r\n3\r\nabc\r\n2\r\nde\r\n0\r\n\r\n";
        assert_eq!(response(chunked), Some((404, "abcde".into())));
        assert_eq!(response(b"garbage"), None);
    }
}
