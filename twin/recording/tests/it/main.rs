//! The MCAP writer and the streaming reader.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

mod schemas;
mod streaming;
mod writer;
