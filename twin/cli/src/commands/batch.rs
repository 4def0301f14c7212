//! `twin batch`: run a manifest of scenarios, one entry, a shard or all of
//! them; `twin batch summarize`: gather their summaries.

use anyhow::{Result, bail};
use clap::{Args, Subcommand};
use std::path::{Path, PathBuf};
use twin_lab::batch::{self, Manifest, Options, Report, Selection, Status, Summary, summarize};

/// Run a manifest of scenario runs: a parameter sweep, seeds, cable lengths.
///
/// The manifest is a JSON Lines file (one entry a line) or a TOML file
/// (`[[run]]` tables). An entry names a scenario (embedded, or a file beside
/// the manifest), `set`: changes as `twin replay --set` takes them
/// (`"node.supervisor.kp=0.6"`, `"duration_s=2"`), a `seed`, and `out`: the
/// name of its recording and summary (default: its index, `0007`):
///
///   {"scenario": "ev-meb", "set": ["node.supervisor.kp=0.6"], "seed": 2, "out": "kp-0.6-s2"}
///
/// Each entry writes NAME.mcap and a one-line JSON summary NAME.json into the
/// output folder, each whole or not at all (a temporary file renamed into
/// place). An entry whose summary says it succeeded is skipped (`--force`
/// runs it again); one that failed says why in its summary, is run again
/// next time, and makes the exit status non-zero, so a scheduler's retries
/// work. `--index I` runs one entry (from 0); without it, an array task's
/// index is read from SLURM_ARRAY_TASK_ID, JOB_COMPLETION_INDEX (Kubernetes
/// Indexed Jobs) or AWS_BATCH_JOB_ARRAY_INDEX; with none of them, every entry
/// runs, `--jobs` at a time.
#[derive(Debug, Args)]
#[command(
    args_conflicts_with_subcommands = true,
    subcommand_negates_reqs = true,
    after_help = "Examples:\n  twin batch sweep.jsonl --count\n  twin batch sweep.jsonl --check\n  twin batch sweep.jsonl --jobs 2 --out sweep\n  twin batch sweep.jsonl --index 7 --out sweep\n  twin batch sweep.jsonl --shard 1/4 --out sweep\n  twin batch summarize sweep --plot step.settling_s --against node.supervisor.kp"
)]
pub struct BatchArgs {
    #[command(subcommand)]
    command: Option<BatchCommand>,
    /// The manifest: JSON Lines, or TOML when it ends in .toml.
    #[arg(value_name = "MANIFEST", required = true)]
    manifest: Option<PathBuf>,
    /// Print how many entries the manifest has (for a launcher) and exit.
    #[arg(long)]
    count: bool,
    /// Check every entry chosen (its scenario loads, its changes apply)
    /// without running any, and exit: non-zero if one is wrong.
    #[arg(long, conflicts_with = "count")]
    check: bool,
    /// The folder of recordings and summaries [default: the manifest's name
    /// without its extension, in the current folder].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Run entry I only (from 0).
    #[arg(long, value_name = "I", value_parser = super::numbers::whole::<usize>,
          conflicts_with_all = ["shard", "all"])]
    index: Option<usize>,
    /// Run shard K of N (K from 0): the entries whose index is K modulo N.
    #[arg(long, value_name = "K/N", conflicts_with = "all")]
    shard: Option<String>,
    /// Run every entry, even in an array task whose scheduler set an index.
    #[arg(long)]
    all: bool,
    /// Entries run at once [default: the cores this process may use].
    #[arg(long, value_name = "N", value_parser = super::numbers::whole::<usize>)]
    jobs: Option<usize>,
    /// Run entries that succeeded before again.
    #[arg(long)]
    force: bool,
}

#[derive(Debug, Subcommand)]
enum BatchCommand {
    Summarize(SummarizeArgs),
}

