//! `twin experiment`: reproduce a source paper's figures from the twin's models.

use super::progress::Progress;
use anyhow::{Result, bail};
use clap::{Args, Subcommand};
use twin_lab::pwmcap::{
    self, BIT_RECOGNITION_DEFINITION, Confusion, IMPEDANCE_ROWS_OHM, ReliabilitySetup,
};

/// Reproduce a paper's figures from the twin's models, paper values beside.
#[derive(Debug, Args)]
pub struct ExperimentArgs {
    #[command(subcommand)]
    experiment: Experiment,
}

#[derive(Debug, Subcommand)]
enum Experiment {
    /// The PWM-capture paper's link (Park, Park & Kang): Table 2, bit-recognition reliability
    /// against added line impedance with and without start-width calibration,
    /// and the longest cable that decodes without errors.
    Pwmcap(PwmcapArgs),
    /// Three parallel EV modules, the master's speed reference sent to two
    /// slaves over PWM-capture (broadcast, designated) and Modbus RTU (115200
    /// baud, 1 Mbit/s): command-to-actuation latency and wheel tracking, read
    /// from the four recordings.
    Parallel(ParallelArgs),
}

/// Options of `twin experiment parallel`.
#[derive(Debug, Args)]
struct ParallelArgs {
    /// Folder for the four recordings (created if missing; recordings of the same
    /// name there are replaced).
    #[arg(long, default_value = "parallel-modules")]
    out_dir: std::path::PathBuf,
    /// Simulated seconds per variant (default: the scenarios' 6 s).
    #[arg(long, value_parser = super::numbers::above_zero)]
    duration: Option<f64>,
    /// Seed of every variant (default: the scenarios' own).
    #[arg(long, value_parser = super::numbers::whole::<u64>)]
    seed: Option<u64>,
}

/// Options of `twin experiment pwmcap`; the defaults are the model's fixed
/// parameters (see docs/protocols/pwmcap-line.md), not fitted to the paper.
#[derive(Debug, Args)]
struct PwmcapArgs {
    /// Seed of the test values, comparator noise and counter phase.
    #[arg(long, default_value_t = ReliabilitySetup::DEFAULT.seed, value_parser = super::numbers::whole::<u64>)]
    seed: u64,
    /// Test signals per impedance row.
    #[arg(long, default_value_t = ReliabilitySetup::DEFAULT.signals, value_parser = super::numbers::whole::<u32>)]
    signals: u32,
    /// Cable length of the reliability rows, m.
    #[arg(long, default_value_t = ReliabilitySetup::DEFAULT.line.cable_length_m, value_parser = super::numbers::zero_or_more)]
    length_m: f64,
    /// Shunt capacitance added in every reliability row, nF.
    #[arg(long, default_value_t = ReliabilitySetup::DEFAULT.added_shunt_farad * 1e9, value_parser = super::numbers::zero_or_more)]
    added_nf: f64,
    /// Comparator input noise, mV rms.
    #[arg(long, default_value_t = ReliabilitySetup::DEFAULT.line.noise_volts_rms * 1e3, value_parser = super::numbers::zero_or_more)]
    noise_mv: f64,
    /// Longest cable the clean-cable search tries, m (0 skips the search).
    #[arg(long, default_value_t = 1000.0, value_parser = super::numbers::zero_or_more)]
    cable_limit_m: f64,
    /// Step of the clean-cable search, m.
    #[arg(long, default_value_t = 10.0, value_parser = super::numbers::above_zero)]
    cable_step_m: f64,
    /// The cable as one lump of R and C (`lumped`), or as a distributed RC
    /// line reduced to the pole with its Elmore delay (`elmore`).
    #[arg(long, value_enum, default_value_t = CableArg::Lumped)]
    cable_model: CableArg,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum CableArg {
    Lumped,
    Elmore,
}

pub fn execute(args: &ExperimentArgs) -> Result<()> {
    match &args.experiment {
        Experiment::Pwmcap(args) => execute_pwmcap(args),
        Experiment::Parallel(args) => execute_parallel(args),
    }
}

fn execute_parallel(args: &ParallelArgs) -> Result<()> {
    use twin_lab::parallel::{VARIANTS, run_variant};
    if let Some(d) = args.duration
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--duration must be a positive number of seconds, got {d}");
    }
    println!(
        "Parallel modules: the master module's VEL to two slave modules, three identical EV modules, \
         set points 1500 / 2500 / 1000 rpm"
    );
    println!(
        "  {:<24} {:>9} {:>21} {:>16} {:>6} {:>19}  link errors",
        "scenario", "cycle", "latency mean / max", "updates skipped", "wrong", "wheel diff max/RMS"
    );
    let replaced = VARIANTS
        .iter()
        .filter(|name| args.out_dir.join(format!("{name}.mcap")).is_file())
        .count();
    for name in VARIANTS {
        let total_s = match args.duration {
            Some(d) => d,
            None => twin_sim::scenario::Scenario::load(name)?.duration_s,
        };
        let bar = Progress::simulated(name, total_s);
        let f = run_variant(name, &args.out_dir, args.duration, args.seed, |done| {
            bar.show(done)
        })?;
        bar.clear();
        let errors: u64 = ["timeout", "bad_check", "dropped"]
            .iter()
            .filter_map(|k| f.events.get(*k))
            .sum();
        let retries = f.events.get("retry").copied().unwrap_or(0);
        println!(
            "  {:<24} {:>6.3} ms {:>9.1} / {:>6.1} µs {:>7} of {:<6} {:>6} {:>7.2} / {:>5.2} rpm  {} ({} retries)",
            f.scenario,
            f.cycle_s * 1e3,
            f.latency_mean_s * 1e6,
            f.latency_max_s * 1e6,
            f.skipped,
            f.master_changes,
            f.wrong_values,
            f.track_max_rpm,
            f.track_rms_rpm,
            errors,
            retries
        );
    }
    println!(
        "recordings: {}{}",
        args.out_dir.display(),
        match replaced {
            0 => String::new(),
            n => format!(" (replaced the {n} there before)"),
        }
    );
    Ok(())
}

