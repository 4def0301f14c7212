//! A protobuf message back to the JSON value a JSON recording holds: every
//! field by its name, a nested message as an object, a repeated field as a
//! list, a number that is not finite as `null` (as JSON wrote it). A
//! top-level field not on the wire is `null`, as JSON wrote it; deeper ones
//! (an empty list, a field of another protocol's frame) are left out.

use serde_json::{Map, Number, Value};

use super::{Kind, Schema, WireValue, next_field, take_varint};

/// Message `bytes` of `schema`'s first type, as JSON; what is wrong in words
/// otherwise.
pub fn to_value(schema: &Schema, bytes: &[u8]) -> Result<Value, String> {
    let mut value = message(schema, 0, bytes, 0)?;
    // A top-level value JSON wrote as `null` (the BMS's trip while it
    // conducts) is `null` again, so every sample has every field and a CSV
    // of them a column for it, empty or not.
    if let (Value::Object(out), Some(m)) = (&mut value, schema.messages.first()) {
        for f in &m.fields {
            if !f.repeated && !matches!(f.kind, Kind::Message(_)) && !out.contains_key(&f.name) {
                out.insert(f.name.clone(), Value::Null);
            }
        }
    }
    Ok(value)
}

/// Nesting deeper than this is a damaged message, not the twin's.
const MAX_DEPTH: usize = 32;

fn message(schema: &Schema, index: usize, mut bytes: &[u8], depth: usize) -> Result<Value, String> {
    let m = schema
        .messages
        .get(index)
        .ok_or("its schema names a message type it does not declare")?;
    if depth > MAX_DEPTH {
        return Err("it nests messages deeper than any the twin writes".into());
    }
    let mut out = Map::new();
    while !bytes.is_empty() {
        let (number, wire) =
            next_field(&mut bytes).ok_or("it does not read as a protobuf message")?;
        // A field the schema does not know: skipped, as protobuf readers do.
        let Some(f) = m.by_number(number) else {
            continue;
        };
        let bad = || format!("field `{}` does not read as its type", f.name);
        let mut values = Vec::new();
        match (wire, f.kind) {
            // A packed list of numbers.
            (WireValue::Len(mut packed), kind) if f.repeated && is_packable(kind) => {
                while !packed.is_empty() {
                    values.push(packed_item(kind, &mut packed).ok_or_else(bad)?);
                }
            }
            (wire, kind) => values.push(scalar(schema, kind, wire, depth).ok_or_else(bad)??),
        }
        if f.repeated {
            let items = out
                .entry(f.name.clone())
                .or_insert_with(|| Value::Array(Vec::new()));
            if let Value::Array(items) = items {
                items.extend(values);
            }
        } else if let Some(v) = values.pop() {
            out.insert(f.name.clone(), v);
        }
    }
    Ok(Value::Object(out))
}

fn is_packable(kind: Kind) -> bool {
    !matches!(kind, Kind::String | Kind::Bytes | Kind::Message(_))
}

fn float(v: f64) -> Value {
    Number::from_f64(v).map_or(Value::Null, Value::Number)
}

fn sint(v: u64) -> i64 {
    ((v >> 1) as i64) ^ -((v & 1) as i64)
}

/// One value; `None` when the wire type is not the field's, an error from a
/// nested message.
fn scalar(
    schema: &Schema,
    kind: Kind,
    wire: WireValue<'_>,
    depth: usize,
) -> Option<Result<Value, String>> {
    let v = match (kind, wire) {
        (Kind::Double, WireValue::I64(b)) => float(f64::from_le_bytes(b)),
        (Kind::Float, WireValue::I32(b)) => float(f32::from_le_bytes(b).into()),
        (Kind::Fixed64, WireValue::I64(b)) => u64::from_le_bytes(b).into(),
        (Kind::Sfixed64, WireValue::I64(b)) => i64::from_le_bytes(b).into(),
        (Kind::Fixed32, WireValue::I32(b)) => u32::from_le_bytes(b).into(),
        (Kind::Sfixed32, WireValue::I32(b)) => i32::from_le_bytes(b).into(),
        (Kind::Bool, WireValue::Varint(v)) => (v != 0).into(),
        (Kind::Int, WireValue::Varint(v)) => (v as i64).into(),
        (Kind::Uint | Kind::Uint32, WireValue::Varint(v)) => v.into(),
        (Kind::Sint, WireValue::Varint(v)) => sint(v).into(),
        (Kind::String, WireValue::Len(b)) => Value::String(std::str::from_utf8(b).ok()?.into()),
        (Kind::Bytes, WireValue::Len(b)) => {
            Value::Array(b.iter().map(|&x| Value::from(x)).collect())
        }
        (Kind::Message(i), WireValue::Len(b)) => return Some(message(schema, i, b, depth + 1)),
        _ => return None,
    };
    Some(Ok(v))
}

