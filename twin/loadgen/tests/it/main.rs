//! serve-bench end to end.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

#![allow(
    clippy::disallowed_methods,
    reason = "the test drives real processes and sockets in real time"
)]

mod smoke;
