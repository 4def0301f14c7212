//! Cutting a byte stream into MEB frames.
//!
//! `@` appears nowhere inside a frame, so every `@` starts one, and `\n` ends it.
//! The decoder therefore needs no timing to stay in step: bytes outside a frame
//! are noise, a frame cut short by a new `@` is dropped, and a frame that reaches
//! [`MEB_MAX_FRAME_LEN`] without its `\n` is dropped at once rather than waited on.
//! Each drop is counted by reason in [`MebDecoderStats`].

use super::{MEB_MAX_FRAME_LEN, MebError, MebFrame, MebRepr};
use crate::time::{SimDuration, SimTime};

/// A frame the decoder dropped, reported in place of the frame it would have been.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, thiserror::Error)]
pub enum MebDecodeError {
    /// The bytes up to a `\n` are not a well-formed frame, or a frame grew past
    /// [`MEB_MAX_FRAME_LEN`] ([`MebError::TooLong`]).
    #[error(transparent)]
    Malformed(#[from] MebError),
    /// A new `@` arrived before this frame's `\n`.
    #[error("a new `@` arrived before the frame's end")]
    Interrupted,
}

/// What the decoder has seen and dropped since it was made.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MebDecoderStats {
    /// Well-formed frames delivered.
    pub frames: u64,
    /// Bytes outside any frame (before an `@`, or after a frame dropped as too long).
    pub noise_bytes: u64,
    /// Partial frames cut short by a new `@`.
    pub interrupted: u64,
    /// Partial frames dropped by [`MebDecoder::handle_timeout`].
    pub timed_out: u64,
    /// Malformed frames, indexed like [`MebError::ALL`].
    malformed: [u64; MebError::ALL.len()],
}

impl MebDecoderStats {
    /// Frames dropped as `kind`.
    pub fn malformed(&self, kind: MebError) -> u64 {
        self.malformed[kind as usize]
    }

    /// Every frame dropped, whatever the reason.
    pub fn dropped_frames(&self) -> u64 {
        self.malformed.iter().sum::<u64>() + self.interrupted + self.timed_out
    }
}

/// A stream decoder for MEB over any byte transport (bus, serial port, pty, TCP).
///
/// Feed it with [`push`](Self::push) (zero-copy, one event per call) or
/// [`frames`](Self::frames) (an iterator of values). It holds at most one frame,
/// in a fixed buffer of [`MEB_MAX_FRAME_LEN`] bytes, and never allocates.
#[derive(Debug, Clone)]
pub struct MebDecoder {
    buffer: [u8; MEB_MAX_FRAME_LEN],
    /// Bytes of the partial frame in `buffer`; zero between frames.
    len: usize,
    /// When the partial frame's `@` arrived.
    started_at: SimTime,
    partial_timeout: Option<SimDuration>,
    stats: MebDecoderStats,
}

/// One event of [`MebDecoder::push`]: a frame (a view into the decoder's buffer) or a drop.
pub type MebEvent<'a> = Result<MebFrame<&'a [u8]>, MebDecodeError>;

impl Default for MebDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl MebDecoder {
    /// A decoder with no partial-frame timeout.
    pub const fn new() -> Self {
        Self {
            buffer: [0; MEB_MAX_FRAME_LEN],
            len: 0,
            started_at: SimTime::ZERO,
            partial_timeout: None,
            stats: MebDecoderStats {
                frames: 0,
                noise_bytes: 0,
                interrupted: 0,
                timed_out: 0,
                malformed: [0; MebError::ALL.len()],
            },
        }
    }

    /// A decoder whose partial frames expire `timeout` after their `@` (see
    /// [`poll_timeout`](Self::poll_timeout)); the spec's TCP default is 5 s.
    pub const fn with_partial_timeout(timeout: SimDuration) -> Self {
        let mut decoder = Self::new();
        decoder.partial_timeout = Some(timeout);
        decoder
    }

    /// Counters of what was delivered and dropped.
    pub fn stats(&self) -> &MebDecoderStats {
        &self.stats
    }

    /// Bytes of a partial frame held, zero between frames.
    pub fn buffered(&self) -> usize {
        self.len
    }