/// One item of a packed list.
fn packed_item(kind: Kind, bytes: &mut &[u8]) -> Option<Value> {
    let wire = match kind {
        Kind::Double | Kind::Fixed64 | Kind::Sfixed64 => {
            WireValue::I64(super::take(bytes, 8)?.try_into().ok()?)
        }
        Kind::Float | Kind::Fixed32 | Kind::Sfixed32 => {
            WireValue::I32(super::take(bytes, 4)?.try_into().ok()?)
        }
        _ => WireValue::Varint(take_varint(bytes)?),
    };
    // Numbers only: no nested message in a packed list.
    scalar(
        &Schema {
            messages: Vec::new(),
        },
        kind,
        wire,
        0,
    )?
    .ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::proto::{encode, schema};
    use serde::Serialize;
    use serde_json::json;

    #[derive(Serialize)]
    struct Inner {
        count: i64,
        at: f64,
    }

    #[derive(Serialize)]
    struct Outer<'a> {
        name: &'a str,
        volts: f64,
        on: bool,
        trip: Option<&'a str>,
        words: Vec<u16>,
        inner: Inner,
        big: u64,
    }

    fn outer_schema() -> Schema {
        schema(
            "test",
            &[
                (
                    "Outer",
                    &[
                        ("name", Kind::String, false),
                        ("volts", Kind::Double, false),
                        ("on", Kind::Bool, false),
                        ("trip", Kind::String, false),
                        ("words", Kind::Uint, true),
                        ("inner", Kind::Message(1), false),
                        ("big", Kind::Uint, false),
                    ],
                ),
                (
                    "Inner",
                    &[("count", Kind::Sint, false), ("at", Kind::Double, false)],
                ),
            ],
        )
    }

    #[test]
    fn a_struct_reads_back_as_the_json_it_would_have_been() {
        let s = outer_schema();
        let value = Outer {
            name: "ev1 \"front\"",
            volts: 12.345678901234567,
            on: true,
            trip: None,
            words: vec![0, 512, 65535],
            inner: Inner {
                count: -3,
                at: f64::NAN,
            },
            big: u64::MAX,
        };
        let mut bytes = vec![0xAA];
        encode(&s, &value, &mut bytes).unwrap();
        let back = to_value(&s, &bytes[1..]).unwrap();
        let json = serde_json::to_value(&value).unwrap();
        // The absent optional field is `null` again, as JSON wrote it.
        assert_eq!(back["trip"], Value::Null);
        assert_eq!(back, json);
        assert_eq!(back["inner"], json!({ "count": -3, "at": null }));
        // A field the schema lacks is refused, in words.
        let other = schema("test", &[("Outer", &[("name", Kind::String, false)])]);
        let e = encode(&other, &value, &mut Vec::new()).unwrap_err();
        assert!(e.to_string().contains("no field `volts`"), "{e}");
    }

    #[test]
    fn damaged_bytes_are_an_error_not_a_panic() {
        let s = outer_schema();
        let mut bytes = Vec::new();
        encode(
            &s,
            &Outer {
                name: "x",
                volts: 1.0,
                on: false,
                trip: Some("OverCurrent"),
                words: vec![1],
                inner: Inner { count: 1, at: 0.5 },
                big: 7,
            },
            &mut bytes,
        )
        .unwrap();
        for cut in 0..bytes.len() {
            let _ = to_value(&s, &bytes[..cut]);
        }
        for i in 0..bytes.len() {
            let mut b = bytes.clone();
            b[i] ^= 0xff;
            let _ = to_value(&s, &b);
        }
        assert!(to_value(&s, &[0x0a, 0x09, b'x']).is_err());
    }
}
