//! `twin check`: a student's program checked against the protocol it must
//! speak. A suite ([`suite`]) is a TOML file of checks, each a few steps
//! (send a frame, expect a reply of a shape or silence within a time),
//! each tied to the requirement it checks and worth some points; the
//! built-in suites are written in the same format a teacher uses for their
//! own. [`run`] plays a suite over a real link (a serial port, a
//! pseudo-terminal or TCP), [`report`] says what passed and, for what did
//! not, the frames that show it, as text, JSON, JUnit XML or a page.
//! [`class`] runs a suite against a whole class's programs at once;
//! [`record`] writes a run to MCAP, like every run of the twin.
//! [`master`] checks a supervisor as master of its bus; [`server`] checks
//! it from its bus and its TCP server at once; [`client`] is a session
//! with a remote client that follows a checklist. [`bench`] holds a
//! slave wired to a twin session's bench to what its registers mean: the
//! motor, the brake, the direction, the inputs against the plant.
//!
//! The fence: no engine, no plant. The checked program is outside the twin;
//! this crate only talks to it over the wire, where the twin's own node
//! code (a slave, a supervisor's image) plays the program's counterpart.

#![allow(
    clippy::disallowed_methods,
    reason = "a check talks to a real program in real time: its replies are timed by the wall clock"
)]

pub mod bench;
pub mod class;
pub mod client;
pub mod framing;
pub mod master;
pub mod record;
pub mod report;
pub mod run;
pub mod server;
pub mod suite;
pub mod wire;

pub use bench::Bench;
pub use framing::Protocol;
pub use run::{CheckOutcome, Outcome, SuiteRun, run_suite, run_suite_on};
pub use suite::{BUILT_IN, Suite, SuiteError};
