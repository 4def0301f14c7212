//! The plant's physics against analytic results and published figures.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

mod physics;
