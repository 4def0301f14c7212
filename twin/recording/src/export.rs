//! A recording as CSV for spreadsheets, MATLAB and Python: one file per
//! channel, a `time_s` column (the log time, simulated seconds, exact to the
//! nanosecond; a message's own `time_s` field, the plant samples', is that
//! time and is not repeated) and one column per flattened field (`energy.battery_out`,
//! `loops.0.measured_rpm`). Numbers are written as recorded, booleans as 1
//! and 0, text quoted when it needs to be; a field a message lacks is empty.

use serde_json::Value;
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use super::Recording;
use super::read::{Encoding, ReadError, Reader};
use super::signals::leaves;

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

/// A channel left out: its messages are in an encoding the twin does not
/// read (another tool's channel beside the twin's, a schema that does not
/// parse). The other channels are written all the same.
#[derive(Debug, Clone, PartialEq)]
pub struct Skipped {
    pub topic: String,
    /// Why, in words.
    pub why: String,
}

/// What an export wrote, and what it left out.
#[derive(Debug, Clone, PartialEq)]
pub struct Exported {
    pub recording: Recording,
    pub written: Vec<Written>,
    pub skipped: Vec<Skipped>,
}

/// Whether the twin reads messages in `encoding` (asked per message: no
/// words built).
fn reads(encoding: &Encoding) -> bool {
    matches!(encoding, Encoding::Json | Encoding::Protobuf(_))
}