fn execute_pwmcap(args: &PwmcapArgs) -> Result<()> {
    if args.signals == 0 {
        bail!("--signals must be at least 1");
    }
    let mut setup = ReliabilitySetup::DEFAULT;
    setup.seed = args.seed;
    setup.signals = args.signals;
    setup.line.cable_length_m = args.length_m;
    setup.line.noise_volts_rms = args.noise_mv * 1e-3;
    setup.added_shunt_farad = args.added_nf * 1e-9;
    setup.line.cable_model = match args.cable_model {
        CableArg::Lumped => nodes::link::CableModel::Lumped,
        CableArg::Elmore => nodes::link::CableModel::Elmore,
    };
    setup.line.validate()?;

    print_table2();
    print_parameters(&setup);
    print_reliability(&setup)?;
    if args.cable_limit_m > 0.0 {
        let cable = pwmcap::longest_clean_cable(&setup, args.cable_step_m, args.cable_limit_m)?;
        println!();
        println!(
            "Longest cable without a bit error (nothing added, {} test signals per length, \
             {} m steps up to {} m; paper: up to 300 m):",
            setup.signals, cable.step_m, cable.limit_m
        );
        println!(
            "  initial coding (start {} ticks): {} m",
            setup.coding.start_ticks(),
            cable.uncalibrated_m
        );
        println!("  calibrated at each length:      {} m", cable.calibrated_m);
    }
    Ok(())
}

