//! A [`Schema`] as the `google.protobuf.FileDescriptorSet` an MCAP schema
//! record holds (schema encoding `protobuf`), written and read back. Only the
//! parts of `descriptor.proto` a message's layout needs: file name, package,
//! syntax, message types (nested ones inside their parent), fields (name,
//! number, label, type, type name), and the fields' comments as
//! `SourceCodeInfo` (what `protoc` keeps of a `.proto` file's comments).

use super::{Field, Kind, LEN, MessageType, Schema, WireValue, close_len, next_field, put_bytes};
use super::{put_tag, put_varint};

// Field numbers of descriptor.proto.
const SET_FILE: u32 = 1;
const FILE_NAME: u32 = 1;
const FILE_PACKAGE: u32 = 2;
const FILE_MESSAGE: u32 = 4;
const FILE_SYNTAX: u32 = 12;
const FILE_SOURCE_CODE_INFO: u32 = 9;
const INFO_LOCATION: u32 = 1;
const LOCATION_PATH: u32 = 1;
const LOCATION_SPAN: u32 = 2;
const LOCATION_LEADING_COMMENTS: u32 = 3;
const MESSAGE_NAME: u32 = 1;
const MESSAGE_FIELD: u32 = 2;
const MESSAGE_NESTED: u32 = 3;
const FIELD_NAME: u32 = 1;
const FIELD_NUMBER: u32 = 3;
const FIELD_LABEL: u32 = 4;
const FIELD_TYPE: u32 = 5;
const FIELD_TYPE_NAME: u32 = 6;
const LABEL_OPTIONAL: u64 = 1;
const LABEL_REPEATED: u64 = 3;

/// `FieldDescriptorProto.Type` of a kind.
fn type_number(kind: Kind) -> u64 {
    match kind {
        Kind::Double => 1,
        Kind::Float => 2,
        Kind::Int => 3,
        Kind::Uint => 4,
        Kind::Uint32 => 13,
        Kind::Fixed64 => 6,
        Kind::Fixed32 => 7,
        Kind::Bool => 8,
        Kind::String => 9,
        Kind::Message(_) => 11,
        Kind::Bytes => 12,
        Kind::Sfixed32 => 15,
        Kind::Sfixed64 => 16,
        Kind::Sint => 18,
    }
}

/// The kind of a `FieldDescriptorProto.Type` (a message's index comes later).
fn kind_of(type_number: u64) -> Option<Kind> {
    Some(match type_number {
        1 => Kind::Double,
        2 => Kind::Float,
        3 | 5 | 14 => Kind::Int,
        4 => Kind::Uint,
        13 => Kind::Uint32,
        6 => Kind::Fixed64,
        7 => Kind::Fixed32,
        8 => Kind::Bool,
        9 => Kind::String,
        11 => Kind::Message(usize::MAX),
        12 => Kind::Bytes,
        15 => Kind::Sfixed32,
        16 => Kind::Sfixed64,
        17 | 18 => Kind::Sint,
        _ => return None,
    })
}

/// The short name of a full one: `twin.Frame.Decoded` → `Decoded`.
fn short(name: &str) -> &str {
    name.rsplit('.').next().unwrap_or(name)
}

/// The parent of a full name: `twin.Frame.Decoded` → `twin.Frame`.
fn parent(name: &str) -> &str {
    name.rsplit_once('.').map_or("", |(p, _)| p)
}

/// `schema` as a serialised `FileDescriptorSet` of one proto2 file.
pub fn descriptor_set(schema: &Schema) -> Vec<u8> {
    let root = schema.name();
    let package = parent(root);
    let mut file = Vec::new();
    put_bytes(
        &mut file,
        FILE_NAME,
        format!("{}.proto", root.replace('.', "/")).as_bytes(),
    );
    put_bytes(&mut file, FILE_PACKAGE, package.as_bytes());
    if !schema.messages.is_empty() {
        put_tag(&mut file, FILE_MESSAGE, LEN);
        let start = file.len();
        message(schema, 0, &mut file);
        close_len(&mut file, start);
    }
    let info = source_code_info(schema);
    if !info.is_empty() {
        put_bytes(&mut file, FILE_SOURCE_CODE_INFO, &info);
    }
    put_bytes(&mut file, FILE_SYNTAX, b"proto2");
    let mut set = Vec::new();
    put_bytes(&mut set, SET_FILE, &file);
    set
}

