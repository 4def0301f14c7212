//! Real AVR firmware in the loop: Arduino sketches compiled for the
//! ATmega328P, run instruction by instruction in simavr (Debian's
//! libsimavr, behind the C shim in `csrc/shim.c`), wired to the twin's
//! plant and bus on the engine's clock.
//!
//! simavr is GPL-3.0-or-later, so this crate and the `twin-avr` binary are
//! too; nothing else in the workspace depends on it, and `twin` builds
//! without any AVR tool.

pub mod builder;
pub mod debug;
pub mod elf;
#[allow(
    unsafe_code,
    reason = "the one module that calls simavr through its C shim"
)]
pub mod ffi;
pub mod node;
pub mod record;
pub mod replay;
pub mod stepper;
pub mod vcd;
pub mod wiring;

pub use builder::register;
pub use node::AvrNode;
pub use wiring::Wiring;
