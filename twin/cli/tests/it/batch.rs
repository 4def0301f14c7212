//! `twin batch` as an HPC user runs it: a manifest of 20 short runs by
//! index, by shard, all at once and as a scheduler's array task; entries
//! skipped, retried and failed; the summaries gathered into a CSV and a
//! plot; and the GNU parallel example of `docs/batch.md` run as written
//! (its Slurm example, on a cluster of one node, is in `slurm`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod slurm;

const SCHEDULER_VARIABLES: [&str; 3] = [
    "SLURM_ARRAY_TASK_ID",
    "JOB_COMPLETION_INDEX",
    "AWS_BATCH_JOB_ARRAY_INDEX",
];

/// `twin ARGS` in `dir`, with no scheduler's index in its environment
/// unless `env` sets one.
fn twin_in(dir: &Path, args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_twin"));
    c.args(args).current_dir(dir);
    for v in SCHEDULER_VARIABLES {
        c.env_remove(v);
    }
    c.envs(env.iter().copied());
    c.output().expect("twin runs")
}

fn ok(dir: &Path, args: &[&str]) -> String {
    let o = twin_in(dir, args, &[]);
    assert!(
        o.status.success(),
        "twin {args:?} failed:\n{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout).expect("utf-8 output")
}

fn scratch(name: &str) -> PathBuf {
    crate::support::folder("batch", name)
}

/// Twenty short runs of the EV module's speed loop, a sweep of the
/// supervisor's kp with a set-point step early enough to settle.
fn sweep_of_20(dir: &Path) -> PathBuf {
    let mut text = String::from("# kp sweep\n");
    for i in 0..20 {
        let kp = 0.2 + 0.02 * f64::from(i);
        text.push_str(&format!(
            "{{\"scenario\": \"ev-meb\", \"set\": [\"duration_s=0.6\", \"node.supervisor.kp={kp:.2}\", \
             \"node.supervisor.set_points=[[0.0, 0.0], [0.05, 400.0]]\"], \"seed\": {}, \"out\": \"kp-{i:02}\"}}\n",
            1 + i % 2
        ));
    }
    let path = dir.join("sweep.jsonl");
    std::fs::write(&path, text).expect("manifest written");
    path
}

fn summary(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(text.lines().count(), 1, "one line: {text}");
    serde_json::from_str(&text).expect("JSON summary")
}

/// Every file in `dir` by name, with its bytes.
fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .expect("output folder")
        .map(|e| e.expect("entry").path())
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).expect("readable"))
        })
        .collect()
}

