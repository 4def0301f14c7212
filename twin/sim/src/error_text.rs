//! An error as a user reads it: its message, then each cause, the way
//! `main` prints an error (`error: {e:#}` through anyhow). A library that
//! says an error itself (a batch's summary, the recording's warnings, the
//! panel's page) prints it through [`in_full`]: `{e:#}` on a thiserror type
//! compiles and prints the message alone, its causes lost.

/// `e` with its causes, `outer: cause: …`.
pub fn in_full(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::in_full;

    #[derive(Debug, thiserror::Error)]
    #[error("cannot read map.toml")]
    struct Outer(#[source] std::io::Error);

    #[test]
    fn the_causes_follow_the_message() {
        let e = Outer(std::io::Error::other("permission denied"));
        assert_eq!(in_full(&e), "cannot read map.toml: permission denied");
    }
}
