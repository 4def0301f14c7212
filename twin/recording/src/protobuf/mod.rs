//! Protobuf, as the twin's busiest channels are recorded. The messages are
//! `.proto` files in the repository (`twin/recording/proto/twin/`), compiled
//! at build time by protox (no `protoc`): their Rust types ([`twin`]) made
//! by prost-build (the busy messages are written field by field by [`wire`],
//! prost's bytes for those types, which tests compare), their
//! `FileDescriptorSet` embedded
//! for the MCAP schema records (schema encoding `protobuf`), which Foxglove,
//! Lichtblick and the MCAP tools decode by field name. The readers decode a
//! message through prost-reflect with the schema its own file carries, back
//! into the JSON value the older JSON recordings hold ([`decode`]), so every
//! reader reads old files and new ones alike.

pub mod decode;
mod transcode;
pub mod wire;

use prost::Message as _;
use prost_reflect::{DescriptorPool, MessageDescriptor};
use std::sync::OnceLock;

pub use decode::to_value;
pub use transcode::{EncodeError, transcode};

/// The messages' Rust types, made from the `.proto` files by prost-build.
#[allow(missing_docs, clippy::all, clippy::pedantic, unused_qualifications)]
pub mod twin {
    include!(concat!(env!("OUT_DIR"), "/twin.rs"));
}

/// The `.proto` files as compiled (with their comments), by build.rs.
const DESCRIPTORS: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/twin.fds"));

/// The twin's own message types.
fn pool() -> Option<&'static DescriptorPool> {
    static POOL: OnceLock<Option<DescriptorPool>> = OnceLock::new();
    // Built from this crate's own build output: it always reads (a test
    // holds it to that), and `None` would only leave channels JSON.
    POOL.get_or_init(|| DescriptorPool::decode(DESCRIPTORS).ok())
        .as_ref()
}

/// The twin's message type named `name` (`twin.Frame`).
pub fn message(name: &str) -> Option<MessageDescriptor> {
    pool()?.get_message_by_name(name)
}

/// What an MCAP schema record of message type `message` holds: the
/// `FileDescriptorSet` of the one `.proto` file that declares it (with its
/// comments, as `protoc` keeps them in `SourceCodeInfo`).
pub fn descriptor_set(message: &MessageDescriptor) -> Vec<u8> {
    prost_types::FileDescriptorSet {
        file: vec![message.parent_file().file_descriptor_proto().clone()],
    }
    .encode_to_vec()
}

/// The message type `name` in a schema record's `FileDescriptorSet`
/// `bytes` (the twin's, or an older twin's, or another tool's); what is
/// wrong in words otherwise.
pub fn schema_in(bytes: &[u8], name: &str) -> Result<MessageDescriptor, String> {
    let pool = DescriptorPool::decode(bytes)
        .map_err(|e| format!("its protobuf schema does not read as a FileDescriptorSet ({e})"))?;
    pool.get_message_by_name(name)
        .ok_or_else(|| format!("its protobuf schema has no message type `{name}`"))
}

/// A message that writes its own protobuf bytes (through its type in
/// [`twin`]) for the channels of the message type [`Protobuf::SCHEMA`].
pub trait Protobuf {
    /// The full name of the message type (`twin.Frame`).
    const SCHEMA: &'static str;

    /// Append the message's bytes to `out`.
    fn write_protobuf(&self, out: &mut Vec<u8>);
}

/// Append `message`'s bytes to `out`, as prost writes them: fields in
/// number order, a set `optional` field written even when zero.
pub fn append(message: &impl prost::Message, out: &mut Vec<u8>) {
    // A `Vec` grows as it is written: it never runs out of room, prost's
    // only error.
    let _ = message.encode(out);
}

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_compiled_proto_files_declare_every_recorded_message_type() {
        assert!(pool().is_some(), "the embedded descriptors read");
        for name in [
            "twin.PlantSensors",
            "twin.Frame",
            "twin.ControllerReadings",
            "twin.SupervisorLoop",
        ] {
            let m = message(name).unwrap_or_else(|| panic!("{name}"));
            // A schema record holds the one file, and reads back.
            let set = descriptor_set(&m);
            assert_eq!(schema_in(&set, name).unwrap().full_name(), name);
        }
        assert!(schema_in(&[0xff], "twin.Frame").is_err());
        let set = descriptor_set(&message("twin.Frame").unwrap());
        assert!(
            schema_in(&set, "twin.Other")
                .unwrap_err()
                .contains("twin.Other")
        );
    }
}
