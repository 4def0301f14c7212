//! One file per subcommand; each parses its arguments and calls library code.

pub mod baseline;
pub mod bench;
pub mod client;
pub mod compare;
pub mod experiment;
pub mod export;
pub mod replay;
pub mod run;
pub mod serve;
pub mod step;
pub mod supervise;
pub mod sweep;
pub mod view;
pub mod vsp;
