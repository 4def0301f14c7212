//! Recordings read back: named signals, frames and events out of an MCAP
//! file, comparison against a baseline, the first departure of a replay,
//! and CSV export. `twin replay`, `compare`, `export` (and the viewer) build
//! on this.

pub mod compare;
pub mod diff;
pub mod export;
mod read;
pub mod signals;

pub use read::{Channel, Event, Frame, Message, Recording};
pub use signals::Signal;
