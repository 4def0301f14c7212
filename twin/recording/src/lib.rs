//! Recordings of the EV lab twin, written and read back.
//!
//! - [`topics`]: the catalogue of channels, their fields and the metadata
//!   records; every writer and reader names topics through it.
//! - [`record`]: the MCAP writer every run and session records through.
//! - [`describe`]: the one frame describer (the `decoded` fields of a frame).
//! - [`proto`], [`typed`]: the busiest messages' protobuf, from the `.proto`
//!   files in `proto/` (compiled at build time), and read back as JSON.
//! - [`read`]: the one reader, streamed chunk by chunk ([`Reader`]), and what
//!   a pass finds ([`Recording`]). On it: named signals as `f64` columns
//!   ([`signals`]), comparison against a baseline ([`compare`]), the first
//!   departure of a replay ([`diff`]) and CSV export ([`export`]).
//!   `twin replay`, `compare`, `export` and the viewer build on this.
//! - [`attachment`]: files a recording carries whole (a run's firmware).
//! - [`identity`]: what a recording says was run, field by field.

pub mod attachment;
mod chunk;
pub mod compare;
pub mod describe;
pub mod diff;
pub mod disk;
pub mod export;
pub mod identity;
mod mcap_file;
pub mod protobuf;
pub mod read;
pub mod record;
pub mod recover;
pub mod signals;
pub mod topics;
pub mod typed;
mod write_error;
mod writer;

pub use read::{
    BusFrame, Channel, Cut, Encoding, Event, Item, Message, ReadError, Reader, Recording,
};
pub use record::{Recorder, WriteError};
pub use signals::{Signal, Signals};