/// The path of message `index` in the file's descriptor: `[4, 0]` for the
/// root, then `3, k` for the k-th type nested in its parent.
fn message_path(schema: &Schema, index: usize) -> Vec<u64> {
    let Some(m) = schema.messages.get(index).filter(|_| index > 0) else {
        return vec![u64::from(FILE_MESSAGE), 0];
    };
    let up = parent(&m.name);
    let Some(p) = schema.messages.iter().position(|o| o.name == up) else {
        return vec![u64::from(FILE_MESSAGE), 0];
    };
    let k = schema.messages[..index]
        .iter()
        .filter(|o| parent(&o.name) == up)
        .count();
    let mut path = message_path(schema, p);
    path.extend([u64::from(MESSAGE_NESTED), k as u64]);
    path
}

/// `SourceCodeInfo` with one location per commented field (empty: none).
fn source_code_info(schema: &Schema) -> Vec<u8> {
    let mut info = Vec::new();
    for (i, m) in schema.messages.iter().enumerate() {
        for (j, f) in m.fields.iter().enumerate() {
            if f.comment.is_empty() {
                continue;
            }
            let mut path = message_path(schema, i);
            path.extend([u64::from(MESSAGE_FIELD), j as u64]);
            let mut location = Vec::new();
            let mut packed = Vec::new();
            for p in path {
                put_varint(&mut packed, p);
            }
            put_bytes(&mut location, LOCATION_PATH, &packed);
            // No .proto file behind it: an empty span (line 0, columns 0 to 0).
            put_bytes(&mut location, LOCATION_SPAN, &[0, 0, 0]);
            put_bytes(
                &mut location,
                LOCATION_LEADING_COMMENTS,
                format!(" {}\n", f.comment).as_bytes(),
            );
            put_bytes(&mut info, INFO_LOCATION, &location);
        }
    }
    info
}

/// `DescriptorProto` of message `index`, its nested types inside it.
fn message(schema: &Schema, index: usize, out: &mut Vec<u8>) {
    let m = &schema.messages[index];
    put_bytes(out, MESSAGE_NAME, short(&m.name).as_bytes());
    for f in &m.fields {
        put_tag(out, MESSAGE_FIELD, LEN);
        let start = out.len();
        put_bytes(out, FIELD_NAME, f.name.as_bytes());
        put_tag(out, FIELD_NUMBER, super::VARINT);
        put_varint(out, u64::from(f.number));
        put_tag(out, FIELD_LABEL, super::VARINT);
        put_varint(
            out,
            if f.repeated {
                LABEL_REPEATED
            } else {
                LABEL_OPTIONAL
            },
        );
        put_tag(out, FIELD_TYPE, super::VARINT);
        put_varint(out, type_number(f.kind));
        if let Kind::Message(i) = f.kind
            && let Some(nested) = schema.messages.get(i)
        {
            put_bytes(out, FIELD_TYPE_NAME, format!(".{}", nested.name).as_bytes());
        }
        close_len(out, start);
    }
    for (i, nested) in schema.messages.iter().enumerate() {
        if parent(&nested.name) == m.name {
            put_tag(out, MESSAGE_NESTED, LEN);
            let start = out.len();
            message(schema, i, out);
            close_len(out, start);
        }
    }
}

/// A message type as read, before its fields' message types are resolved.
struct Read {
    name: String,
    /// Fields, a message field's type by name.
    fields: Vec<(Field, String)>,
}