    /// Consumes `bytes` that arrived at `now` up to the first event — a complete
    /// frame or a dropped one — and returns how many bytes it used with the event.
    /// Call again with the rest until all are used. `None` means "need more".
    pub fn push(&mut self, now: SimTime, bytes: &[u8]) -> (usize, Option<MebEvent<'_>>) {
        let mut used = 0;
        if self.len == 0 {
            let Some(bof) = bytes.iter().position(|&b| b == b'@') else {
                self.stats.noise_bytes += bytes.len() as u64;
                return (bytes.len(), None);
            };
            self.stats.noise_bytes += bof as u64;
            self.buffer[0] = b'@';
            self.len = 1;
            self.started_at = now;
            used = bof + 1;
        }
        let rest = bytes.get(used..).unwrap_or_default();
        // One byte past the room left decides "too long" without waiting for more.
        let room = MEB_MAX_FRAME_LEN - self.len;
        let window = rest.get(..room + 1).unwrap_or(rest);
        match window.iter().position(|&b| b == b'@' || b == b'\n') {
            Some(at) if window[at] == b'@' => {
                // The `@` is left unused: it starts the next frame on the next call.
                self.len = 0;
                self.stats.interrupted += 1;
                (used + at, Some(Err(MebDecodeError::Interrupted)))
            }
            Some(at) if at < room => {
                let end = self.len + at + 1;
                self.buffer[self.len..end].copy_from_slice(&window[..=at]);
                self.len = 0;
                let frame = MebFrame::new_checked(&self.buffer[..end]);
                match frame {
                    Ok(_) => self.stats.frames += 1,
                    Err(kind) => self.stats.malformed[kind as usize] += 1,
                }
                (
                    used + at + 1,
                    Some(frame.map_err(MebDecodeError::Malformed)),
                )
            }
            None if window.len() <= room => {
                self.buffer[self.len..self.len + window.len()].copy_from_slice(window);
                self.len += window.len();
                (used + window.len(), None)
            }
            // The byte after a full buffer, `\n` or not: the frame is too long.
            _ => {
                self.len = 0;
                self.stats.malformed[MebError::TooLong as usize] += 1;
                (
                    used + room + 1,
                    Some(Err(MebDecodeError::Malformed(MebError::TooLong))),
                )
            }
        }
    }

    /// All events in `bytes`, as values. Bytes after the last event stay in the
    /// decoder as a partial frame; stopping the iterator early leaves the rest of
    /// `bytes` unused, so drain it.
    pub fn frames<'d, 'b>(&'d mut self, now: SimTime, bytes: &'b [u8]) -> MebFrames<'d, 'b> {
        MebFrames {
            decoder: self,
            now,
            rest: bytes,
        }
    }

    /// When the partial frame held expires, if there is one and a timeout is set.
    pub fn poll_timeout(&self) -> Option<SimTime> {
        match (self.len, self.partial_timeout) {
            (0, _) | (_, None) => None,
            (_, Some(timeout)) => Some(self.started_at + timeout),
        }
    }

    /// Drops the partial frame if it has expired by `now`; returns whether it did,
    /// so a TCP server can close the connection.
    pub fn handle_timeout(&mut self, now: SimTime) -> bool {
        match self.poll_timeout() {
            Some(deadline) if now >= deadline => {
                self.len = 0;
                self.stats.timed_out += 1;
                true
            }
            _ => false,
        }
    }
}

/// The iterator of [`MebDecoder::frames`].
#[derive(Debug)]
pub struct MebFrames<'d, 'b> {
    decoder: &'d mut MebDecoder,
    now: SimTime,
    rest: &'b [u8],
}

impl Iterator for MebFrames<'_, '_> {
    type Item = Result<MebRepr, MebDecodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.rest.is_empty() {
            let (used, event) = self.decoder.push(self.now, self.rest);
            let event = event.map(|e| e.map(|frame| MebRepr::from_frame(&frame)));
            self.rest = self.rest.get(used..).unwrap_or_default();
            if event.is_some() {
                return event;
            }
        }
        None
    }
}
