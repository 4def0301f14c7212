//! Parallel EV modules (the PWM-capture paper's three-phase load): one master module sends
//! its speed reference to slave modules, over the PWM-capture link or over
//! Modbus RTU.
//!
//! The reference is `VEL`, the 12-bit throttle voltage the module's inverter
//! takes as its speed command: the master module closes the speed loop on its
//! own wheel and every slave drives its motor with the same command, as the
//! paper's master load hands its current command to the other phases.
//!
//! The PWM frames (paper Fig. 8), four symbols each:
//! - **broadcast**: start, status (upper nibble 1 = run, 0 = stop; lower
//!   nibble the command type, voltage), `VEL >> 8`, `VEL & 0xFF`;
//! - **designated**: start, status (upper nibble the slave id, 1–15), the
//!   two `VEL` symbols. The slave answers once the master has released the
//!   line with the same layout carrying its own id and the `VEL` it took,
//!   which is the master's acknowledgement; a missing or different answer
//!   makes the master retransmit.
//!
//! [`PwmReceiver`] is the receiving DSP's software: it assembles the capture
//! records the link delivers, finds frames by time (a pulse that rose more
//! than 1.5 symbol periods after the previous one's rising edge starts a new
//! frame; a frame still short of symbols 2.5 periods after its last pulse's
//! rising edge has timed out), and hands
//! out whole frames for [`PwmRepr::parse`] (start-width compensation, dummy
//! bits dropped).

mod master;
mod slave;

pub use master::{
    ParallelConfigError, ParallelLink, ParallelMaster, ParallelMasterConfig, SlaveCounters,
};
pub use slave::{PwmAddressing, PwmSlave, PwmSlaveConfig, PwmSlaveCounters};

use crate::link::pwmbus::PWM_RECORD_BYTES;
use protocols::pwmcap::{
    PWM_MAX_SYMBOLS, PwmCoding, PwmCommandType, PwmData, PwmError, PwmRepr, PwmStatus,
};
use protocols::time::{SimDuration, SimTime};

/// Symbols in every frame of this application, start included.
pub const FRAME_SYMBOLS: usize = 4;
/// Upper status nibble of a broadcast that runs the slaves.
pub const STATUS_RUN: u8 = 1;
/// Upper status nibble of a broadcast that stops them.
pub const STATUS_STOP: u8 = 0;
/// Highest slave id a designated frame can carry (a 4-bit nibble; 0 unused).
pub const MAX_PWM_SLAVE_ID: u8 = 15;

/// The two data symbols that carry a 12-bit `VEL`.
fn vel_data(vel: u16) -> PwmData {
    PwmData::from_slice(&[(vel >> 8) & 0x0F, vel & 0xFF]).unwrap_or_default()
}

/// `VEL` from the two data symbols, if that is what the frame carries.
pub fn vel_of(data: &PwmData) -> Option<u16> {
    match data.as_slice() {
        &[high, low] if high <= 0x0F && low <= 0xFF => Some(high << 8 | low),
        _ => None,
    }
}

/// A broadcast reference frame.
pub fn broadcast_frame(run: bool, vel: u16) -> PwmRepr {
    PwmRepr::Broadcast {
        status: PwmStatus {
            high: if run { STATUS_RUN } else { STATUS_STOP },
            command: PwmCommandType::Voltage,
        },
        data: vel_data(vel),
    }
}

/// A designated reference frame to slave `id`, or its answer from slave `id`.
pub fn designated_frame(id: u8, vel: u16) -> PwmRepr {
    PwmRepr::Designated {
        status: PwmStatus {
            high: id,
            command: PwmCommandType::Voltage,
        },
        data: vel_data(vel),
    }
}

/// Writes `frame`'s widths as the link takes them (4-byte little-endian
/// records) to `buf`; `None` if it does not fit or cannot be coded.
pub fn emit_widths(frame: &PwmRepr, coding: &PwmCoding, buf: &mut [u8]) -> Option<usize> {
    let mut widths = [0u32; PWM_MAX_SYMBOLS];
    let count = frame.emit(coding, &mut widths).ok()?;
    let out = buf.get_mut(..count * PWM_RECORD_BYTES)?;
    for (chunk, width) in out.chunks_exact_mut(PWM_RECORD_BYTES).zip(&widths[..count]) {
        chunk.copy_from_slice(&width.to_le_bytes());
    }
    Some(count * PWM_RECORD_BYTES)
}

