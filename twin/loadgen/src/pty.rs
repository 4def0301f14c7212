//! Pseudo-terminal pairs: the benchmark keeps the master side and hands the
//! slave's path to the server under test, as a master on a real port would.

use anyhow::{Context, Result};
use rustix::fs::OFlags;
use rustix::pty::{OpenptFlags, grantpt, openpt, ptsname, unlockpt};
use rustix::termios::{OptionalActions, tcgetattr, tcsetattr};
use std::ffi::OsString;
use std::fs::{File, OpenOptions};
use std::os::unix::ffi::OsStringExt;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

#[derive(Debug)]
pub struct PtyPair {
    /// Our end: bytes written here arrive at the slave's reader.
    pub master: File,
    pub slave_path: PathBuf,
    /// Held open so the pair does not hang up while the server (re)opens it.
    _slave: File,
}

impl PtyPair {
    pub fn open() -> Result<Self> {
        let master = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY).context("posix_openpt")?;
        grantpt(&master).context("grantpt")?;
        unlockpt(&master).context("unlockpt")?;
        let name = ptsname(&master, Vec::new()).context("ptsname")?;
        let slave_path = PathBuf::from(OsString::from_vec(name.into_bytes()));
        let slave = open_raw(&slave_path)?;
        Ok(Self {
            master: File::from(master),
            slave_path,
            _slave: slave,
        })
    }
}

/// Opens a terminal device in raw mode (no echo, no line editing, no CR/LF
/// translation): a serial port as a Modbus peer expects it.
pub fn open_raw(path: &Path) -> Result<File> {
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(OFlags::NOCTTY.bits() as i32)
        .open(path)
        .with_context(|| format!("opening {}", path.display()))?;
    let mut termios = tcgetattr(&file).with_context(|| format!("tcgetattr {}", path.display()))?;
    termios.make_raw();
    tcsetattr(&file, OptionalActions::Now, &termios)
        .with_context(|| format!("tcsetattr {}", path.display()))?;
    Ok(file)
}
