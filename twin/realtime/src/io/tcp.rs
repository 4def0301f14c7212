//! TCP listeners with errors that say what to do.

use std::net::SocketAddr;
use tokio::net::TcpListener;

use super::OpenError;

/// Binds `addr` (port 0: any free port; read it back with `local_addr`).
/// Must run inside a tokio runtime.
pub async fn bind(addr: SocketAddr) -> Result<TcpListener, OpenError> {
    TcpListener::bind(addr).await.map_err(|e| match e.kind() {
        std::io::ErrorKind::AddrInUse => OpenError::PortInUse { addr },
        std::io::ErrorKind::AddrNotAvailable => OpenError::NoSuchAddress { addr },
        _ => OpenError::Listen { addr, source: e },
    })
}
