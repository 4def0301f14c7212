//! A value's protobuf bytes, straight from its `Serialize`: each field of a
//! struct found by name in the schema (the next one first, as the fields come
//! in the same order every time) and written with its tag. No `Value` and no
//! allocation: a nested message is written in place and its length put in
//! front of it after. A map with text keys (a `serde_json::Value` object, as
//! a master's loop report is) is a message too, its keys the field names.

use serde::Serialize;
use serde::ser::{self, Impossible};

use super::{Field, I64, Kind, LEN, Schema, VARINT, close_len, put_tag, put_varint};

/// A value that does not fit its channel's schema (a field it does not have,
/// or of another type): a mistake of the twin's, told as such.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EncodeError(String);

impl std::fmt::Display for EncodeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the message does not fit its channel's schema: {}",
            self.0
        )
    }
}

impl std::error::Error for EncodeError {}

impl ser::Error for EncodeError {
    fn custom<T: std::fmt::Display>(msg: T) -> Self {
        EncodeError(msg.to_string())
    }
}

fn misfit(what: &str, field: &Field) -> EncodeError {
    EncodeError(format!("{what} for field `{}`", field.name))
}

/// Append `value`, a message of `schema`'s first type, to `out`. On an error
/// `out` may hold part of it: the caller cuts it back.
pub fn encode<T: Serialize + ?Sized>(
    schema: &Schema,
    value: &T,
    out: &mut Vec<u8>,
) -> Result<(), EncodeError> {
    value.serialize(Root { schema, out })
}

/// The top level: a struct, the channel's message.
struct Root<'a> {
    schema: &'a Schema,
    out: &'a mut Vec<u8>,
}

/// A message's fields being written.
struct Fields<'a> {
    schema: &'a Schema,
    message: usize,
    out: &'a mut Vec<u8>,
    /// The field after the last one written: most likely the next.
    next: usize,
    /// Where the message's bytes start, when its length goes in front.
    start: Option<usize>,
    /// A map's field whose key came and whose value has not yet.
    pending: Option<&'a Field>,
}

impl<'a> Fields<'a> {
    fn field(&mut self, name: &str) -> Result<&'a Field, EncodeError> {
        let schema: &'a Schema = self.schema;
        let m = &schema.messages[self.message];
        // Fields come in the schema's order, some left out (a frame has
        // only its protocol's): the rest of the message first, then all of it.
        let later = m.fields.get(self.next..).unwrap_or_default();
        let index = match later.iter().position(|f| f.name == name) {
            Some(i) => self.next + i,
            None => m
                .fields
                .iter()
                .position(|f| f.name == name)
                .ok_or_else(|| EncodeError(format!("no field `{name}` in `{}`", m.name)))?,
        };
        self.next = index + 1;
        Ok(&m.fields[index])
    }

    /// [`Fields::field`] for a struct's field, whose name is static: the
    /// next field is checked by the name's address first.
    fn static_field(&mut self, name: &'static str) -> Result<&'a Field, EncodeError> {
        let schema: &'a Schema = self.schema;
        let m = &schema.messages[self.message];
        if let Some(f) = m.fields.get(self.next)
            && f.key.is(name)
            && f.name.len() == name.len()
        {
            self.next += 1;
            return Ok(f);
        }
        let f = self.field(name)?;
        f.key.set(name);
        Ok(f)
    }

    fn end(self) {
        if let Some(start) = self.start {
            close_len(self.out, start);
        }
    }
}

impl ser::SerializeStruct for Fields<'_> {
    type Ok = ();
    type Error = EncodeError;

    fn serialize_field<T: Serialize + ?Sized>(
        &mut self,
        key: &'static str,
        value: &T,
    ) -> Result<(), EncodeError> {
        let field = self.static_field(key)?;
        value.serialize(Value {
            schema: self.schema,
            field,
            out: &mut *self.out,
            in_list: false,
        })
    }

    fn end(self) -> Result<(), EncodeError> {
        Fields::end(self);
        Ok(())
    }
}

impl<'a> ser::SerializeMap for Fields<'a> {
    type Ok = ();
    type Error = EncodeError;

    fn serialize_key<T: Serialize + ?Sized>(&mut self, key: &T) -> Result<(), EncodeError> {
        let field = key.serialize(Key { fields: self })?;
        self.pending = Some(field);
        Ok(())
    }

    fn serialize_value<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), EncodeError> {
        let field = self
            .pending
            .take()
            .ok_or_else(|| EncodeError("a map's value without its key".into()))?;
        value.serialize(Value {
            schema: self.schema,
            field,
            out: &mut *self.out,
            in_list: false,
        })
    }

    fn end(self) -> Result<(), EncodeError> {
        Fields::end(self);
        Ok(())
    }
}

