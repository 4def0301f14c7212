//! A crossed pair of pseudo-terminals, like the lab's virtual-serial-port
//! utility: what a program writes to one end's device is read from the other's.
//!
//! Each end is a pty: its *slave* device (`/dev/pts/N`) is what a serial
//! program opens, reached through a stable symlink the user names; its *master*
//! side stays with us. We copy bytes master to master, so the two slave devices
//! behave like two serial ports joined by a null-modem cable.
//!
//! A pty whose slave has no open descriptor hangs up its master (reads fail with
//! `EIO`), and the Controller_network master opens and closes the port for every
//! transaction.
//! So each end holds its own descriptor of its slave, opened through the master
//! (`TIOCGPTPEER`, no path race) and put in raw mode: the pair never hangs up,
//! and a program that opens the port without configuring it still gets raw,
//! unechoed bytes. Bytes written towards an end whose buffer is full (nobody
//! reading it) are dropped and counted, as a UART overruns, rather than stalling
//! the other direction.

use rustix::fs::{OFlags, fcntl_getfl, fcntl_setfl};
use rustix::pty::{OpenptFlags, grantpt, ioctl_tiocgptpeer, openpt, ptsname, unlockpt};
use rustix::termios::{OptionalActions, tcgetattr, tcsetattr};
use std::io::ErrorKind;
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tokio::net::unix::pipe;

