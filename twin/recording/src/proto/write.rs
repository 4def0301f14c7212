//! Protobuf written by hand, field by field, for the messages a run records
//! hundreds of times a simulated second (plant samples, frames, readings,
//! loop reports). [`super::encode`] finds every field of a `Serialize` value
//! by name in the schema, which a profile of a pinned ev-meb run put at a
//! fifth of what recording cost; a type that knows its schema's field
//! numbers writes the same bytes without looking anything up. Each such
//! writer is checked against [`super::encode`] byte for byte in tests.

use super::{I64, LEN, VARINT, put_varint, varint_into};

/// Fills `digits` (two bytes per byte of `bytes`) with `bytes` in
/// lowercase hex.
pub(crate) fn spell_hex(digits: &mut [u8], bytes: &[u8]) {
    // The lengths always agree here (two digits a byte, made so by the
    // callers); a mismatch would leave the digits as they were.
    let _ = hex::encode_to_slice(bytes, digits);
}

/// `bytes` in lowercase hex, handed to `each` a run of up to 128 digits at
/// a time, spelled on the stack: no string is made for them.
pub(crate) fn hex_runs<E>(
    bytes: &[u8],
    mut each: impl FnMut(&str) -> Result<(), E>,
) -> Result<(), E> {
    let mut digits = [0u8; 128];
    for run in bytes.chunks(digits.len() / 2) {
        let spelled = &mut digits[..2 * run.len()];
        spell_hex(spelled, run);
        // Hex digits are ASCII: never an error.
        each(std::str::from_utf8(spelled).unwrap_or_default())?;
    }
    Ok(())
}

/// A message's fields appended to `out`, each with its tag, in the order
/// they are given (the order its `Serialize` gives them, so that the bytes
/// are those [`super::encode`] writes).
#[derive(Debug)]
pub struct ProtoOut<'a> {
    out: &'a mut Vec<u8>,
}

impl<'a> ProtoOut<'a> {
    pub fn new(out: &'a mut Vec<u8>) -> Self {
        Self { out }
    }

    #[inline]
    fn tag(&mut self, number: u32, wire: u8) {
        let key = (number << 3) | u32::from(wire);
        if key < 0x80 {
            self.out.push(key as u8);
        } else {
            put_varint(self.out, key.into());
        }
    }

    /// A `double`.
    #[inline]
    pub fn double(&mut self, number: u32, v: f64) {
        self.tag(number, I64);
        self.out.extend_from_slice(&v.to_le_bytes());
    }

    /// A `bool`.
    #[inline]
    pub fn bool(&mut self, number: u32, v: bool) {
        self.tag(number, VARINT);
        self.out.push(u8::from(v));
    }

    /// A `uint32` or `uint64`.
    #[inline]
    pub fn uint(&mut self, number: u32, v: u64) {
        self.tag(number, VARINT);
        if v < 0x80 {
            self.out.push(v as u8);
        } else {
            put_varint(self.out, v);
        }
    }

    /// A `sint32` or `sint64` (zigzag).
    #[inline]
    pub fn sint(&mut self, number: u32, v: i64) {
        self.uint(number, ((v << 1) ^ (v >> 63)) as u64);
    }

    /// A `string`.
    #[inline]
    pub fn str(&mut self, number: u32, v: &str) {
        self.bytes(number, v.as_bytes());
    }

    /// A `string` field holding `v` spelled in hex, two lowercase digits a
    /// byte, with no string made first.
    #[inline]
    pub fn hex(&mut self, number: u32, v: &[u8]) {
        self.tag(number, LEN);
        put_varint(self.out, 2 * v.len() as u64);
        let start = self.out.len();
        self.out.resize(start + 2 * v.len(), 0);
        if let Some(digits) = self.out.get_mut(start..) {
            spell_hex(digits, v);
        }
    }

    /// A `string` or `bytes` field from bytes.
    #[inline]
    pub fn bytes(&mut self, number: u32, v: &[u8]) {
        self.tag(number, LEN);
        put_varint(self.out, v.len() as u64);
        self.out.extend_from_slice(v);
    }

    /// A nested message, its fields written by `fields`. Its length goes in
    /// front once known: one byte is kept for it, as the twin's nested
    /// messages are shorter than 128 bytes, and the bytes move when not.
    #[inline]
    pub fn nested(&mut self, number: u32, fields: impl FnOnce(&mut ProtoOut<'_>)) {
        self.tag(number, LEN);
        let at = self.out.len();
        self.out.push(0);
        fields(&mut ProtoOut { out: self.out });
        let len = self.out.len() - at - 1;
        if len < 0x80 {
            self.out[at] = len as u8;
        } else {
            let mut buf = [0u8; 10];
            let n = varint_into(len as u64, &mut buf);
            self.out.splice(at..at + 1, buf[..n].iter().copied());
        }
    }
}

/// A message that writes its own protobuf bytes for the channels of the
/// schema named [`Protobuf::SCHEMA`].
pub trait Protobuf {
    /// The full name of the schema's message type (`twin.Frame`).
    const SCHEMA: &'static str;

    fn write_protobuf(&self, out: &mut ProtoOut<'_>);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_nested_message_moves_behind_its_two_byte_length() {
        let mut bytes = Vec::new();
        let text = "x".repeat(200);
        ProtoOut::new(&mut bytes).nested(7, |m| m.str(1, &text));
        // tag 7/LEN, length 203 as two bytes, then tag 1/LEN, 200 as two bytes.
        assert_eq!(&bytes[..5], &[0x3a, 0xcb, 0x01, 0x0a, 0xc8]);
        assert_eq!(bytes.len(), 3 + 3 + 200);
        let mut short = Vec::new();
        ProtoOut::new(&mut short).nested(2, |m| m.uint(3, 300));
        assert_eq!(short, [0x12, 3, 0x18, 0xac, 0x02]);
    }

    #[test]
    fn field_numbers_past_fifteen_take_a_two_byte_tag() {
        let mut bytes = Vec::new();
        let mut out = ProtoOut::new(&mut bytes);
        out.uint(20, 5);
        out.sint(1, -3);
        out.bool(16, true);
        assert_eq!(bytes, [0xa0, 0x01, 5, 0x08, 5, 0x80, 0x01, 1]);
    }
}
