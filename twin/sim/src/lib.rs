//! The EV lab bench on a virtual clock: scenarios (TOML), the discrete-event
//! engine that wires modules, nodes and media, the node builders, observers
//! (the recorder, the null one, a tee), open-loop runs, replay and baselines.
//!
//! The fence: nothing here reads a clock or an unseeded RNG (the workspace's
//! `clippy.toml` forbids it, see `ARCHITECTURE.md`), nothing here does I/O but
//! reading scenarios and writing recordings, and nothing depends on tokio,
//! rerun or plotters. The same scenario and seed give the same recording,
//! byte for byte.

pub mod baseline;
pub mod engine;
pub mod error_text;
pub mod external;
pub mod interrupt;
pub mod nodes_build;
pub mod nodes_parallel;
pub mod observe;
pub mod openloop;
mod plant_sample;
pub mod replay;
pub mod scenario;
pub mod scenario_pwm;
pub mod step_metrics;
pub mod virtual_run;
