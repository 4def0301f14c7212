//! The nodes against the protocol vectors, the simulated media and each other.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

mod controller_network;
mod controller_network_slaves;
mod fault_replies;
mod firmware_frontend;
mod firmware_meb_slave;
mod firmware_modbus_slave;
mod firmware_plant;
mod master_image_server;
mod master_layout;
mod master_pi;
mod master_props;
mod master_supervisor;
mod meb_vectors;
mod modbus8_vectors;
mod parallel_props;
mod pwmbus;
mod pwmline_model;
mod simbus_faults;
mod simbus_noise;
mod simbus_props;
mod simbus_timing;