/// A map's key: the name of the field it stands for.
struct Key<'f, 'a> {
    fields: &'f mut Fields<'a>,
}

fn not_a_name() -> EncodeError {
    EncodeError("a map whose keys are not text".into())
}

/// The key serializer's methods that take what is not text.
macro_rules! not_names {
    ($($method:ident($ty:ty)),* $(,)?) => {$(
        fn $method(self, _: $ty) -> Result<&'a Field, EncodeError> {
            Err(not_a_name())
        }
    )*};
}

impl<'a> ser::Serializer for Key<'_, 'a> {
    type Ok = &'a Field;
    type Error = EncodeError;
    type SerializeSeq = Impossible<&'a Field, EncodeError>;
    type SerializeTuple = Impossible<&'a Field, EncodeError>;
    type SerializeTupleStruct = Impossible<&'a Field, EncodeError>;
    type SerializeTupleVariant = Impossible<&'a Field, EncodeError>;
    type SerializeMap = Impossible<&'a Field, EncodeError>;
    type SerializeStruct = Impossible<&'a Field, EncodeError>;
    type SerializeStructVariant = Impossible<&'a Field, EncodeError>;

    fn serialize_str(self, v: &str) -> Result<&'a Field, EncodeError> {
        self.fields.field(v)
    }
    fn serialize_unit_variant(
        self,
        _: &'static str,
        _: u32,
        variant: &'static str,
    ) -> Result<&'a Field, EncodeError> {
        self.fields.field(variant)
    }
    fn serialize_newtype_struct<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        value: &T,
    ) -> Result<&'a Field, EncodeError> {
        value.serialize(self)
    }
    not_names!(
        serialize_bool(bool),
        serialize_i8(i8),
        serialize_i16(i16),
        serialize_i32(i32),
        serialize_i64(i64),
        serialize_u8(u8),
        serialize_u16(u16),
        serialize_u32(u32),
        serialize_u64(u64),
        serialize_f32(f32),
        serialize_f64(f64),
        serialize_char(char),
        serialize_bytes(&[u8]),
        serialize_unit_struct(&'static str),
    );
    fn serialize_none(self) -> Result<&'a Field, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_some<T: Serialize + ?Sized>(self, _: &T) -> Result<&'a Field, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_unit(self) -> Result<&'a Field, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: &T,
    ) -> Result<&'a Field, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<Self::SerializeSeq, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_tuple(self, _: usize) -> Result<Self::SerializeTuple, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_tuple_struct(
        self,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeTupleStruct, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_tuple_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeTupleVariant, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Self::SerializeMap, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_struct(
        self,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeStruct, EncodeError> {
        Err(not_a_name())
    }
    fn serialize_struct_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeStructVariant, EncodeError> {
        Err(not_a_name())
    }
}

/// One field's value (or one item of a repeated field's).
struct Value<'a> {
    schema: &'a Schema,
    field: &'a Field,
    out: &'a mut Vec<u8>,
    in_list: bool,
}

impl Value<'_> {
    fn int(self, v: i64) -> Result<(), EncodeError> {
        let f = self.field;
        match f.kind {
            Kind::Sint => {
                put_tag(self.out, f.number, VARINT);
                put_varint(self.out, ((v << 1) ^ (v >> 63)) as u64);
            }
            Kind::Int => {
                put_tag(self.out, f.number, VARINT);
                put_varint(self.out, v as u64);
            }
            Kind::Uint | Kind::Uint32 => {
                let v = u64::try_from(v).map_err(|_| misfit("a negative number", f))?;
                put_tag(self.out, f.number, VARINT);
                put_varint(self.out, v);
            }
            Kind::Double => return self.float(v as f64),
            _ => return Err(misfit("an integer", f)),
        }
        Ok(())
    }

    fn uint(self, v: u64) -> Result<(), EncodeError> {
        match self.field.kind {
            Kind::Uint => {
                put_tag(self.out, self.field.number, VARINT);
                put_varint(self.out, v);
                Ok(())
            }
            Kind::Uint32 => {
                let v = u32::try_from(v).map_err(|_| misfit("a number too large", self.field))?;
                put_tag(self.out, self.field.number, VARINT);
                put_varint(self.out, v.into());
                Ok(())
            }
            _ => {
                let v = i64::try_from(v).map_err(|_| misfit("a number too large", self.field))?;
                self.int(v)
            }
        }
    }

    fn float(self, v: f64) -> Result<(), EncodeError> {
        let f = self.field;
        match f.kind {
            Kind::Double => {
                put_tag(self.out, f.number, I64);
                self.out.extend_from_slice(&v.to_le_bytes());
                Ok(())
            }
            _ => Err(misfit("a number with a fraction", f)),
        }
    }

    fn text(self, v: &[u8]) -> Result<(), EncodeError> {
        match self.field.kind {
            Kind::String | Kind::Bytes => {
                put_tag(self.out, self.field.number, LEN);
                put_varint(self.out, v.len() as u64);
                self.out.extend_from_slice(v);
                Ok(())
            }
            _ => Err(misfit("text", self.field)),
        }
    }
}

