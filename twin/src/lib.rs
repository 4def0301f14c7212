//! The `twin` binary's library: running the bench and recording it. The
//! command-line front end in `main.rs` is a thin layer over these modules.

pub mod baseline;
pub mod bench;
pub mod client;
pub mod engine;
pub mod experiment;
pub mod frames_to;
pub mod io;
pub mod nodes_build;
pub mod nodes_parallel;
pub mod observe;
pub mod openloop;
pub mod realtime;
pub mod record;
pub mod recording;
pub mod replay;
pub mod scenario;
pub mod scenario_pwm;
pub mod serve;
pub mod supervise;
pub mod view;
pub mod virtual_run;
pub mod vsp;
