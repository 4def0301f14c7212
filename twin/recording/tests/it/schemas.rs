//! The `.proto` files against the schemas earlier twins wrote by hand into
//! their recordings: the same message types, field for field (name, number,
//! type, optional or repeated), so that a reader that knows one reads the
//! other, both ways.

use prost_reflect::{Kind, MessageDescriptor};
use std::path::{Path, PathBuf};
use twin_recording::{Encoding, Recording, protobuf};

fn repository() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Every field of `m` and of the message types it nests, one line each.
fn shape(m: &MessageDescriptor, out: &mut Vec<String>) {
    let mut fields: Vec<_> = m.fields().collect();
    fields.sort_by_key(|f| f.number());
    for f in fields {
        let kind = match f.kind() {
            Kind::Message(nested) => {
                shape(&nested, out);
                nested.full_name().to_string()
            }
            other => format!("{other:?}"),
        };
        out.push(format!(
            "{}.{} = {} {:?} {kind}",
            m.full_name(),
            f.name(),
            f.number(),
            f.cardinality()
        ));
    }
}

fn shape_of(m: &MessageDescriptor) -> Vec<String> {
    let mut out = Vec::new();
    shape(m, &mut out);
    out
}

#[test]
fn the_proto_files_declare_the_messages_earlier_twins_wrote_field_for_field() {
    let root = repository();
    // A baseline (the plant's samples and the frames as protobuf) and a
    // recording from before frames kept their bytes once (all four types).
    let files = [
        root.join("recordings/baselines/controller-network.mcap"),
        root.join("twin/cli/tests/fixtures/ev-meb-frames-stored-twice.mcap"),
    ];
    let mut seen = std::collections::BTreeSet::new();
    for path in &files {
        let recording = Recording::read(path).unwrap();
        for channel in &recording.channels {
            let Encoding::Protobuf(old) = &channel.encoding else {
                continue;
            };
            let new = protobuf::message(old.full_name())
                .unwrap_or_else(|| panic!("no .proto declares {}", old.full_name()));
            let (old_shape, new_shape) = (shape_of(old), shape_of(&new));
            assert!(!new_shape.is_empty());
            assert_eq!(
                old_shape,
                new_shape,
                "{} in {}",
                channel.topic,
                path.display()
            );
            seen.insert(old.full_name().to_string());
        }
    }
    assert_eq!(
        seen.into_iter().collect::<Vec<_>>(),
        [
            "twin.ControllerReadings",
            "twin.Frame",
            "twin.PlantSensors",
            "twin.SupervisorLoop"
        ]
    );
}
