//! MEB's frames (the MEB page, docs/protocols/meb.md): `@`, id, command,
//! address, count and data as upper-case hex text, the XOR FCS, `*\n`.

use super::shown_text as shown;

pub(super) fn check_send(body: &str) -> Result<(), String> {
    if body.starts_with('@') {
        Ok(())
    } else {
        Err(format!("send `{body}`: a frame starts with @"))
    }
}

pub(super) fn check_pattern(pattern: &str) -> Result<(), String> {
    if pattern.starts_with('@') {
        Ok(())
    } else {
        Err(format!("expect `{pattern}`: a reply starts with @"))
    }
}

/// `body`, its FCS (one too many when `spoil`), `ending`.
pub(super) fn request(body: &str, spoil: bool, ending: &str) -> Vec<u8> {
    let fcs = fcs(body.as_bytes()).wrapping_add(u8::from(spoil));
    format!("{body}{fcs:02X}{ending}").into_bytes()
}

/// The error reply (`ER`, the request's address, one word: the code).
pub(super) fn error_pattern(request: &[u8], id: u8, code: u8) -> String {
    let addr = request
        .get(5..7)
        .map_or_else(|| "##".into(), |a| String::from_utf8_lossy(a).into_owned());
    format!("@{id:02}ER{addr}01{code:04X}")
}

/// Where the first frame in `bytes` ends (after its `\n`), if one is whole.
pub(super) fn frame_end(bytes: &[u8]) -> Option<usize> {
    bytes.iter().position(|&b| b == b'\n').map(|i| i + 1)
}

/// Whether `frame` is a well-formed reply matching `pattern` (`#`: any
/// upper-case hex digit) and then `words` words of data.
pub(super) fn judge(frame: &[u8], pattern: &str, words: u16) -> Result<(), String> {
    let text = String::from_utf8_lossy(frame);
    let Some(start) = text.find('@') else {
        return Err(format!("`{}` is no frame (no @)", shown(frame)));
    };
    if start > 0 {
        return Err(format!(
            "{start} bytes before the reply's @ (`{}`)",
            shown(&frame[..start])
        ));
    }
    let Some(head) = text.strip_suffix("*\n") else {
        return Err(format!(
            "`{}` does not end in *\\n (the MEB page: replies end *\\n)",
            shown(frame)
        ));
    };
    if head.len() < 3 {
        return Err(format!("`{}` is too short for a frame", shown(frame)));
    }
    let (body, fcs_text) = head.split_at(head.len() - 2);
    let computed = fcs(body.as_bytes());
    match u8::from_str_radix(fcs_text, 16) {
        Ok(given) if given == computed && fcs_text == fcs_text.to_uppercase() => {}
        Ok(_) if fcs_text != fcs_text.to_uppercase() => {
            return Err(format!(
                "its FCS `{fcs_text}` is lower case (replies are upper case)"
            ));
        }
        _ => {
            return Err(format!(
                "its FCS is `{fcs_text}`; its bytes give {computed:02X}"
            ));
        }
    }
    let expected_len = pattern.len() + 4 * usize::from(words);
    let hex = |c: char| c.is_ascii_digit() || ('A'..='F').contains(&c);
    let fits = body.len() == expected_len
        && body
            .chars()
            .zip(pattern.chars())
            .all(|(c, p)| if p == '#' { hex(c) } else { c == p })
        && body.chars().skip(pattern.len()).all(hex);
    if fits {
        Ok(())
    } else {
        Err(format!("the reply was `{body}`"))
    }
}

/// The MEB check: XOR of every byte from `@` to the last before the FCS.
fn fcs(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0, |x, b| x ^ b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replies_are_judged_by_form_fcs_and_pattern() {
        assert_eq!(judge(b"@01EA000643*\n", "@01EA0006", 0), Ok(()));
        let read = b"@01EA00020BD608004F*\n";
        assert_eq!(judge(read, "@01EA0002", 2), Ok(()));
        assert_eq!(judge(read, "@##EA0002", 2), Ok(()));
        assert!(
            judge(read, "@01EA0002", 1)
                .unwrap_err()
                .contains("the reply was")
        );
        assert!(
            judge(b"@01EA000644*\n", "@01EA0006", 0)
                .unwrap_err()
                .contains("its bytes give 43")
        );
        assert!(
            judge(b"@01EA000643*\r\n", "@01EA0006", 0)
                .unwrap_err()
                .contains("does not end")
        );
        assert!(
            judge(b"xx@01EA000643*\n", "@01EA0006", 0)
                .unwrap_err()
                .contains("2 bytes before")
        );
    }

    #[test]
    fn an_error_pattern_carries_the_requests_address() {
        assert_eq!(error_pattern(b"@01EAF001", 1, 2), "@01ERF0010002");
    }
}
