//! A recording as the measured log: `twin supervise`'s recording of a real
//! module, or one of the twin's own. Its signals are named as `twin export`
//! and `twin view` name them (`/master/supervisor/loop.loops.0.measured_rpm`).

use super::CalibrateError;
use std::path::{Path, PathBuf};
use twin_recording::signals::Signals;

/// The numeric signals of one recording.
#[derive(Debug)]
pub struct Recorded {
    path: PathBuf,
    signals: Signals,
}

impl Recorded {
    pub fn read(path: &Path) -> Result<Recorded, CalibrateError> {
        let signals = Signals::read(path).map_err(|source| CalibrateError::ReadRecording {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(Recorded {
            path: path.to_path_buf(),
            signals,
        })
    }

    /// `(time s, value)` of the signal `name`.
    pub fn signal(&self, name: &str) -> Result<Vec<(f64, f64)>, CalibrateError> {
        let Some(signal) = self.signals.by_name.get(name) else {
            // The loops' signals are the ones a calibration reads; the
            // plant's dozens of sensor fields would bury them.
            let loops: Vec<&str> = self
                .signals
                .by_name
                .keys()
                .map(String::as_str)
                .filter(|n| n.starts_with("/master/"))
                .filter(|n| {
                    ["measured_rpm", "set_point_rpm", "output"]
                        .iter()
                        .any(|end| n.ends_with(end))
                })
                .collect();
            let hint = if loops.is_empty() {
                " (it has no master's loop: was it recorded by `twin supervise` or a scenario \
                 with a supervisor?)"
                    .to_string()
            } else {
                format!(" (its loop signals: {})", loops.join(", "))
            };
            return Err(CalibrateError::NoSignal {
                path: self.path.clone(),
                name: name.to_string(),
                hint,
            });
        };
        let samples: Vec<(f64, f64)> = signal
            .times
            .iter()
            .copied()
            .zip(signal.values.iter().copied())
            .filter(|p| p.1.is_finite())
            .collect();
        if samples.len() < 2 {
            return Err(CalibrateError::TooFewSignalValues {
                path: self.path.clone(),
                name: name.to_string(),
            });
        }
        Ok(samples)
    }

    /// The recording's first and last time (s) over `signals`.
    pub fn time_span(samples: &[Vec<(f64, f64)>]) -> (f64, f64) {
        let first = samples
            .iter()
            .filter_map(|s| s.first().map(|p| p.0))
            .fold(f64::INFINITY, f64::min);
        let last = samples
            .iter()
            .filter_map(|s| s.last().map(|p| p.0))
            .fold(f64::NEG_INFINITY, f64::max);
        (first, last)
    }
}

/// The set point's schedule: its first value from the start, then each
/// change, a microsecond after the last sample before it.
///
/// Why then: a supervisor takes the set point when a reading arrives and
/// reports it once its cycle is over, so a change reported at 0.512 s was
/// taken at the cycle's reading, some time after the report before it
/// (0.498 s) and before 0.512 s; replayed at 0.512 s it would come one
/// cycle late, and at 0.498 s itself one cycle early (that report's reading
/// arrived at that very time).
pub fn changes(set_point: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut out: Vec<(f64, f64)> = Vec::new();
    let mut before = 0.0;
    for &(t, v) in set_point {
        match out.last() {
            None => out.push((0.0, v)),
            Some(&(_, last)) if last != v => out.push((before + 1e-6, v)),
            Some(_) => {}
        }
        before = t;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_schedule_keeps_each_change_once() {
        let sp = [
            (0.1, 0.0),
            (0.2, 0.0),
            (0.5, 1000.0),
            (0.6, 1000.0),
            (4.0, 1500.0),
        ];
        let at: Vec<(f64, f64)> = changes(&sp)
            .iter()
            .map(|&(t, v)| ((t * 1e6).round() / 1e6, v))
            .collect();
        assert_eq!(at, vec![(0.0, 0.0), (0.200001, 1000.0), (0.600001, 1500.0)]);
        assert!(changes(&[]).is_empty());
    }
}
