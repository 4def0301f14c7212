//! The frames a session's links carried, gathered between two passes of the
//! engine's loop in one buffer and handed to the sink as one message: no
//! allocation and no channel send per frame on the request path.

use protocols::time::SimTime;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, Sender, channel};

/// Frames handed to the sink and not yet recorded, shared by the log that
/// ships them and the batches that carry them. The connections stop reading
/// while it is above [`Backlog::LIMIT`], so a session whose recording falls
/// behind (a machine busy with other work leaves the sink little time)
/// slows its clients down instead of queueing without bound, and the
/// session says for how long.
#[derive(Debug, Clone, Default)]
pub struct Backlog(Arc<BacklogCounts>);

#[derive(Debug, Default)]
struct BacklogCounts {
    frames: AtomicUsize,
    /// Waits of the connections for the recording, in
    /// [`Backlog::WAIT`]s summed over the connections.
    waits: AtomicU64,
}

impl Backlog {
    /// About 15 MB of queue (a frame waits as its bytes, a 40-byte record
    /// and its end): one to two seconds of eight clients at full speed, so a
    /// burst goes through at the links' rate and only a recording that stays
    /// behind holds the clients back. A larger queue only held more memory:
    /// at 1 M frames a ten-minute session at eight clients grew to 383 MiB,
    /// the queue's batches reallocated at every size from 0 up.
    pub const LIMIT: usize = 256 * 1024;

    /// How long a connection waits before it looks at the backlog again.
    pub const WAIT: std::time::Duration = std::time::Duration::from_millis(1);

    /// Frames shipped and not recorded yet.
    pub fn frames(&self) -> usize {
        self.0.frames.load(Ordering::Relaxed)
    }

    /// While the backlog is full, waits [`Backlog::WAIT`] at a time and
    /// counts the waits.
    pub fn wait_while_full(&self) {
        while self.is_full() {
            std::thread::sleep(Self::WAIT);
            self.0.waits.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// How long connections have waited for the recording to catch up,
    /// summed over the connections.
    pub fn waited(&self) -> std::time::Duration {
        Self::WAIT
            .saturating_mul(u32::try_from(self.0.waits.load(Ordering::Relaxed)).unwrap_or(u32::MAX))
    }

    /// Whether a connection should wait before it reads more.
    pub fn is_full(&self) -> bool {
        self.frames() > Self::LIMIT
    }

    fn add(&self, n: usize) {
        self.0.frames.fetch_add(n, Ordering::Relaxed);
    }

    fn sub(&self, n: usize) {
        self.0.frames.fetch_sub(n, Ordering::Relaxed);
    }
}

/// A connection's id, unique for the session.
pub type ConnId = u64;

/// Frames due on a connection, in order, for its task to write (each in one
/// write). The task keeps one and the front fills it, so neither allocates
/// once it has grown to the largest burst.
pub type Outgoing = PackedFrames;

/// Which way a frame went.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// From the peer to the twin.
    Rx,
    /// From the twin to the peer.
    Tx,
}

/// Frames back to back in one buffer, with where each ends: any number of
/// frames in two allocations, which a cleared store keeps for the next.
#[derive(Debug, Default)]
pub struct PackedFrames {
    bytes: Vec<u8>,
    ends: Vec<usize>,
    /// Whether the front waits to hear when these frames were written
    /// ([`crate::Endpoint::reports_writes`]): their carrier tells it
    /// (`FrontHandle::written`) once they are.
    report: bool,
}

impl PackedFrames {
    pub fn push(&mut self, frame: &[u8]) {
        self.bytes.extend_from_slice(frame);
        self.ends.push(self.bytes.len());
    }

    /// The front waits to hear when the frames pushed are written.
    pub fn report_when_written(&mut self) {
        self.report = true;
    }

    /// Whether the front waits to hear when these frames are written.
    pub fn reports(&self) -> bool {
        self.report && !self.is_empty()
    }

    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }

    pub fn clear(&mut self) {
        self.bytes.clear();
        self.ends.clear();
        self.report = false;
    }

