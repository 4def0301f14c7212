//! systemd's readiness protocol (`sd_notify`): a unit of `Type=notify`
//! learns that the twin is serving (`READY=1`, once every link is open) and
//! that it is stopping (`STOPPING=1`), from a datagram sent to the socket
//! named by `$NOTIFY_SOCKET`. Without that variable (not under systemd)
//! nothing is sent. The protocol is a line of `KEY=VALUE` text per
//! datagram; `@` at the start of the path names a socket in the abstract
//! namespace (sd_notify(3)).

use std::io;
use std::os::unix::net::{SocketAddr, UnixDatagram};

/// The variable systemd sets for a `Type=notify` service.
pub const NOTIFY_SOCKET: &str = "NOTIFY_SOCKET";

/// Sends `state` (`READY=1\nSTATUS=…`) to the service manager, if there is
/// one: `Ok(false)` when not started by one.
pub fn notify(state: &str) -> io::Result<bool> {
    let Some(path) = std::env::var_os(NOTIFY_SOCKET) else {
        return Ok(false);
    };
    let bytes = path.as_encoded_bytes();
    let addr = match bytes.split_first() {
        Some((b'@', name)) => {
            use std::os::linux::net::SocketAddrExt;
            SocketAddr::from_abstract_name(name)?
        }
        Some((b'/', _)) => SocketAddr::from_pathname(&path)?,
        _ => {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("{NOTIFY_SOCKET}={}: not a socket path", path.display()),
            ));
        }
    };
    let socket = UnixDatagram::unbound()?;
    socket.send_to_addr(state.as_bytes(), &addr)?;
    Ok(true)
}

/// `READY=1`, with a status line for `systemctl status`.
pub fn ready(status: &str) {
    say(&format!("READY=1\nSTATUS={status}"));
}

/// `STOPPING=1`: the recording is being finished.
pub fn stopping(status: &str) {
    say(&format!("STOPPING=1\nSTATUS={status}"));
}

/// A status line for `systemctl status` (a rotation, a reread configuration).
pub fn status(status: &str) {
    say(&format!("STATUS={status}"));
}

fn say(state: &str) {
    if let Err(e) = notify(state) {
        // The service manager then thinks the start failed, and says so:
        // this line tells the journal why.
        eprintln!("warning: cannot tell the service manager ({NOTIFY_SOCKET}): {e}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_a_service_manager_nothing_is_sent() {
        // The variable is not set in tests run by cargo.
        if std::env::var_os(NOTIFY_SOCKET).is_none() {
            assert!(!notify("READY=1").unwrap());
        }
    }
}
