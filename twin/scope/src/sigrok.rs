//! A waveform as a sigrok session (`.sr`), the file PulseView and
//! `sigrok-cli -i` open: a zip holding `version` (`2`), `metadata` (an ini
//! file naming the channels and the sample rate) and the samples in
//! `logic-1-1`, `logic-1-2`, … (one bit per channel, `unitsize` bytes per
//! sample, channel 1 in the lowest bit), deflated as sigrok writes them.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use protocols::time::TICKS_PER_SECOND;
use zip::CompressionMethod;
use zip::write::{SimpleFileOptions, ZipWriter};

use crate::ScopeError;
use crate::wave::Waveform;

/// Bytes per `logic-1-N` member.
const CHUNK: usize = 4 << 20;
/// The most sample bytes held at once.
const MAX_BYTES: u64 = 1 << 30;

/// What was written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Written {
    pub lines: usize,
    pub samples: u64,
    pub rate: u64,
}

/// The default sample rate: 16 samples per bit.
pub fn default_rate(wave: &Waveform) -> u64 {
    16 * u64::from(wave.format.baud)
}

/// The samples of `wave` at `rate` per second, `unitsize` bytes each.
pub fn samples(wave: &Waveform, rate: u64) -> Result<(Vec<u8>, usize, u64), ScopeError> {
    if rate == 0 {
        return Err(ScopeError::ZeroRate);
    }
    let lines = wave.lines();
    let unitsize = lines.len().div_ceil(8).max(1);
    // The samples begin with the window's idle lead-in, if it has one.
    let lead = u128::from(wave.lead_in);
    let span = u128::from(wave.to - wave.from) + lead;
    let count = (span * u128::from(rate)).div_ceil(u128::from(TICKS_PER_SECOND));
    let count = u64::try_from(count).unwrap_or(u64::MAX);
    if count.saturating_mul(unitsize as u64) > MAX_BYTES {
        return Err(ScopeError::TooManySamples {
            rate,
            samples: count,
            lines: lines.len(),
        });
    }
    let mut data = vec![0u8; count as usize * unitsize];
    // The first sample at or after tick `at`.
    let index = |at: u64| -> u64 {
        let since = lead + u128::from(at.saturating_sub(wave.from));
        let i = (since * u128::from(rate)).div_ceil(u128::from(TICKS_PER_SECOND));
        u64::try_from(i).unwrap_or(u64::MAX).min(count)
    };
    for (bit, line) in lines.iter().enumerate() {
        let (byte, mask) = (bit / 8, 1u8 << (bit % 8));
        let mut fill = |from: u64, to: u64, level: bool| {
            if level {
                for s in from..to {
                    data[s as usize * unitsize + byte] |= mask;
                }
            }
        };
        let mut level = Waveform::idle(line.kind);
        let mut at_sample = 0;
        for (at, l) in wave.edges(line.kind) {
            let i = index(at);
            if i >= count {
                break;
            }
            fill(at_sample, i, level);
            at_sample = i;
            level = l;
        }
        fill(at_sample, count, level);
    }
    Ok((data, unitsize, count))
}

/// Writes `wave` sampled at `rate` per second to `path` as a sigrok session.
pub fn write(wave: &Waveform, rate: u64, path: &Path) -> Result<Written, ScopeError> {
    let (data, unitsize, count) = samples(wave, rate)?;
    let lines = wave.lines();
    let mut meta = format!(
        "[global]\nsigrok version=0.5.2\n\n[device 1]\ncapturefile=logic-1\ntotal probes={}\nsamplerate={rate} Hz\ntotal analog=0\n",
        lines.len()
    );
    for (i, line) in lines.iter().enumerate() {
        meta.push_str(&format!("probe{}={}\n", i + 1, line.name));
    }
    meta.push_str(&format!("unitsize={unitsize}\n"));
    let io = |e: zip::result::ZipError| match e {
        zip::result::ZipError::Io(e) => e,
        other => std::io::Error::other(other),
    };
    let written = (|| -> std::io::Result<()> {
        let file = File::create(path)?;
        let mut zip = ZipWriter::new(BufWriter::new(file));
        let stored = SimpleFileOptions::default().compression_method(CompressionMethod::Stored);
        let deflated = SimpleFileOptions::default().compression_method(CompressionMethod::Deflated);
        zip.start_file("version", stored).map_err(io)?;
        zip.write_all(b"2")?;
        zip.start_file("metadata", deflated).map_err(io)?;
        zip.write_all(meta.as_bytes())?;
        let per_chunk = (CHUNK / unitsize) * unitsize;
        for (n, chunk) in data.chunks(per_chunk).enumerate() {
            zip.start_file(format!("logic-1-{}", n + 1), deflated)
                .map_err(io)?;
            zip.write_all(chunk)?;
        }
        zip.finish().map_err(io)?.flush()
    })();
    written.map_err(|source| ScopeError::Write {
        path: path.to_path_buf(),
        source,
    })?;
    Ok(Written {
        lines: lines.len(),
        samples: count,
        rate,
    })
}