/// Display written into the output, its length put in front after.
struct Appender<'a>(&'a mut Vec<u8>);

impl std::fmt::Write for Appender<'_> {
    fn write_str(&mut self, s: &str) -> std::fmt::Result {
        self.0.extend_from_slice(s.as_bytes());
        Ok(())
    }
}

impl<'a> ser::Serializer for Value<'a> {
    type Ok = ();
    type Error = EncodeError;
    type SerializeSeq = List<'a>;
    type SerializeTuple = List<'a>;
    type SerializeTupleStruct = Impossible<(), EncodeError>;
    type SerializeTupleVariant = Impossible<(), EncodeError>;
    type SerializeMap = Fields<'a>;
    type SerializeStruct = Fields<'a>;
    type SerializeStructVariant = Impossible<(), EncodeError>;

    fn serialize_bool(self, v: bool) -> Result<(), EncodeError> {
        match self.field.kind {
            Kind::Bool => {
                put_tag(self.out, self.field.number, VARINT);
                self.out.push(u8::from(v));
                Ok(())
            }
            _ => Err(misfit("a yes/no", self.field)),
        }
    }
    fn serialize_i8(self, v: i8) -> Result<(), EncodeError> {
        self.int(v.into())
    }
    fn serialize_i16(self, v: i16) -> Result<(), EncodeError> {
        self.int(v.into())
    }
    fn serialize_i32(self, v: i32) -> Result<(), EncodeError> {
        self.int(v.into())
    }
    fn serialize_i64(self, v: i64) -> Result<(), EncodeError> {
        self.int(v)
    }
    fn serialize_u8(self, v: u8) -> Result<(), EncodeError> {
        self.uint(v.into())
    }
    fn serialize_u16(self, v: u16) -> Result<(), EncodeError> {
        self.uint(v.into())
    }
    fn serialize_u32(self, v: u32) -> Result<(), EncodeError> {
        self.uint(v.into())
    }
    fn serialize_u64(self, v: u64) -> Result<(), EncodeError> {
        self.uint(v)
    }
    fn serialize_f32(self, v: f32) -> Result<(), EncodeError> {
        self.float(v.into())
    }
    fn serialize_f64(self, v: f64) -> Result<(), EncodeError> {
        self.float(v)
    }
    fn serialize_char(self, v: char) -> Result<(), EncodeError> {
        self.text(v.encode_utf8(&mut [0; 4]).as_bytes())
    }
    fn serialize_str(self, v: &str) -> Result<(), EncodeError> {
        self.text(v.as_bytes())
    }
    fn serialize_bytes(self, v: &[u8]) -> Result<(), EncodeError> {
        self.text(v)
    }
    /// Absent: a proto2 optional field not written.
    fn serialize_none(self) -> Result<(), EncodeError> {
        Ok(())
    }
    fn serialize_some<T: Serialize + ?Sized>(self, value: &T) -> Result<(), EncodeError> {
        value.serialize(self)
    }
    fn serialize_unit(self) -> Result<(), EncodeError> {
        Ok(())
    }
    fn serialize_unit_struct(self, _: &'static str) -> Result<(), EncodeError> {
        Ok(())
    }
    /// An enum's variant by its name, as JSON has it.
    fn serialize_unit_variant(
        self,
        _: &'static str,
        _: u32,
        variant: &'static str,
    ) -> Result<(), EncodeError> {
        self.text(variant.as_bytes())
    }
    fn serialize_newtype_struct<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        value: &T,
    ) -> Result<(), EncodeError> {
        value.serialize(self)
    }
    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: &T,
    ) -> Result<(), EncodeError> {
        Err(misfit("a tagged choice", self.field))
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<List<'a>, EncodeError> {
        if !self.field.repeated || self.in_list {
            return Err(misfit("a list", self.field));
        }
        Ok(List {
            schema: self.schema,
            field: self.field,
            out: self.out,
        })
    }
    fn serialize_tuple(self, len: usize) -> Result<List<'a>, EncodeError> {
        self.serialize_seq(Some(len))
    }
    fn serialize_tuple_struct(
        self,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeTupleStruct, EncodeError> {
        Err(misfit("a tuple", self.field))
    }
    fn serialize_tuple_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeTupleVariant, EncodeError> {
        Err(misfit("a tagged choice", self.field))
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Fields<'a>, EncodeError> {
        self.serialize_struct("", 0)
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Fields<'a>, EncodeError> {
        let Kind::Message(message) = self.field.kind else {
            return Err(misfit("a group of fields", self.field));
        };
        if message >= self.schema.messages.len() {
            return Err(misfit("a message of an undeclared type", self.field));
        }
        put_tag(self.out, self.field.number, LEN);
        let start = self.out.len();
        Ok(Fields {
            schema: self.schema,
            message,
            out: self.out,
            next: 0,
            start: Some(start),
            pending: None,
        })
    }
    fn serialize_struct_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeStructVariant, EncodeError> {
        Err(misfit("a tagged choice", self.field))
    }
    fn collect_str<T: std::fmt::Display + ?Sized>(self, value: &T) -> Result<(), EncodeError> {
        if !matches!(self.field.kind, Kind::String) {
            return Err(misfit("text", self.field));
        }
        put_tag(self.out, self.field.number, LEN);
        let start = self.out.len();
        std::fmt::write(&mut Appender(self.out), format_args!("{value}"))
            .map_err(|_| misfit("text that does not format", self.field))?;
        close_len(self.out, start);
        Ok(())
    }
}

