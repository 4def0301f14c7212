//! What the firmware tests share: the shipped sketches built by
//! `firmware/Makefile` (gcc-avr, avr-libc, Debian's Arduino core) into the
//! target folder.

use std::path::PathBuf;
use std::process::Command;
use std::sync::Mutex;

/// Tests of one binary run on parallel threads and share its build folder:
/// two `make`s writing the same `core.a` at once leave it corrupt.
static MAKE: Mutex<()> = Mutex::new(());

/// `make -C firmware` of `sketches` (every sketch when empty) with
/// `DEFINES=defines` into `<target tmp>/avr-firmware-TAG`; returns that folder.
pub fn make(tag: &str, defines: &str, sketches: &[&str]) -> PathBuf {
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("avr-firmware-{tag}"));
    // A failed make (whose test then panicked) poisons the lock, but make
    // redoes whatever that run left unfinished, so the next may go ahead.
    let _one_at_a_time = MAKE.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
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