/// Why the pair cannot be made or stopped copying.
#[derive(Debug, thiserror::Error)]
pub enum VspError {
    #[error("the two ends need different paths")]
    SamePaths,
    #[error("--baud must be above 0")]
    ZeroBaud,
    #[error("cannot open /dev/ptmx (are pseudo-terminals available?)")]
    NoPtmx(#[source] std::io::Error),
    /// A step of making a new pseudo-terminal, as the system call says it.
    #[error("{step}")]
    Pty {
        step: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("the pseudo-terminal's name is not UTF-8")]
    NameNotUtf8(#[source] std::ffi::IntoStringError),
    #[error("cannot open {}", device.display())]
    OpenDevice {
        device: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} exists and is not a symlink; remove it or choose another path", link.display())]
    NotASymlink { link: PathBuf },
    #[error("cannot replace the old symlink {}", link.display())]
    ReplaceLink {
        link: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot check {}", link.display())]
    CheckLink {
        link: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot create the symlink {}", link.display())]
    CreateLink {
        link: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("waiting on the pty")]
    Wait(#[source] std::io::Error),
    #[error("reading {}", device.display())]
    Read {
        device: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("writing {}", device.display())]
    Write {
        device: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

type Result<T, E = VspError> = std::result::Result<T, E>;

/// The error of `step` in making a pseudo-terminal (rustix's errno values
/// as `std::io::Error`, so they read as every other system error does).
fn pty_step<E: Into<std::io::Error>>(step: &'static str) -> impl FnOnce(E) -> VspError {
    move |e| VspError::Pty {
        step,
        source: e.into(),
    }
}

/// One end of the pair: the master side we copy through, and the slave side we
/// hold open so the master never sees a hang-up.
#[derive(Debug)]
pub struct PtyEnd {
    /// The master side, registered twice with the runtime (one descriptor
    /// each way): tokio's pipe types poll any non-blocking descriptor.
    rx: pipe::Receiver,
    tx: pipe::Sender,
    /// Never read or written: it only keeps the slave device open.
    _held_slave: OwnedFd,
    /// `/dev/pts/N`.
    device: PathBuf,
    /// The symlink the user opens.
    link: PathBuf,
    /// Where an old symlink at `link` pointed, replaced by this one.
    replaced: Option<PathBuf>,
}

impl PtyEnd {
    /// Opens a new pty in raw mode (inside a tokio runtime) and points `link` at its slave device. An
    /// existing symlink at `link` (left by a run that was killed) is replaced;
    /// anything else there is refused, so a mistyped path never deletes a file.
    pub fn open(link: &Path) -> Result<Self> {
        let master_fd = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY | OpenptFlags::CLOEXEC)
            .map_err(|e| VspError::NoPtmx(e.into()))?;
        grantpt(&master_fd).map_err(pty_step("grantpt on the new pseudo-terminal"))?;
        unlockpt(&master_fd).map_err(pty_step("unlockpt on the new pseudo-terminal"))?;
        let device = PathBuf::from(
            ptsname(&master_fd, Vec::new())
                .map_err(pty_step("ptsname of the new pseudo-terminal"))?
                .into_string()
                .map_err(VspError::NameNotUtf8)?,
        );
        let held_slave = ioctl_tiocgptpeer(
            &master_fd,
            OpenptFlags::RDWR | OpenptFlags::NOCTTY | OpenptFlags::CLOEXEC,
        )
        .map_err(|e| VspError::OpenDevice {
            device: device.clone(),
            source: e.into(),
        })?;
        let mut termios = tcgetattr(&held_slave).map_err(pty_step("tcgetattr on the pty"))?;
        termios.make_raw();
        tcsetattr(&held_slave, OptionalActions::Now, &termios)
            .map_err(pty_step("tcsetattr on the pty"))?;
        let flags = fcntl_getfl(&master_fd).map_err(pty_step("fcntl on the pty master"))?;
        fcntl_setfl(&master_fd, flags | OFlags::NONBLOCK)
            .map_err(pty_step("fcntl on the pty master"))?;
        let tx_fd = master_fd
            .try_clone()
            .map_err(pty_step("dup of the pty master"))?;
        let rx = pipe::Receiver::from_owned_fd_unchecked(master_fd)
            .map_err(pty_step("registering the pty with the runtime"))?;
        let tx = pipe::Sender::from_owned_fd_unchecked(tx_fd)
            .map_err(pty_step("registering the pty with the runtime"))?;
        let replaced = place_link(link, &device)?;
        Ok(Self {
            rx,
            tx,
            _held_slave: held_slave,
            device,
            link: link.to_path_buf(),
            replaced,
        })
    }

    /// The slave device the link points at.
    pub fn device(&self) -> &Path {
        &self.device
    }

    /// The symlink.
    pub fn link(&self) -> &Path {
        &self.link
    }

    /// Where the symlink this one replaced pointed (left by a run that was
    /// killed), if there was one.
    pub fn replaced(&self) -> Option<&Path> {
        self.replaced.as_deref()
    }
}

impl Drop for PtyEnd {
    fn drop(&mut self) {
        // Only our own link: another `twin vsp` may have taken the path since.
        if std::fs::read_link(&self.link).is_ok_and(|target| target == self.device) {
            let _ = std::fs::remove_file(&self.link);
        }
    }
}

/// Points `link` at `device`; returns where an old symlink there pointed.
fn place_link(link: &Path, device: &Path) -> Result<Option<PathBuf>> {
    let replaced = match std::fs::symlink_metadata(link) {
        Ok(meta) if meta.file_type().is_symlink() => {
            let old = std::fs::read_link(link).ok();
            std::fs::remove_file(link).map_err(|source| VspError::ReplaceLink {
                link: link.to_path_buf(),
                source,
            })?;
            old
        }
        Ok(_) => {
            return Err(VspError::NotASymlink {
                link: link.to_path_buf(),
            });
        }
        Err(e) if e.kind() == ErrorKind::NotFound => None,
        Err(source) => {
            return Err(VspError::CheckLink {
                link: link.to_path_buf(),
                source,
            });
        }
    };
    std::os::unix::fs::symlink(device, link).map_err(|source| VspError::CreateLink {
        link: link.to_path_buf(),
        source,
    })?;
    Ok(replaced)
}

/// Bytes copied one way, and bytes dropped because the far end's buffer was full.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DirectionCounters {
    pub bytes: u64,
    pub chunks: u64,
    pub dropped: u64,
}

/// How the pair copies.
#[derive(Debug, Clone, Copy, Default)]
pub struct PairOptions {
    /// Deliver bytes no faster than this baud rate (8N1: 10 bits a byte); a pty
    /// ignores the baud rate a program sets, so without it bytes cross at once.
    pub baud: Option<u32>,
}

/// One chunk that crossed, for a monitor.
#[derive(Debug)]
pub struct Crossing<'a> {
    /// 0: from the first end to the second; 1: back.
    pub direction: usize,
    pub at: Duration,
    pub bytes: &'a [u8],
}

/// The running pair.
#[derive(Debug)]
pub struct Pair {
    ends: [PtyEnd; 2],
    options: PairOptions,
    counters: [DirectionCounters; 2],
    /// Per direction, when the simulated line is free again (baud pacing).
    line_free: [Instant; 2],
    started: Instant,
}

impl Pair {
    /// Opens both ends; inside a tokio runtime (the masters are polled by it).
    pub fn open(links: [&Path; 2], options: PairOptions) -> Result<Self> {
        if links[0] == links[1] {
            return Err(VspError::SamePaths);
        }
        if options.baud == Some(0) {
            return Err(VspError::ZeroBaud);
        }
        let first = PtyEnd::open(links[0])?;
        let second = PtyEnd::open(links[1])?;
        let now = Instant::now();
        Ok(Self {
            ends: [first, second],
            options,
            counters: [DirectionCounters::default(); 2],
            line_free: [now; 2],
            started: now,
        })
    }

    pub fn end(&self, index: usize) -> &PtyEnd {
        &self.ends[index.min(1)]
    }

    pub fn counters(&self) -> [DirectionCounters; 2] {
        self.counters
    }

    /// Copies bytes both ways until the future is dropped; `on_crossing` sees
    /// every chunk (for the monitor), `on_stats` gets the counters every
    /// `stats_every` when they changed.
    pub async fn run(
        &mut self,
        stats_every: Option<Duration>,
        mut on_crossing: impl FnMut(&Crossing<'_>),
        mut on_stats: impl FnMut([DirectionCounters; 2]),
    ) -> Result<()> {
        let mut bufs = [[0u8; 4096]; 2];
        let mut stats = stats_every.map(tokio::time::interval);
        let mut last_shown = self.counters;
        loop {
            let tick = async {
                match stats.as_mut() {
                    Some(interval) => {
                        interval.tick().await;
                    }
                    None => std::future::pending::<()>().await,
                }
            };
            let [buf0, buf1] = &mut bufs;
            let (direction, n) = tokio::select! {
                read = read_ready(&self.ends[0], buf0) => (0, read?),
                read = read_ready(&self.ends[1], buf1) => (1, read?),
                () = tick => {
                    if self.counters != last_shown {
                        last_shown = self.counters;
                        on_stats(self.counters);
                    }
                    continue;
                }
            };
            if n == 0 {
                continue;
            }
            let chunk = &bufs[direction][..n];
            if let Some(baud) = self.options.baud {
                // The chunk leaves once its wire time has passed after the
                // line was free, so a burst is spread out at the baud rate.
                let wire = Duration::from_secs_f64(n as f64 * 10.0 / f64::from(baud));
                let start = self.line_free[direction].max(Instant::now());
                self.line_free[direction] = start + wire;
                tokio::time::sleep_until(self.line_free[direction].into()).await;
            }
            let written = write_some(&self.ends[1 - direction], chunk)?;
            let counters = &mut self.counters[direction];
            counters.bytes += written as u64;
            counters.chunks += 1;
            counters.dropped += (n - written) as u64;
            on_crossing(&Crossing {
                direction,
                at: self.started.elapsed(),
                bytes: chunk,
            });
        }
    }
}

async fn read_ready(end: &PtyEnd, buf: &mut [u8]) -> Result<usize> {
    loop {
        end.rx.readable().await.map_err(VspError::Wait)?;
        match end.rx.try_read(buf) {
            Ok(n) => return Ok(n),
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::Interrupted) => {}
            // Cannot happen while we hold the slave open; if it does, say which end.
            Err(source) => {
                return Err(VspError::Read {
                    device: end.device.clone(),
                    source,
                });
            }
        }
    }
}

/// Writes what the far end's buffer takes now; the rest is dropped.
fn write_some(end: &PtyEnd, mut bytes: &[u8]) -> Result<usize> {
    let mut written = 0;
    while !bytes.is_empty() {
        match end.tx.try_write(bytes) {
            Ok(0) => break,
            Ok(n) => {
                written += n;
                bytes = &bytes[n..];
            }
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) if e.kind() == ErrorKind::WouldBlock => break,
            Err(source) => {
                return Err(VspError::Write {
                    device: end.device.clone(),
                    source,
                });
            }
        }
    }
    Ok(written)
}

/// `40 30 31 …  |@01…|`: hex and printable ASCII of a chunk, for the monitor.
pub fn hex_line(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len() * 4 + 4);
    for (i, b) in bytes.iter().enumerate() {
        if i > 0 {
            out.push(' ');
        }
        out.push_str(&format!("{b:02x}"));
    }
    out.push_str("  |");
    out.extend(bytes.iter().map(|&b| {
        if b.is_ascii_graphic() || b == b' ' {
            char::from(b)
        } else {
            '.'
        }
    }));
    out.push('|');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_line_shows_bytes_and_printable_text() {
        assert_eq!(hex_line(b"@0*\n"), "40 30 2a 0a  |@0*.|");
    }
}
