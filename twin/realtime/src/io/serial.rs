//! Serial devices and pseudo-terminals as tokio streams (tokio-serial, built
//! without libudev: no port enumeration is needed to open a path).

use std::path::Path;
use tokio_serial::{DataBits, FlowControl, SerialStream, StopBits};

use super::OpenError;
use super::spec::{LinkAddr, LinkSpec, Parity, SerialSettings};

type Result<T, E = OpenError> = std::result::Result<T, E>;

/// Refuses a serial path that does not exist, saying it may be a
/// pseudo-terminal some other program has not created yet (what `open` and
/// the services' `--check` say alike).
pub fn present(path: &Path) -> Result<()> {
    if !path.exists() {
        return Err(OpenError::NoSuchPort {
            path: path.to_path_buf(),
        });
    }
    Ok(())
}

/// `--check` of a link: its serial port there already, unless the session
/// waits for ports to appear. A TCP link has nothing to check before binding.
pub fn check_port(spec: &LinkSpec, wait_for_ports: bool) -> Result<()> {
    match &spec.addr {
        LinkAddr::Serial(path) if !wait_for_ports => present(path),
        _ => Ok(()),
    }
}

/// Opens `path` with `settings`. Must run inside a tokio runtime. A path that
/// does not exist gets an error that says it may be a pseudo-terminal some
/// other program has not created yet.
pub fn open(path: &Path, settings: &SerialSettings) -> Result<SerialStream> {
    present(path)?;
    let Some(name) = path.to_str() else {
        return Err(OpenError::NotUtf8 {
            path: path.to_path_buf(),
        });
    };
    let builder = tokio_serial::new(name, settings.baud)
        .data_bits(match settings.data_bits {
            7 => DataBits::Seven,
            _ => DataBits::Eight,
        })
        .parity(match settings.parity {
            Parity::None => tokio_serial::Parity::None,
            Parity::Even => tokio_serial::Parity::Even,
            Parity::Odd => tokio_serial::Parity::Odd,
        })
        .stop_bits(match settings.stop_bits {
            2 => StopBits::Two,
            _ => StopBits::One,
        })
        .flow_control(FlowControl::None);
    SerialStream::open(&builder).map_err(|source| OpenError::Serial {
        path: path.to_path_buf(),
        settings: *settings,
        source,
    })
}