/// Gather a batch's summaries into one CSV, and plot a figure against a
/// parameter.
///
/// The CSV has a row per entry (in manifest order) and a column per `--set`
/// path (`set.PATH`) and per figure: MODULE.wheel_rpm (the true speed),
/// MODULE.hall_rpm and MODULE.light_rpm (RPM_M and RPM_L as the controller
/// reads them), the module's volts, amps and state of charge, per bus its
/// collisions and noise, events by kind, and, where the scenario's
/// supervisor steps its set point, the wheel's step.settling_s, step.rise_s,
/// step.overshoot_pct and step.error_rpm.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  twin batch summarize sweep\n  twin batch summarize sweep --plot step.settling_s --against node.supervisor.kp\n  twin batch summarize sweep --plot ev1.light_rpm --against ev1.wheel_rpm --png light.png"
)]
struct SummarizeArgs {
    /// The batch's output folder.
    #[arg(value_name = "DIR")]
    dir: PathBuf,
    /// Where to write the CSV [default: DIR/summary.csv].
    #[arg(long, value_name = "PATH")]
    csv: Option<PathBuf>,
    /// Plot this figure (a column of the CSV)...
    #[arg(long, value_name = "FIGURE", requires = "against")]
    plot: Option<String>,
    /// ...against this parameter (a `--set` path) or figure.
    #[arg(long, value_name = "COLUMN", requires = "plot")]
    against: Option<String>,
    /// Where to write the plot [default: DIR/FIGURE-against-COLUMN.png].
    #[arg(long, value_name = "PATH", requires = "plot")]
    png: Option<PathBuf>,
}

pub fn execute(args: &BatchArgs) -> Result<()> {
    if let Some(BatchCommand::Summarize(s)) = &args.command {
        return execute_summarize(s);
    }
    let Some(path) = &args.manifest else {
        bail!("name a manifest: twin batch MANIFEST");
    };
    let manifest = Manifest::load(path)?;
    let count = manifest.entries.len();
    if args.count {
        println!("{count}");
        return Ok(());
    }
    let selection = select(args)?;
    let indices = selection.indices(count)?;
    if args.check {
        return check(&manifest, &indices, path);
    }
    let dir = args.out.clone().unwrap_or_else(|| default_dir(path));
    let jobs = args.jobs.unwrap_or_else(|| {
        std::thread::available_parallelism().map_or(1, std::num::NonZeroUsize::get)
    });
    if jobs == 0 {
        bail!("--jobs must be 1 or more");
    }
    let options = Options {
        dir: dir.clone(),
        force: args.force,
        jobs,
    };
    let total = indices.len();
    let finished = std::sync::atomic::AtomicUsize::new(0);
    let reports = batch::runner::run(&manifest, &indices, &options, |report| {
        let n = finished.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        print_report(report, n, total, &dir);
    })?;
    let failed: Vec<&Summary> = reports
        .iter()
        .filter_map(|r| match r {
            Report::Ran(s) if s.status == Status::Failed => Some(s),
            _ => None,
        })
        .collect();
    let skipped = reports
        .iter()
        .filter(|r| matches!(r, Report::Skipped(_)))
        .count();
    let stopped = reports
        .iter()
        .filter(|r| matches!(r, Report::Stopped { .. }))
        .count();
    println!(
        "twin batch: {total} of {count} entries: {} ran, {skipped} done before, {} failed{}; summaries in {}",
        total - skipped - stopped,
        failed.len(),
        if stopped > 0 {
            format!(", {stopped} stopped")
        } else {
            String::new()
        },
        dir.display()
    );
    if stopped > 0 {
        // Stopped as asked, as `twin run` is: the exit status of a command
        // ended by Ctrl-C, and the entries not done run next time.
        eprintln!("stopped: {stopped} entries not done; they run next time");
        std::process::exit(130);
    }
    if !failed.is_empty() {
        let names: Vec<String> = failed
            .iter()
            .map(|s| format!("{} ({})", s.entry, s.name))
            .collect();
        bail!(
            "{} of the entries failed: {}; each says why in its summary, and runs again next time",
            failed.len(),
            names.join(", ")
        );
    }
    Ok(())
}

/// `--check`: each entry prepared as a run would prepare it, none run.
fn check(manifest: &Manifest, indices: &[usize], path: &Path) -> Result<()> {
    let mut wrong = 0;
    for &i in indices {
        match batch::runner::prepare(manifest, i) {
            Ok(s) => println!(
                "entry {i} {}: ok, scenario {}, {} s, seed {}",
                manifest.name(i),
                s.name,
                s.duration_s,
                s.seed
            ),
            Err(e) => {
                wrong += 1;
                let e = anyhow::Error::from(e);
                println!("entry {i} {}: WRONG: {e:#}", manifest.name(i));
            }
        }
    }
    let shown = path.display();
    if wrong > 0 {
        bail!(
            "{shown}: {wrong} of {} entries checked are wrong; nothing was run",
            indices.len()
        );
    }
    let n = indices.len();
    let entries = if n == 1 { "entry" } else { "entries" };
    println!("{shown}: {n} {entries} checked, every one would run");
    Ok(())
}

