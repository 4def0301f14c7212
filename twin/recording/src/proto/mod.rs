//! Protobuf, as the twin's busiest channels are recorded: a plant sample or
//! a frame written straight to its wire bytes ([`encode`]), its schema a
//! `FileDescriptorSet` in the MCAP schema record (schema encoding
//! `protobuf`), which Foxglove, Lichtblick and the MCAP tools decode by field
//! name. The readers turn a message back into the JSON value the older JSON
//! recordings hold ([`decode`]), so every reader reads both.
//!
//! Only what the twin needs is here: proto2 messages of doubles, booleans,
//! strings, integers and nested messages, singular or repeated (not packed,
//! proto2's default); the reader also takes the other scalar types and
//! packed lists, which other tools write.

pub(crate) mod decode;
pub(crate) mod descriptor;
pub(crate) mod encode;
pub mod write;

pub use decode::to_value;
pub use encode::{EncodeError, encode};
pub use write::{ProtoOut, Protobuf};

/// What a field holds, on the wire and as JSON.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Double,
    Float,
    Bool,
    String,
    Bytes,
    /// `int32`, `int64` and enums: two's complement varints.
    Int,
    /// `uint64`.
    Uint,
    /// `uint32` (small counters and codes: tools show them as plain numbers).
    Uint32,
    /// `sint32`, `sint64`: zigzag varints.
    Sint,
    Fixed32,
    Fixed64,
    Sfixed32,
    Sfixed64,
    /// A nested message: its index in [`Schema::messages`].
    Message(usize),
}

/// One field of a message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Field {
    pub name: String,
    pub number: u32,
    pub kind: Kind,
    pub repeated: bool,
    /// What the field means, with its unit: written as the field's comment
    /// in the descriptor (empty: none; not read back).
    pub comment: String,
    /// Where the name of the struct field last found to be this one lives
    /// (a `&'static str` of a serde derive): the encoder's lookup compares
    /// an address instead of the text.
    pub key: KeySeen,
}

/// The address of a `&'static str` field name that matched a [`Field`]:
/// static text never moves or changes, so the same address and length is
/// the same name. Shared by the threads that encode with one schema.
#[derive(Debug, Default)]
pub struct KeySeen(std::sync::atomic::AtomicUsize);

impl KeySeen {
    pub(crate) fn is(&self, key: &'static str) -> bool {
        self.0.load(std::sync::atomic::Ordering::Relaxed) == key.as_ptr() as usize
    }

    pub(crate) fn set(&self, key: &'static str) {
        self.0
            .store(key.as_ptr() as usize, std::sync::atomic::Ordering::Relaxed);
    }
}

impl Clone for KeySeen {
    fn clone(&self) -> Self {
        Self::default()
    }
}

/// A cache, not part of what the field is.
impl PartialEq for KeySeen {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl Eq for KeySeen {}

/// One message type: its full name (`twin.PlantSensors.Shaft`) and fields.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MessageType {
    pub name: String,
    pub fields: Vec<Field>,
}

impl MessageType {
    /// The field numbered `number`.
    pub fn by_number(&self, number: u32) -> Option<&Field> {
        self.fields.iter().find(|f| f.number == number)
    }
}

/// A message type and every type it nests: `messages[0]` is the channel's.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Schema {
    pub messages: Vec<MessageType>,
}

impl Schema {
    /// The channel's message type name, as the MCAP schema record names it.
    pub fn name(&self) -> &str {
        self.messages.first().map_or("", |m| m.name.as_str())
    }
}

/// A field as a hand-written schema gives it: name, kind, repeated.
pub(crate) type FieldSpec<'a> = (&'a str, Kind, bool);