/// Whether a coding can carry this application's frames (8 data bits at least).
pub fn check_coding(coding: &PwmCoding) -> Result<(), PwmError> {
    if coding.data_bits() < 8 {
        return Err(PwmError::InvalidCoding);
    }
    Ok(())
}

/// What the receiver made of the pulses so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RxOutcome {
    /// A whole frame's captured widths, start first.
    Frame([u32; FRAME_SYMBOLS]),
    /// A frame that stopped short: `got` of [`FRAME_SYMBOLS`] pulses.
    Incomplete {
        /// Pulses captured before the gap.
        got: usize,
    },
}

/// Frames out of the capture records a PWM port receives.
///
/// The record arrives at the pulse's falling edge and carries its width, so
/// the receiver knows when the pulse rose: `now − width`. Rising edges of one
/// frame are one symbol period apart whatever the values, falling edges are
/// not, so framing goes by rising edges.
#[derive(Debug, Clone)]
pub struct PwmReceiver {
    coding: PwmCoding,
    /// 1.5 symbol periods: longer than from one rising edge of a frame to the next.
    gap: SimDuration,
    /// 2.5 symbol periods: the next pulse has surely fallen by then.
    timeout: SimDuration,
    record: [u8; PWM_RECORD_BYTES],
    record_len: usize,
    widths: [u32; FRAME_SYMBOLS],
    count: usize,
    /// The last pulse's rising edge.
    last_rise: Option<SimTime>,
}

impl PwmReceiver {
    /// A receiver for symbols every `period_ticks` of `coding`'s counter.
    pub fn new(coding: &PwmCoding, period_ticks: u32) -> Self {
        let period = u64::from(period_ticks);
        PwmReceiver {
            coding: *coding,
            gap: coding.ticks_to_duration(period * 3 / 2),
            timeout: coding.ticks_to_duration(period * 5 / 2),
            record: [0; PWM_RECORD_BYTES],
            record_len: 0,
            widths: [0; FRAME_SYMBOLS],
            count: 0,
            last_rise: None,
        }
    }

    /// Forget a partial frame (the master starts a new exchange).
    pub fn reset(&mut self) {
        self.record_len = 0;
        self.count = 0;
        self.last_rise = None;
    }

    /// One byte of a capture record, arrived at `now`. A record that starts
    /// a new frame while the previous one is short reports that one as
    /// incomplete (and keeps the new pulse as the next frame's start).
    pub fn push(&mut self, now: SimTime, byte: u8) -> Option<RxOutcome> {
        self.record[self.record_len] = byte;
        self.record_len += 1;
        if self.record_len < PWM_RECORD_BYTES {
            return None;
        }
        self.record_len = 0;
        let width = u32::from_le_bytes(self.record);
        let width_time = self.coding.ticks_to_duration(u64::from(width));
        let rise = SimTime(now.0.saturating_sub(width_time.0));
        let mut outcome = None;
        if self.last_rise.is_some_and(|last| rise > last + self.gap) && self.count > 0 {
            outcome = Some(RxOutcome::Incomplete { got: self.count });
            self.count = 0;
        }
        self.last_rise = Some(rise);
        self.widths[self.count] = width;
        self.count += 1;
        if self.count == FRAME_SYMBOLS {
            self.count = 0;
            self.last_rise = None;
            // A late incomplete frame and a whole one cannot both end here:
            // a whole frame needs this record to be its fourth.
            return Some(RxOutcome::Frame(self.widths));
        }
        outcome
    }

    /// When a partial frame times out.
    pub fn poll_timeout(&self) -> Option<SimTime> {
        (self.count > 0)
            .then_some(self.last_rise)
            .flatten()
            .map(|last| last + self.timeout)
    }

    /// The timeout of [`PwmReceiver::poll_timeout`] has come.
    pub fn handle_timeout(&mut self, now: SimTime) -> Option<RxOutcome> {
        if self.poll_timeout().is_some_and(|due| due <= now) {
            let got = self.count;
            self.reset();
            return Some(RxOutcome::Incomplete { got });
        }
        None
    }
}
