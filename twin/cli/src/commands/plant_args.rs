//! `--preset` and `--params`: the bench to simulate, as `twin run
//! --open-loop`, `twin step --open-loop` and `twin sweep` take it.

use anyhow::{Result, bail};
use clap::Args;
use plant::PlantParams;
use plant::params::PRESETS;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct PlantArgs {
    /// Bench to simulate: `vemodule` (the M3CVME tool's EV module) or
    /// `controller-network` (the Controller_network project's geared motor
    /// and light sensor).
    #[arg(long, default_value = "vemodule", value_name = "NAME")]
    pub preset: String,
    /// Plant parameter file (TOML) whose fields override the preset's.
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
