//! What the firmware tests share: the shipped sketches built by
//! `firmware/Makefile` (gcc-avr, avr-libc, Debian's Arduino core) into the
//! target folder.

// Each test crate compiles this module for itself.
#![allow(dead_code)]

use std::path::PathBuf;
use std::process::Command;

/// `make -C firmware` of `sketches` (every sketch when empty) with
/// `DEFINES=defines` into `<target tmp>/avr-firmware-TAG`; returns that folder.
pub fn make(tag: &str, defines: &str, sketches: &[&str]) -> PathBuf {
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("avr-firmware-{tag}"));
    let status = Command::new("make")
        .arg("-s")
        .arg("-C")
        .arg(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("firmware"))
        .arg(format!("BUILD={}", out.display()))
        .arg(format!("DEFINES={defines}"))
        .args(sketches)
        .status()
        .expect("make runs (install gcc-avr, avr-libc, arduino-core-avr: .ci/install)");
    assert!(
        status.success(),
        "the sketches {sketches:?} do not build (DEFINES={defines})"
    );
    out
}
