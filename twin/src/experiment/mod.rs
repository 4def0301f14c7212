//! Experiments that reproduce a seed paper's figures from the twin's models;
//! `twin experiment <name>` prints them.

pub mod parallel;
pub mod pwmcap;
