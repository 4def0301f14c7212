//! Who may use the panel. On 127.0.0.1 (the default) anyone on this machine
//! may; on any other address every request and stream needs the token,
//! printed at start inside the URL to open (as Jupyter does), and kept across
//! restarts in `--web-token-file`. `--web-read-only` serves no controls.

use std::net::SocketAddr;
use std::path::PathBuf;

type Result<T, E = TokenError> = std::result::Result<T, E>;

/// Why the panel has no token to ask for.
#[derive(Debug, thiserror::Error)]
pub enum TokenError {
    #[error("cannot read /dev/urandom for the panel's token")]
    Random(#[source] std::io::Error),
    #[error(
        "--web-token-file {}: the token must be at least 16 letters or digits on one line (delete the file for a new one)",
        path.display()
    )]
    Malformed { path: PathBuf },
    #[error("--web-token-file {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("--web-token-file {}: cannot write it", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// What the command line says about access.
#[derive(Debug, Clone, Default)]
pub struct AccessOptions {
    /// Read the token from this file, or write a new one there.
    pub token_file: Option<PathBuf>,
    /// Show, never change: no controls, every command refused.
    pub read_only: bool,
}

/// The rules in force.
#[derive(Debug)]
pub struct Access {
    token: Option<String>,
    read_only: bool,
}

/// Why a request was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refused {
    /// No token, or the wrong one: 401.
    Token,
    /// A command on a read-only panel: 403.
    ReadOnly,
}

impl Access {
    /// The rules for a panel on `addr`: a token unless it is a loopback
    /// address (then only if a token file is given).
    pub fn new(options: &AccessOptions, addr: &SocketAddr) -> Result<Self> {
        let needs = !addr.ip().is_loopback() || options.token_file.is_some();
        let token = if needs {
            Some(match &options.token_file {
                Some(path) => token_from_file(path)?,
                None => new_token()?,
            })
        } else {
            None
        };
        Ok(Self {
            token,
            read_only: options.read_only,
        })
    }

    /// A panel with these rules, for tests.
    pub fn with(token: Option<String>, read_only: bool) -> Self {
        Self { token, read_only }
    }

    pub fn token(&self) -> Option<&str> {
        self.token.as_deref()
    }

    pub fn read_only(&self) -> bool {
        self.read_only
    }

    /// Whether a request carrying `given` (from `?token=`, the
    /// `Authorization: Bearer` header or the panel's cookie) may read.
    pub fn check(&self, given: Option<&str>) -> Result<(), Refused> {
        match (&self.token, given) {
            (None, _) => Ok(()),
            (Some(t), Some(g)) if same(t.as_bytes(), g.as_bytes()) => Ok(()),
            (Some(_), _) => Err(Refused::Token),
        }
    }

    /// Whether it may also change something.
    pub fn check_command(&self, given: Option<&str>) -> Result<(), Refused> {
        self.check(given)?;
        if self.read_only {
            return Err(Refused::ReadOnly);
        }
        Ok(())
    }
}

/// Compares without stopping at the first difference, so the time a
/// refusal takes says nothing about how much of a guess was right.
fn same(a: &[u8], b: &[u8]) -> bool {
    use subtle::ConstantTimeEq;
    a.ct_eq(b).into()
}

/// 24 random bytes from the kernel, as 48 hex digits.
fn new_token() -> Result<String> {
    use std::io::Read;
    let mut bytes = [0u8; 24];
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut bytes))
        .map_err(TokenError::Random)?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// The token kept in `path`; a new one written there (readable by its owner
/// only) if the file does not exist yet.
fn token_from_file(path: &std::path::Path) -> Result<String> {
    match std::fs::read_to_string(path) {
        Ok(text) => {
            let token = text.trim().to_string();
            if token.len() < 16 || !token.chars().all(|c| c.is_ascii_alphanumeric()) {
                return Err(TokenError::Malformed { path: path.into() });
            }
            Ok(token)
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let token = new_token()?;
            write_private(path, &token).map_err(|source| TokenError::Write {
                path: path.into(),
                source,
            })?;
            Ok(token)
        }
        Err(source) => Err(TokenError::Read {
            path: path.into(),
            source,
        }),
    }
}

fn write_private(path: &std::path::Path, token: &str) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)?;
    writeln!(f, "{token}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loopback_is_open_and_anything_else_needs_the_token() {
        let local =
            Access::new(&AccessOptions::default(), &"127.0.0.1:0".parse().unwrap()).unwrap();
        assert!(local.token().is_none());
        assert_eq!(local.check(None), Ok(()));
        let open = Access::new(&AccessOptions::default(), &"0.0.0.0:0".parse().unwrap()).unwrap();
        let token = open.token().unwrap().to_string();
        assert_eq!(token.len(), 48);
        assert_eq!(open.check(None), Err(Refused::Token));
        assert_eq!(open.check(Some("nope")), Err(Refused::Token));
        assert_eq!(open.check(Some(&token)), Ok(()));
        let ro = Access::with(None, true);
        assert_eq!(ro.check(None), Ok(()));
        assert_eq!(ro.check_command(None), Err(Refused::ReadOnly));
    }

    #[test]
    fn the_token_file_keeps_the_token_across_restarts() {
        let dir = std::env::temp_dir().join(format!("twin-panel-token-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let options = AccessOptions {
            token_file: Some(dir.join("token")),
            read_only: false,
        };
        let addr = "0.0.0.0:0".parse().unwrap();
        let first = Access::new(&options, &addr).unwrap();
        let again = Access::new(&options, &addr).unwrap();
        assert_eq!(first.token(), again.token());
        std::fs::write(dir.join("token"), "short\n").unwrap();
        let err = Access::new(&options, &addr).unwrap_err().to_string();
        assert!(err.contains("at least 16"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