    /// Moves every frame of `self` to the end of `to`.
    pub fn move_to(&mut self, to: &mut PackedFrames) {
        if to.is_empty() {
            std::mem::swap(self, to);
        } else {
            let base = to.bytes.len();
            to.bytes.extend_from_slice(&self.bytes);
            to.ends.extend(self.ends.iter().map(|e| e + base));
            to.report |= self.report;
        }
        self.clear();
    }

    /// The frames, in order.
    pub fn iter(&self) -> impl Iterator<Item = &[u8]> {
        let mut start = 0;
        self.ends.iter().map(move |&end| {
            let frame = self.bytes.get(start..end).unwrap_or_default();
            start = end;
            frame
        })
    }
}

/// Where a frame of a [`FrameBatch`] went, and when: a whole frame (tx), or
/// a chunk as read (rx).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRecord {
    pub link: usize,
    pub conn: ConnId,
    pub direction: Direction,
    pub start: SimTime,
    pub end: SimTime,
}

/// Frames and their records. Emptied batches go back to the log that
/// filled them ([`FrameBatch::recycle`]), so a steady session allocates none.
#[derive(Debug, Default)]
pub struct FrameBatch {
    frames: PackedFrames,
    records: Vec<FrameRecord>,
    home: Option<Sender<FrameBatch>>,
    /// Where its frames are counted until it is recycled or dropped.
    counted: Option<(Backlog, usize)>,
}

impl Drop for FrameBatch {
    fn drop(&mut self) {
        if let Some((backlog, n)) = self.counted.take() {
            backlog.sub(n);
        }
    }
}

impl FrameBatch {
    pub fn push(&mut self, record: FrameRecord, bytes: &[u8]) {
        self.frames.push(bytes);
        self.records.push(record);
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// The frames in the order they were pushed, with their bytes.
    pub fn iter(&self) -> impl Iterator<Item = (&FrameRecord, &[u8])> {
        self.records.iter().zip(self.frames.iter())
    }

    /// Empties the batch and sends it back to the log it came from.
    pub fn recycle(mut self) {
        if let Some((backlog, n)) = self.counted.take() {
            backlog.sub(n);
        }
        self.frames.clear();
        self.records.clear();
        if let Some(home) = self.home.take() {
            let _ = home.send(self);
        }
    }
}

/// The front's side: the batch being filled and the emptied ones coming back.
#[derive(Debug)]
pub struct FrameLog {
    filling: FrameBatch,
    spares: Receiver<FrameBatch>,
    /// Emptied batches kept for reuse, at most [`SPARES_KEPT`].
    pool: Vec<FrameBatch>,
    home: Sender<FrameBatch>,
    backlog: Backlog,
}

/// Emptied batches a log keeps: a steady session has two or three out.
const SPARES_KEPT: usize = 8;
/// A batch that came back holding room for more frames than this is freed
/// rather than kept: one filled while the engine was held up would keep
/// its memory for ever, and the kept batches are reused at every size.
const SPARE_FRAMES_KEPT: usize = 4096;

impl Default for FrameLog {
    fn default() -> Self {
        let (home, spares) = channel();
        Self {
            filling: FrameBatch::default(),
            spares,
            pool: Vec::new(),
            home,
            backlog: Backlog::default(),
        }
    }
}

impl FrameLog {
    pub fn push(&mut self, record: FrameRecord, bytes: &[u8]) {
        self.filling.push(record, bytes);
    }

    /// The frames logged so far (none if there are none), replaced by an
    /// emptied batch when one has come back.
    /// The count of this log's frames not yet recorded.
    pub fn backlog(&self) -> Backlog {
        self.backlog.clone()
    }

