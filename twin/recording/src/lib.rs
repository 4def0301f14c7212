//! Recordings of the EV lab twin, written and read back.
//!
//! - [`record`]: the MCAP writer every run and session records through.
//! - [`describe`]: the one frame describer (the `decoded` fields of a frame).
//! - Reading back, streamed chunk by chunk: named signals, frames and events
//!   out of an MCAP file ([`Recording`]), comparison against a baseline
//!   ([`compare`]), the first departure of a replay ([`diff`]) and CSV export
//!   ([`export`]). `twin replay`, `compare`, `export` and the viewer build on
//!   this.

pub mod compare;
pub mod describe;
pub mod diff;
pub mod export;
mod read;
pub mod record;
pub mod signals;

pub use read::{Channel, Event, Frame, Message, Recording};
pub use record::Recorder;
pub use signals::Signal;