/// The entries asked for: `--index`, `--shard`, `--all`, a scheduler's
/// index, or every one.
fn select(args: &BatchArgs) -> Result<Selection> {
    if let Some(i) = args.index {
        return Ok(Selection::One(i));
    }
    if let Some(shard) = &args.shard {
        return Ok(Selection::parse_shard(shard)?);
    }
    if args.all {
        return Ok(Selection::All);
    }
    match batch::scheduler_index(|name| std::env::var(name).ok())? {
        Some((i, variable)) => {
            eprintln!("twin batch: entry {i}, from {variable}");
            Ok(Selection::One(i))
        }
        None => Ok(Selection::All),
    }
}

/// `sweep.jsonl` → `sweep`, in the current folder.
fn default_dir(manifest: &Path) -> PathBuf {
    let stem = manifest
        .file_stem()
        .map_or_else(|| "batch".into(), |s| s.to_string_lossy().into_owned());
    PathBuf::from(stem)
}

fn print_report(report: &Report, n: usize, total: usize, dir: &Path) {
    match report {
        Report::Skipped(s) => println!(
            "[{n}/{total}] entry {} {}: done before, skipped (--force runs it again)",
            s.entry, s.name
        ),
        Report::Stopped { entry, name } => {
            println!("[{n}/{total}] entry {entry} {name}: stopped, not done")
        }
        Report::Ran(s) if s.status == Status::Ok => println!(
            "[{n}/{total}] entry {} {}: ok, {} in {:.2} s{}",
            s.entry,
            s.name,
            dir.join(s.recording.as_deref().unwrap_or_default())
                .display(),
            s.wall_s,
            headline(s)
        ),
        Report::Ran(s) => {
            let why = s.error.as_deref().unwrap_or("no reason given");
            println!("[{n}/{total}] entry {} {}: FAILED: {why}", s.entry, s.name);
            eprintln!("entry {} {} failed: {why}", s.entry, s.name);
        }
    }
}

/// The figures a line of progress shows: each wheel's speed, and the step's
/// settling time where there is one.
fn headline(s: &Summary) -> String {
    let mut parts: Vec<String> = s
        .figures
        .iter()
        .filter(|(k, _)| k.ends_with(".wheel_rpm"))
        .filter_map(|(k, v)| v.map(|v| format!("{k} {v:.1}")))
        .collect();
    match s.figures.get("step.settling_s") {
        Some(Some(v)) => parts.push(format!("step.settling_s {v:.3}")),
        Some(None) => parts.push("step not settled".into()),
        None => {}
    }
    if parts.is_empty() {
        String::new()
    } else {
        format!("; {}", parts.join(", "))
    }
}

fn execute_summarize(args: &SummarizeArgs) -> Result<()> {
    let summaries = summarize::gather(&args.dir)?;
    let csv_path = args
        .csv
        .clone()
        .unwrap_or_else(|| args.dir.join("summary.csv"));
    let text = summarize::csv(&summaries);
    batch::summary::write_atomically(&csv_path, text.as_bytes())?;
    let failed: Vec<String> = summaries
        .iter()
        .filter(|s| s.status == Status::Failed)
        .map(|s| format!("{} ({})", s.entry, s.name))
        .collect();
    println!(
        "summary: {} runs, {} ok, {} failed{}; {} columns in {}",
        summaries.len(),
        summaries.len() - failed.len(),
        failed.len(),
        if failed.is_empty() {
            String::new()
        } else {
            format!(": {}", failed.join(", "))
        },
        summarize::columns(&summaries).len(),
        csv_path.display()
    );
    if let (Some(y), Some(x)) = (&args.plot, &args.against) {
        let png = args
            .png
            .clone()
            .unwrap_or_else(|| args.dir.join(format!("{y}-against-{x}.png")));
        let plotted = summarize::plot(&summaries, y, x, &png)?;
        println!(
            "plot: {y} against {x}, {} runs{}, in {}",
            plotted.points,
            if plotted.left_out > 0 {
                format!(
                    " ({} left out: failed, or without a value)",
                    plotted.left_out
                )
            } else {
                String::new()
            },
            png.display()
        );
    }
    Ok(())
}
