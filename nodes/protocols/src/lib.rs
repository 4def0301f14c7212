//! The lab's serial protocols as sans-IO codecs, with no physics: MEB, the
//! Controller_network project's 8-byte Modbus, Modbus RTU/ASCII/TCP and PWM-capture
//! symbols. Wire formats as pure parse/emit code: a checked view plus a small value
//! type per frame, and a stream decoder per format fed `(now, bytes)`, with time as
//! [`time::SimTime`]. Beside them, the grammar of the links they travel on
//! (`link`: `tcp://HOST:PORT`, serial paths and their options).

pub mod crc;
pub mod hex;
pub mod link;
pub mod meb;
pub mod modbus;
pub mod modbus8;
pub mod pwmcap;
pub mod time;
pub mod words;
