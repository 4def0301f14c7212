//! Experiments that reproduce a seed paper's figures from the twin's models;
//! `twin experiment <name>` prints them.

pub mod instruments;
pub mod parallel;
pub mod plot;
pub mod pwmcap;
pub mod step;
pub mod step_metrics;
pub mod sweep;
