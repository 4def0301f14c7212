//! What every node on a link is: a sans-IO state machine driven by `now`.
//!
//! The engine (virtual or real-time) owns the clock and the links. It hands a
//! node the bytes that reached it ([`Node::handle_bytes`]), wakes it at the
//! instant it asked for ([`Node::poll_timeout`] / [`Node::handle_timeout`]) and
//! asks it for bytes to send ([`Node::poll_transmit`]). A node never sleeps and
//! never reads a clock, so the same code runs on the simulated bus, a serial
//! port, a pseudo-terminal or TCP. A node that controls a plant (the EV
//! module's firmware, the Controller_network Arduinos) also implements [`Firmware`]: the
//! engine steps the plant up to each loop tick and hands the firmware the
//! sensors; the firmware answers with the actuators to hold until its next tick.

use crate::refusal::Refusal;
use protocols::time::{SimDuration, SimTime};

/// Longest frame any node sends in one piece (an MEB frame with 99 words and
/// `*\r\n` is 410 bytes; Modbus ASCII 513).
pub const MAX_FRAME: usize = 520;

/// Something worth recording that a node noticed: a timeout, a bad check, a
/// retry, a trip, a state change. Rare, so a `String` is fine here.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeEvent {
    pub at: SimTime,
    /// Short machine-readable kind: `timeout`, `bad_check`, `retry`, `exception`,
    /// `state`, `trip`, `dropped`, `log`, `framing` (a UART at another baud).
    pub kind: &'static str,
    /// Human-readable detail (for `log`, the line the real program would print).
    pub detail: String,
}

/// A node on a byte link.
pub trait Node {
    /// Bytes that arrived at `now` (the end of the last byte's stop bit).
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]);

    /// The instant this node asked for through [`Node::poll_timeout`] has come.
    fn handle_timeout(&mut self, now: SimTime);

    /// A frame the node wants on the wire now: written to `buf`, its length
    /// returned. The engine calls this after every `handle_*` and at every
    /// timeout until it returns `None`. A node that must wait (turnaround,
    /// poll period) returns `None` and reports the instant in `poll_timeout`.
    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize>;

    /// The next instant the node needs to be woken, if any.
    fn poll_timeout(&self) -> Option<SimTime>;

    /// The node's link finished sending its last frame at `now` (the end of the
    /// last stop bit): masters start reply timeouts from here.
    fn transmit_done(&mut self, _now: SimTime) {}

    /// Take the next event to record, if any.
    fn poll_event(&mut self) -> Option<NodeEvent> {
        None
    }

    /// Answer every request addressed to this node with `refusal` (an
    /// injected fault: MEB `ER`, a Modbus exception, the Controller_network
    /// project's exception frame), or serve normally again with `None`.
    /// False for a node that serves no requests (a master).
    fn force_refusal(&mut self, _refusal: Option<Refusal>) -> bool {
        false
    }
}

/// A node that runs a plant's control loop.
pub trait Firmware {
    /// Time between two loop ticks.
    fn loop_period(&self) -> SimDuration;

    /// One loop pass at `now`: read the sensors (ADC samples, edge captures)
    /// and say what the pins drive until the next pass.
    fn loop_tick(&mut self, now: SimTime, sensors: &plant::Sensors) -> plant::Actuators;
}
