//! Real links: TCP sockets, serial ports and pseudo-terminals, as tokio byte
//! streams. A link is named by a spec (`tcp://127.0.0.1:5020`,
//! `/tmp/ttyV1?baud=9600&parity=E&stop=2`), parsed by [`LinkSpec::parse`].

pub mod serial;
pub mod tcp;

/// The link grammar, from `protocols` (serve-bench reads it too).
pub use protocols::link as spec;

pub use spec::{LinkAddr, LinkDefaults, LinkSpec, Parity, SerialSettings};
