//! `twin scope`: a bus of a recording as a logic analyzer shows it. The
//! frames the recording holds (who sent what, when its first start bit
//! went) are laid out bit by bit at the bus's baud and character format on
//! the lines one would probe: each node's TX, its RS-485 driver enable and
//! its RX, and the pair itself ([`wave`]). Writers turn the lines into a VCD
//! file ([`vcd_out`], edges only, 1 ns timescale) or a sigrok session
//! ([`sigrok`], the `.sr` zip PulseView opens); the scope picture
//! (`twin_lab::scope_png`, where plotters lives) walks the same edges.
//!
//! A real-time session's link has no line to probe (a pseudo-terminal or a
//! socket carries bytes, not bits): its picture is reconstructed from the
//! frames' recorded times at the link's baud.
//!
//! Reads recordings only: never builds tokio, rerun, plotters or axum.

use std::path::PathBuf;

use thiserror::Error;

pub mod load;
pub mod sigrok;
pub mod vcd_out;
pub mod wave;

pub use load::{Choice, Window, load};
pub use wave::{LineFormat, LineKind, Waveform};

/// Why a scope picture could not be made.
#[derive(Debug, Error)]
pub enum ScopeError {
    #[error("cannot read {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: twin_recording::read::ReadError,
    },
    #[error("{} holds no frames of a bus or link", path.display())]
    NoFrames { path: PathBuf },
    #[error("{} has several buses and links ({have}): choose one with --bus or --link", path.display())]
    WhichBus { path: PathBuf, have: String },
    #[error("{} has no bus or link `{bus}` with frames (it has {have})", path.display())]
    NoSuchBus {
        path: PathBuf,
        bus: String,
        have: String,
    },
    #[error("--frame {frame}: {} has frames 0 to {} on this bus", path.display(), frames.saturating_sub(1))]
    NoSuchFrame {
        path: PathBuf,
        frame: usize,
        frames: usize,
    },
    #[error("--from {from} s is not before --to {to} s")]
    EmptyWindow { from: f64, to: f64 },
    #[error("{} does not say which scenario it ran (`twin.run` lacks `scenario_toml`)", path.display())]
    NoScenario { path: PathBuf },
    #[error("{}: its scenario does not read: {why}", path.display())]
    Scenario { path: PathBuf, why: String },
    #[error(
        "--rate {rate}: {samples} samples of {lines} lines is more than 1 GiB; choose a shorter window or a lower rate"
    )]
    TooManySamples {
        rate: u64,
        samples: u64,
        lines: usize,
    },
    #[error("--rate must be above zero")]
    ZeroRate,
    #[error("cannot write {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}
