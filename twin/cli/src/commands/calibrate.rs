//! `twin calibrate`: fit the plant's parameters to a log of the real bench.

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use twin_lab::calibrate::{self, Job, Options, Outcome, short};

use super::output::Earlier;
use super::progress::Progress;

/// Fit the plant's parameters to a log of the real bench (system identification).
///
/// JOB is a calibration file (TOML): the measured log (a CSV file, or an MCAP
/// recording that `twin supervise` made of a real module), which of its
/// columns or signals are the measured ones (and in what units), the step
/// that was applied or the signal holding the set point, the scenario that
/// ran the experiment,
/// and the parameters to fit, each by its path in a plant parameter file
/// with bounds and a starting value. The twin runs the same experiment on
/// the virtual clock with the node code the bench ran, and a Nelder–Mead
/// search (two at once, one per core) changes the parameters until what the
/// twin's master reads matches the log.
///
/// Prints each fitted value with its standard error, the fit per signal (NRMSE
/// FIT %, raw and on 100 ms averages, in the fit window and in the check
/// window left out of the fit), pairs of parameters the log cannot tell apart,
/// and the step figures of bench and twin. Writes calibrate.json,
/// calibrate.png, calibrate-residual.png and the fitted values as a plant
/// parameter file (calibrated-params.toml, for `--params` or a scenario
/// module's `params`) into the current folder or `--out DIR`.
///
/// The Controller_network bench's step response is shipped as an example:
/// `twin calibrate recordings/calibration/controller-network-step.toml`; so
/// is a calibration of the EV module from a supervisor's recording,
/// `recordings/calibration/ev-module-step.toml` (give it the recording with
/// `--log`).
#[derive(Debug, Args)]
pub struct CalibrateArgs {
    /// The calibration file (TOML).
    #[arg(value_name = "JOB")]
    job: PathBuf,
    /// Most Nelder–Mead iterations of each simplex (a search restarts its
    /// simplex, smaller, up to three times while that improves).
    #[arg(long, default_value_t = 150, value_name = "N", value_parser = clap::value_parser!(u64).range(1..=100_000))]
    max_iterations: u64,
    /// The measured log to fit, in place of the one the calibration file
    /// names: a CSV file, or an MCAP recording (`twin supervise` of a real
    /// module, or a run of the twin) if its name ends in `.mcap`.
    #[arg(long, value_name = "FILE")]
    log: Option<PathBuf>,
    /// Folder for the results (created if needed) [default: the current folder].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
}

pub fn execute(args: &CalibrateArgs) -> Result<()> {
    let job = Job::load_with_log(&args.job, args.log.as_deref())?;
    let dir = args.out.clone().unwrap_or_default();
    if args.out.is_some() {
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create folder {}", dir.display()))?;
    }
    let names = [
        "calibrate.json",
        "calibrated-params.toml",
        "calibrate.png",
        "calibrate-residual.png",
    ];
    let [json, params, png, residual] = names.map(|f| dir.join(f));
    let earlier = [&json, &params, &png, &residual].map(|p| Earlier::at(p));
    println!(
        "twin calibrate: {} of scenario {} against {} ({})",
        count(job.parameters.len(), "parameter"),
        job.scenario.name,
        job.log.display(),
        count(job.signals.len(), "signal")
    );
    let options = Options {
        max_iterations: args.max_iterations,
    };
    // Two searches of about 1.5 simulations per iteration, plus the error bars.
    let expected = (2 * (options.max_iterations * 3 / 2 + job.parameters.len() as u64 + 1)
        + 2 * job.parameters.len() as u64) as f64;
    let progress = Progress::fraction("calibration");
    let outcome = calibrate::calibrate(&job, options, &|n| {
        progress.show((n as f64 / expected).min(0.99));
    })?;
    progress.clear();
    print_outcome(&outcome);
    std::fs::write(&json, serde_json::to_string_pretty(&outcome)? + "\n")
        .with_context(|| format!("cannot write {}", json.display()))?;
    println!(
        "figures: {}{}",
        json.display(),
        Earlier::note(earlier[0].as_ref())
    );
    std::fs::write(&params, calibrate::params_toml(&outcome)?)
        .with_context(|| format!("cannot write {}", params.display()))?;
    println!(
        "fitted parameters: {}{} (give it to --params, or copy it into a scenario module's params)",
        params.display(),
        Earlier::note(earlier[1].as_ref())
    );
    let drawn = calibrate::draw(&job, &outcome, &dir)?;
    for (path, earlier) in drawn.iter().zip(&earlier[2..]) {
        println!(
            "plot: {}{}",
            path.display(),
            Earlier::note(earlier.as_ref())
        );
    }
    Ok(())
}

