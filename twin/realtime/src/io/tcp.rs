//! TCP listeners with errors that say what to do.

use anyhow::{Result, anyhow};
use std::net::SocketAddr;
use tokio::net::TcpListener;

/// Binds `addr` (port 0: any free port; read it back with `local_addr`).
/// Must run inside a tokio runtime.
pub async fn bind(addr: SocketAddr) -> Result<TcpListener> {
    TcpListener::bind(addr).await.map_err(|e| match e.kind() {
        std::io::ErrorKind::AddrInUse => anyhow!(
            "cannot listen on tcp://{addr}: the port is in use (choose another, or port 0 for any free one)"
        ),
        std::io::ErrorKind::AddrNotAvailable => anyhow!(
            "cannot listen on tcp://{addr}: no such local address (127.0.0.1 is the default)"
        ),
        _ => anyhow!("cannot listen on tcp://{addr}: {e}"),
    })
}
