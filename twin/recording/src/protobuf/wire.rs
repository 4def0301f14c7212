//! The busiest messages' fields appended straight to the batch, field by
//! field, in field-number order: the bytes prost writes for the same values
//! through the types made from the `.proto` files (tests hold each writer
//! to prost's bytes), without prost's per-field calls.
//!
//! Why: prost writes every tag and integer through `encode_varint`, which
//! the compiler keeps out of line (a loop unrolled ten times), and sizes
//! each nested message twice before writing it. In a pinned recorded ev-meb
//! run (`perf record`, 1000 simulated seconds) prost's encoding took 5.4 %
//! of the samples where the earlier hand-written writer took 1.4 %, and a
//! recorded run 1.09x the CPU time of the build before the `.proto` files
//! (`twin run ev-meb --duration 300` pinned, 15 pairs). Written here: 1.4 %
//! of the samples, and 0.93x prost's CPU time, 1.01-1.03x the build before
//! (`docs/measurements-recording.md`, "A run's messages written field by
//! field").

/// Wire types used here.
const VARINT: u32 = 0;
const I64: u32 = 1;
const LEN: u32 = 2;

/// A message's fields appended to a buffer, each with its tag.
#[derive(Debug)]
pub struct Fields<'a> {
    out: &'a mut Vec<u8>,
}

impl<'a> Fields<'a> {
    pub fn new(out: &'a mut Vec<u8>) -> Self {
        Self { out }
    }

    #[inline]
    fn tag(&mut self, number: u32, wire: u32) {
        self.varint(u64::from((number << 3) | wire));
    }

    #[inline]
    fn varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.out.push((v as u8) | 0x80);
            v >>= 7;
        }
        self.out.push(v as u8);
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
        self.varint(v);
    }

    /// A `sint64` (zigzag).
    #[inline]
    pub fn sint(&mut self, number: u32, v: i64) {
        self.uint(number, ((v << 1) ^ (v >> 63)) as u64);
    }

    /// A `string`.
    #[inline]
    pub fn str(&mut self, number: u32, v: &str) {
        self.tag(number, LEN);
        self.varint(v.len() as u64);
        self.out.extend_from_slice(v.as_bytes());
    }

    /// A `string` field holding `bytes` spelled in hex, two lowercase
    /// digits a byte, with no string made first.
    #[inline]
    pub fn hex(&mut self, number: u32, bytes: &[u8]) {
        self.tag(number, LEN);
        self.varint(2 * bytes.len() as u64);
        let start = self.out.len();
        self.out.resize(start + 2 * bytes.len(), 0);
        if let Some(digits) = self.out.get_mut(start..) {
            super::spell_hex(digits, bytes);
        }
    }

    /// A nested message, its fields written by `fields`. One byte is kept
    /// for its length (these messages are shorter than 128 bytes); a longer
    /// one moves behind its longer length.
    #[inline]
    pub fn nested(&mut self, number: u32, fields: impl FnOnce(&mut Fields<'_>)) {
        self.tag(number, LEN);
        let at = self.out.len();
        self.out.push(0);
        fields(&mut Fields { out: self.out });
        let len = self.out.len() - at - 1;
        if len < 0x80 {
            self.out[at] = len as u8;
        } else {
            let (mut length, mut n, mut v) = ([0u8; 10], 0, len as u64);
            while v >= 0x80 {
                length[n] = (v as u8) | 0x80;
                v >>= 7;
                n += 1;
            }
            length[n] = v as u8;
            self.out.splice(at..=at, length[..=n].iter().copied());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_nested_message_moves_behind_its_two_byte_length() {
        let mut bytes = Vec::new();
        let text = "x".repeat(200);
        Fields::new(&mut bytes).nested(7, |m| m.str(1, &text));
        // tag 7/LEN, length 203 as two bytes, then tag 1/LEN, 200 as two bytes.
        assert_eq!(&bytes[..5], &[0x3a, 0xcb, 0x01, 0x0a, 0xc8]);
        assert_eq!(bytes.len(), 3 + 3 + 200);
        let mut short = Vec::new();
        Fields::new(&mut short).nested(2, |m| m.uint(3, 300));
        assert_eq!(short, [0x12, 3, 0x18, 0xac, 0x02]);
    }

    #[test]
    fn field_numbers_past_fifteen_take_a_two_byte_tag() {
        let mut bytes = Vec::new();
        let mut out = Fields::new(&mut bytes);
        out.uint(20, 5);
        out.sint(1, -3);
        out.bool(16, true);
        out.uint(2, u64::MAX);
        assert_eq!(
            bytes,
            [
                0xa0, 0x01, 5, 0x08, 5, 0x80, 0x01, 1, 0x10, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
                0xff, 0xff, 0xff, 0x01
            ]
        );
    }
}
