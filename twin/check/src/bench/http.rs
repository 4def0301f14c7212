//! A panel's JSON API (`docs/panel-api.md`) read over plain HTTP with ureq
//! (no TLS: the panel is the twin's own, on the lab's network), its
//! failures said in the bench's words. ureq in place of the hand-written
//! client adds 7 small crates to this crate's build (176 to 183), about
//! 11 s of a cold debug build on the 2-core test machine, and reads what a
//! hand-written client would have to learn (chunks, keep-alive, limits).

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
const MAX_BODY: u64 = 1 << 20;

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
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .timeout_connect(Some(TIMEOUT))
            .timeout_global(Some(TIMEOUT))
            // A refusal's status and its JSON `error` are the message.
            .http_status_as_error(false)
            .build()
            .into();
        let mut request = agent
            .get(format!("http://{}{path}", self.host_port))
            .header("Accept", "application/json");
        if let Some(token) = &self.token {
            request = request.header("Authorization", format!("Bearer {token}"));
        }
        let response = request.call().map_err(|e| self.failed(e))?;
        let status = response.status().as_u16();
        let body = response
            .into_body()
            .with_config()
            .limit(MAX_BODY)
            .read_to_string()
            .map_err(|e| format!("the bench's panel at {} did not answer: {e}", self.shown))?;
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

    /// Why a request got no answer, in the bench's words.
    fn failed(&self, e: ureq::Error) -> String {
        let why = match &e {
            ureq::Error::Io(io) if io.kind() == std::io::ErrorKind::ConnectionRefused => {
                "connection refused".to_string()
            }
            ureq::Error::Timeout(_) => "no answer".to_string(),
            ureq::Error::HostNotFound => "the host has no address".to_string(),
            ureq::Error::Io(io) => io.to_string(),
            // What came back was no HTTP a panel speaks.
            other => {
                return format!(
                    "the bench's panel at {} answered no HTTP: {other}",
                    self.shown
                );
            }
        };
        format!(
            "cannot reach the bench's panel at {}: {why} (is `twin serve --web` running there?)",
            self.shown
        )
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

    /// A one-shot server on 127.0.0.1 that answers the first request with
    /// `answer`; the panel's address.
    fn answering(answer: &'static [u8]) -> Panel {
        use std::io::{Read, Write};
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        std::thread::spawn(move || {
            let (mut s, _) = listener.accept().unwrap();
            let mut head = Vec::new();
            let mut byte = [0u8];
            while !head.ends_with(b"\r\n\r\n") && s.read(&mut byte).is_ok_and(|n| n == 1) {
                head.push(byte[0]);
            }
            let _ = s.write_all(answer);
        });
        Panel::parse(&format!("http://{addr}/?token=5f0c")).unwrap()
    }

    #[test]
    fn bodies_refusals_and_silence_are_said_in_words() {
        let whole = answering(b"HTTP/1.1 200 OK\r\ncontent-length: 2\r\n\r\n{}");
        assert_eq!(whole.get("/api/info").as_deref(), Ok("{}"));
        let chunked = answering(
            b"HTTP/1.1 404 Not Found\r\nTransfer-Encoding: chunked\r\n\r\n5\r\n{\"err\r\n15\r\nor\": \"no such thing\"}\r\n0\r\n\r\n",
        );
        let e = chunked.get("/api/thing").unwrap_err();
        assert!(
            e.ends_with("answered /api/thing with 404: no such thing"),
            "{e}"
        );
        let garbage = answering(b"SSH-2.0-OpenSSH\r\n\r\n");
        let e = garbage.get("/api/info").unwrap_err();
        assert!(e.contains("answered no HTTP"), "{e}");
        // Nothing listens on port 9 (discard) here.
        let nobody = Panel::parse("http://127.0.0.1:9").unwrap();
        let e = nobody.get("/api/info").unwrap_err();
        assert!(
            e.starts_with(
                "cannot reach the bench's panel at http://127.0.0.1:9: connection refused"
            ),
            "{e}"
        );
    }
}
