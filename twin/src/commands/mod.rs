//! One file per subcommand; each parses its arguments and calls library code.

pub mod bench;
pub mod experiment;
pub mod run;
pub mod serve;
