//! `--preset` and `--params`: the bench to simulate, as `twin run
//! --open-loop`, `twin step --open-loop` and `twin sweep` take it; closed
//! loop, `--params` changes every module of the scenario.

use anyhow::{Context, Result, bail};
use clap::Args;
use plant::PlantParams;
use plant::params::PRESETS;
use std::path::{Path, PathBuf};
use twin_sim::scenario::Scenario;

#[derive(Debug, Args)]
pub struct PlantArgs {
    /// Bench to simulate: `vemodule` (the M3CVME tool's EV module) or
    /// `controller-network` (the Controller_network project's geared motor
    /// and light sensor).
    #[arg(long, default_value = "vemodule", value_name = "NAME")]
    pub preset: String,
    /// Plant parameter file (TOML) whose fields override the preset's; with a
    /// scenario, those of every module of it (`twin calibrate` writes one).
    #[arg(long, value_name = "FILE")]
    pub params: Option<PathBuf>,
}

impl PlantArgs {
    /// The preset's parameters, with the file's fields over them.
    pub fn load(&self) -> Result<PlantParams> {
        let Some(base) = PlantParams::preset(&self.preset) else {
            bail!(
                "unknown preset `{}`: choose one of {}",
                self.preset,
                PRESETS.join(", ")
            );
        };
        Ok(match &self.params {
            Some(file) => PlantParams::load(file, &base)?,
            None => base,
        })
    }
}

/// Closed loop: the fields of the parameter file `file` over every module of
/// `scenario`, each module keeping its own preset. The file is checked
/// against each module's preset first, so a mistake names its line.
pub fn apply_to_scenario(scenario: &mut Scenario, file: &Path) -> Result<()> {
    let text = std::fs::read_to_string(file)
        .with_context(|| format!("cannot read the parameter file {}", file.display()))?;
    for module in &scenario.modules {
        let Some(base) = PlantParams::preset(&module.preset) else {
            bail!(
                "module `{}`: unknown preset `{}`",
                module.name,
                module.preset
            );
        };
        PlantParams::from_toml(&text, file, &base)?;
    }
    let table: toml::Table = toml::from_str(&text)
        .with_context(|| format!("{}: not a table of parameters", file.display()))?;
    for module in &mut scenario.modules {
        merge(&mut module.params, &table);
    }
    Ok(())
}

/// `over`'s values into `into`, tables merged key by key.
fn merge(into: &mut toml::Table, over: &toml::Table) {
    for (key, value) in over {
        match (into.get_mut(key), value) {
            (Some(toml::Value::Table(a)), toml::Value::Table(b)) => merge(a, b),
            _ => {
                into.insert(key.clone(), value.clone());
            }
        }
    }
}
