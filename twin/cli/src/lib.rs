//! The commands of `twin`, each parsing its arguments (clap) and calling the
//! library crates. `main.rs` is the `twin` binary over them; `twin-avr`, the
//! GPL build that also runs compiled AVR firmware, flattens the same
//! argument groups and calls the same runners.

#![allow(
    clippy::disallowed_methods,
    reason = "commands time their runs and wait on real links and viewers"
)]

pub mod commands;
