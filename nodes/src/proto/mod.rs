//! Wire formats, as pure parse/emit code: a checked view plus a small value type
//! per frame, and a stream decoder per format fed `(now, bytes)`.

pub mod crc;
pub mod meb;
pub mod modbus;
pub mod modbus8;
pub mod pwmcap;
pub mod words;
