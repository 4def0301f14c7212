//! The Slurm example of `docs/batch.md` on a real Slurm: a cluster of one
//! node started by `deploy/slurm/one-node.sh` (our own munged, slurmctld
//! and slurmd), the book's job script (`docs/examples/sweep.sbatch`, which
//! the book includes) submitted as an array by the book's own block, and
//! what the array wrote checked against `twin batch` run on this machine.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use super::{files, ok, repo, scratch, summary};

/// Where Debian puts the daemons, which a user's PATH may lack.
const SBIN: &str = "/usr/sbin:/sbin";

/// This build of `twin` first on the PATH, then the user's, then the daemons'.
fn path() -> String {
    let bin = Path::new(env!("CARGO_BIN_EXE_twin")).parent().unwrap();
    format!(
        "{}:{}:{SBIN}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    )
}

/// The Slurm and munge programs the cluster needs that are not on this
/// machine.
fn missing_programs() -> Vec<&'static str> {
    let path = path();
    [
        "munged",
        "mungekey",
        "slurmctld",
        "slurmd",
        "sbatch",
        "sinfo",
        "scancel",
    ]
    .into_iter()
    .filter(|p| !std::env::split_paths(&path).any(|d| d.join(p).is_file()))
    .collect()
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A running one-node cluster; dropping it stops every daemon it started,
/// whether the test passed or not.
struct OneNode {
    dir: PathBuf,
}

impl OneNode {
    fn script() -> PathBuf {
        repo().join("deploy/slurm/one-node.sh")
    }

    /// Its state in a folder of a fixed name, not this process's scratch
    /// folder: a run killed before its guard could stop the cluster leaves
    /// daemons marked with this folder, which the next start stops first.
    fn start() -> OneNode {
        let cluster = OneNode {
            dir: std::env::temp_dir().join("twin-slurm-test"),
        };
        // Ports beside Slurm's own, which a Slurm of the machine's own may hold.
        let o = Command::new(Self::script())
            .arg("start")
            .arg(&cluster.dir)
            .env("PATH", path())
            .env("SLURMCTLD_PORT", "16817")
            .env("SLURMD_PORT", "16818")
            .output()
            .expect("one-node.sh runs");
        assert!(
            o.status.success(),
            "the one-node cluster did not start:\n{}",
            text(&o)
        );
        assert_eq!(
            String::from_utf8_lossy(&o.stdout).trim(),
            format!("SLURM_CONF={}", cluster.conf().display())
        );
        cluster
    }

    fn conf(&self) -> PathBuf {
        self.dir.join("slurm.conf")
    }
}

impl Drop for OneNode {
    fn drop(&mut self) {
        match Command::new(Self::script())
            .arg("stop")
            .arg(&self.dir)
            .env("PATH", path())
            .output()
        {
            Ok(o) if o.status.success() => {}
            Ok(o) => eprintln!("one-node.sh stop failed:\n{}", text(&o)),
            Err(e) => eprintln!("one-node.sh stop did not run: {e}"),
        }
    }
}

/// A task's or a local run's lines with the wall time of each run elided.
fn without_wall_time(text: &str) -> String {
    text.lines()
        .map(|l| match (l.find(" in "), l.find(" s; ")) {
            (Some(a), Some(b)) if a < b => format!("{} in [..]{}", &l[..a], &l[b..]),
            _ => l.to_string(),
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// `summary.csv` without its `wall_s` column.
fn csv_without_wall_time(csv: &str) -> Vec<Vec<String>> {
    let wall = csv
        .lines()
        .next()
        .and_then(|h| h.split(',').position(|c| c == "wall_s"))
        .expect("a wall_s column");
    csv.lines()
        .map(|l| {
            let mut cells: Vec<String> = l.split(',').map(str::to_string).collect();
            cells.remove(wall);
            cells
        })
        .collect()
}

#[test]
fn the_slurm_array_of_the_docs_runs_on_a_one_node_cluster() {
    let missing = missing_programs();
    if !missing.is_empty() {
        eprintln!(
            "skipped: Slurm is not installed ({} missing; Debian: apt-get install \
             slurmctld slurmd slurm-client munge, as .ci/install does)",
            missing.join(", ")
        );
        return;
    }
    // The job script the book shows is the file it includes.
    let doc = std::fs::read_to_string(repo().join("docs/batch.md")).unwrap();
    assert!(
        doc.contains("```sh\n{{#include examples/sweep.sbatch}}\n```"),
        "docs/batch.md includes docs/examples/sweep.sbatch"
    );
    let submit = super::doc_block("```sh slurm");

    let dir = scratch("slurm");
    for file in ["sweep.jsonl", "sweep.sbatch"] {
        std::fs::copy(repo().join("docs/examples").join(file), dir.join(file)).unwrap();
    }
    let cluster = OneNode::start();
    // Not a speed bound: a node that died mid-run would leave `sbatch
    // --wait` waiting forever, and the whole test run with it.
    let o = Command::new("timeout")
        .args(["600", "bash", "-euo", "pipefail", "-c", &submit])
        .current_dir(&dir)
        .env("PATH", path())
        .env("HOME", &dir)
        .env("SLURM_CONF", cluster.conf())
        .output()
        .expect("bash runs");
    assert!(o.status.success(), "{submit}\n{}", text(&o));
    // The last sbatch waited for the summary, which waited for the array.
    assert!(
        String::from_utf8_lossy(&o.stdout).starts_with("Submitted batch job "),
        "{}",
        text(&o)
    );

    // The same manifest on this machine, all entries in one process.
    let local = dir.join("local");
    std::fs::create_dir(&local).unwrap();
    std::fs::copy(dir.join("sweep.jsonl"), local.join("sweep.jsonl")).unwrap();
    let local_out = ok(&local, &["batch", "sweep.jsonl", "--jobs", "1"]);
    ok(
        &local,
        &[
            "batch",
            "summarize",
            "sweep",
            "--plot",
            "step.settling_s",
            "--against",
            "node.supervisor.kp",
        ],
    );
    let n: usize = ok(&dir, &["batch", "sweep.jsonl", "--count"])
        .trim()
        .parse()
        .unwrap();

    // Same files; recordings and plot byte for byte, summaries but for the
    // wall time.
    let (array, here) = (files(&dir.join("sweep")), files(&local.join("sweep")));
    assert_eq!(
        array.keys().collect::<Vec<_>>(),
        here.keys().collect::<Vec<_>>()
    );
    assert_eq!(array.len(), 2 * n + 2, "{:?}", array.keys());
    for (name, bytes) in &array {
        if name.ends_with(".json") {
            let (mut a, mut b) = (
                summary(&dir.join("sweep").join(name)),
                summary(&local.join("sweep").join(name)),
            );
            assert_eq!(a["status"], "ok", "{name}: {a}");
            a["wall_s"] = 0.into();
            b["wall_s"] = 0.into();
            assert_eq!(a, b, "{name}");
        } else if name == "summary.csv" {
            let (a, b) = (
                String::from_utf8(bytes.clone()).unwrap(),
                String::from_utf8(here[name].clone()).unwrap(),
            );
            assert_eq!(a.lines().count(), n + 1, "{a}");
            assert_eq!(csv_without_wall_time(&a), csv_without_wall_time(&b));
        } else {
            // The recordings and the plot.
            assert!(bytes == &here[name], "{name} differs from the local run's");
        }
    }

    // One log per task, each task one entry, its index taken from
    // SLURM_ARRAY_TASK_ID, printing what the local run printed of it.
    let logs = files(&dir.join("logs"));
    assert_eq!(logs.len(), n, "{:?}", logs.keys());
    let job = logs
        .keys()
        .next()
        .and_then(|name| name.strip_prefix("twin-sweep-"))
        .and_then(|rest| rest.split_once('_'))
        .map(|(job, _)| job.to_string())
        .expect("logs named twin-sweep-JOB_INDEX.out");
    let local_lines: BTreeMap<usize, String> = local_out
        .lines()
        .filter_map(|l| {
            let rest = &l[l.find("] entry ")? + 2..];
            let index = rest.split_whitespace().nth(1)?.parse().ok()?;
            Some((index, without_wall_time(rest)))
        })
        .collect();
    assert_eq!(local_lines.len(), n, "{local_out}");
    for (index, line) in &local_lines {
        let name = format!("twin-sweep-{job}_{index}.out");
        let log =
            String::from_utf8(logs.get(&name).unwrap_or_else(|| panic!("{name}")).clone()).unwrap();
        assert_eq!(
            without_wall_time(&log),
            format!(
                "twin batch: entry {index}, from SLURM_ARRAY_TASK_ID\n\
                 [1/1] {line}\n\
                 twin batch: 1 of {n} entries: 1 ran, 0 done before, 0 failed; summaries in sweep"
            ),
            "{name}"
        );
    }
    // The task's output the book shows is task 1's.
    let shown = doc
        .find("Each task's output is in")
        .map(|at| &doc[at..])
        .and_then(|rest| rest.find("```text\n").map(|s| &rest[s + 8..]))
        .and_then(|rest| rest.find("```").map(|e| &rest[..e]))
        .expect("a ```text block after \"Each task's output is in\"");
    let task_1 = String::from_utf8(logs[&format!("twin-sweep-{job}_1.out")].clone()).unwrap();
    assert_eq!(without_wall_time(shown), without_wall_time(&task_1));
    drop(cluster);
}
