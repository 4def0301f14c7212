//! A protobuf message back to the JSON value a JSON recording holds,
//! decoded by prost-reflect with the schema the file carries: every field by
//! its `.proto` name (not protobuf JSON's lowerCamelCase), 64-bit integers as
//! numbers (not strings), a nested message as an object, a repeated field as
//! a list, `bytes` as a list of numbers, a number that is not finite as
//! `null` (as JSON wrote it). A top-level field not on the wire is `null`,
//! as JSON wrote it; deeper ones (an empty list, a field of another
//! protocol's frame) are left out. prost-reflect's own serde output is
//! protobuf JSON, which differs in each of these, so the value is built here
//! from the decoded fields.

use prost_reflect::{DynamicMessage, MessageDescriptor, Value as Field};
use serde_json::{Map, Number, Value};

/// Message `bytes` of type `schema`, as JSON; what is wrong in words
/// otherwise.
pub fn to_value(schema: &MessageDescriptor, bytes: &[u8]) -> Result<Value, String> {
    let message = DynamicMessage::decode(schema.clone(), bytes).map_err(|e| {
        format!(
            "it does not read as a protobuf `{}` ({e})",
            schema.full_name()
        )
    })?;
    let mut out = object(&message);
    // A top-level value JSON wrote as `null` (the BMS's trip while it
    // conducts) is `null` again, so every sample has every field and a CSV
    // of them a column for it, empty or not.
    for f in schema.fields() {
        if !f.is_list() && !f.is_map() && f.kind().as_message().is_none() {
            out.entry(f.name()).or_insert(Value::Null);
        }
    }
    Ok(Value::Object(out))
}

/// The fields on the wire, by name.
fn object(message: &DynamicMessage) -> Map<String, Value> {
    message
        .fields()
        .map(|(f, v)| (f.name().to_string(), value(v)))
        .collect()
}

fn float(v: f64) -> Value {
    Number::from_f64(v).map_or(Value::Null, Value::Number)
}

fn value(v: &Field) -> Value {
    match v {
        Field::Bool(b) => Value::Bool(*b),
        Field::I32(n) => (*n).into(),
        Field::I64(n) => (*n).into(),
        Field::U32(n) => (*n).into(),
        Field::U64(n) => (*n).into(),
        Field::F32(x) => float((*x).into()),
        Field::F64(x) => float(*x),
        Field::String(s) => Value::String(s.clone()),
        Field::Bytes(b) => Value::Array(b.iter().map(|&x| Value::from(x)).collect()),
        Field::EnumNumber(n) => (*n).into(),
        Field::Message(m) => Value::Object(object(m)),
        Field::List(items) => Value::Array(items.iter().map(value).collect()),
        // A map is, on the wire, a list of key and value entries.
        Field::Map(entries) => Value::Array(
            entries
                .iter()
                .map(|(k, v)| {
                    let key = value(&Field::from(k.clone()));
                    serde_json::json!({ "key": key, "value": value(v) })
                })
                .collect(),
        ),
    }
}