/// The schema of message type `root` (a full name, `twin.Frame`) in the
/// serialised `FileDescriptorSet` `bytes`; what is wrong in words otherwise.
pub fn parse(bytes: &[u8], root: &str) -> Result<Schema, String> {
    let bad = || "its protobuf schema does not read as a FileDescriptorSet".to_string();
    let mut read = Vec::new();
    let mut set = bytes;
    while !set.is_empty() {
        let (number, value) = next_field(&mut set).ok_or_else(bad)?;
        if let (SET_FILE, WireValue::Len(mut file)) = (number, value) {
            let mut package = String::new();
            let mut messages = Vec::new();
            while !file.is_empty() {
                match next_field(&mut file).ok_or_else(bad)? {
                    (FILE_PACKAGE, WireValue::Len(p)) => {
                        package = String::from_utf8_lossy(p).into_owned();
                    }
                    (FILE_MESSAGE, WireValue::Len(m)) => messages.push(m),
                    _ => {}
                }
            }
            for m in messages {
                read_message(m, &package, &mut read).ok_or_else(bad)?;
            }
        }
    }
    // The root first, then every type it reaches.
    let mut order: Vec<usize> = Vec::new();
    let start = read
        .iter()
        .position(|m| m.name == root)
        .ok_or_else(|| format!("its protobuf schema has no message type `{root}`"))?;
    order.push(start);
    let mut next = 0;
    while next < order.len() {
        for (_, type_name) in &read[order[next]].fields {
            if type_name.is_empty() {
                continue;
            }
            let name = type_name.trim_start_matches('.');
            let i = read
                .iter()
                .position(|m| m.name == name)
                .ok_or_else(|| format!("its protobuf schema uses `{name}` without declaring it"))?;
            if !order.contains(&i) {
                order.push(i);
            }
        }
        next += 1;
    }
    let messages = order
        .iter()
        .map(|&i| MessageType {
            name: read[i].name.clone(),
            fields: read[i]
                .fields
                .iter()
                .map(|(f, type_name)| {
                    let mut f = f.clone();
                    if let Kind::Message(_) = f.kind {
                        let name = type_name.trim_start_matches('.');
                        let at = order.iter().position(|&j| read[j].name == name);
                        f.kind = Kind::Message(at.unwrap_or(usize::MAX));
                    }
                    f
                })
                .collect(),
        })
        .collect();
    Ok(Schema { messages })
}

/// Read a `DescriptorProto` (and its nested types) under `scope`.
fn read_message(mut bytes: &[u8], scope: &str, out: &mut Vec<Read>) -> Option<()> {
    let mut name = String::new();
    let mut fields = Vec::new();
    let mut nested = Vec::new();
    while !bytes.is_empty() {
        match next_field(&mut bytes)? {
            (MESSAGE_NAME, WireValue::Len(n)) => name = String::from_utf8_lossy(n).into_owned(),
            (MESSAGE_FIELD, WireValue::Len(f)) => fields.push(f),
            (MESSAGE_NESTED, WireValue::Len(m)) => nested.push(m),
            _ => {}
        }
    }
    let full = if scope.is_empty() {
        name
    } else {
        format!("{scope}.{name}")
    };
    let mut read = Read {
        name: full.clone(),
        fields: Vec::new(),
    };
    for mut f in fields {
        let mut field = Field {
            name: String::new(),
            number: 0,
            kind: Kind::Bytes,
            repeated: false,
            comment: String::new(),
            key: super::KeySeen::default(),
        };
        let mut type_name = String::new();
        let mut known = true;
        while !f.is_empty() {
            match next_field(&mut f)? {
                (FIELD_NAME, WireValue::Len(n)) => {
                    field.name = String::from_utf8_lossy(n).into_owned();
                }
                (FIELD_NUMBER, WireValue::Varint(n)) => field.number = u32::try_from(n).ok()?,
                (FIELD_LABEL, WireValue::Varint(l)) => field.repeated = l == LABEL_REPEATED,
                (FIELD_TYPE, WireValue::Varint(t)) => match kind_of(t) {
                    Some(kind) => field.kind = kind,
                    // Groups: not read.
                    None => known = false,
                },
                (FIELD_TYPE_NAME, WireValue::Len(n)) => {
                    type_name = String::from_utf8_lossy(n).into_owned();
                }
                _ => {}
            }
        }
        if !matches!(field.kind, Kind::Message(_)) {
            type_name.clear();
        }
        if known {
            read.fields.push((field, type_name));
        }
    }
    out.push(read);
    for m in nested {
        read_message(m, &full, out)?;
    }
    Some(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::proto::schema;

    #[test]
    fn a_schema_reads_back_from_its_descriptor_set() {
        let s = schema(
            "twin",
            &[
                (
                    "Frame",
                    &[
                        ("from", Kind::String, false),
                        ("decoded", Kind::Message(1), false),
                    ],
                ),
                (
                    "Decoded",
                    &[("data", Kind::Uint, true), ("error", Kind::String, false)],
                ),
            ],
        );
        let bytes = descriptor_set(&s);
        assert_eq!(parse(&bytes, "twin.Frame"), Ok(s));
        assert!(
            parse(&bytes, "twin.Other")
                .unwrap_err()
                .contains("twin.Other")
        );
        assert!(parse(&bytes[..bytes.len() - 3], "twin.Frame").is_err());
    }
}
