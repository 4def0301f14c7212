//! The recordings' protobuf messages, from their `.proto` files in `proto/`:
//! compiled by protox (no `protoc` needed), the `FileDescriptorSet` kept for
//! the MCAP schema records and the readers (`OUT_DIR/twin.fds`), and the
//! Rust types made from it by prost-build (`OUT_DIR/twin.rs`).

use prost::Message;
use std::path::PathBuf;

const FILES: [&str; 4] = [
    "twin/plant_sensors.proto",
    "twin/frame.proto",
    "twin/controller_readings.proto",
    "twin/supervisor_loop.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    let fds = protox::compile(FILES, ["proto"])?;
    // prost-build finds each element's doc comment by its location: it gets
    // them all.
    prost_build::Config::new().compile_fds(fds.clone())?;
    let mut fds = fds;
    // Of the source info, only the comments are for the readers (what a
    // field means, its unit): a location for every name, number and type
    // would make each schema record in each recording twice as long.
    for file in &mut fds.file {
        if let Some(info) = &mut file.source_code_info {
            info.location.retain(|l| {
                l.leading_comments.is_some()
                    || l.trailing_comments.is_some()
                    || !l.leading_detached_comments.is_empty()
            });
        }
    }
    std::fs::write(out.join("twin.fds"), fds.encode_to_vec())?;
    Ok(())
}