    pub fn take(&mut self) -> Option<FrameBatch> {
        if self.filling.is_empty() {
            return None;
        }
        // After a backlog, more batches come back than the log fills again
        // soon: keep a few, free the rest (they would hold their memory).
        while let Ok(spare) = self.spares.try_recv() {
            if self.pool.len() < SPARES_KEPT && spare.records.capacity() <= SPARE_FRAMES_KEPT {
                self.pool.push(spare);
            }
        }
        let next = self.pool.pop().unwrap_or_default();
        let mut batch = std::mem::replace(&mut self.filling, next);
        batch.home = Some(self.home.clone());
        self.backlog.add(batch.records.len());
        batch.counted = Some((self.backlog.clone(), batch.records.len()));
        Some(batch)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packed_frames_keep_their_bounds_when_moved() {
        let (mut a, mut b) = (PackedFrames::default(), PackedFrames::default());
        a.push(b"one");
        a.move_to(&mut b);
        assert!(a.is_empty());
        a.push(b"two");
        a.push(b"");
        a.push(b"three");
        a.move_to(&mut b);
        let frames: Vec<_> = b.iter().collect();
        assert_eq!(frames, [&b"one"[..], b"two", b"", b"three"]);
    }

    #[test]
    fn frames_come_out_as_pushed_and_batches_are_reused() {
        let mut log = FrameLog::default();
        assert!(log.take().is_none(), "nothing logged, nothing to send");
        let t = SimTime::ZERO;
        let record = |link, conn, direction| FrameRecord {
            link,
            conn,
            direction,
            start: t,
            end: t,
        };
        log.push(record(0, 1, Direction::Rx), b"ab");
        log.push(record(1, 2, Direction::Tx), b"");
        log.push(record(0, 1, Direction::Tx), b"cde");
        let batch = log.take().unwrap();
        let frames: Vec<_> = batch
            .iter()
            .map(|(r, b)| (r.link, r.conn, r.direction, b.to_vec()))
            .collect();
        assert_eq!(
            frames,
            [
                (0, 1, Direction::Rx, b"ab".to_vec()),
                (1, 2, Direction::Tx, vec![]),
                (0, 1, Direction::Tx, b"cde".to_vec()),
            ]
        );
        let capacity = batch.frames.bytes.capacity();
        batch.recycle();
        // The batch filling while the first was away goes out, and the one
        // that came back fills next: its buffer is the first one's.
        log.push(record(0, 3, Direction::Rx), b"x");
        log.take().unwrap().recycle();
        log.push(record(0, 3, Direction::Rx), b"y");
        let again = log.take().unwrap();
        let bytes: Vec<_> = again.iter().map(|(_, b)| b.to_vec()).collect();
        assert_eq!(bytes, [b"y".to_vec()]);
        assert_eq!(
            again.frames.bytes.capacity(),
            capacity,
            "the buffer was reused"
        );
    }

    fn a_received_chunk() -> FrameRecord {
        FrameRecord {
            link: 0,
            conn: 1,
            direction: Direction::Rx,
            start: SimTime::ZERO,
            end: SimTime::ZERO,
        }
    }

    #[test]
    fn the_backlog_counts_frames_until_recorded_or_dropped() {
        let mut log = FrameLog::default();
        let backlog = log.backlog();
        let record = a_received_chunk();
        log.push(record, b"a");
        log.push(record, b"b");
        let first = log.take().unwrap();
        log.push(record, b"c");
        let second = log.take().unwrap();
        assert_eq!(backlog.frames(), 3);
        first.recycle();
        assert_eq!(backlog.frames(), 1);
        // A batch the sink never took (it stopped) is uncounted when dropped.
        drop(second);
        assert_eq!(backlog.frames(), 0);
        assert!(!backlog.is_full());
        for _ in 0..=Backlog::LIMIT {
            log.push(record, b"");
        }
        let big = log.take().unwrap();
        assert!(backlog.is_full());
        big.recycle();
        assert!(!backlog.is_full());
    }

    #[test]
    fn a_connection_waits_while_the_backlog_is_full_and_the_wait_is_counted() {
        let mut log = FrameLog::default();
        let backlog = log.backlog();
        let record = a_received_chunk();
        backlog.wait_while_full();
        assert!(backlog.waited().is_zero(), "no wait while there is room");
        for _ in 0..=Backlog::LIMIT {
            log.push(record, b"");
        }
        let big = log.take().unwrap();
        // The sink records the batch a little later.
        let sink = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(20));
            big.recycle();
        });
        backlog.wait_while_full();
        assert!(!backlog.is_full());
        assert!(backlog.waited() >= Backlog::WAIT, "{:?}", backlog.waited());
        sink.join().unwrap();
    }
}
