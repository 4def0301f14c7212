//! A message that has no protobuf writer of its own (one the twin records
//! seldom: a `twin check` frame, a test's) written by its channel's message
//! type anyway: its `Serialize` value read into a prost-reflect
//! `DynamicMessage` by field name, then encoded. It also tells whether a
//! channel's first message fits the catalogue's message type at all (a
//! PWM-capture frame or another master's loop report does not, and stays
//! JSON). Not for the busy channels: it builds a JSON value and a message
//! each time, where [`super::Protobuf`] writers build neither.

use prost::Message as _;
use prost_reflect::{DynamicMessage, MessageDescriptor};
use serde::Serialize;

/// A value that does not fit its channel's message type (a field it does
/// not have, or of another type): a mistake of the twin's, told as such.
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

/// Append `value`, a message of type `schema`, to `out`; nothing is
/// appended when it does not fit.
pub fn transcode<T: Serialize + ?Sized>(
    schema: &MessageDescriptor,
    value: &T,
    out: &mut Vec<u8>,
) -> Result<(), EncodeError> {
    let json = serde_json::to_value(value).map_err(|e| EncodeError(e.to_string()))?;
    let message = DynamicMessage::deserialize(schema.clone(), json)
        .map_err(|e| EncodeError(format!("{e} (in `{}`)", schema.full_name())))?;
    message.encode(out).map_err(|e| EncodeError(e.to_string()))
}
