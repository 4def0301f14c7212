//! The places a TCP listener has for clients (`--max-clients`), and which
//! of them are taken by connections whose peer has already gone.
//!
//! A connection's thread frees its place when it ends, which is a moment
//! after its peer closes; a newcomer arriving in that moment (right after a
//! burst of connect-and-close) would be refused although nobody is there.
//! So each place keeps a duplicate of its socket, and a full listener asks
//! the kernel which peers have hung up (`POLLRDHUP`) before it refuses.

use std::os::fd::OwnedFd;
use std::sync::{Mutex, MutexGuard};

use rustix::event::{PollFd, PollFlags, Timespec, poll};

use super::frame_log::ConnId;

/// The taken places of one listener.
#[derive(Debug, Default)]
pub struct Slots {
    taken: Mutex<Vec<(ConnId, OwnedFd)>>,
}

impl Slots {
    fn lock(&self) -> MutexGuard<'_, Vec<(ConnId, OwnedFd)>> {
        self.taken.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// `conn`, whose socket `socket` duplicates, takes a place.
    pub fn take(&self, conn: ConnId, socket: OwnedFd) {
        self.lock().push((conn, socket));
    }

    /// `conn`'s thread has ended: its place is free.
    pub fn free(&self, conn: ConnId) {
        self.lock().retain(|(c, _)| *c != conn);
    }

    /// Places taken by connections whose peer is still there.
    pub fn in_use(&self) -> usize {
        let taken = self.lock();
        let mut fds: Vec<PollFd<'_>> = taken
            .iter()
            .map(|(_, fd)| PollFd::new(fd, PollFlags::RDHUP))
            .collect();
        let now = Timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        if poll(&mut fds, Some(&now)).is_err() {
            return taken.len();
        }
        let gone = PollFlags::RDHUP | PollFlags::HUP | PollFlags::ERR;
        fds.iter()
            .filter(|fd| !fd.revents().intersects(gone))
            .count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::{TcpListener, TcpStream};

    #[test]
    fn a_place_whose_peer_hung_up_is_not_in_use() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let slots = Slots::default();
        let stay = TcpStream::connect(addr).unwrap();
        let leave = TcpStream::connect(addr).unwrap();
        for conn in [1, 2] {
            let (socket, _) = listener.accept().unwrap();
            slots.take(conn, OwnedFd::from(socket));
        }
        assert_eq!(slots.in_use(), 2);
        drop(leave);
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while slots.in_use() != 1 {
            assert!(std::time::Instant::now() < deadline, "the hang-up is seen");
            std::thread::yield_now();
        }
        slots.free(2);
        slots.free(1);
        assert_eq!(slots.in_use(), 0);
        drop(stay);
    }
}
