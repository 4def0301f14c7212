//! TOML files read into serde structs, with errors in a user's words at the
//! line of the key at fault. Shared by parameter files and scenarios.
//!
//! Two things stand between serde and a user. Its messages name Rust types
//! ("invalid type: string \"x\", expected f64"); a user wrote TOML, so they
//! become "expected a number, found the string \"x\"". And an internally
//! tagged enum (a scenario's `[[node]]`, chosen by its `kind`) reads its
//! table into a buffer before it knows the variant, so an error inside it
//! carries only the table's span: the header line, not the line with the
//! typo. [`deserialize`] then finds the key itself, by asking which key's
//! absence changes the error.

use serde::de::DeserializeOwned;
use std::ops::Range;
use toml::Spanned;
use toml::de::{DeTable, DeValue, ValueDeserializer};

/// Why a TOML value does not deserialise: the message in words, the dotted
/// path of the field at fault (empty at the top) and where it lies.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TomlError {
    pub message: String,
    pub path: String,
    pub span: Option<Range<usize>>,
}

/// Parses a TOML document into one spanned value, its spans offsets into `text`.
pub fn parse(text: &str) -> Result<Spanned<DeValue<'_>>, TomlError> {
    let doc = DeTable::parse(text).map_err(|e| TomlError {
        message: e.message().trim().to_string(),
        path: String::new(),
        span: e.span(),
    })?;
    let span = doc.span();
    Ok(Spanned::new(span, DeValue::Table(doc.into_inner())))
}

/// `T` from `value`: on error, the message in words and the span of the key
/// at fault, in the document `value` was parsed from.
pub fn deserialize<T: DeserializeOwned>(value: &Spanned<DeValue<'_>>) -> Result<T, TomlError> {
    let (path, error) = match attempt::<T>(value) {
        Ok(t) => return Ok(t),
        Err(e) => e,
    };
    let message = error.message().trim().to_string();
    // The deepest value the path reaches, and the keys that reach it.
    let (reached, keys, whole) = walk(value, &path);
    // toml's own span is that of the value it was reading, and for a table
    // of an array of tables, the array's first header: the value the path
    // reaches is better when the path is followed to its end.
    let mut span = if whole {
        Some(reached.span())
    } else {
        error.span()
    };
    let mut keys = keys;
    if let Some(field) = backticked(&message, "unknown field `") {
        // The path may end at the unknown key's value or at its table.
        span = if keys.last().is_some_and(|k| k == field) {
            span_of(value, &keys.join("."))
        } else {
            key_span(reached, field)
        }
        .or(span);
    } else if !message.starts_with("missing field")
        && matches!(reached.get_ref(), DeValue::Table(_))
        && let Some(key) = blame::<T>(value, &keys, &(path.to_string(), message.clone()))
    {
        span = key_span(reached, &key).or(span);
        keys.push(key);
    }
    Err(TomlError {
        message: in_words(&message),
        path: keys.join("."),
        span,
    })
}

/// The span of the key at a dotted path (`wheel.mass_kg`, `node[2].kp`).
pub fn span_of(value: &Spanned<DeValue<'_>>, dotted: &str) -> Option<Range<usize>> {
    let (parents, last) = match dotted.rsplit_once('.') {
        Some((parents, last)) => (parents.split('.').collect::<Vec<_>>(), last),
        None => (Vec::new(), dotted),
    };
    let mut here = value;
    for key in parents {
        here = step(here, key)?;
    }
    let (name, index) = split_step(last);
    match index {
        None => key_span(here, name),
        Some(_) => step(here, last).map(Spanned::span),
    }
}

/// 1-based line and column of a byte offset.
pub fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let col = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, col)
}

type Attempt = (serde_path_to_error::Path, toml::de::Error);

fn attempt<T: DeserializeOwned>(value: &Spanned<DeValue<'_>>) -> Result<T, Attempt> {
    serde_path_to_error::deserialize(ValueDeserializer::from(value.clone())).map_err(|e| {
        let path = e.path().clone();
        (path, e.into_inner())
    })
}

/// Follows `path` down `value` as far as it goes: the value reached and the
/// names of the steps taken (`node[2]` for the third `[[node]]`).
fn walk<'v, 'i>(
    value: &'v Spanned<DeValue<'i>>,
    path: &serde_path_to_error::Path,
) -> (&'v Spanned<DeValue<'i>>, Vec<String>, bool) {
    use serde_path_to_error::Segment;
    let mut here = value;
    let mut keys: Vec<String> = Vec::new();
    for segment in path.iter() {
        let next = match (segment, here.get_ref()) {
            (Segment::Map { key }, DeValue::Table(t)) => t
                .iter()
                .find(|(k, _)| k.get_ref() == key)
                .map(|(_, v)| (v, key.clone())),
            (Segment::Seq { index }, DeValue::Array(a)) => a.get(*index).map(|v| {
                let last = keys.pop().unwrap_or_default();
                (v, format!("{last}[{}]", index + 1))
            }),
            _ => None,
        };
        let Some((v, key)) = next else {
            return (here, keys, false);
        };
        here = v;
        keys.push(key);
    }
    (here, keys, true)
}

