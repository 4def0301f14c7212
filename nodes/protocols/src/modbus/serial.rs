//! The stream decoding shared by the binary serial framings (RTU and the
//! 8-byte variant): frames delimited by their length where the header gives it
//! and by line silence where it does not, with the resynchronisation rules of
//! `docs/protocols/modbus8.md`.
//!
//! Timing comes with each chunk: all bytes of a chunk are taken to have arrived
//! at its `now`. A gap of at least the configured silence between two chunks
//! ends whatever was in progress: a partial frame is dropped, a frame whose
//! length only the silence gives is complete, and the discarding that follows a
//! bad check stops. Where bytes carry no timing at all (RTU over TCP), the
//! decoder instead drops one byte at a time until a frame checks.

use crate::time::{SimDuration, SimTime};

use super::Drops;

/// How long a pseudo-terminal line must be quiet to end a frame: bytes on a
/// pty carry no timing, so the spec fixes 5 ms.
pub const PTY_SILENCE: SimDuration = SimDuration::from_millis(5);

/// 3.5 character times at `baud` with `bits_per_char` bits per character
/// (10 for 8N1, 11 for 8E1 or 8N2): the silence that ends a frame.
pub fn silence_3_5_chars(baud: u32, bits_per_char: u32) -> SimDuration {
    let baud = u64::from(baud.max(1));
    // 3.5 chars = 7 half characters; one rounding at the end keeps it exact
    // wherever 2 x baud divides the tick rate.
    SimDuration(7 * u64::from(bits_per_char) * crate::time::TICKS_PER_SECOND / (2 * baud))
}

/// The inter-frame silence the Modbus serial line specification (2.5.1.1)
/// prescribes: 3.5 character times, but a fixed 1.75 ms above 19 200 baud
/// because UART interrupt load makes shorter gaps impractical to time.
pub fn standard_rtu_silence(baud: u32, bits_per_char: u32) -> SimDuration {
    if baud > 19_200 {
        SimDuration::from_micros(1_750)
    } else {
        silence_3_5_chars(baud, bits_per_char)
    }
}

/// How a binary serial decoder finds frame boundaries it cannot derive from the
/// header, and recovers after a bad frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timing {
    /// Bytes carry arrival times: this much silence ends a frame (at least one
    /// tick is used, since a zero silence would split every chunk).
    Silence(SimDuration),
    /// Bytes carry no timing (RTU over TCP): resynchronise by dropping one byte
    /// at a time; frames of unknown length cannot be delimited and are dropped.
    None,
}

/// What the header in the buffer says about the frame's length.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameLen {
    /// The frame is this long.
    Known(usize),
    /// At least this many bytes are needed to tell.
    NeedAtLeast(usize),
    /// Only the silence after it tells (an unknown function code).
    UntilSilence,
}

/// The framing-specific half of a decoder: lengths and checks.
pub(crate) trait Framing {
    /// What a failed check reports.
    type Error;
    /// The length the bytes so far imply (`buf` is never empty).
    fn frame_len(&self, buf: &[u8]) -> FrameLen;
    /// Checks a complete frame.
    fn check(&self, frame: &[u8]) -> Result<(), Self::Error>;
}

/// Buffer, timing and drop accounting of a serial stream decoder. `N` is the
/// buffer size, the framing's longest frame.
#[derive(Debug, Clone)]
pub(crate) struct SerialCore<const N: usize> {
    buf: [u8; N],
    len: usize,
    /// Bytes at the front of `buf` that were handed out as a frame last call.
    yielded: usize,
    last_rx: Option<SimTime>,
    timing: Timing,
    /// Throwing bytes away until the next silence (after a bad frame).
    discarding: bool,
    /// The current discard has been counted as an event.
    discard_counted: bool,
    pub(crate) drops: Drops,
}