/// Why the messages of a channel in `encoding` cannot be read, if they
/// cannot: the reader's own words.
fn unreadable(topic: &str, encoding: &Encoding) -> Option<String> {
    let error = match encoding {
        Encoding::Json | Encoding::Protobuf(_) => return None,
        Encoding::BadSchema(why) => ReadError::BadSchema {
            topic: topic.to_string(),
            why: why.clone(),
        },
        Encoding::Other(name) => ReadError::OtherEncoding {
            topic: topic.to_string(),
            encoding: name.clone(),
        },
    };
    Some(error.to_string())
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

/// The leading column, the log time, and the name of a message's own field
/// that would clash with it (the plant samples carry their time).
const TIME: &str = "time_s";

/// A channel's columns: every field path in the order first seen.
#[derive(Debug, Default)]
struct Columns {
    names: Vec<String>,
    index: HashMap<String, usize>,
    /// A message's own `time_s` differs from its log time somewhere.
    own_time_differs: bool,
}

impl Columns {
    /// A message's own `time_s` is left out where it is the log time to
    /// the nanosecond (one `time_s` column, as a spreadsheet wants), and
    /// named apart where it is not.
    fn settle_own_time(&mut self) {
        let Some(i) = self.index.remove(TIME) else {
            return;
        };
        if self.own_time_differs {
            self.names[i] = format!("{TIME} (in the message)");
            // The second pass finds the field by its path in the message.
            self.index.insert(TIME.to_string(), i);
        } else {
            self.names.remove(i);
            for v in self.index.values_mut() {
                if *v > i {
                    *v -= 1;
                }
            }
        }
    }
}

/// A channel's file being written.
struct Sheet {
    out: BufWriter<File>,
    path: PathBuf,
    /// Rows to write: the messages the first pass counted.
    rows_left: u64,
    row: Vec<String>,
}

/// Why a recording was not exported.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error(transparent)]
    Read(#[from] ReadError),
    /// The recording holds no message (`why` says so, with where a file cut
    /// short stops: [`Recording::holds_no_messages`]).
    #[error("{why}: no CSV file was written")]
    NoMessages { why: String },
    /// No channel is in an encoding the twin reads: `why`, for the first,
    /// and how many others there are.
    #[error("{why}: no CSV file was written")]
    NothingReadable { why: String },
    #[error("cannot create folder {}", path.display())]
    CreateFolder {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot write {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Write every channel of the recording at `path` into `dir` (created if
/// needed), but those whose messages the twin does not read (said in
/// [`Exported::skipped`]). Two passes, streamed: the columns of every
/// channel, then the rows.
pub fn to_csv(path: &Path, dir: &Path) -> Result<Exported, ExportError> {
    let cannot_write = |path: &Path| {
        let path = path.to_path_buf();
        move |source| ExportError::Write { path, source }
    };
    let mut columns: Vec<Columns> = Vec::new();
    let mut buf = String::new();
    let recording = Recording::scan(path, |m| {
        if !reads(m.encoding) {
            return Ok(());
        }
        let value: Value = m.json()?;
        if columns.len() <= m.channel {
            columns.resize_with(m.channel + 1, Columns::default);
        }
        let c = &mut columns[m.channel];
        buf.clear();
        let log_time_ns = m.log_time_ns;
        leaves(&value, &mut buf, &mut |p, leaf| {
            if p == TIME {
                let same = leaf
                    .as_f64()
                    .is_some_and(|t| (t * 1e9).round() == log_time_ns as f64);
                c.own_time_differs |= !same;
            }
            if !c.index.contains_key(p) {
                c.index.insert(p.to_string(), c.names.len());
                c.names.push(p.to_string());
            }
        });
        Ok(())
    })?;
    columns.iter_mut().for_each(Columns::settle_own_time);
    if recording.message_count() == 0 {
        return Err(ExportError::NoMessages {
            why: recording.holds_no_messages(),
        });
    }
    columns.resize_with(recording.channels.len(), Columns::default);
    let skipped: Vec<Skipped> = recording
        .channels
        .iter()
        .filter_map(|c| {
            let why = unreadable(&c.topic, &c.encoding)?;
            Some(Skipped {
                topic: c.topic.clone(),
                why,
            })
        })
        .collect();
    if let Some(first) = skipped.first()
        && skipped.len() == recording.channels.len()
    {
        let why = match skipped.len() - 1 {
            0 => first.why.clone(),
            1 => format!("{}, nor does it read the other channel", first.why),
            n => format!("{}, nor does it read the other {n} channels", first.why),
        };
        return Err(ExportError::NothingReadable { why });
    }
    std::fs::create_dir_all(dir).map_err(|source| ExportError::CreateFolder {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut sheets = Vec::with_capacity(recording.channels.len());
    for (channel, c) in recording.channels.iter().zip(&columns) {
        if !reads(&channel.encoding) {
            sheets.push(None);
            continue;
        }
        let file = dir.join(file_name(&channel.topic));
        let sheet = header(&file, c, channel.message_count).map_err(cannot_write(&file))?;
        sheets.push(Some(sheet));
    }
    // The second pass stops where the first did, should the file have
    // grown since (a session still recording).
    let mut reader = Reader::open(path)?;
    while let Some(item) = reader.next()? {
        let Some(m) = item.message()? else {
            continue;
        };
        let (Some(Some(sheet)), Some(c)) = (sheets.get_mut(m.channel), columns.get(m.channel))
        else {
            continue;
        };
        if sheet.rows_left == 0 {
            continue;
        }
        sheet.rows_left -= 1;
        let value: Value = m.json()?;
        sheet.row.iter_mut().for_each(String::clear);
        buf.clear();
        leaves(&value, &mut buf, &mut |p, leaf| {
            if let Some(&i) = c.index.get(p) {
                sheet.row[i] = cell(leaf);
            }
        });
        row(sheet, m.log_time_ns).map_err(cannot_write(&sheet.path))?;
    }
    let mut written = Vec::with_capacity(sheets.len());
    for ((channel, c), sheet) in recording.channels.iter().zip(&columns).zip(sheets) {
        let Some(mut sheet) = sheet else {
            continue;
        };
        sheet.out.flush().map_err(cannot_write(&sheet.path))?;
        written.push(Written {
            topic: channel.topic.clone(),
            path: sheet.path,
            rows: usize::try_from(channel.message_count).unwrap_or(usize::MAX),
            columns: c.names.len() + 1,
        });
    }
    Ok(Exported {
        recording,
        written,
        skipped,
    })
}

/// Create a channel's file and write its header line.
fn header(path: &Path, columns: &Columns, rows: u64) -> std::io::Result<Sheet> {
    let mut out = BufWriter::new(File::create(path)?);
    write!(out, "{TIME}")?;
    for c in &columns.names {
        write!(
            out,
            ",{}",
            cell_text(if c.is_empty() { "value" } else { c })
        )?;
    }
    writeln!(out)?;
    Ok(Sheet {
        out,
        path: path.to_path_buf(),
        rows_left: rows,
        row: vec![String::new(); columns.names.len()],
    })
}

/// Write the sheet's row at `log_time_ns`.
fn row(sheet: &mut Sheet, log_time_ns: u64) -> std::io::Result<()> {
    write!(
        sheet.out,
        "{}.{:09}",
        log_time_ns / 1_000_000_000,
        log_time_ns % 1_000_000_000
    )?;
    for c in &sheet.row {
        write!(sheet.out, ",{c}")?;
    }
    writeln!(sheet.out)?;
    Ok(())
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