/// The key, in the table at `keys`, that serde stumbled on: of the keys
/// whose value is what the message says was found (the string "x", the
/// integer 300, an array of 1 item), the one whose removal changes the
/// error. Only the error path pays, with a deserialisation per candidate.
fn blame<T: DeserializeOwned>(
    value: &Spanned<DeValue<'_>>,
    keys: &[String],
    error: &(String, String),
) -> Option<String> {
    let table = table_at(value, keys)?;
    let mut names: Vec<(usize, String)> = table
        .iter()
        .filter(|(_, v)| is_what_was_found(v.get_ref(), &error.1))
        .map(|(k, _)| (k.span().start, k.get_ref().to_string()))
        .collect();
    names.sort();
    if let [(_, only)] = names.as_slice() {
        return Some(only.clone());
    }
    names.into_iter().map(|(_, name)| name).find(|name| {
        let mut without = value.clone();
        if let Some(DeValue::Table(t)) = table_at_mut(&mut without, keys).map(Spanned::get_mut) {
            t.remove(name.as_str());
        }
        match attempt::<T>(&without) {
            Ok(_) => true,
            Err((path, e)) => (path.to_string(), e.message().trim().to_string()) != *error,
        }
    })
}

/// Whether `value` is, or holds, what serde's `message` says it found;
/// `true` when the message says nothing of it.
///
/// Why "holds": an item of a list (`set_points = [0.45, 1000.0]`, where
/// pairs are expected) is found inside the key's value, and a key beside
/// it with the very same value (`kp = 0.45`) must not take the blame alone.
fn is_what_was_found(value: &DeValue<'_>, message: &str) -> bool {
    let inside = match value {
        DeValue::Array(a) => a.iter().any(|v| is_what_was_found(v.get_ref(), message)),
        DeValue::Table(t) => t.values().any(|v| is_what_was_found(v.get_ref(), message)),
        _ => false,
    };
    inside || is_what_was_found_here(value, message)
}

fn is_what_was_found_here(value: &DeValue<'_>, message: &str) -> bool {
    if let Some(variant) = backticked(message, "unknown variant `") {
        return matches!(value, DeValue::String(s) if s == variant);
    }
    if let Some(rest) = message.strip_prefix("invalid length ") {
        let len = rest.split(',').next().unwrap_or_default();
        return matches!(value, DeValue::Array(a) if a.len().to_string() == len);
    }
    let Some(found) = ["invalid type: ", "invalid value: "]
        .iter()
        .find_map(|p| message.strip_prefix(p))
        .and_then(|rest| rest.rsplit_once(", expected "))
        .map(|(found, _)| found)
    else {
        return true;
    };
    let inner = |prefix: &str| {
        found
            .strip_prefix(prefix)
            .map(|v| v.trim_matches('`').to_string())
    };
    match value {
        DeValue::String(s) => found == format!("string {:?}", s.as_ref()),
        DeValue::Integer(i) => inner("integer ").is_some_and(|n| {
            i128::from_str_radix(i.as_str(), i.radix()).is_ok_and(|v| v.to_string() == n)
        }),
        DeValue::Float(f) => inner("floating point ")
            .is_some_and(|n| n.parse::<f64>().ok() == f.as_str().parse::<f64>().ok()),
        DeValue::Boolean(b) => inner("boolean ").is_some_and(|n| n == b.to_string()),
        DeValue::Array(_) => found == "sequence",
        DeValue::Table(_) => found == "map",
        DeValue::Datetime(_) => true,
    }
}

fn table_at<'v, 'i>(value: &'v Spanned<DeValue<'i>>, keys: &[String]) -> Option<&'v DeTable<'i>> {
    let mut here = value;
    for key in keys {
        here = step(here, key)?;
    }
    match here.get_ref() {
        DeValue::Table(t) => Some(t),
        _ => None,
    }
}

fn table_at_mut<'v, 'i>(
    value: &'v mut Spanned<DeValue<'i>>,
    keys: &[String],
) -> Option<&'v mut Spanned<DeValue<'i>>> {
    let mut here = value;
    for key in keys {
        here = step_mut(here, key)?;
    }
    Some(here)
}