impl<const N: usize> SerialCore<N> {
    pub(crate) fn new(timing: Timing) -> Self {
        let timing = match timing {
            Timing::Silence(d) => Timing::Silence(SimDuration(d.0.max(1))),
            Timing::None => Timing::None,
        };
        SerialCore {
            buf: [0; N],
            len: 0,
            yielded: 0,
            last_rx: None,
            timing,
            discarding: false,
            discard_counted: false,
            drops: Drops::default(),
        }
    }

    /// Bytes held for a frame not yet complete.
    pub(crate) fn pending(&self) -> usize {
        self.len.saturating_sub(self.yielded)
    }

    pub(crate) fn timing(&self) -> Timing {
        self.timing
    }

    /// Forgets the frame handed out by the previous call.
    fn release(&mut self) {
        if self.yielded > 0 {
            let yielded = self.yielded.min(self.len);
            self.buf.copy_within(yielded..self.len, 0);
            self.len -= yielded;
            self.yielded = 0;
        }
    }

    /// When a silence would end what is in progress, if anything is.
    pub(crate) fn poll_timeout(&self) -> Option<SimTime> {
        match (self.timing, self.last_rx) {
            (Timing::Silence(silence), Some(last))
                if self.len > self.yielded || self.discarding =>
            {
                Some(last + silence)
            }
            _ => None,
        }
    }

    /// Applies the silence rule at `now`; may complete a frame whose length
    /// only the silence gives.
    pub(crate) fn handle_timeout<F: Framing>(
        &mut self,
        framing: &F,
        now: SimTime,
    ) -> Option<Result<&[u8], F::Error>> {
        let frame_end = self.expire(framing, now)?;
        Some(frame_end.map(|len| &self.buf[..len]))
    }

    fn expire<F: Framing>(&mut self, framing: &F, now: SimTime) -> Option<Result<usize, F::Error>> {
        self.release();
        let Timing::Silence(silence) = self.timing else {
            return None;
        };
        let last = self.last_rx?;
        if now.saturating_since(last) < silence {
            return None;
        }
        self.discarding = false;
        if self.len == 0 {
            return None;
        }
        if framing.frame_len(&self.buf[..self.len]) == FrameLen::UntilSilence {
            // The silence has already passed: nothing after this frame to discard.
            return Some(self.complete(framing, self.len, false));
        }
        self.drops.timed_out.add(self.len);
        self.len = 0;
        None
    }

    /// Takes bytes from `input` (arrived at `now`) until a frame is complete or
    /// the input is used up (`None`: need more).
    pub(crate) fn decode<F: Framing>(
        &mut self,
        framing: &F,
        now: SimTime,
        input: &mut &[u8],
    ) -> Option<Result<&[u8], F::Error>> {
        // Borrowing rules: find the frame length first, then hand out the slice.
        let frame_end = self.advance(framing, now, input)?;
        Some(frame_end.map(|len| &self.buf[..len]))
    }

