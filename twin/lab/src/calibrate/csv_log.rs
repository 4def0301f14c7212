//! The measured log: a CSV file with a header row, `#` comments allowed
//! (a provenance header), read with the `csv` crate.

use super::CalibrateError as E;
use std::path::{Path, PathBuf};

/// The log's cells, by column, with the line each row came from.
#[derive(Debug)]
pub struct Table {
    path: PathBuf,
    headers: Vec<String>,
    /// Per row: its line in the file, its time (s), its cells.
    rows: Vec<(u64, f64, Vec<String>)>,
}

/// Reads `path`; the time column is checked here (numbers, never going back).
pub fn read(path: &Path, time_column: &str, time_scale: f64) -> Result<Table, E> {
    let at = |line: u64| format!("{}:{line}", path.display());
    let mut reader = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .flexible(false)
        .from_path(path)
        .map_err(|source| E::ReadLog {
            path: path.to_path_buf(),
            source,
        })?;
    let headers: Vec<String> = reader
        .headers()
        .map_err(|source| E::NoHeader {
            path: path.to_path_buf(),
            source,
        })?
        .iter()
        .map(str::to_string)
        .collect();
    let Some(time_at) = headers.iter().position(|h| h == time_column) else {
        return Err(E::NoTimeColumn {
            path: path.to_path_buf(),
            column: time_column.to_string(),
            columns: headers.join(", "),
        });
    };
    let mut rows = Vec::new();
    let mut last_time = f64::NEG_INFINITY;
    for record in reader.records() {
        let record = record.map_err(|e| in_words(path, &e))?;
        let line = record.position().map_or(0, csv::Position::line);
        let cell = record.get(time_at).unwrap_or("");
        let time = number(cell)
            .map(|t| t * time_scale)
            .map_err(|source| E::NotATime {
                at: at(line),
                column: time_column.to_string(),
                cell: cell.to_string(),
                source,
            })?;
        if time <= last_time {
            return Err(E::TimeBackwards {
                at: at(line),
                column: time_column.to_string(),
                cell: cell.to_string(),
                before: last_time / time_scale,
            });
        }
        last_time = time;
        rows.push((line, time, record.iter().map(str::to_string).collect()));
    }
    if rows.len() < 2 {
        return Err(E::TooFewRows {
            path: path.to_path_buf(),
        });
    }
    Ok(Table {
        path: path.to_path_buf(),
        headers,
        rows,
    })
}

/// A finite number; NaN and infinities are refused.
fn number(cell: &str) -> Result<f64, NotANumber> {
    let v: f64 = cell.parse().map_err(|_| NotANumber::NotANumber)?;
    if !v.is_finite() {
        return Err(NotANumber::NotFinite);
    }
    Ok(v)
}

/// A cell that is not a finite number.
#[derive(Debug, Clone, Copy, thiserror::Error)]
pub enum NotANumber {
    #[error("not a number")]
    NotANumber,
    #[error("not a finite number")]
    NotFinite,
}

fn in_words(path: &Path, e: &csv::Error) -> E {
    let at = |pos: &Option<csv::Position>| {
        format!(
            "{}:{}",
            path.display(),
            pos.as_ref().map_or(0, csv::Position::line)
        )
    };
    match e.kind() {
        csv::ErrorKind::UnequalLengths {
            pos,
            expected_len,
            len,
        } => E::UnequalRow {
            at: at(pos),
            len: *len,
            expected: *expected_len,
        },
        csv::ErrorKind::Utf8 { pos, .. } => E::NotUtf8 { at: at(pos) },
        _ => E::Csv {
            path: path.to_path_buf(),
            why: e.to_string(),
        },
    }
}

impl Table {
    /// First and last time (s).
    pub fn time_span(&self) -> (f64, f64) {
        let first = self.rows.first().map_or(0.0, |r| r.1);
        let last = self.rows.last().map_or(0.0, |r| r.1);
        (first, last)
    }

    /// `(time, value)` of a column; an empty cell is skipped when
    /// `skip_empty`, an error otherwise, and so is anything not a number.
    pub fn column(&self, name: &str, skip_empty: bool) -> Result<Vec<(f64, f64)>, E> {
        let Some(at) = self.headers.iter().position(|h| h == name) else {
            return Err(E::NoColumn {
                path: self.path.clone(),
                column: name.to_string(),
                columns: self.headers.join(", "),
            });
        };
        let line_at = |line: &u64| format!("{}:{line}", self.path.display());
        let mut out = Vec::with_capacity(self.rows.len());
        for (line, time, cells) in &self.rows {
            let cell = cells.get(at).map_or("", String::as_str);
            if cell.is_empty() {
                if skip_empty {
                    continue;
                }
                return Err(E::EmptyCell {
                    at: line_at(line),
                    column: name.to_string(),
                });
            }
            let v = number(cell).map_err(|source| E::NotANumber {
                at: line_at(line),
                column: name.to_string(),
                cell: cell.to_string(),
                source,
            })?;
            out.push((*time, v));
        }
        if out.len() < 2 {
            return Err(E::TooFewValues {
                path: self.path.clone(),
                column: name.to_string(),
            });
        }
        Ok(out)
    }
}
