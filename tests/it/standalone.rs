//! The repository stands on its own: a clone without the directory that once
//! sat beside it (the shared protocol contracts) builds and tests. No tracked
//! text file points outside the repository for its vectors or specs, and the
//! copies it carries instead — the test vectors in `nodes/tests/vectors/` and
//! the specs in `docs/protocols/` — are there and not empty.

use std::path::{Path, PathBuf};
use std::process::Command;

/// What a path into the old sibling directory looks like. Spelled in pieces
/// so that this file never matches itself.
const FORBIDDEN: [&str; 3] = [
    concat!("..", "/shared"),
    concat!("shared", "/vectors"),
    concat!("shared", "/spec"),
];

/// This file, as `git ls-files` names it.
const THIS_FILE: &str = "tests/it/standalone.rs";

const VECTORS: [&str; 3] = ["meb.jsonl", "meb_slave.jsonl", "modbus8.jsonl"];
const SPECS: [&str; 4] = ["meb.md", "modbus-map.md", "modbus8.md", "pwmcap.md"];

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the e2e crate sits inside the repository")
        .to_path_buf()
}

/// The tracked files, or `None` (with the reason printed) where there is no
/// git or no repository, e.g. in an unpacked source archive.
fn tracked_files(root: &Path) -> Option<Vec<String>> {
    if !root.join(".git").exists() {
        println!(
            "note: no .git in {}: the check of tracked files is skipped",
            root.display()
        );
        return None;
    }
    let output = match Command::new("git")
        .arg("-C")
        .arg(root)
        .args(["ls-files", "-z"])
        .output()
    {
        Ok(output) => output,
        Err(e) => {
            println!("note: git cannot be run ({e}): the check of tracked files is skipped");
            return None;
        }
    };
    if !output.status.success() {
        println!(
            "note: `git ls-files` failed ({}): the check of tracked files is skipped",
            String::from_utf8_lossy(&output.stderr).trim()
        );
        return None;
    }
    let list = String::from_utf8(output.stdout).expect("git prints paths as UTF-8 here");
    Some(
        list.split('\0')
            .filter(|path| !path.is_empty())
            .map(str::to_owned)
            .collect(),
    )
}

#[test]
fn no_tracked_file_reads_the_sibling_shared_directory() {
    let root = repo_root();
    let Some(files) = tracked_files(&root) else {
        return;
    };
    assert!(
        files.iter().any(|f| f == THIS_FILE),
        "`git ls-files` does not list {THIS_FILE}; is {} the repository root?",
        root.display()
    );
    let mut mentions = Vec::new();
    for path in files.iter().filter(|f| *f != THIS_FILE) {
        // A tracked file deleted in the working tree (a move in progress) has
        // nothing to check; a binary file (NUL or not UTF-8) is not text.
        let Ok(bytes) = std::fs::read(root.join(path)) else {
            continue;
        };
        if bytes.contains(&0) {
            continue;
        }
        let Ok(text) = std::str::from_utf8(&bytes) else {
            continue;
        };
        for (n, line) in text.lines().enumerate() {
            if FORBIDDEN.iter().any(|pattern| line.contains(pattern)) {
                mentions.push(format!("{path}:{}: {}", n + 1, line.trim()));
            }
        }
    }
    assert!(
        mentions.is_empty(),
        "{} line(s) of tracked files still point outside the repository ({}); \
         the vectors are in nodes/tests/vectors/, the specs in docs/protocols/:\n{}",
        mentions.len(),
        FORBIDDEN.join(", "),
        mentions.join("\n")
    );
}

fn assert_non_empty(path: &Path) {
    let meta =
        std::fs::metadata(path).unwrap_or_else(|e| panic!("{} is missing: {e}", path.display()));
    assert!(meta.is_file(), "{} is not a file", path.display());
    assert!(meta.len() > 0, "{} is empty", path.display());
}

#[test]
fn the_vectors_are_in_the_repository() {
    let dir = repo_root().join("nodes/tests/vectors");
    for name in VECTORS {
        let path = dir.join(name);
        assert_non_empty(&path);
        let text = std::fs::read_to_string(&path).expect("vectors are UTF-8");
        for (n, line) in text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
        {
            serde_json::from_str::<serde_json::Value>(line)
                .unwrap_or_else(|e| panic!("{}:{}: not a JSON object: {e}", path.display(), n + 1));
        }
    }
}

#[test]
fn the_protocol_specs_are_in_the_repository() {
    let dir = repo_root().join("docs/protocols");
    for name in SPECS.iter().chain(["README.md"].iter()) {
        assert_non_empty(&dir.join(name));
    }
}
