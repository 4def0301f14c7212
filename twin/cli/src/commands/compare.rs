//! `twin compare`: hold a run against a baseline, signal by signal.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use twin_recording::compare::{self, Tolerances};
use twin_recording::identity::Identity;
use twin_recording::{Recording, Signals};

/// Differences in the run's settings printed before the rest are summed up.
const SHOWN_DIFFERENCES: usize = 8;

/// Compare a recording with a baseline recording, signal by signal
///
/// Every numeric field of every channel is a signal (`/plant/ev1/sensors.wheel_rpm`,
/// `/master/supervisor/loop.loops.0.measured_rpm`, …). For each baseline sample
/// the run's value is looked up at the same time (interpolated between sensor
/// samples, held between events; anywhere within the signal's time shift) and
/// must lie within `abs + rel·|baseline|`. Prints, per signal beyond tolerance,
/// when it first went beyond and its worst sample, and exits non-zero if any
/// signal is beyond its tolerance or missing from the run. A recording cut short is compared up to
/// its last complete chunk.
///
/// First the two recordings' runs are held against each other (their `twin.run`
/// records): whatever differs is printed before any signal, the seed, the
/// duration and every setting of the scenario or bench by its dotted path
/// (`node.supervisor.kp`). Recordings of different runs (another scenario or
/// bench, or another kind of run) are refused, as their signals do not match up,
/// unless --force is given.
///
/// The defaults (abs 1e-9, rel 1e-9, no time shift) hold a deterministic re-run
/// to its baseline. A tolerance file loosens them, per signal pattern (`*` any
/// run of characters, `?` one; the last matching rule wins):
///
///   [default]
///   abs = 1e-6
///   [[signal]]
///   pattern = "/plant/*/sensors.*rpm"
///   abs = 5.0
///   rel = 0.01
///   time_shift_s = 0.02
///   [[signal]]
///   pattern = "/bus/*"
///   ignore = true
#[derive(Debug, Args)]
#[command(verbatim_doc_comment)]
pub struct CompareArgs {
    /// The recording to check.
    #[arg(value_name = "RUN.mcap")]
    run: PathBuf,
    /// The reference recording.
    #[arg(value_name = "BASELINE.mcap")]
    baseline: PathBuf,
    /// Tolerance file (TOML): `[default]` and `[[signal]]` rules.
    #[arg(long, value_name = "FILE.toml")]
    tolerances: Option<PathBuf>,
    /// Print every signal, not only the ones beyond tolerance.
    #[arg(long)]
    all: bool,
    /// Compare recordings of different scenarios, benches or kinds of run anyway.
    #[arg(long)]
    force: bool,
}

pub fn execute(args: &CompareArgs) -> Result<()> {
    let tolerances = match &args.tolerances {
        Some(p) => Tolerances::load(p)?,
        None => Tolerances::default(),
    };
    let run = Signals::read(&args.run)?;
    let baseline = Signals::read(&args.baseline)?;
    println!(
        "twin compare: {} against baseline {}",
        args.run.display(),
        args.baseline.display()
    );
    refuse_empty_or_cut(&run.recording, &baseline.recording)?;
    same_run_or_force(&run.recording, &baseline.recording, args.force)?;
    for (r, what) in [(&run.recording, "run"), (&baseline.recording, "baseline")] {
        if let Some(why) = &r.truncated {
            println!("  {what} {}: {why}", r.path.display());
        }
    }
    let c = compare::compare(&run, &baseline, &tolerances);
    if let Some(note) = &c.span_note {
        println!("  {note}");
    }
    // Said before any figure: of runs of different lengths only the
    // stretch both cover is compared, and they cannot pass as one.
    let like_the_baseline = c.span_mismatch.as_ref().map(|m| {
        println!(
            "  the lengths differ: {m}; compared over the first {:.3} s, which both cover",
            c.compared_until_s
        );
        let how = rerun_like(&run.recording, &baseline.recording);
        println!("  {how}");
        how
    });
    let failures = c.failures().count();
    if failures > 0 || args.all {
        print!("{}", compare::table(&c, args.all));
    }
    if !c.only_in_run.is_empty() {
        println!(
            "  {} signal(s) only in the run (not compared): {}",
            c.only_in_run.len(),
            c.only_in_run.join(", ")
        );
    }
    let samples: usize = c.rows.iter().map(|r| r.samples).sum();
    println!(
        "  {} signals, {} samples compared{}: {} within tolerance, {} beyond",
        c.rows.len(),
        samples,
        if c.ignored > 0 {
            format!(" ({} ignored)", c.ignored)
        } else {
            String::new()
        },
        c.rows.len() - failures,
        failures
    );
    if samples == 0 {
        bail!(
            "nothing was compared: no signal of the baseline has a sample the tolerances do not ignore"
        );
    }
    if let Some(how) = like_the_baseline
        && c.failures().next().is_none()
    {
        bail!(
            "the run and the baseline differ in length, so the run cannot pass for the \
             baseline, though over the first {:.3} s every signal is within tolerance; {how}",
            c.compared_until_s
        );
    }
    if !c.passed() {
        let first = c
            .failures()
            .filter_map(|r| Some((r.first_beyond_s?, r)))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(t, r)| format!(": first {} at {t:.3} s", r.signal))
            .unwrap_or_default();
        bail!("the run departs from the baseline{first}");
    }
    println!("  PASS");
    Ok(())
}