    fn advance<F: Framing>(
        &mut self,
        framing: &F,
        now: SimTime,
        input: &mut &[u8],
    ) -> Option<Result<usize, F::Error>> {
        if !input.is_empty() {
            // A silence before this chunk ends what came before it.
            if let Some(item) = self.expire(framing, now) {
                return Some(item);
            }
        }
        self.release();
        loop {
            if self.discarding {
                if !input.is_empty() {
                    self.discard(input.len());
                    self.last_rx = Some(now);
                    *input = &[];
                }
                return None;
            }
            if self.len == 0 && input.is_empty() {
                return None;
            }
            let wanted = if self.len == 0 {
                1
            } else {
                match framing.frame_len(&self.buf[..self.len]) {
                    FrameLen::Known(n) if n > N => {
                        self.drop_bad_start(false);
                        continue;
                    }
                    FrameLen::Known(n) if self.len >= n => {
                        match self.complete(framing, n, true) {
                            Ok(len) => return Some(Ok(len)),
                            Err(err) if self.timing != Timing::None => return Some(Err(err)),
                            // Without timing a failed check is most likely a
                            // misaligned start: slide by one byte.
                            Err(_) => continue,
                        }
                    }
                    FrameLen::Known(n) | FrameLen::NeedAtLeast(n) => n,
                    FrameLen::UntilSilence => match self.timing {
                        Timing::Silence(_) => N,
                        Timing::None => {
                            self.drop_bad_start(true);
                            continue;
                        }
                    },
                }
            };
            if input.is_empty() {
                return None;
            }
            if self.len >= N {
                // A silence-delimited frame that outgrew the longest legal one.
                self.drops.oversize.add(self.len);
                self.len = 0;
                self.start_discarding();
                continue;
            }
            let take = wanted
                .min(N)
                .saturating_sub(self.len)
                .min(input.len())
                .max(1);
            let (head, rest) = input.split_at(take.min(input.len()));
            self.buf[self.len..self.len + head.len()].copy_from_slice(head);
            self.len += head.len();
            *input = rest;
            self.last_rx = Some(now);
        }
    }

    fn start_discarding(&mut self) {
        self.discarding = true;
        self.discard_counted = false;
    }

    /// Counts `bytes` thrown away while discarding; one event per discard.
    fn discard(&mut self, bytes: usize) {
        if bytes == 0 {
            return;
        }
        if !self.discard_counted {
            self.drops.after_bad_frame.events += 1;
            self.discard_counted = true;
        }
        self.drops.after_bad_frame.bytes += bytes as u64;
    }

    /// The buffer starts with a header that cannot begin a legal frame: drop
    /// it up to the next silence, or one byte where no timing exists.
    fn drop_bad_start(&mut self, unknown_function: bool) {
        let tally = if unknown_function {
            &mut self.drops.malformed
        } else {
            &mut self.drops.oversize
        };
        match self.timing {
            Timing::Silence(_) => {
                tally.add(self.len);
                self.len = 0;
                self.start_discarding();
            }
            Timing::None => {
                self.drops.malformed.add(1);
                self.buf.copy_within(1..self.len, 0);
                self.len -= 1;
            }
        }
    }

    /// Checks the first `n` buffered bytes as a frame. On success they are
    /// handed out; on failure they are dropped and, with timing and
    /// `discard_after`, so is what follows up to the next silence.
    fn complete<F: Framing>(
        &mut self,
        framing: &F,
        n: usize,
        discard_after: bool,
    ) -> Result<usize, F::Error> {
        match framing.check(&self.buf[..n]) {
            Ok(()) => {
                self.yielded = n;
                Ok(n)
            }
            Err(err) => {
                match self.timing {
                    Timing::Silence(_) => {
                        self.drops.bad_check.add(n);
                        let rest = self.len - n;
                        self.len = 0;
                        if discard_after {
                            self.start_discarding();
                            self.discard(rest);
                        }
                    }
                    Timing::None => {
                        self.drops.malformed.add(1);
                        self.buf.copy_within(1..self.len, 0);
                        self.len -= 1;
                    }
                }
                Err(err)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn silences_in_character_times() {
        // 8N1 at 115 200 baud: 35 bit times, about 304 µs.
        assert_eq!(
            silence_3_5_chars(115_200, 10),
            SimDuration::bit_times(35, 115_200)
        );
        // 8E1 at 9600 baud: 3.5 x 11 = 38.5 bit times = 4.0104 ms.
        assert_eq!(
            silence_3_5_chars(9_600, 11),
            SimDuration::bit_times(77, 19_200)
        );
        // The serial line spec fixes 1.75 ms above 19 200 baud.
        assert_eq!(
            standard_rtu_silence(115_200, 10),
            SimDuration::from_micros(1_750)
        );
        assert_eq!(
            standard_rtu_silence(19_200, 10),
            silence_3_5_chars(19_200, 10)
        );
    }
}