/// One step of a path written by [`walk`]: `name` or `name[n]` (1-based).
fn split_step(key: &str) -> (&str, Option<usize>) {
    match key.strip_suffix(']').and_then(|k| k.rsplit_once('[')) {
        Some((name, n)) => (name, n.parse::<usize>().ok().and_then(|n| n.checked_sub(1))),
        None => (key, None),
    }
}

fn step<'v, 'i>(here: &'v Spanned<DeValue<'i>>, key: &str) -> Option<&'v Spanned<DeValue<'i>>> {
    let (name, index) = split_step(key);
    let DeValue::Table(t) = here.get_ref() else {
        return None;
    };
    let v = t.get(name)?;
    match (index, v.get_ref()) {
        (None, _) => Some(v),
        (Some(i), DeValue::Array(a)) => a.get(i),
        _ => None,
    }
}

fn step_mut<'v, 'i>(
    here: &'v mut Spanned<DeValue<'i>>,
    key: &str,
) -> Option<&'v mut Spanned<DeValue<'i>>> {
    let (name, index) = split_step(key);
    let DeValue::Table(t) = here.get_mut() else {
        return None;
    };
    let v = t.get_mut(name)?;
    let Some(i) = index else {
        return Some(v);
    };
    match v.get_mut() {
        DeValue::Array(a) => a.get_mut(i),
        _ => None,
    }
}

fn key_span(table: &Spanned<DeValue<'_>>, key: &str) -> Option<Range<usize>> {
    let DeValue::Table(t) = table.get_ref() else {
        return None;
    };
    t.iter()
        .find(|(k, _)| k.get_ref() == key)
        .map(|(k, _)| k.span())
}

/// The name between `prefix` and the next backtick.
fn backticked<'m>(message: &'m str, prefix: &str) -> Option<&'m str> {
    message.strip_prefix(prefix)?.split('`').next()
}

/// serde's message with TOML words for Rust types: "invalid type: string
/// \"x\", expected f64" becomes "expected a number, found the string \"x\"".
pub fn in_words(message: &str) -> String {
    for (prefix, found_is_value) in [("invalid type: ", false), ("invalid value: ", true)] {
        if let Some(rest) = message.strip_prefix(prefix)
            && let Some((found, expected)) = rest.rsplit_once(", expected ")
        {
            let found = found_in_words(found);
            let expected = expected_in_words(expected);
            return if found_is_value {
                format!("expected {expected}, got {found}")
            } else {
                format!("expected {expected}, found {found}")
            };
        }
    }
    if let Some(rest) = message.strip_prefix("invalid length ")
        && let Some((len, expected)) = rest.split_once(", expected ")
    {
        let items = if len == "1" { "item" } else { "items" };
        return format!(
            "expected {}, found {len} {items}",
            expected_in_words(expected)
        );
    }
    message.to_string()
}

/// What serde found, as TOML calls it.
fn found_in_words(found: &str) -> String {
    let quoted = |prefix: &str| {
        found
            .strip_prefix(prefix)
            .and_then(|v| v.strip_prefix('`'))
            .and_then(|v| v.strip_suffix('`'))
            .map(str::to_string)
    };
    if let Some(s) = found.strip_prefix("string ") {
        return format!("the string {s}");
    }
    if let Some(v) = quoted("integer ").or_else(|| quoted("floating point ")) {
        return v;
    }
    if let Some(v) = quoted("boolean ") {
        return v;
    }
    match found {
        "sequence" => "an array".into(),
        "map" => "a table".into(),
        other => other.to_string(),
    }
}

/// What serde expected, as TOML calls it.
fn expected_in_words(expected: &str) -> String {
    let integer = |max: u64| format!("an integer from 0 to {max}");
    match expected {
        "f64" | "f32" => "a number".into(),
        "u8" => integer(u64::from(u8::MAX)),
        "u16" => integer(u64::from(u16::MAX)),
        "u32" | "u64" | "usize" => "an integer of 0 or more".into(),
        "i8" | "i16" | "i32" | "i64" | "isize" => "an integer".into(),
        "a boolean" => "true or false".into(),
        "a sequence" => "an array".into(),
        "a string" | "a borrowed string" | "string or map" => "a string".into(),
        "a map" => "a table".into(),
        other if other.starts_with("struct ") || other.starts_with("internally tagged enum ") => {
            "a table".into()
        }
        other if other.starts_with("an array of length ") => other.to_string(),
        other if other.starts_with("enum ") => "one of the names it takes".into(),
        other => other.to_string(),
    }
}