#[test]
fn twenty_entries_by_index_by_shard_and_all_at_once_give_the_same_runs() {
    let dir = scratch("twenty");
    let manifest = sweep_of_20(&dir);
    let m = manifest.to_str().unwrap();
    assert_eq!(ok(&dir, &["batch", m, "--count"]).trim(), "20");

    // One entry: only its files.
    let out = ok(&dir, &["batch", m, "--index", "7", "--out", "one"]);
    assert!(out.contains("[1/1] entry 7 kp-07: ok"), "{out}");
    assert_eq!(
        files(&dir.join("one")).keys().collect::<Vec<_>>(),
        ["kp-07.json", "kp-07.mcap"]
    );
    let s = summary(&dir.join("one/kp-07.json"));
    assert_eq!(s["entry"], 7);
    assert_eq!(s["status"], "ok");
    assert_eq!(s["seed"], 2);
    assert_eq!(s["set"]["node.supervisor.kp"], 0.34);
    assert_eq!(s["set"]["duration_s"], 0.6);
    assert_eq!(s["figures"]["simulated_s"], 0.6);
    // The wheel answered the step to 400 rpm, and the controller read it.
    let wheel = s["figures"]["ev1.wheel_rpm"].as_f64().expect("wheel rpm");
    assert!((300.0..500.0).contains(&wheel), "{s}");
    assert!(
        s["figures"]["ev1.hall_rpm"].as_f64().expect("RPM_M") > 200.0,
        "{s}"
    );
    assert_eq!(s["figures"]["step.to_rpm"], 400.0);
    assert_eq!(s["figures"]["step.at_s"], 0.05);
    assert!(
        s["figures"]["step.rise_s"].as_f64().expect("rise") > 0.0,
        "{s}"
    );

    // Three shards, one process each, cover every entry once.
    let mut seen = Vec::new();
    for k in 0..3 {
        let out = ok(
            &dir,
            &[
                "batch",
                m,
                "--shard",
                &format!("{k}/3"),
                "--jobs",
                "1",
                "--out",
                "shards",
            ],
        );
        let n = out.lines().filter(|l| l.contains(": ok,")).count();
        assert_eq!(n, if k < 2 { 7 } else { 6 }, "{out}");
        for l in out.lines().filter(|l| l.contains(": ok,")) {
            let entry: usize = l.split_whitespace().nth(2).unwrap().parse().unwrap();
            assert_eq!(entry % 3, k, "{l}");
            seen.push(entry);
        }
    }
    seen.sort_unstable();
    assert_eq!(seen, (0..20).collect::<Vec<_>>());

    // All at once on two threads: the same files, byte for byte.
    let out = ok(&dir, &["batch", m, "--jobs", "2", "--out", "all"]);
    assert!(
        out.contains("twin batch: 20 of 20 entries: 20 ran, 0 done before, 0 failed"),
        "{out}"
    );
    let (shards, all) = (files(&dir.join("shards")), files(&dir.join("all")));
    assert_eq!(all.len(), 40, "{:?}", all.keys());
    for (name, bytes) in &all {
        let other = &shards[name];
        if name.ends_with(".mcap") {
            assert!(bytes == other, "{name} differs between shards and --jobs 2");
        } else {
            let (mut a, mut b) = (
                summary(&dir.join("all").join(name)),
                summary(&dir.join("shards").join(name)),
            );
            // Only the wall time may differ.
            a["wall_s"] = 0.into();
            b["wall_s"] = 0.into();
            assert_eq!(a, b, "{name}");
        }
    }
    assert_eq!(all["kp-07.mcap"], files(&dir.join("one"))["kp-07.mcap"]);
    // A stiffer loop rises faster: kp 0.58 against kp 0.20, same seed.
    let rise = |name: &str| {
        summary(&dir.join("all").join(name))["figures"]["step.rise_s"]
            .as_f64()
            .unwrap()
    };
    assert!(rise("kp-19.json") < rise("kp-01.json") || rise("kp-18.json") < rise("kp-00.json"));
}

#[test]
fn a_batch_run_records_what_twin_run_records() {
    let dir = scratch("same");
    std::fs::write(
        dir.join("m.toml"),
        "[[run]]\nscenario = \"ev-meb\"\nset = [\"duration_s=0.6\"]\nseed = 4\nout = \"plain\"\n",
    )
    .unwrap();
    ok(&dir, &["batch", "m.toml", "--index", "0"]);
    ok(
        &dir,
        &[
            "run",
            "ev-meb",
            "--duration",
            "0.6",
            "--seed",
            "4",
            "--out",
            "run.mcap",
        ],
    );
    let batch = std::fs::read(dir.join("m/plain.mcap")).expect("the batch's recording, in m/");
    assert!(
        batch == std::fs::read(dir.join("run.mcap")).unwrap(),
        "recordings differ"
    );
}

