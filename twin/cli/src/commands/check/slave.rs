//! `twin check slave`: the student's module controller, sent requests by
//! the twin; one student, or a class from a roster.

use anyhow::{Result, bail};
use clap::Args;
use std::path::Path;
use twin_check::bench::{Converters, MAP_BITS};
use twin_check::class;
use twin_check::{Bench, Suite, record, report, run_suite_on, wire::Wire};

#[derive(Debug, Args)]
pub struct SlaveArgs {
    /// Where the slave is: tcp://HOST:PORT, or a serial device or
    /// pseudo-terminal (PATH?baud=9600&parity=E).
    #[arg(required_unless_present = "roster", conflicts_with = "roster")]
    link: Option<String>,
    /// The slave's id (MEB: the M3CVME tool's device number, 1-99; Modbus:
    /// the unit id, 1-247); with --roster, of every student whose line
    /// gives none. The 8-byte Modbus suite addresses the Controller_network
    /// project's own ids, 01 and 02.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=247))]
    id: u8,
    /// The suite: a built-in one's name (--list: meb-slave,
    /// modbus-rtu-slave, modbus-tcp-slave, modbus8-slave) or a TOML file.
    #[arg(long, default_value = "meb-slave", value_name = "NAME|FILE")]
    suite: String,
    /// A reply's deadline in ms where the suite's steps set none (the suite's
    /// own otherwise: 100 ms for MEB, the MEB page's master timeout, and
    /// for the 8-byte Modbus; 200 ms for Modbus RTU and TCP). Give a slow
    /// board more.
    #[arg(long, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..=60_000))]
    timeout_ms: Option<u64>,
    /// Wait FACTOR times as long for a slow program (a sketch that does
    /// much between reads, a loaded machine): every reply's deadline,
    /// silence and wait of the suite, said in the report's first line. The
    /// timing checks keep the protocol's deadlines, and a reply later than
    /// the suite's own deadline is noted under its check.
    #[arg(long, default_value_t = 1.0, value_name = "FACTOR", value_parser = patience)]
    patience: f64,
    /// The bench the slave is wired to: the panel of its twin session
    /// (`twin serve --web`), http://HOST:PORT[/?token=…]. Its bench checks
    /// then hold the slave to what its registers mean on the plant (VEL
    /// moves the motor, EN, BRK and FR do what the map says, the inputs
    /// match the plant); without it they are not applicable. With
    /// --roster, each student's bench is the roster's `bench` column.
    #[arg(long, value_name = "URL")]
    bench: Option<String>,
    /// The bits of the slave's ADC, where fewer than the map's 12: an
    /// Arduino's (a sketch in twin-avr) has 10. The inputs it reads back
    /// are then held to one step of it and a count of rounding (5 counts
    /// for 10 bits) instead of one count.
    #[arg(long, value_name = "BITS", requires = "bench", default_value_t = MAP_BITS,
          value_parser = clap::value_parser!(u8).range(1..=12))]
    adc_bits: u8,
    /// The bits VEL reaches the bench with, where fewer than the map's 12:
    /// an Arduino's PWM (10 bits on Timer1, 8 by analogWrite) through the
    /// bench's RC filter. The plant's speed input is then held to one step
    /// of it and the PWM's ripple (0.1 V), the motor's speed to one step.
    #[arg(long, value_name = "BITS", requires = "bench", default_value_t = MAP_BITS,
          value_parser = clap::value_parser!(u8).range(1..=12))]
    vel_bits: u8,
    #[command(flatten)]
    reports: super::reports::ReportArgs,
}

/// One student's slave checked, or a class's from a roster.
pub fn execute(slave: &SlaveArgs) -> Result<()> {
    let mut suite = Suite::load(&slave.suite)?;
    let ids = suite.protocol.ids();
    if !ids.contains(&slave.id) {
        bail!(
            "--id {}: the {} suite's slaves have ids {} to {}",
            slave.id,
            suite.name,
            ids.start(),
            ids.end()
        );
    }
    if let Some(ms) = slave.timeout_ms {
        suite.timeout_ms = ms;
    }
    suite.patience = slave.patience;
    if let Some(roster) = &slave.reports.roster {
        if slave.bench.is_some() {
            bail!(
                "--bench is one slave's bench: with --roster, give each student's in the roster's `bench` column (the panel of the twin session their slave is wired to)"
            );
        }
        return class(slave, &suite, roster);
    }
    let link = slave.link.as_deref().unwrap_or_default();
    let bench = match &slave.bench {
        Some(url) => Some(
            Bench::connect(url)
                .map_err(|why| anyhow::anyhow!("--bench: {why}"))?
                .with_converters(Converters {
                    adc_bits: slave.adc_bits,
                    vel_bits: slave.vel_bits,
                }),
        ),
        None => None,
    };
    let mut wire = Wire::open(link)?;
    let run = run_suite_on(&suite, &mut wire, slave.id, bench.as_ref());
    print!("{}", report::text(&run));
    slave
        .reports
        .record("slave", &record::suite_toml(&slave.suite), &run)?;
    slave.reports.reports_and_verdict(&run)
}

/// `--patience`: 1 to 100.
fn patience(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(f) if (1.0..=100.0).contains(&f) => Ok(f),
        _ => Err(format!(
            "`{text}`: patience is a factor from 1 (the suite's waits as written) to 100"
        )),
    }
}

/// Every student of the roster checked (see [`super::class`]).
fn class(slave: &SlaveArgs, suite: &Suite, roster: &Path) -> Result<()> {
    let students = class::load_roster(roster, slave.id, suite.protocol)?;
    let toml = (!slave.reports.no_record).then(|| record::suite_toml(&slave.suite));
    let options = super::class::Class {
        suite_name: &suite.name,
        suite_arg: &slave.suite,
        role: "slave",
        out: slave.reports.out.as_deref(),
        jobs: slave.reports.jobs,
        suite_toml: toml.as_deref(),
    };
    super::class::run(&options, &students, |student| class::check(suite, student))
}
