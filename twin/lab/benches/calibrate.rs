//! How long the shipped calibrations take: the goal is under a minute for
//! 4–6 parameters against a 4-second log (Rust nodes, this 2-core machine).
//!
//! `cargo bench -p twin-lab --bench calibrate` — each figure is one whole
//! calibration (the scan, both searches, the error bars), as `twin
//! calibrate` runs it, without the plots.

use criterion::{Criterion, criterion_group, criterion_main};
use std::path::{Path, PathBuf};
use std::time::Duration;
use twin_lab::calibrate::{self, Job, Options, apply};
use twin_sim::scenario::Scenario;

fn shipped(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../recordings/calibration")
        .join(file)
}

/// The EV module's stand-in recording, made once: the stand-in scenario
/// with its own parameters, recorded as `twin run` records it.
fn stand_in_recording() -> PathBuf {
    let scenario = Scenario::load(&shipped("ev-module-stand-in.toml").display().to_string())
        .expect("stand-in scenario");
    let params: toml::Table = std::fs::read_to_string(shipped("ev-module-stand-in-params.toml"))
        .expect("stand-in parameters")
        .parse()
        .expect("a table");
    let mut paths = Vec::new();
    let mut values = Vec::new();
    for (table, fields) in &params {
        for (key, value) in fields.as_table().expect("a table of numbers") {
            paths.push(format!("{table}.{key}"));
            values.push(value.as_float().expect("a number"));
        }
    }
    let scenario = apply::with_values(&scenario, &paths, &values);
    let out = std::env::temp_dir().join(format!("twin-bench-{}-ev1-step.mcap", std::process::id()));
    twin_sim::virtual_run::run(&scenario, &out, |_| {}).expect("the stand-in runs");
    out
}

fn calibrations(c: &mut Criterion) {
    let mut g = c.benchmark_group("calibrate");
    // A calibration is seconds long: ten of them are the fewest criterion
    // takes, and they are the figure.
    g.sample_size(10).measurement_time(Duration::from_secs(60));
    let options = Options::default();
    let network = Job::load(&shipped("controller-network-step.toml")).expect("job");
    g.bench_function("controller-network-step/4-parameters", |b| {
        b.iter(|| calibrate::calibrate(&network, options, &|_| {}).expect("calibrates"))
    });
    let recording = stand_in_recording();
    let ev = Job::load_with_log(&shipped("ev-module-step.toml"), Some(&recording)).expect("job");
    g.bench_function("ev-module-step/3-parameters", |b| {
        b.iter(|| calibrate::calibrate(&ev, options, &|_| {}).expect("calibrates"))
    });
    g.finish();
    let _ = std::fs::remove_file(&recording);
}

criterion_group!(benches, calibrations);
criterion_main!(benches);