fn print_table2() {
    let t = pwmcap::table2();
    println!("Table 2: transfer time of 8 bytes / 8 symbols (paper | model)");
    println!(
        "  Modbus 1 Mbit/s, data bits only   64 µs (text), 62 µs (table) | {:7.3} µs",
        t.modbus_data_us
    );
    println!(
        "  Modbus 1 Mbit/s, with start bits  92 µs                       | {:7.3} µs",
        t.modbus_with_start_us
    );
    println!(
        "  PWM 8 × 256 ticks at 150 MHz      13.6 µs                     | {:7.3} µs",
        t.pwm_bare_us
    );
    println!(
        "  PWM, with 100-tick start symbol   14.3 µs                     | {:7.3} µs",
        t.pwm_with_start_us
    );
    println!(
        "  speed-up, data / with start       ~4.7× / up to 6×            | {:.2}× / {:.2}×",
        t.speedup_data, t.speedup_with_start
    );
    println!(
        "  twin's real frame (start + 8 symbols of S + C_max): {:.3} µs with Table 2's \
         coding, {:.3} µs with the paper's 10-bit coding and 200-tick start",
        t.twin_table2_coding_us, t.twin_paper_coding_us
    );
}

fn print_parameters(setup: &ReliabilitySetup) {
    let line = &setup.line;
    println!();
    println!(
        "Line model (fixed from datasheets before any figure was computed; docs/protocols/pwmcap-line.md):"
    );
    println!(
        "  driver {} Ω, cable {} Ω/m loop and {} pF/m × {} m, receiver {} pF, \
         {} V drive, threshold {} V, comparator noise {} mV rms",
        line.driver_ohm,
        line.cable_ohm_per_m,
        line.cable_farad_per_m * 1e12,
        line.cable_length_m,
        line.receiver_input_farad * 1e12,
        line.drive_volts,
        line.threshold_volts,
        line.noise_volts_rms * 1e3
    );
    if line.cable_model == nodes::link::CableModel::Elmore {
        println!(
            "  cable as a distributed RC line: the pole with its Elmore delay (--cable-model elmore)"
        );
    }
    println!(
        "  coding: {} MHz counter, {} data + {} dummy bits, start {} ticks; \
         added shunt C {} nF in every row",
        setup.coding.clock_hz() / 1_000_000,
        setup.coding.data_bits(),
        setup.coding.dummy_bits(),
        setup.coding.start_ticks(),
        setup.added_shunt_farad * 1e9
    );
}

fn print_reliability(setup: &ReliabilitySetup) -> Result<()> {
    let rows = pwmcap::reliability(setup)?;
    println!();
    println!(
        "Bit recognition, {} test signals per row ({} bits):",
        setup.signals,
        setup.signals as usize * pwmcap::VALUES_PER_SIGNAL * 8
    );
    for line in BIT_RECOGNITION_DEFINITION.lines() {
        println!("  {line}");
    }
    println!(
        "  {:>6} {:>7} {:<12} {:>8} {:>9} {:>7} {:>7} {:>6} {:>6} {:>6} {:>6}",
        "+R Ω", "τ ticks", "mode", "accuracy", "precision", "recall", "F1", "TP", "FP", "FN", "TN"
    );
    for row in &rows {
        let print = |mode: &str, c: &Confusion| {
            println!(
                "  {:>6} {:>7.1} {:<12} {:>8.4} {:>9.4} {:>7.4} {:>7.4} {:>6} {:>6} {:>6} {:>6}",
                row.added_series_ohm,
                row.tau_ticks,
                mode,
                c.accuracy(),
                c.precision(),
                c.recall(),
                c.f1(),
                c.true_positive,
                c.false_positive,
                c.false_negative,
                c.true_negative
            );
        };
        print("initial", &row.uncalibrated);
        print("calibrated", &row.calibrated);
        match row.calibration {
            Some(cal) => println!(
                "  {:>6} calibration: start {} ticks, guard {} ticks, {} training frames",
                "",
                cal.coding.start_ticks(),
                cal.guard_ticks,
                cal.frames_sent
            ),
            None => println!("  {:>6} calibration: no start width found", ""),
        }
    }
    println!(
        "  paper ({} Ω rows): accuracy ≥ 0.985 at ≤ 5 Ω, 0.94 at 20 Ω; precision 0.99 / 0.912, \
         recall ≥ 0.98 / 0.97 (≤ 5 Ω / 20 Ω); no calibrated figures given",
        IMPEDANCE_ROWS_OHM.map(|r| r.to_string()).join(", ")
    );
    Ok(())
}