/// A repeated field's items, each with its tag (proto2's unpacked lists).
struct List<'a> {
    schema: &'a Schema,
    field: &'a Field,
    out: &'a mut Vec<u8>,
}

impl ser::SerializeSeq for List<'_> {
    type Ok = ();
    type Error = EncodeError;
    fn serialize_element<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), EncodeError> {
        value.serialize(Value {
            schema: self.schema,
            field: self.field,
            out: &mut *self.out,
            in_list: true,
        })
    }
    fn end(self) -> Result<(), EncodeError> {
        Ok(())
    }
}

impl ser::SerializeTuple for List<'_> {
    type Ok = ();
    type Error = EncodeError;
    fn serialize_element<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), EncodeError> {
        ser::SerializeSeq::serialize_element(self, value)
    }
    fn end(self) -> Result<(), EncodeError> {
        Ok(())
    }
}

impl<'a> ser::Serializer for Root<'a> {
    type Ok = ();
    type Error = EncodeError;
    type SerializeSeq = Impossible<(), EncodeError>;
    type SerializeTuple = Impossible<(), EncodeError>;
    type SerializeTupleStruct = Impossible<(), EncodeError>;
    type SerializeTupleVariant = Impossible<(), EncodeError>;
    type SerializeMap = Fields<'a>;
    type SerializeStruct = Fields<'a>;
    type SerializeStructVariant = Impossible<(), EncodeError>;

    fn serialize_map(self, _: Option<usize>) -> Result<Fields<'a>, EncodeError> {
        self.serialize_struct("", 0)
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Fields<'a>, EncodeError> {
        if self.schema.messages.is_empty() {
            return Err(EncodeError("the schema has no message type".into()));
        }
        Ok(Fields {
            schema: self.schema,
            message: 0,
            out: self.out,
            next: 0,
            start: None,
            pending: None,
        })
    }
    fn serialize_newtype_struct<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        value: &T,
    ) -> Result<(), EncodeError> {
        value.serialize(self)
    }
    fn serialize_some<T: Serialize + ?Sized>(self, value: &T) -> Result<(), EncodeError> {
        value.serialize(self)
    }

    fn serialize_bool(self, _: bool) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_i8(self, _: i8) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_i16(self, _: i16) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_i32(self, _: i32) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_i64(self, _: i64) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_u8(self, _: u8) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_u16(self, _: u16) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_u32(self, _: u32) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_u64(self, _: u64) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_f32(self, _: f32) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_f64(self, _: f64) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_char(self, _: char) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_str(self, _: &str) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_bytes(self, _: &[u8]) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_none(self) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_unit(self) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_unit_struct(self, _: &'static str) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_unit_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
    ) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: &T,
    ) -> Result<(), EncodeError> {
        Err(not_a_message())
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<Self::SerializeSeq, EncodeError> {
        Err(not_a_message())
    }
    fn serialize_tuple(self, _: usize) -> Result<Self::SerializeTuple, EncodeError> {
        Err(not_a_message())
    }
    fn serialize_tuple_struct(
        self,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeTupleStruct, EncodeError> {
        Err(not_a_message())
    }
    fn serialize_tuple_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeTupleVariant, EncodeError> {
        Err(not_a_message())
    }
    fn serialize_struct_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self::SerializeStructVariant, EncodeError> {
        Err(not_a_message())
    }
}

fn not_a_message() -> EncodeError {
    EncodeError("only a group of named fields is a message".into())
}
