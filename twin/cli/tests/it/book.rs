//! The README's and the book's examples, run: every ```console block of
//! `README.md` and `docs/**/*.md` is a trycmd case, so a page shows what the
//! program prints today or this test fails.
//!
//! Each page runs in a scratch folder of its own holding copies of what the
//! pages use from a clone (`recordings/`, `docs/examples/`, `deploy/`), laid
//! out as at the repository's root, so a page's commands read as a user
//! types them there and one page's files never meet another's. trycmd runs
//! a page's commands in order in that folder (a recording made by one block
//! is there for the next) and compares stdout and stderr together; `...`
//! and `[..]` on a page stand for what differs from run to run (wall-clock
//! times, rates, absolute paths). Blocks a test cannot run as written
//! (pipes, a second process, a device) are `sh` or `text` blocks, and their
//! page says so.
//!
//! The failing page's copy is named in trycmd's report; the page itself is
//! the file of that name under the repository's root (`README.md`, or
//! `docs/…`, with `/` written as `--`).

use std::path::{Path, PathBuf};

/// What the pages use from a clone, copied beside each one.
const FILES_THE_PAGES_USE: [&str; 3] = ["recordings", "docs/examples", "deploy"];

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// `README.md` and every Markdown page under `docs/`, relative to the root.
fn pages(root: &Path) -> Vec<PathBuf> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<PathBuf>) {
        let mut entries: Vec<_> = std::fs::read_dir(root.join(dir))
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .flatten()
            .map(|e| e.path())
            .collect();
        entries.sort();
        for p in entries {
            let rel = p.strip_prefix(root).unwrap().to_path_buf();
            if p.is_dir() {
                walk(root, &rel, out);
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(rel);
            }
        }
    }
    let mut pages = vec![PathBuf::from("README.md")];
    walk(root, Path::new("docs"), &mut pages);
    pages
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let p = e.path();
        let dest = to.join(e.file_name());
        if p.is_dir() {
            copy_tree(&p, &dest);
        } else {
            std::fs::copy(&p, &dest).unwrap();
        }
    }
}

/// trycmd runs a fence with no language as a case; on the pages such a
/// fence is plain text (a frame's layout, a file's lines). Line for line, so
/// trycmd's line numbers are the page's.
fn label_bare_fences(text: &str) -> String {
    let mut open: Option<&str> = None;
    let mut out = String::with_capacity(text.len() + 64);
    for line in text.split_inclusive('\n') {
        let bare = line.trim_end();
        let ticks = bare.len() - bare.trim_start_matches('`').len();
        match open {
            Some(fence) if bare.starts_with(fence) && bare.trim_start_matches('`').is_empty() => {
                open = None;
            }
            None if ticks >= 3 => {
                open = Some(&bare[..ticks]);
                if bare.len() == ticks {
                    out.push_str(bare);
                    out.push_str("text");
                    out.push_str(&line[bare.len()..]);
                    continue;
                }
            }
            _ => {}
        }
        out.push_str(line);
    }
    out
}

/// A page's copy (`NAME.md`), the folder its commands start from
/// (`NAME.in`), and an empty `NAME.out`, which asks trycmd to run them in a
/// fresh copy of `NAME.in` and to check no file there.
fn lay_out(root: &Path, page: &Path, scratch: &Path) -> PathBuf {
    let name = page.to_string_lossy().replace('/', "--");
    let name = name.trim_end_matches(".md");
    let copy = scratch.join(format!("{name}.md"));
    let text = std::fs::read_to_string(root.join(page)).unwrap();
    std::fs::write(&copy, label_bare_fences(&text)).unwrap();
    let start = scratch.join(format!("{name}.in"));
    for dir in FILES_THE_PAGES_USE {
        if root.join(dir).is_dir() {
            copy_tree(&root.join(dir), &start.join(dir));
        }
    }
    std::fs::create_dir_all(scratch.join(format!("{name}.out"))).unwrap();
    copy
}

#[test]
fn every_console_block_of_the_readme_and_the_book_prints_what_it_shows() {
    let root = repo_root();
    let scratch = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("book");
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch).unwrap();

    let twin = PathBuf::from(env!("CARGO_BIN_EXE_twin"));
    // twin-avr is another package's binary (GPL, built by `cargo test
    // --workspace`): its chapter runs only where it has been built.
    let twin_avr = twin.with_file_name("twin-avr");
    let _cores = crate::support::cores_to_myself();
    let cases = trycmd::TestCases::new();
    cases.register_bin("twin", &twin);
    for page in pages(&root) {
        if page.ends_with("firmware.md") && !twin_avr.exists() {
            println!(
                "note: {} not run: twin-avr is not built (cargo test --workspace builds it)",
                page.display()
            );
            continue;
        }
        cases.case(lay_out(&root, &page, &scratch));
    }
    if twin_avr.exists() {
        cases.register_bin("twin-avr", &twin_avr);
    }
}
