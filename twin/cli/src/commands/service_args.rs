//! What makes `twin serve` and `twin supervise` services: a configuration
//! file (`--config`, checked with `--check`) and the client addresses the
//! TCP links serve (`--allow`).

use clap::Args;
use std::path::PathBuf;
use twin_realtime::allow::Network;

#[derive(Debug, Args)]
pub struct ServiceArgs {
    /// Read the options from this TOML file: its keys are the long options
    /// without the dashes (`rotate-every = "1h"`, `meb =
    /// ["tcp://0.0.0.0:5700"]`, `quiet = true`). An option on the command
    /// line replaces the file's. SIGHUP rereads what can change while
    /// serving (--allow and the recording's rotation and --keep options)
    /// and names what needs a restart.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Check the options (and the --config file) and say what would be
    /// served, without opening any link.
    #[arg(long)]
    pub check: bool,
    /// Serve TCP clients only from this address or network (`10.0.3.0/24`,
    /// `127.0.0.1`); repeat it for more [default: any]. A client from
    /// elsewhere is closed at once and the refusal logged.
    #[arg(long, value_name = "NETWORK", value_parser = network)]
    pub allow: Vec<Network>,
}

fn network(text: &str) -> Result<Network, String> {
    Network::parse(text)
}