/// A schema written by hand, in the order of [`Schema::messages`]: each
/// message's short name and fields (`name`, kind, repeated); a nested
/// message's kind names it by its index.
pub(crate) fn schema(package: &str, messages: &[(&str, &[FieldSpec<'_>])]) -> Schema {
    let root = messages.first().map_or("", |m| m.0);
    Schema {
        messages: messages
            .iter()
            .enumerate()
            .map(|(i, (name, fields))| MessageType {
                name: if i == 0 {
                    format!("{package}.{name}")
                } else {
                    format!("{package}.{root}.{name}")
                },
                fields: fields
                    .iter()
                    .enumerate()
                    .map(|(n, (name, kind, repeated))| Field {
                        name: (*name).to_string(),
                        number: n as u32 + 1,
                        kind: *kind,
                        repeated: *repeated,
                        comment: String::new(),
                        key: KeySeen::default(),
                    })
                    .collect(),
            })
            .collect(),
    }
}

/// `schema` with `comments` (message index, field name, what it means) on
/// its fields.
pub(crate) fn with_comments(mut schema: Schema, comments: &[(usize, &str, &str)]) -> Schema {
    for (message, name, comment) in comments {
        let field = schema
            .messages
            .get_mut(*message)
            .and_then(|m| m.fields.iter_mut().find(|f| f.name == *name));
        if let Some(field) = field {
            field.comment = (*comment).to_string();
        }
    }
    schema
}

/// Wire types.
pub(crate) const VARINT: u8 = 0;
pub(crate) const I64: u8 = 1;
pub(crate) const LEN: u8 = 2;
pub(crate) const I32: u8 = 5;

/// `v` as a varint into `buf`; how many bytes it took.
pub(crate) fn varint_into(mut v: u64, buf: &mut [u8; 10]) -> usize {
    let mut n = 0;
    loop {
        let byte = (v & 0x7f) as u8;
        v >>= 7;
        if v == 0 {
            buf[n] = byte;
            return n + 1;
        }
        buf[n] = byte | 0x80;
        n += 1;
    }
}

/// Byte by byte: a copy of a length only known at run time is a call to
/// `memmove`, which for one or two bytes cost more than the varint (a
/// recording's engine thread spent half its `memmove` time here).
#[inline]
pub(crate) fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push(v as u8 | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

pub(crate) fn put_tag(out: &mut Vec<u8>, number: u32, wire: u8) {
    put_varint(out, (u64::from(number) << 3) | u64::from(wire));
}

/// Put the length of what was written since `start` in front of it.
pub(crate) fn close_len(out: &mut Vec<u8>, start: usize) {
    let len = out.len() - start;
    let mut buf = [0u8; 10];
    let n = varint_into(len as u64, &mut buf);
    out.extend_from_slice(&buf[..n]);
    out.copy_within(start..start + len, start + n);
    out[start..start + n].copy_from_slice(&buf[..n]);
}

/// A length-delimited field: tag, length, bytes.
pub(crate) fn put_bytes(out: &mut Vec<u8>, number: u32, bytes: &[u8]) {
    put_tag(out, number, LEN);
    put_varint(out, bytes.len() as u64);
    out.extend_from_slice(bytes);
}

/// Read a varint from the front of `bytes`.
pub(crate) fn take_varint(bytes: &mut &[u8]) -> Option<u64> {
    let mut v = 0u64;
    for shift in (0..70).step_by(7) {
        let (&b, rest) = bytes.split_first()?;
        *bytes = rest;
        if shift == 63 && b > 1 {
            return None;
        }
        v |= u64::from(b & 0x7f) << shift;
        if b & 0x80 == 0 {
            return Some(v);
        }
    }
    None
}

/// Take `n` bytes from the front of `bytes`.
pub(crate) fn take<'a>(bytes: &mut &'a [u8], n: usize) -> Option<&'a [u8]> {
    if bytes.len() < n {
        return None;
    }
    let (head, rest) = bytes.split_at(n);
    *bytes = rest;
    Some(head)
}

/// One field as read off the wire.
pub(crate) enum WireValue<'a> {
    Varint(u64),
    I64([u8; 8]),
    Len(&'a [u8]),
    I32([u8; 4]),
}

/// The next field of a message: its number and value; `None` when the
/// bytes do not read as protobuf.
pub(crate) fn next_field<'a>(bytes: &mut &'a [u8]) -> Option<(u32, WireValue<'a>)> {
    let key = take_varint(bytes)?;
    let number = u32::try_from(key >> 3).ok().filter(|n| *n > 0)?;
    let value = match (key & 7) as u8 {
        VARINT => WireValue::Varint(take_varint(bytes)?),
        I64 => WireValue::I64(take(bytes, 8)?.try_into().ok()?),
        LEN => {
            let n = usize::try_from(take_varint(bytes)?).ok()?;
            WireValue::Len(take(bytes, n)?)
        }
        I32 => WireValue::I32(take(bytes, 4)?.try_into().ok()?),
        _ => return None,
    };
    Some((number, value))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn varints_and_lengths_read_back() {
        for v in [0u64, 1, 127, 128, 300, u64::from(u32::MAX), u64::MAX] {
            let mut out = Vec::new();
            put_varint(&mut out, v);
            let mut bytes = out.as_slice();
            assert_eq!(take_varint(&mut bytes), Some(v));
            assert!(bytes.is_empty());
        }
        // A length put in front of 200 bytes takes two.
        let mut out = vec![9u8];
        out.extend(std::iter::repeat_n(7u8, 200));
        close_len(&mut out, 1);
        assert_eq!(&out[..3], &[9, 0xc8, 0x01]);
        assert_eq!(out.len(), 203);
        assert!(out[3..].iter().all(|b| *b == 7));
        // Cut short or overlong: not protobuf.
        assert_eq!(take_varint(&mut &[0x80u8][..]), None);
        assert_eq!(next_field(&mut &[0x0au8, 5, 1][..]).map(|f| f.0), None);
    }
}
