//! `--map FILE`: the I/O map of the MEB links, in TOML, as the M3CVME tool
//! lets one set it (Fig. 8: type, address, tag). A table per block replaces
//! that block's default placement; blocks not named keep theirs.
//!
//! ```toml
//! [EA]            # analog inputs: signal = address
//! V1 = 0
//! V2 = 1
//! I = 2
//! [SD]            # digital outputs: signal = "WORD.BIT"
//! EN = "0.0"
//! BRK = "0.1"
//! ```

use nodes::firmware::MebMap;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use toml::{Spanned, Value};

fn line_of(text: &str, offset: usize) -> usize {
    text.get(..offset)
        .map_or(1, |t| t.matches('\n').count() + 1)
}

/// Why a map file (`--map`) gives no map.
#[derive(Debug, thiserror::Error)]
pub enum MapFileError {
    #[error("cannot read I/O map {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A mistake in its text, at the file's line (the text's error is
    /// said in these words, not kept as a cause).
    #[error("{}:{line}: {message}", path.display())]
    Text {
        path: PathBuf,
        line: usize,
        message: String,
    },
}

/// Reads a map file; every mistake names the file and line.
pub fn load(path: &Path) -> Result<MebMap, MapFileError> {
    let text = std::fs::read_to_string(path).map_err(|source| MapFileError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse(&text, path)
}

/// Parses a map from `text` (read from `path`, for the messages).
pub fn parse(text: &str, path: &Path) -> Result<MebMap, MapFileError> {
    parse_text(text).map_err(|e| MapFileError::Text {
        path: path.to_path_buf(),
        line: e.line,
        message: e.message,
    })
}

/// A mistake in a map's text: its line and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("line {line}: {message}")]
pub struct MapTextError {
    pub line: usize,
    pub message: String,
}

/// Parses a map's text, with the checks `--map` makes (the panel's map box
/// is checked by this too).
pub fn parse_text(text: &str) -> Result<MebMap, MapTextError> {
    let at = |line: usize, message: String| MapTextError { line, message };
    let tables: BTreeMap<String, BTreeMap<String, Spanned<Value>>> =
        toml::from_str(text).map_err(|e| {
            let line = e.span().map_or(1, |s| line_of(text, s.start));
            at(
                line,
                format!(
                    "{} (the map is one table per block, e.g. [EA] with V1 = 0)",
                    plant::toml_errors::in_words(e.message().trim())
                ),
            )
        })?;
    let mut map = MebMap::default();
    for (block, entries) in &tables {
        let block = block.to_ascii_uppercase();
        map.clear_block(&block);
        for (tag, value) in entries {
            let line = line_of(text, value.span().start);
            let (address, bit) = match value.get_ref() {
                Value::Integer(a) => (u16::try_from(*a).ok(), None),
                Value::String(s) => match s.split_once('.') {
                    Some((w, b)) => (w.trim().parse().ok(), b.trim().parse().ok().map(Some)),
                    None => (s.trim().parse().ok(), None),
                },
                _ => (None, None),
            };
            let (Some(address), bit) = (address, bit) else {
                return Err(at(
                    line,
                    format!("`{tag}` needs an address (a number) or \"WORD.BIT\""),
                ));
            };
            let bit = bit.flatten();
            map.place(&block, tag, address, bit)
                .map_err(|e| at(line, format!("[{block}] {e}")))?;
        }
    }
    Ok(map)
}

/// The map as the text of a map file: every block, every signal, so what
/// it shows is the whole map (and reads back as the same map).
pub fn to_text(map: &MebMap) -> String {
    let mut text = String::new();
    let mut block = "";
    for (name, tag, address, bit) in map.placements() {
        if name != block {
            if !text.is_empty() {
                text.push('\n');
            }
            text.push_str(&format!("[{name}]\n"));
            block = name;
        }
        match bit {
            Some(b) => text.push_str(&format!("{tag} = \"{address}.{b}\"\n")),
            None => text.push_str(&format!("{tag} = {address}\n")),
        }
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_map_file_places_signals_and_mistakes_name_their_line() {
        let path = Path::new("map.toml");
        let map = parse("[EA]\nV1 = 0\nV2 = 1\n[SD]\nEN = \"0.3\"\n", path).unwrap();
        assert!(!map.is_default());
        assert!(parse("", path).unwrap().is_default());
        let e = parse("[EA]\nV1 = 0\nV2 = 0\n", path)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("map.toml:3: [EA]"), "{e}");
        let e = parse("[EA]\nV1 = 0\n\nWHEEL = 4\n", path)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("map.toml:4:") && e.contains("unknown signal"),
            "{e}"
        );
        let e = parse("[SD]\nEN = \"zero\"\n", path)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("map.toml:2:"), "{e}");
        let e = parse("V1 = 0\n", path).unwrap_err().to_string();
        assert!(
            e.starts_with("map.toml:1:") && e.contains("one table per block"),
            "{e}"
        );
        assert!(e.contains("expected a table, found 0"), "{e}");
        assert!(!e.contains("a map"), "{e}");
    }

    #[test]
    fn a_map_shown_as_text_reads_back_as_itself() {
        let path = Path::new("map.toml");
        let default = MebMap::default();
        let text = to_text(&default);
        assert!(text.starts_with("[EA]\nV2 = 0\nI = 1\n"), "{text}");
        assert!(text.contains("[SD]\nEN = \"0.0\"\n"), "{text}");
        assert_eq!(parse(&text, path).unwrap(), default);
        assert!(parse(&text, path).unwrap().is_default());
        let moved = parse("[EA]\nV1 = 0\nV2 = 1\n[SD]\nEN = \"0.3\"\n", path).unwrap();
        assert_eq!(parse(&to_text(&moved), path).unwrap(), moved);
        let e = parse_text("[EA]\nV1 = 0\nV2 = 0\n").unwrap_err();
        assert_eq!(e.line, 3);
        assert!(e.to_string().starts_with("line 3: [EA]"), "{e}");
    }
}
