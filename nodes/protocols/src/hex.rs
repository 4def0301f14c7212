//! Bytes written as hex in the lab's own files: a check suite's steps and a
//! scenario's scripted requests (`send = "01 06 0001 0080"`). Two digits a
//! byte, spaces between any whole bytes; in a reply's pattern `..` stands
//! for a byte of any value. Read once, when the file is loaded, so these
//! allocate.

/// Why a text is not hex bytes, in the words of the file that holds it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HexError {
    #[error("`{word}` has an odd number of hex digits (a byte is two)")]
    OddDigits { word: String },
    #[error("`{pair}` in `{word}` is not a hex byte")]
    NotHex { pair: String, word: String },
    #[error("no bytes given")]
    Empty,
    #[error("`{text}`: `..` (any byte) is for replies only")]
    AnyByte { text: String },
}

/// The bytes `text` spells; `..` is refused.
pub fn bytes(text: &str) -> Result<Vec<u8>, HexError> {
    pattern(text)?
        .into_iter()
        .map(|b| {
            b.ok_or_else(|| HexError::AnyByte {
                text: text.to_string(),
            })
        })
        .collect()
}

/// A reply's pattern: hex bytes as [`bytes`], `None` for `..` (any byte).
pub fn pattern(text: &str) -> Result<Vec<Option<u8>>, HexError> {
    let mut out = Vec::new();
    for word in text.split_whitespace() {
        if word.len() % 2 != 0 {
            return Err(HexError::OddDigits {
                word: word.to_string(),
            });
        }
        for pair in word.as_bytes().chunks(2) {
            let pair = String::from_utf8_lossy(pair);
            if pair == ".." {
                out.push(None);
                continue;
            }
            let byte = u8::from_str_radix(&pair, 16)
                .ok()
                .filter(|_| pair.chars().all(|c| c.is_ascii_hexdigit()))
                .ok_or_else(|| HexError::NotHex {
                    pair: pair.to_string(),
                    word: word.to_string(),
                })?;
            out.push(Some(byte));
        }
    }
    if out.is_empty() {
        return Err(HexError::Empty);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spaces_fall_between_whole_bytes_and_dots_are_any_byte() {
        assert_eq!(bytes("01 03 0000 000A"), Ok(vec![1, 3, 0, 0, 0, 0x0A]));
        assert_eq!(pattern("01 .. 0c"), Ok(vec![Some(1), None, Some(0x0C)]));
        assert!(
            bytes("01 3")
                .unwrap_err()
                .to_string()
                .contains("odd number")
        );
        assert!(bytes("01 0G").unwrap_err().to_string().contains("`0G`"));
        assert!(bytes("01 +1").unwrap_err().to_string().contains("`+1`"));
        assert!(
            bytes("01 ..")
                .unwrap_err()
                .to_string()
                .contains("replies only")
        );
        assert_eq!(bytes("  "), Err(HexError::Empty));
        // Multi-byte characters: no panic, an error naming them.
        assert!(bytes("0é").is_err());
    }
}
