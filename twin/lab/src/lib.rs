//! Experiments on the twin: batch runs of a manifest (`twin batch`), the step response (`twin step`), the light
//! sensor's sweep (`twin sweep`), the PWM-capture paper's figures and the
//! parallel modules (`twin experiment`), and the engine's benchmark (`twin
//! bench`), and the scope pictures of `twin scope --png`. The only crate that
//! draws plots (plotters). The step-response
//! metrics themselves are `twin_sim::step_metrics`, for crates without plots.

#![allow(
    clippy::disallowed_methods,
    reason = "the bench times the engine on the wall clock, and a batch its runs"
)]
#![allow(
    clippy::result_large_err,
    reason = "an experiment's error carries the run's (its scenario's place and \
              message); it is made once, when an experiment fails, never on a path \
              that runs per step"
)]

pub mod batch;
pub mod bench;
pub mod calibrate;
pub mod instruments;
pub mod parallel;
pub mod plot;
pub mod pwmcap;
pub mod scope_png;
pub mod step;
pub mod step_against;
pub mod sweep;
