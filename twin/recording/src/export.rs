//! A recording as CSV for spreadsheets, MATLAB and Python: one file per
//! channel, a `time_s` column (the log time, simulated seconds, exact to the
//! nanosecond) and one column per flattened field (`energy.battery_out`,
//! `loops.0.measured_rpm`). Numbers are written as recorded, booleans as 1
//! and 0, text quoted when it needs to be; a field a message lacks is empty.

use anyhow::{Context, Result};
use serde_json::Value;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use super::signals::leaves;
use super::{Channel, Recording};

/// One CSV file written.
#[derive(Debug, Clone, PartialEq)]
pub struct Written {
    pub topic: String,
    pub path: PathBuf,
    /// Data rows (the header not counted).
    pub rows: usize,
    /// Columns, `time_s` included.
    pub columns: usize,
}

/// The file name of a topic: `/plant/ev1/sensors` → `plant_ev1_sensors.csv`.
pub fn file_name(topic: &str) -> String {
    let stem: String = topic
        .trim_start_matches('/')
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    format!("{}.csv", if stem.is_empty() { "root" } else { &stem })
}

/// Write every channel of `recording` into `dir` (created if needed).
pub fn to_csv(recording: &Recording, dir: &Path) -> Result<Vec<Written>> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create folder {}", dir.display()))?;
    recording
        .channels
        .iter()
        .map(|c| {
            let path = dir.join(file_name(&c.topic));
            write_channel(c, &path).with_context(|| format!("cannot write {}", path.display()))
        })
        .collect()
}

fn write_channel(channel: &Channel, path: &Path) -> Result<Written> {
    // Columns: every field path in the order first seen.
    let mut columns: Vec<String> = Vec::new();
    let mut index = std::collections::HashMap::new();
    let mut buf = String::new();
    for m in &channel.messages {
        buf.clear();
        leaves(&m.value, &mut buf, &mut |p, _| {
            if !index.contains_key(p) {
                index.insert(p.to_string(), columns.len());
                columns.push(p.to_string());
            }
        });
    }
    let mut out = BufWriter::new(std::fs::File::create(path)?);
    write!(out, "time_s")?;
    for c in &columns {
        write!(
            out,
            ",{}",
            cell_text(if c.is_empty() { "value" } else { c })
        )?;
    }
    writeln!(out)?;
    let mut row: Vec<String> = vec![String::new(); columns.len()];
    for m in &channel.messages {
        row.iter_mut().for_each(String::clear);
        buf.clear();
        leaves(&m.value, &mut buf, &mut |p, leaf| {
            if let Some(&i) = index.get(p) {
                row[i] = cell(leaf);
            }
        });
        write!(
            out,
            "{}.{:09}",
            m.log_time_ns / 1_000_000_000,
            m.log_time_ns % 1_000_000_000
        )?;
        for c in &row {
            write!(out, ",{c}")?;
        }
        writeln!(out)?;
    }
    out.flush()?;
    Ok(Written {
        topic: channel.topic.clone(),
        path: path.to_path_buf(),
        rows: channel.messages.len(),
        columns: columns.len() + 1,
    })
}

fn cell(v: &Value) -> String {
    match v {
        Value::Null => String::new(),
        Value::Bool(b) => u8::from(*b).to_string(),
        Value::Number(n) => n.to_string(),
        Value::String(s) => cell_text(s),
        other => cell_text(&other.to_string()),
    }
}

/// Text quoted as RFC 4180 wants when it holds a comma, quote or line break.
fn cell_text(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_cells() {
        assert_eq!(file_name("/plant/ev1/sensors"), "plant_ev1_sensors.csv");
        assert_eq!(file_name("/bus/rs485/frames"), "bus_rs485_frames.csv");
        assert_eq!(cell(&serde_json::json!("a,\"b\"")), "\"a,\"\"b\"\"\"");
        assert_eq!(cell(&serde_json::json!(true)), "1");
        assert_eq!(cell(&serde_json::json!(null)), "");
    }
}