#[test]
fn succeeded_entries_are_skipped_failed_ones_named_and_retried() {
    let dir = scratch("retry");
    std::fs::write(
        dir.join("m.jsonl"),
        "{\"scenario\": \"ev-meb\", \"set\": [\"duration_s=0.3\"], \"out\": \"first\"}\n\
         {\"scenario\": \"later.toml\", \"set\": [\"duration_s=0.3\"], \"out\": \"later\"}\n\
         {\"scenario\": \"ev-meb\", \"set\": [\"duration_s=0.3\", \"node.nosuch.kp=1\"], \"out\": \"typo\"}\n",
    )
    .unwrap();
    let run = |args: &[&str]| {
        let mut all = vec!["batch", "m.jsonl", "--out", "out"];
        all.extend_from_slice(args);
        twin_in(&dir, &all, &[])
    };
    let o = run(&["--jobs", "2"]);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert_eq!(o.status.code(), Some(1), "{stdout}{stderr}");
    assert!(stdout.contains("entry 0 first: ok"), "{stdout}");
    assert!(
        stderr.contains("2 of the entries failed: 1 (later), 2 (typo)"),
        "{stderr}"
    );
    let later = summary(&dir.join("out/later.json"));
    assert_eq!(later["status"], "failed");
    assert!(
        later["error"]
            .as_str()
            .unwrap()
            .contains("no scenario `later.toml`"),
        "{later}"
    );
    let typo = summary(&dir.join("out/typo.json"));
    assert!(
        typo["error"]
            .as_str()
            .unwrap()
            .contains("`node` has no item `nosuch`"),
        "{typo}"
    );
    assert!(!dir.join("out/later.mcap").exists());
    let first = std::fs::read(dir.join("out/first.json")).unwrap();

    // Again: the success is skipped, the failures run (and fail) again.
    let o = run(&[]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stdout.contains("entry 0 first: done before, skipped"),
        "{stdout}"
    );
    assert!(stdout.contains("entry 1 later: FAILED"), "{stdout}");

    // The missing scenario appears, the typo stays: one more done.
    let ev_meb =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recordings/scenarios/ev-meb.toml");
    std::fs::copy(ev_meb, dir.join("later.toml")).unwrap();
    let o = run(&[]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1));
    assert!(stdout.contains("entry 1 later: ok"), "{stdout}");
    assert_eq!(summary(&dir.join("out/later.json"))["status"], "ok");
    assert!(
        // Two ran (the typo again, and failed again), one was done before.
        stdout.contains("2 ran, 1 done before, 1 failed"),
        "{stdout}"
    );
    assert_eq!(
        std::fs::read(dir.join("out/first.json")).unwrap(),
        first,
        "a skipped entry is left alone"
    );

    // --force runs a done entry again.
    let o = run(&["--index", "0", "--force"]);
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("entry 0 first: ok"));
    // Nothing half-written is left behind.
    let names: Vec<String> = files(&dir.join("out")).into_keys().collect();
    assert!(names.iter().all(|n| !n.starts_with('.')), "{names:?}");
}

/// What it prints (the variable it took the index from, `--index` over the
/// variable, a bad index refused in words) is tests/cmd/batch-array.trycmd;
/// here, that it runs that entry alone.
#[test]
fn an_array_task_takes_its_index_from_its_scheduler() {
    let dir = scratch("array");
    let manifest = sweep_of_20(&dir);
    let m = manifest.to_str().unwrap();
    for (variable, index) in SCHEDULER_VARIABLES.iter().zip(["3", "11", "19"]) {
        let o = twin_in(&dir, &["batch", m, "--out", variable], &[(variable, index)]);
        let (stdout, stderr) = (
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr),
        );
        assert!(o.status.success(), "{stdout}{stderr}");
        let names: Vec<String> = files(&dir.join(variable)).into_keys().collect();
        assert_eq!(names, {
            let n: usize = index.parse().unwrap();
            [format!("kp-{n:02}.json"), format!("kp-{n:02}.mcap")]
        });
    }
}

