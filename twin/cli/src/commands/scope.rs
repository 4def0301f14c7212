//! `twin scope`: a recording's bus as a logic-analyzer capture.

use std::fs::File;
use std::io::BufWriter;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use twin_scope::{Choice, Window, sigrok, vcd_out};

/// Write a bus of a recording as a logic analyzer would capture it: VCD, a sigrok session, or a scope picture.
///
/// Each frame is laid out bit by bit at the bus's baud and character format
/// (start bit, 8 data bits least significant first, parity, stop bits) on the
/// lines one would probe: the pair itself (`bus.rs485.line`: what the
/// receivers got; where two nodes drive at once, each one's characters as
/// the engine garbled them, low wherever either is low), and
/// per node its UART's TX, its RS-485 driver enable (`de`) and its RX (off,
/// so high, while the node drives). A real-time session's link (`twin
/// serve`, `twin supervise`) has no line to probe: its waveform is
/// reconstructed from the recorded byte times at the link's baud, with a TX
/// line per side.
///
/// The TX lines carry the bytes as sent; the pair and the RX lines carry
/// them as the engine delivered them: a character a collision garbled as
/// garbled, bits noise flipped at a listener flipped (on its RX, and on the
/// pair). A window whose first frame starts right at its start (a frame at
/// 0 s) begins with a character of idle line, so a decoder sees the start bit.
///
/// A scope picture (`--png`) shows each talking node's TX above the bus line
/// at 0/5 V TTL levels, the bytes in hex under each character, and under the
/// screen the frames as a bus table (who sent it, its bytes, what it is), a
/// wrong CRC or an exception marked in red, and a character received other
/// than sent in red under the bus line.
///
/// Open the file in PulseView (or `sigrok-cli -i FILE`) and decode with the
/// `uart` decoder on the line (and `modbus` on top for Modbus RTU); the
/// command prints the decoder settings.
#[derive(Debug, Args)]
pub struct ScopeArgs {
    /// The recording.
    #[arg(value_name = "RUN.mcap")]
    recording: PathBuf,
    /// Write a VCD file: edges only, on a 1 ns timescale.
    #[arg(long, value_name = "FILE", required_unless_present_any = ["sr", "png"])]
    vcd: Option<PathBuf>,
    /// Write a sigrok session (.sr), sampled at --rate.
    #[arg(long, value_name = "FILE")]
    sr: Option<PathBuf>,
    /// Draw a scope picture (PNG): the nodes' TX lines and the bus line, the
    /// bytes and the frames under them.
    #[arg(long, value_name = "FILE")]
    png: Option<PathBuf>,
    /// Start of the window (s; default: just before the first frame).
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    from: Option<f64>,
    /// End of the window (s; default: just after the last frame).
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    to: Option<f64>,
    /// Only frame N of the bus (from 0, in the order they went), with two
    /// characters of idle line on either side.
    #[arg(long, value_name = "N", conflicts_with_all = ["from", "to"])]
    frame: Option<usize>,
    /// The simulated bus, when the recording has several.
    #[arg(long, value_name = "NAME", conflicts_with = "link")]
    bus: Option<String>,
    /// The real-time session's link (`meb`, `modbus-rtu`, …), when it has several.
    #[arg(long, value_name = "NAME")]
    link: Option<String>,
    /// The link's baud, when the recording does not say (a TCP link; default 115200).
    #[arg(long, value_name = "BAUD")]
    baud: Option<u32>,
    /// Samples per second of the .sr file (default: 16 per bit).
    #[arg(long, value_name = "HZ")]
    rate: Option<u64>,
    /// The scope picture's width (default 1280).
    #[arg(long, value_name = "PX", requires = "png")]
    width: Option<u32>,
    /// The scope picture's height (default: 150 px a channel, and the bus table).
    #[arg(long, value_name = "PX", requires = "png")]
    height: Option<u32>,
}

pub fn execute(args: &ScopeArgs) -> Result<()> {
    for (flag, value) in [("--from", args.from), ("--to", args.to)] {
        if value.is_some_and(|s| !s.is_finite() || s < 0.0) {
            bail!("{flag}: give seconds from 0 on");
        }
    }
    let window = match args.frame {
        Some(n) => Window::Frame(n),
        None if args.from.is_none() && args.to.is_none() => Window::All,
        None => Window::Span(args.from, args.to),
    };
    let choice = Choice {
        bus: args.bus.clone().or_else(|| args.link.clone()),
        window,
        baud: args.baud,
    };
    let wave = twin_scope::load(&args.recording, &choice)?;
    let seconds = |ticks: u64| ticks as f64 / protocols::time::TICKS_PER_SECOND as f64;
    println!(
        "twin scope: {} from {:.6} s to {:.6} s, {} frame{} at {} baud ({}){}{}",
        wave.name,
        seconds(wave.from),
        seconds(wave.to),
        wave.frames.len(),
        if wave.frames.len() == 1 { "" } else { "s" },
        wave.format.baud,
        char_format(&wave.format),
        if wave.lead_in > 0 {
            ", after a character of idle line (a frame starts the window)"
        } else {
            ""
        },
        if wave.reconstructed {
            "; reconstructed from the recorded byte times (a link has no line to probe)"
        } else {
            ""
        }
    );
    if !wave.flips.is_empty() || !wave.garbled.is_empty() {
        println!(
            "  as received: {} character{} garbled by collisions, {} with bits flipped by noise",
            wave.garbled.len(),
            if wave.garbled.len() == 1 { "" } else { "s" },
            wave.flips.len()
        );
    }
    if let Some(path) = &args.vcd {
        let file = File::create(path)
            .with_context(|| format!("--vcd {}: cannot create it", path.display()))?;
        let written = vcd_out::write(&wave, BufWriter::new(file))
            .with_context(|| format!("--vcd {}: cannot write it", path.display()))?;
        println!(
            "  {}: {} lines, {} edges, 1 ns timescale",
            path.display(),
            written.lines,
            written.edges
        );
    }
    if let Some(path) = &args.sr {
        let rate = args.rate.unwrap_or_else(|| sigrok::default_rate(&wave));
        let written = sigrok::write(&wave, rate, path)?;
        println!(
            "  {}: {} lines, {} samples at {} Hz",
            path.display(),
            written.lines,
            written.samples,
            written.rate
        );
    }
    if let Some(path) = &args.png {
        let size = twin_lab::scope_png::Size {
            width: args.width.unwrap_or(twin_lab::scope_png::WIDTH),
            height: args.height,
        };
        let drawn = twin_lab::scope_png::draw(&wave, path, size)
            .with_context(|| format!("--png {}: cannot draw it", path.display()))?;
        println!(
            "  {}: {}×{} px, channels {}",
            path.display(),
            drawn.width,
            drawn.height,
            drawn.channels.join(", ")
        );
    }
    println!(
        "decode: sigrok-cli -i FILE -P uart:rx={}.line:{}",
        wave.name,
        wave.format.sigrok_options()
    );
    Ok(())
}

fn char_format(format: &twin_scope::LineFormat) -> String {
    let parity = match format.parity {
        twin_scope::wave::Parity::None => 'N',
        twin_scope::wave::Parity::Even => 'E',
        twin_scope::wave::Parity::Odd => 'O',
    };
    format!("8{parity}{}", format.stop_bits)
}
