//! The process's open-file budget. Every link connection (a socket and the
//! eventfd of its thread), every recording file and every panel connection
//! is one file descriptor or more, and they all come out of one soft limit,
//! `RLIMIT_NOFILE`. A login shell's and a systemd service's soft limit is
//! 1024 while the hard limit is far higher: systemd leaves a program that
//! needs more to raise its own soft limit, which [`raise_to_hard`] does when a
//! real-time session starts.

use rustix::process::{Resource, Rlimit, getrlimit, setrlimit};

/// The highest open-file limit Linux grants when the hard limit says
/// "unlimited" (`fs.nr_open`'s default); the kernel refuses an infinite one.
const NR_OPEN_DEFAULT: u64 = 1 << 20;

/// What [`raise_to_hard`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Raised {
    /// The soft limit was already the hard one (or unlimited).
    Already(Option<u64>),
    /// The soft limit went from `from` to `to`.
    From { from: u64, to: u64 },
}

/// The soft limit could not be raised: the session runs with what it had.
#[derive(Debug, thiserror::Error)]
#[error(
    "cannot raise the open-file limit from {soft} to {hard} ({source}); the links, \
     the recording and the panel share {soft} file descriptors: raise it with \
     `ulimit -n` or `LimitNOFILE=` in the service"
)]
pub struct CannotRaise {
    pub soft: u64,
    pub hard: u64,
    #[source]
    pub source: std::io::Error,
}

/// The open-file limits now (`None`: unlimited).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OpenFiles {
    pub soft: Option<u64>,
    pub hard: Option<u64>,
}

/// The process's open-file limits now.
pub fn open_files() -> OpenFiles {
    let Rlimit { current, maximum } = getrlimit(Resource::Nofile);
    OpenFiles {
        soft: current,
        hard: maximum,
    }
}

/// [`raise_to_hard`], the first time a process asks: `None` after that, so
/// a class server's sessions, each starting in a thread of its own, say a
/// failure once.
pub fn raise_once() -> Option<Result<Raised, CannotRaise>> {
    static DONE: std::sync::Once = std::sync::Once::new();
    let mut result = None;
    DONE.call_once(|| result = Some(raise_to_hard()));
    result
}

/// Raises the soft open-file limit to the hard one.
pub fn raise_to_hard() -> Result<Raised, CannotRaise> {
    let Rlimit { current, maximum } = getrlimit(Resource::Nofile);
    let Some(soft) = current else {
        return Ok(Raised::Already(None));
    };
    let hard = maximum.unwrap_or_else(nr_open);
    if soft >= hard {
        return Ok(Raised::Already(Some(soft)));
    }
    setrlimit(
        Resource::Nofile,
        Rlimit {
            current: Some(hard),
            maximum,
        },
    )
    .map_err(|e| CannotRaise {
        soft,
        hard,
        source: e.into(),
    })?;
    Ok(Raised::From {
        from: soft,
        to: hard,
    })
}

/// The kernel's ceiling on any process's open-file limit.
fn nr_open() -> u64 {
    std::fs::read_to_string("/proc/sys/fs/nr_open")
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(NR_OPEN_DEFAULT)
}