#[test]
fn summarize_gathers_a_known_set_into_csv_and_plot() {
    let dir = scratch("summarize");
    let out = dir.join("set");
    std::fs::create_dir_all(&out).unwrap();
    // Three runs as `twin batch` writes them, one failed, and a temporary
    // file a writer was interrupted in, which is no summary.
    let line = |entry: u32, kp: f64, settling: &str, status: &str| {
        format!(
            "{{\"entry\":{entry},\"name\":\"kp{entry}\",\"status\":\"{status}\",\"scenario\":\"ev-meb\",\"seed\":1,\
             \"set\":{{\"node.supervisor.kp\":{kp}}},\"simulated_s\":2.0,\"wall_s\":0.25,\"recording\":\"kp{entry}.mcap\",\
             \"figures\":{{\"ev1.wheel_rpm\":{},\"step.settling_s\":{settling}}},\"error\":null}}\n",
            1000.0 - kp * 10.0
        )
    };
    std::fs::write(out.join("kp0.json"), line(0, 0.3, "1.5", "ok")).unwrap();
    std::fs::write(out.join("kp1.json"), line(1, 0.6, "0.75", "ok")).unwrap();
    std::fs::write(out.join("kp2.json"), line(2, 0.9, "null", "failed")).unwrap();
    std::fs::write(out.join(".kp3.json.77.tmp"), "{\"entry\": 3, \"na").unwrap();
    // What it prints, and a column that is not there named with the ones
    // that are: tests/cmd/batch-summarize.trycmd.
    ok(
        &dir,
        &[
            "batch",
            "summarize",
            "set",
            "--plot",
            "step.settling_s",
            "--against",
            "node.supervisor.kp",
        ],
    );
    let csv = std::fs::read_to_string(out.join("summary.csv")).unwrap();
    assert_eq!(
        csv,
        "entry,name,status,scenario,seed,simulated_s,wall_s,set.node.supervisor.kp,ev1.wheel_rpm,step.settling_s,recording,error\n\
         0,kp0,ok,ev-meb,1,2,0.25,0.3,997,1.5,kp0.mcap,\n\
         1,kp1,ok,ev-meb,1,2,0.25,0.6,994,0.75,kp1.mcap,\n\
         2,kp2,failed,ev-meb,1,2,0.25,0.9,991,,kp2.mcap,\n"
    );
    let png = std::fs::read(out.join("step.settling_s-against-node.supervisor.kp.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 5000);
    // The PNG header's size: 900 × 560.
    assert_eq!(&png[16..24], &[0, 0, 3, 0x84, 0, 0, 2, 0x30]);
}

// A broken manifest is refused with its file, line and field:
// tests/cmd/batch-broken.trycmd.

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The body of the block of `docs/batch.md` that opens with `fence`.
fn doc_block(fence: &str) -> String {
    let doc = std::fs::read_to_string(repo().join("docs/batch.md")).expect("docs/batch.md");
    let start = doc
        .find(&format!("{fence}\n"))
        .unwrap_or_else(|| panic!("a {fence} block in docs/batch.md"));
    let block = &doc[start..];
    let block = &block[block.find('\n').unwrap() + 1..];
    block[..block.find("```").unwrap()].to_string()
}

/// The GNU parallel example of `docs/batch.md`, its shell block run as
/// written (with this build of `twin` first on the PATH).
#[test]
fn the_gnu_parallel_example_of_the_docs_runs() {
    assert!(
        Command::new("parallel")
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success()),
        "GNU parallel is missing: install it (Debian: apt-get install parallel; .ci/install does)"
    );
    let root = repo();
    let block = doc_block("```sh parallel");
    let block = block.as_str();
    let dir = scratch("parallel");
    std::fs::copy(
        root.join("docs/examples/sweep.jsonl"),
        dir.join("sweep.jsonl"),
    )
    .unwrap();
    let bin = Path::new(env!("CARGO_BIN_EXE_twin")).parent().unwrap();
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let o = Command::new("bash")
        .args(["-euo", "pipefail", "-c", block])
        .current_dir(&dir)
        .env("PATH", path)
        .env("HOME", &dir)
        .output()
        .expect("bash runs");
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{block}\n{stdout}\n{stderr}");
    let csv = std::fs::read_to_string(dir.join("sweep/summary.csv")).expect("the summary CSV");
    let n: usize = ok(&dir, &["batch", "sweep.jsonl", "--count"])
        .trim()
        .parse()
        .unwrap();
    assert_eq!(csv.lines().count(), n + 1, "{csv}");
    assert!(
        csv.lines()
            .skip(1)
            .all(|l| l.split(',').nth(2) == Some("ok")),
        "{csv}"
    );
    assert!(
        dir.join("sweep/step.settling_s-against-node.supervisor.kp.png")
            .exists(),
        "{stdout}"
    );
    // The job log GNU parallel kept: one line per entry, every one exit 0.
    let log = std::fs::read_to_string(dir.join("sweep.log")).expect("the job log");
    assert_eq!(
        log.lines()
            .skip(1)
            .filter(|l| l.split('\t').nth(6) == Some("0"))
            .count(),
        n,
        "{log}"
    );
}

/// What `--check` prints of every entry, and its exit code, is
/// tests/cmd/batch-check.trycmd; here, that it runs none.
#[test]
fn check_runs_none() {
    let dir = scratch("check");
    std::fs::write(
        dir.join("m.jsonl"),
        "{\"scenario\": \"ev-meb\", \"set\": [\"duration_s=0.3\"], \"out\": \"first\"}\n\
         {\"scenario\": \"later.toml\", \"out\": \"later\"}\n\
         {\"scenario\": \"ev-meb\", \"set\": [\"node.nosuch.kp=1\"], \"out\": \"typo\"}\n",
    )
    .unwrap();
    let o = twin_in(&dir, &["batch", "m.jsonl", "--check"], &[]);
    assert_eq!(o.status.code(), Some(1));
    assert!(!dir.join("m").exists(), "nothing run, no output folder");

    std::fs::write(
        dir.join("good.jsonl"),
        "{\"scenario\": \"ev-meb\", \"seed\": 4}\n{\"scenario\": \"ten-modules\"}\n",
    )
    .unwrap();
    ok(&dir, &["batch", "good.jsonl", "--check", "--index", "0"]);
    assert!(!dir.join("good").exists());
}
