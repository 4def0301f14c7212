//! Compiles the C shim over Debian's libsimavr (package `libsimavr-dev`):
//! a handful of plain functions, so no bindgen and no libclang.

fn main() {
    println!("cargo:rerun-if-changed=csrc/shim.c");
    if !std::path::Path::new("/usr/include/simavr/sim_avr.h").exists() {
        // A build error from the C compiler would not say what to install.
        eprintln!(
            "twin-avr links simavr: install Debian's libsimavr-dev (apt-get install \
             libsimavr-dev; .ci/install does it). `cargo build -p twin` builds the \
             twin without it."
        );
        std::process::exit(1);
    }
    cc::Build::new()
        .file("csrc/shim.c")
        .include("/usr/include/simavr")
        .warnings(true)
        .compile("twin_avr_shim");
    println!("cargo:rustc-link-lib=dylib=simavr");
}
