//! The measured log: a CSV file with a header row, `#` comments allowed
//! (a provenance header), read with the `csv` crate.

use anyhow::{Context, Result, bail};
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
pub fn read(path: &Path, time_column: &str, time_scale: f64) -> Result<Table> {
    let mut reader = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .flexible(false)
        .from_path(path)
        .with_context(|| format!("cannot read the log {}", path.display()))?;
    let headers: Vec<String> = reader
        .headers()
        .with_context(|| format!("{}: no header row", path.display()))?
        .iter()
        .map(str::to_string)
        .collect();
    let Some(time_at) = headers.iter().position(|h| h == time_column) else {
        bail!(
            "{}: no column `{time_column}` for the time (columns: {})",
            path.display(),
            headers.join(", ")
        );
    };
    let mut rows = Vec::new();
    let mut last_time = f64::NEG_INFINITY;
    for record in reader.records() {
        let record = record.map_err(|e| in_words(path, &e))?;
        let line = record.position().map_or(0, csv::Position::line);
        let cell = record.get(time_at).unwrap_or("");
        let time = number(cell).map(|t| t * time_scale).with_context(|| {
            format!(
                "{}:{line}: column `{time_column}`: `{cell}` is not a time",
                path.display()
            )
        })?;
        if time <= last_time {
            bail!(
                "{}:{line}: column `{time_column}`: time goes backwards or stands still \
                 ({cell} after {})",
                path.display(),
                last_time / time_scale
            );
        }
        last_time = time;
        rows.push((line, time, record.iter().map(str::to_string).collect()));
    }
    if rows.len() < 2 {
        bail!("{}: fewer than two rows of data", path.display());
    }
    Ok(Table {
        path: path.to_path_buf(),
        headers,
        rows,
    })
}

/// A finite number; NaN and infinities are refused.
fn number(cell: &str) -> Result<f64> {
    let v: f64 = cell.parse().map_err(|_| anyhow::anyhow!("not a number"))?;
    if !v.is_finite() {
        bail!("not a finite number");
    }
    Ok(v)
}

fn in_words(path: &Path, e: &csv::Error) -> anyhow::Error {
    match e.kind() {
        csv::ErrorKind::UnequalLengths {
            pos,
            expected_len,
            len,
        } => anyhow::anyhow!(
            "{}:{}: {len} cells where the header has {expected_len}",
            path.display(),
            pos.as_ref().map_or(0, csv::Position::line)
        ),
        csv::ErrorKind::Utf8 { pos, .. } => anyhow::anyhow!(
            "{}:{}: not UTF-8 text: is this a CSV file?",
            path.display(),
            pos.as_ref().map_or(0, csv::Position::line)
        ),
        _ => anyhow::anyhow!("{}: {e}", path.display()),
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
    pub fn column(&self, name: &str, skip_empty: bool) -> Result<Vec<(f64, f64)>> {
        let Some(at) = self.headers.iter().position(|h| h == name) else {
            bail!(
                "{}: no column `{name}` (columns: {})",
                self.path.display(),
                self.headers.join(", ")
            );
        };
        let mut out = Vec::with_capacity(self.rows.len());
        for (line, time, cells) in &self.rows {
            let cell = cells.get(at).map_or("", String::as_str);
            if cell.is_empty() {
                if skip_empty {
                    continue;
                }
                bail!(
                    "{}:{line}: column `{name}` is empty; if the signal was not measured there, \
                     say `empty = \"skip\"` for it in the calibration file",
                    self.path.display()
                );
            }
            let v = number(cell).with_context(|| {
                format!("{}:{line}: column `{name}`: `{cell}`", self.path.display())
            })?;
            out.push((*time, v));
        }
        if out.len() < 2 {
            bail!(
                "{}: column `{name}` has fewer than two values",
                self.path.display()
            );
        }
        Ok(out)
    }
}
