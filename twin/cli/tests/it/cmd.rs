//! Commands that end on their own, their whole output checked: every
//! `tests/cmd/*.trycmd` case runs `twin` as a user types it and compares what
//! it printed, stdout and stderr together, and its exit code (`? N`).
//!
//! A case with a `NAME.out/` folder (a `.keep` in it) runs its commands in
//! order in a fresh scratch folder, a copy of `NAME.in/` if there is one;
//! the others (the `--help` pages, refusals that write nothing) run in the
//! crate's folder. The simulation is deterministic: only what differs from
//! run to run is elided, with `[..]` within a line (wall-clock times and the
//! rates made of them); `[REPO]` is the repository's root.
//!
//! `TRYCMD=overwrite cargo test -p twin --test it cmd` writes what the
//! program prints now into the cases (keeping their `[..]` where they still
//! match): read the diff before committing it. `cargo test -p twin --test it
//! -- cmd trycmd=NAME` runs the cases whose file names hold NAME.

use std::path::Path;

#[test]
fn every_case_prints_what_it_shows() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .expect("the repository's root")
        .to_str()
        .expect("a UTF-8 path")
        .to_owned();
    let _cores = crate::support::cores_to_myself();
    trycmd::TestCases::new()
        .register_bin("twin", Path::new(env!("CARGO_BIN_EXE_twin")))
        // clap wraps help at the terminal's width (100 columns at most):
        // the same width wherever the tests run.
        .env("COLUMNS", "100")
        .insert_var("[REPO]", repo)
        .expect("a variable trycmd takes")
        .case("tests/cmd/*.trycmd");
}