/// `1 signal`, `2 signals`.
fn count(n: usize, what: &str) -> String {
    if n == 1 {
        format!("1 {what}")
    } else {
        format!("{n} {what}s")
    }
}

fn print_outcome(o: &Outcome) {
    println!(
        "  {} after {} iterations, {} simulations{}; cost {} (start {})",
        o.stopped,
        o.iterations,
        o.simulations,
        if o.refused_simulations > 0 {
            format!(" ({} refused by the plant)", o.refused_simulations)
        } else {
            String::new()
        },
        short(o.cost),
        short(o.cost_start)
    );
    println!(
        "  {:34} {:>12} {:>12} {:>12}",
        "parameter", "start", "fitted", "± 1 s.e."
    );
    for p in &o.parameters {
        let se = p.std_error.map_or("—".to_string(), short);
        let note = if p.at_bound { "  at its bound" } else { "" };
        println!(
            "  {:34} {:>12} {:>12} {:>12}{note}",
            p.path,
            short(p.start),
            short(p.value),
            se
        );
    }
    for e in &o.entangled {
        println!(
            "  cannot tell apart: {} and {} (correlation {:+.2}); {}",
            e.a, e.b, e.correlation, e.separate_by
        );
    }
    for u in &o.unseen {
        println!("  not determined: no reading in the log changes with {u}");
    }
    // A recording's signals have long names; the column is as wide as they.
    let w = o
        .fit
        .iter()
        .map(|f| "check ".len() + f.column.chars().count())
        .fold(18, usize::max);
    println!(
        "  {:w$} {:>14} {:>10} {:>12} {:>12} {:>11}",
        "fit (NRMSE FIT %)", "window (s)", "raw", "100 ms avg", "bench mean", "twin mean"
    );
    let pct = |v: Option<f64>| v.map_or("—".to_string(), |v| format!("{v:.1} %"));
    for (label, fits) in [
        ("fit", &o.fit),
        ("check", &o.check),
        ("start", &o.fit_at_start),
    ] {
        for f in fits {
            println!(
                "  {:w$} {:>14} {:>10} {:>12} {:>12.0} {:>11.0}",
                format!("{label} {}", f.column),
                format!("{:.2}–{:.2}", f.window_s.0, f.window_s.1),
                pct(f.fit_raw_pct),
                pct(f.fit_averaged_pct),
                f.measured_mean,
                f.twin_mean
            );
        }
    }
    let secs = |v: Option<f64>| v.map_or("—".to_string(), |s| format!("{s:.3} s"));
    for s in &o.steps {
        let (m, t) = (s.measured.as_ref(), s.twin.as_ref());
        println!(
            "  step {}: rise 10–90 {} bench, {} twin; overshoot {} bench, {} twin",
            s.column,
            secs(m.and_then(|m| m.rise_time_s)),
            secs(t.and_then(|m| m.rise_time_s)),
            m.map_or("—".into(), |m| format!("{:.1} %", m.overshoot_pct)),
            t.map_or("—".into(), |m| format!("{:.1} %", m.overshoot_pct)),
        );
        let passes: Vec<String> = s
            .crossings
            .iter()
            .map(|(level, b, t)| format!("{level:.0} at +{} / +{}", secs(*b), secs(*t)))
            .collect();
        println!("    passes (bench / twin): {}", passes.join(", "));
    }
}
