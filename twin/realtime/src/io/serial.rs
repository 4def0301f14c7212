//! Serial devices and pseudo-terminals as tokio streams (tokio-serial, built
//! without libudev: no port enumeration is needed to open a path).

use anyhow::{Result, bail};
use std::path::Path;
use tokio_serial::{DataBits, FlowControl, SerialStream, StopBits};

use super::spec::{LinkAddr, LinkSpec, Parity, SerialSettings};

/// Refuses a serial path that does not exist, saying it may be a
/// pseudo-terminal some other program has not created yet (what `open` and
/// the services' `--check` say alike).
pub fn present(path: &Path) -> Result<()> {
    if !path.exists() {
        bail!(
            "serial port {} does not exist; if it is a pseudo-terminal that another program \
             creates (twin vsp, socat), start that program first, or pass --wait-for-ports",
            path.display()
        );
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
    let shown = path.display();
    present(path)?;
    let Some(name) = path.to_str() else {
        bail!("serial port path {shown} is not valid UTF-8");
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
    SerialStream::open(&builder)
        .map_err(|e| anyhow::anyhow!("cannot open serial port {shown} at {settings}: {e}"))
}
