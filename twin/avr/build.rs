//! Compiles the C shim over Debian's libsimavr (package `libsimavr-dev`):
//! a handful of plain functions, so no bindgen and no libclang.

fn main() {
    println!("cargo:rerun-if-changed=csrc/shim.c");
    cc::Build::new()
        .file("csrc/shim.c")
        .include("/usr/include/simavr")
        .warnings(true)
        .compile("twin_avr_shim");
    println!("cargo:rustc-link-lib=dylib=simavr");
}
