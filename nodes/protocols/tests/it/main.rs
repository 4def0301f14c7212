//! The codecs: properties, the PWM-capture symbols, and pymodbus as a peer.
//!
//! One test binary for the crate: each module is one area, and the
//! shared helpers are compiled once.

mod meb_props;
mod modbus_props;
mod modbus_pymodbus;
mod pwmcap;