/// How to record a run as long as the baseline, with its settings: the
/// baseline's own duration, seed and `--set`s, read from its `twin.run`
/// record (a baseline is a cut-down of its scenario).
fn rerun_like(run: &Recording, baseline: &Recording) -> String {
    let (a, b) = (Identity::of(run), Identity::of(baseline));
    let duration = b.get("duration_s").and_then(|d| d.parse::<f64>().ok());
    let (Some(scenario), Some(duration), Some("scenario"), None) = (
        b.get("scenario"),
        duration,
        b.get("kind"),
        b.get("experiment"),
    ) else {
        return match duration {
            Some(d) => {
                format!("to compare like with like, record the run {d} s long, as the baseline")
            }
            None => "to compare like with like, record the run as long as the baseline".into(),
        };
    };
    let mut words = vec![format!("twin run {scenario} --duration {duration}")];
    let differences = a.differences(&b);
    // Of another scenario or kind of run, every setting differs: the
    // scenario's own are the baseline's then, with its seed.
    let of_another_run = differences.iter().any(|d| d.of_what_ran());
    for d in &differences {
        if d.field == "duration_s" || (of_another_run && d.field != "seed") {
            continue;
        }
        // A setting the run's record lacks is no setting it changed.
        let (Some(_), Some(value)) = (&d.first, &d.second) else {
            continue;
        };
        let plain = value
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "._-".contains(c));
        words.push(match (d.field.as_str(), plain) {
            ("seed", _) => format!("--seed {value}"),
            (field, true) => format!("--set {field}={value}"),
            (field, false) => format!("--set '{field}={value}'"),
        });
    }
    words.push("--out run.mcap".into());
    format!(
        "to compare like with like, record the run as the baseline was: `{}`",
        words.join(" ")
    )
}

/// Say first what differs between the two runs; refuse recordings of
/// different runs unless `force`.
fn same_run_or_force(run: &Recording, baseline: &Recording, force: bool) -> Result<()> {
    let (a, b) = (Identity::of(run), Identity::of(baseline));
    for (identity, r, what) in [(&a, run, "run"), (&b, baseline, "baseline")] {
        if identity.is_empty() {
            println!(
                "  the {what} {} has no `twin.run` record: what it ran cannot be checked",
                r.path.display()
            );
        }
    }
    if a.is_empty() || b.is_empty() {
        return Ok(());
    }
    let differences = a.differences(&b);
    if differences.is_empty() {
        return Ok(());
    }
    let other_runs: Vec<_> = differences.iter().filter(|d| d.of_what_ran()).collect();
    if other_runs.is_empty() {
        println!("  the run's settings differ from the baseline's:");
    } else {
        println!("  the recordings come from different runs:");
        println!("    run       {}", a.describe());
        println!("    baseline  {}", b.describe());
    }
    // Of different runs, every setting differs: what ran, the seed and the
    // length say it; of one run, the settings changed are the point.
    let shown: Vec<_> = if other_runs.is_empty() {
        differences.iter().take(SHOWN_DIFFERENCES).collect()
    } else {
        differences
            .iter()
            .filter(|d| d.of_what_ran() || d.of_seed_or_length())
            .collect()
    };
    let width = shown.iter().map(|d| d.field.len()).max().unwrap_or(0);
    for d in &shown {
        println!("    {:width$}  run {d}", d.field);
    }
    if differences.len() > shown.len() {
        println!(
            "    and {} {}setting(s) of the scenario or bench",
            differences.len() - shown.len(),
            if shown.is_empty() { "" } else { "more " }
        );
    }
    if !other_runs.is_empty() && !force {
        let what: Vec<String> = other_runs
            .iter()
            .map(|d| format!("{} ({})", d.field, d))
            .collect();
        bail!(
            "the run and the baseline are recordings of different runs, so their signals do not \
             match up: they differ in {}. Compare a run with a baseline of the same scenario \
             (`twin run NAME --out run.mcap`, then `twin compare run.mcap BASELINE.mcap`), or \
             give --force to compare them anyway",
            what.join(", ")
        );
    }
    Ok(())
}

/// A comparison against nothing is no pass: a baseline (or run) with no
/// message, or a baseline cut short, fails with what to do about it.
fn refuse_empty_or_cut(run: &Recording, baseline: &Recording) -> Result<()> {
    for (r, what) in [(baseline, "baseline"), (run, "run")] {
        if r.message_count() == 0 {
            bail!(
                "the {what} {}: there is nothing to compare",
                r.holds_no_messages()
            );
        }
    }
    if let Some(cut) = &baseline.truncated {
        bail!(
            "the baseline {} is not whole: {cut}. A baseline must be complete to hold a run \
             against: make it whole with `twin recover` or record it again",
            baseline.path.display()
        );
    }
    Ok(())
}
