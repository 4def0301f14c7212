//! `twin sweep`: the light sensor's rpm against the true wheel rpm over a
//! range of speeds, and where it stops seeing the flag.

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use std::path::PathBuf;
use twin_lab::sweep::{self, SweepConfig, SweepReport};

use super::output::Earlier;

use super::progress::Progress;

/// Light-sensor rpm against true rpm over a range of speeds: where the flag is lost.
///
/// Runs the wheel open loop at each speed and holds the light sensor's rpm
/// against the true rpm: below the fastest speed the photoresistor sees
/// (worked out from the flag's angle, the cell's time constants and the
/// detector's threshold, and printed here) it tracks, above it the
/// reading falls to 0 or to a fraction of the speed.
///
/// Each speed is reached with the VEL the DC motor's steady state asks for,
/// held for `--settle` seconds, then averaged over `--measure` seconds (at
/// least four and three turns of the wheel). Prints a
/// table and writes sweep.json and sweep.png into the current folder, replacing
/// those there; with `--out DIR` into DIR, with one recording per speed in
/// DIR/runs/.
#[derive(Debug, Args)]
pub struct SweepArgs {
    #[command(flatten)]
    plant: super::plant_args::PlantArgs,
    /// The EV controller's light detector: fixed threshold, adaptive, or both.
    #[arg(long, value_enum, default_value_t = Detector::Both)]
    detector: Detector,
    /// Lowest and highest wheel speed (rpm) [default: 50 and 1.6 × the detector's limit].
    #[arg(long, value_name = "RPM", num_args = 2, value_names = ["FROM", "TO"], value_parser = super::numbers::above_zero)]
    rpm: Option<Vec<f64>>,
    /// Number of speeds, evenly spaced.
    #[arg(long, default_value_t = 24, value_name = "N", value_parser = super::numbers::whole::<usize>)]
    points: usize,
    /// Time to reach each speed before measuring (s).
    #[arg(long, default_value_t = 3.0, value_name = "SECONDS", value_parser = super::numbers::above_zero)]
    settle: f64,
    /// Time measured at each speed (s).
    #[arg(long, default_value_t = 3.0, value_name = "SECONDS", value_parser = super::numbers::above_zero)]
    measure: f64,
    /// Seed of the sensor noise.
    #[arg(long, default_value_t = 1, value_parser = super::numbers::whole::<u64>)]
    seed: u64,
    /// Folder for sweep.json, sweep.png and the runs' recordings [default: the
    /// figures and the plot in the current folder, no recordings].
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Detector {
    Fixed,
    Adaptive,
    Both,
}

pub fn execute(args: &SweepArgs) -> Result<()> {
    let params = args.plant.load()?;
    if args.points < 2 {
        bail!("--points must be at least 2, got {}", args.points);
    }
    // The Controller_network light-sensor Nano has one detector.
    let detectors: &[bool] = match (args.plant.preset.as_str(), args.detector) {
        ("controller-network", _) => &[false],
        (_, Detector::Fixed) => &[false],
        (_, Detector::Adaptive) => &[true],
        (_, Detector::Both) => &[false, true],
    };
    let speeds = |adaptive: bool| -> Result<Vec<f64>> {
        let (from, to) = match args.rpm.as_deref() {
            Some([a, b]) => (*a, *b),
            _ => {
                let (_, limit) =
                    twin_lab::instruments::light_limit(&params, &args.plant.preset, adaptive);
                (50.0, (1.6 * limit).round())
            }
        };
        if !(from > 0.0 && to > from) {
            bail!("--rpm FROM TO needs 0 < FROM < TO, got {from} {to}");
        }
        Ok((0..args.points)
            .map(|i| from + (to - from) * i as f64 / (args.points - 1) as f64)
            .collect())
    };
    let runs_dir = match &args.out {
        Some(dir) => {
            let runs = dir.join("runs");
            std::fs::create_dir_all(&runs)
                .with_context(|| format!("cannot create folder {}", runs.display()))?;
            Some(runs)
        }
        None => None,
    };
    let mut reports = Vec::new();
    let progress = Progress::fraction("sweep");
    for (i, &adaptive) in detectors.iter().enumerate() {
        let config = SweepConfig {
            params: params.clone(),
            preset: args.plant.preset.clone(),
            adaptive,
            target_rpm: speeds(adaptive)?,
            settle_s: args.settle,
            measure_s: args.measure,
            seed: args.seed,
        };
        let dir = runs_dir
            .as_ref()
            .map(|d| d.join(if adaptive { "adaptive" } else { "fixed" }));
        if let Some(d) = &dir {
            std::fs::create_dir_all(d)
                .with_context(|| format!("cannot create folder {}", d.display()))?;
        }
        let n = detectors.len() as f64;
        let report = sweep::run(&config, dir.as_deref(), |f| {
            progress.show((i as f64 + f) / n)
        })?;
        reports.push(report);
    }
    progress.clear();
    for r in &reports {
        print_report(r);
    }
    // The current folder as `sweep.json`, not `./sweep.json`.
    let dir = args.out.clone().unwrap_or_default();
    let json = dir.join("sweep.json");
    let png = dir.join("sweep.png");
    let earlier = [&json, &png].map(|p| Earlier::at(p));
    std::fs::write(&json, serde_json::to_string_pretty(&reports)? + "\n")
        .with_context(|| format!("cannot write {}", json.display()))?;
    println!(
        "figures: {}{}",
        json.display(),
        Earlier::note(earlier[0].as_ref())
    );
    let png = sweep::plot(&reports, &png)?;
    println!(
        "plot: {}{}",
        png.display(),
        Earlier::note(earlier[1].as_ref())
    );
    if let Some(runs) = &runs_dir {
        println!("recordings: {}", runs.display());
    }
    Ok(())
}

fn print_report(r: &SweepReport) {
    println!(
        "twin sweep: {} preset, light detector {}",
        r.preset, r.light_detector
    );
    println!(
        "  by the light sensor's model (flag angle, photoresistor time constants, threshold): \
         the flag is seen up to {:.0} rpm; every dip lasts a sample below the threshold up to {:.0} rpm",
        r.light_limit_rpm, r.every_dip_sampled_below_rpm
    );
    println!(
        "  {:>6} {:>10} {:>10} {:>10} {:>10}",
        "VEL %", "true rpm", "motor rpm", "light rpm", "light/true"
    );
    for p in &r.points {
        println!(
            "  {:>6.2} {:>10.1} {:>10.1} {:>10.1} {:>10.3}{}",
            p.vel_fraction * 100.0,
            p.wheel_rpm,
            p.motor_rpm,
            p.light_rpm,
            p.light_ratio,
            if p.tracks { "" } else { "  ✗" }
        );
    }
    let pct = r.tolerance * 100.0;
    match (r.tracks_from_rpm, r.tracks_up_to_rpm, r.first_failure_rpm) {
        (Some(a), Some(b), Some(bad)) => println!(
            "  tracks within {pct:.0} % from {a:.0} to {b:.0} rpm; fails from {bad:.0} rpm (formula: {:.0} rpm)",
            r.light_limit_rpm
        ),
        (Some(a), Some(b), None) => {
            println!("  tracks within {pct:.0} % from {a:.0} to {b:.0} rpm, the fastest point run")
        }
        _ => println!("  does not track within {pct:.0} % at any speed run"),
    }
}
