//! End to end across the twin's crates: the engine with its nodes and plant, the baselines, the workspace's fences.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

mod architecture;
mod baselines;
mod calibrate;
mod engine_bit_errors;
mod engine_controller_network;
mod engine_loop;
mod engine_pwmcap;
mod light_limits;
mod profiles;
mod standalone;
mod step_response;
