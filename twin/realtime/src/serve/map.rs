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

use anyhow::{Result, anyhow};
use nodes::firmware::MebMap;
use std::collections::BTreeMap;
use std::path::Path;
use toml::{Spanned, Value};

fn line_of(text: &str, offset: usize) -> usize {
    text.get(..offset)
        .map_or(1, |t| t.matches('\n').count() + 1)
}

/// Reads a map file; every mistake names the file and line.
pub fn load(path: &Path) -> Result<MebMap> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| anyhow!("cannot read I/O map {}: {e}", path.display()))?;
    parse(&text, path)
}

/// Parses a map from `text` (read from `path`, for the messages).
pub fn parse(text: &str, path: &Path) -> Result<MebMap> {
    let shown = path.display();
    let tables: BTreeMap<String, BTreeMap<String, Spanned<Value>>> =
        toml::from_str(text).map_err(|e| {
            let line = e.span().map_or(1, |s| line_of(text, s.start));
            anyhow!(
                "{shown}:{line}: {} (the map is one table per block, e.g. [EA] with V1 = 0)",
                plant::toml_errors::in_words(e.message().trim())
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
                return Err(anyhow!(
                    "{shown}:{line}: `{tag}` needs an address (a number) or \"WORD.BIT\""
                ));
            };
            let bit = bit.flatten();
            map.place(&block, tag, address, bit)
                .map_err(|e| anyhow!("{shown}:{line}: [{block}] {e}"))?;
        }
    }
    Ok(map)
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
}
